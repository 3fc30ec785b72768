"""A training step with a non-finite loss or gradient is skipped before the optimiser update; too many in a row stop.

A tiny DVDs on the embedded shapes (the main job's model), trained by a Lightning Trainer on fixed batches, one of
which carries NaN normals (the reported case: before, the update made 2,473 parameters non-finite and the next
step failed blaming ``points``).
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import pytest
import torch
from lightning.pytorch import Callback, LightningModule, Trainer

from _training import fit_batches  # type: ignore[import-not-found]
from lcreg.cli import build_cli
from lcreg.types import RegistrationBatch

from _cli_runs import TINY_DVDS, config_args  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")


DVDS = [*config_args("dvds.yaml"), *TINY_DVDS]
# PointNetLK is supervised: a NaN ground-truth pose makes its loss NaN (DVDs' loss does not use the pose).
POINTNETLK = [
    *config_args("models/pointnetlk.yaml", "data/embedded.yaml"),
    "--model.init_args.encoder_channels=[16,32]",
    *(arg for arg in TINY_DVDS if not arg.startswith("--model.")),
]


def _model_and_batches(*extra: str, config: list[str] = DVDS) -> tuple[Any, list[RegistrationBatch]]:
    """A tiny model (default DVDs + LC) and its two training batches (dataset indices in ``batch.index``)."""
    cli = build_cli([*config, *extra], run=False)
    cli.datamodule.setup("fit")
    return cli.model, list(cli.datamodule.train_dataloader())


def _nan_normals(batch: RegistrationBatch) -> RegistrationBatch:
    assert batch.normals_src is not None
    normals = batch.normals_src.clone()
    normals[0, 0] = float("nan")
    return dataclasses.replace(batch, normals_src=normals)


def _nan_pose(batch: RegistrationBatch) -> RegistrationBatch:
    assert batch.transform_ref_src is not None
    pose = batch.transform_ref_src.clone()
    pose[1, 0, 3] = float("nan")
    return dataclasses.replace(batch, transform_ref_src=pose)


class _Snapshots(Callback):
    """Parameters and Adam state after every training batch."""

    def __init__(self) -> None:
        self.params: list[dict[str, torch.Tensor]] = []
        self.adam_steps: list[int] = []

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, *args: Any) -> None:
        self.params.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})
        state = trainer.optimizers[0].state
        self.adam_steps.append(max((int(s["step"]) for s in state.values()), default=0))


def _fit(model: LightningModule, batches: list[RegistrationBatch], *callbacks: Callback) -> None:
    fit_batches(model, batches, *callbacks)


@pytest.mark.parametrize(
    ("config", "corrupt"), [(DVDS, _nan_normals), (POINTNETLK, _nan_pose)], ids=["dvds-nan-normals", "plk-nan-pose"]
)
def test_a_step_with_a_nan_loss_is_skipped_and_names_the_batch(config: list[str], corrupt: Any) -> None:
    """Before: no warning, the update made the parameters non-finite."""
    model, (good, other) = _model_and_batches(config=config)
    bad = corrupt(other)
    assert bad.index is not None
    snapshots = _Snapshots()
    indices = re.escape(str(bad.index.tolist()))
    with pytest.warns(UserWarning, match=rf"skipped: non-finite loss .* batch indices {indices}"):
        _fit(model, [good, bad, good], snapshots)
    before, after, last = snapshots.params
    for name, value in before.items():
        assert torch.equal(after[name], value), name  # the bad step changed nothing
        assert torch.isfinite(last[name]).all(), name
    assert snapshots.adam_steps == [1, 1, 2]  # nor the optimiser state
    assert any(not torch.equal(last[n], v) for n, v in before.items())  # the next good step trains


def test_a_step_with_a_non_finite_gradient_is_skipped(monkeypatch: pytest.MonkeyPatch) -> None:
    """A finite loss whose gradient is NaN (``0 * d sqrt(x) / dx`` at 0): the update is dropped as well."""
    model, (good, bad) = _model_and_batches()
    assert bad.index is not None
    losses = model.training_losses

    def nan_gradient_on_bad(result: Any, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        out = losses(result, batch)
        if batch.index is not None and torch.equal(batch.index, bad.index):
            weight = next(p for p in model.parameters() if p.requires_grad)
            out["loss"] = out["loss"] + 0.0 * (weight - weight.detach()).abs().sqrt().sum()
        return out

    monkeypatch.setattr(model, "training_losses", nan_gradient_on_bad)
    snapshots = _Snapshots()
    indices = re.escape(str(bad.index.tolist()))
    with pytest.warns(UserWarning, match=rf"skipped: non-finite gradient on batch indices {indices}"):
        _fit(model, [good, bad], snapshots)
    before, after = snapshots.params
    assert all(torch.equal(after[name], value) for name, value in before.items())
    assert snapshots.adam_steps == [1, 1]


def test_consecutive_bad_steps_stop_training_with_a_clear_error() -> None:
    """``max_bad_steps`` is a model argument (LightningCLI: ``--model.init_args.max_bad_steps``)."""
    from lcreg.models.base import NonFiniteTrainingError

    model, (good, other) = _model_and_batches("--model.init_args.max_bad_steps=2")
    assert model.max_bad_steps == 2
    bad = _nan_normals(other)
    with (
        pytest.warns(UserWarning, match="1 in a row"),
        pytest.raises(NonFiniteTrainingError, match=r"2 consecutive steps .* batch indices"),
    ):
        _fit(model, [good, bad, bad, good])
    with pytest.raises(ValueError, match="max_bad_steps"):
        _model_and_batches("--model.init_args.max_bad_steps=0")


# --- a non-finite parameter or a diverging model: one line, and last.ckpt keeps the last good state ---------------
class _PoisonAt(Callback):
    """Fill the first trainable parameter with NaN before the batch of optimiser step ``step`` (a step gone wrong)."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: Trainer, pl_module: LightningModule, *args: Any) -> None:
        if trainer.global_step == self.step:
            with torch.no_grad():
                next(p for p in pl_module.parameters() if p.requires_grad).fill_(float("nan"))


