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
