"""benchmarks/learning_curves.py: its variants' values build the models they describe (nothing trained)."""

from __future__ import annotations

import pytest
from tests.benchmarks.test_smoke import load

from lcreg.cli import LcregCLI
from lcreg.experiments.benchmarking import build_cli_for, synthetic_overrides

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_variant_values_build_their_models() -> None:
    variants = load("learning_curves").VARIANTS

    def cli(name: str) -> LcregCLI:
        variant = variants[name]
        return build_cli_for(variant.method, variant.configs, {**synthetic_overrides(), **variant.overrides})

    only = cli("self_motion_only").model
    assert [(type(t).__name__, t.name) for t in only.loss_terms] == [("SelfMotionLoss", "self_motion")]
    assert only.hparams.lambda_global == 0 and only.hparams.lambda_recon == 0
    steplr = cli("selfsup_steplr").config["model"]["init_args"]["lr_scheduler"]
    assert steplr["class_path"] == "torch.optim.lr_scheduler.StepLR" and steplr["init_args"]["step_size"] == 5
    nobn = cli("pointnetlk_nobn")
    assert nobn.model.hparams.batch_norm is False and nobn.model.hparams.jacobian == "analytic"
    assert nobn.trainer.gradient_clip_val == 1.0


def test_recipe_levers_change_only_their_self_motion_argument() -> None:
    """``recipe_with`` rebuilds the recipe's loss terms (LC as configs/lc.yaml, the self-motion term as
    configs/self_motion.yaml) and changes only the named argument."""
    module = load("learning_curves")

    def terms(variant: object) -> list[list[tuple[str, str, dict[str, object]]]]:
        """Every loss term's modules (LC's LocalConsistency included) with their public attributes."""
        model = build_cli_for(variant.method, variant.configs, {**synthetic_overrides(), **variant.overrides}).model
        return [
            [
                (name, type(m).__name__, {k: v for k, v in vars(m).items() if not k.startswith("_")})
                for name, m in term.named_modules()
            ]
            for term in model.loss_terms
        ]

    recipe = terms(module.VARIANTS["selfsup"])
    assert terms(module.recipe_with()) == recipe
    assert [term[0][1] for term in recipe] == ["LocalConsistencyLoss", "SelfMotionLoss"]
    assert recipe[0][1][1] == "LocalConsistency" and recipe[0][1][2]["num_local_points"] == 64
    levers = {"selfsup_tw25": {"translation_weight": 25.0}, "selfsup_tw100": {"translation_weight": 100.0}}
    for name, changed in {**levers, "selfsup_frac50": {"sample_fraction": 0.5}}.items():
        lever = terms(module.VARIANTS[name])
        assert lever[0] == recipe[0]
        assert lever[1][0][2] == {**recipe[1][0][2], **changed} != recipe[1][0][2]