def test_a_non_finite_parameter_stops_training_naming_it_and_last_ckpt_resumes_from_the_last_good_step() -> None:
    """Before: the run went on into a raw LinAlgError or a NonFiniteError naming an internal argument, and the
    periodic last.ckpt could record the NaN weights. Now: stop at once, name step and parameter and the last good
    state; last.ckpt holds that state and ``--ckpt_path last`` finishes the run from it."""
    from lcreg.callbacks import LatestCheckpoint
    from lcreg.cli import main
    from lcreg.models.base import NonFiniteTrainingError

    args = [*DVDS, "--trainer.max_steps=8", "--trainer.max_epochs=-1", "--trainer.enable_progress_bar=false"]
    cli = build_cli(args, run=False)
    (latest,) = [c for c in cli.trainer.callbacks if isinstance(c, LatestCheckpoint)]
    latest.every_n_train_steps = 2
    cli.trainer.callbacks.append(_PoisonAt(5))
    name = next(n for n, p in cli.model.named_parameters() if p.requires_grad)
    last = latest.path(cli.trainer)
    with pytest.raises(NonFiniteTrainingError) as stop:
        cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    message = str(stop.value)
    assert f"parameter `{name}` holds" in message and "NaN/Inf" in message and "\n" not in message
    assert f"the last good state is {last} (step 4)" in message and "--ckpt_path last" in message
    saved = torch.load(last, map_location="cpu", weights_only=False)
    assert saved["global_step"] == 4
    assert all(torch.isfinite(v).all() for v in saved["state_dict"].values() if v.is_floating_point())
    main(["fit", *args, "--ckpt_path=last"])
    resumed = torch.load(last, map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 8
    assert all(torch.isfinite(v).all() for v in resumed["state_dict"].values() if v.is_floating_point())


def test_a_diverging_run_stops_with_one_line_that_says_so() -> None:
    """SGD-like blow-up (Adam at lr 1e12): before, ``NonFiniteError: `points_a` contains ...`` from deep inside."""
    from lcreg.cli import main
    from lcreg.models.base import NonFiniteTrainingError

    args = [*DVDS, "--trainer.max_steps=6", "--model.init_args.optimizer.init_args.lr=1e12"]
    with (
        pytest.warns(UserWarning, match="forward pass produced non-finite values"),
        pytest.raises(NonFiniteTrainingError, match=r"training stopped at step \d+: .*diverged") as stop,
    ):
        main(["fit", *args])
    assert "\n" not in str(stop.value)
