"""`lcreg fit --ckpt_path last` resumes a stopped run: same batches, same random numbers, same final state.

A run stopped after k optimiser steps (mid-epoch, its last.ckpt written at step k) and resumed with one command ends
exactly where an uninterrupted run with the same seed ends. ``benchmarks/kill_resume.py`` does the same with a real
``kill -9`` at a random step.
"""

from __future__ import annotations

import csv
import json
import random
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcreg.checkpoints import CheckpointNotFoundError
from lcreg.cli import main
from lcreg.resume import changed_settings

from _cli_runs import TINY_DVDS, cli_isolation, config_args  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")

# 6 training shapes in batches of 2: 3 steps per epoch, 2 epochs.
RUN = [
    *config_args("dvds.yaml"),
    *TINY_DVDS,
    "--data.init_args.num_train=6",
    "--trainer.limit_train_batches=1.0",
    "--trainer.max_epochs=2",
]
# A stop at the first step of the second epoch (mid-epoch; last.ckpt written at max_steps), and at the end of the first
# epoch (last.ckpt written after its validation).
STOPS = [4, 3]


def _fit(save_dir: Path, *extra: str) -> Path:
    """``lcreg fit`` logging under ``save_dir``; the run's folder."""
    outputs = [f"--trainer.logger.init_args.save_dir={save_dir}", f"--trainer.default_root_dir={save_dir}"]
    main(["fit", *RUN, *outputs, *extra])
    return save_dir / "lcreg" / "version_0"


def _val_errors(run: Path) -> list[tuple[int, float]]:
    """``(epoch, val/rre_mean_deg)`` of every validation logged in the run's metrics files."""
    rows = [row for path in sorted(run.glob("metrics*.csv")) for row in csv.DictReader(path.open())]
    return sorted({(int(r["epoch"]), float(r["val/rre_mean_deg"])) for r in rows if r.get("val/rre_mean_deg")})


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The uninterrupted run."""
    root = tmp_path_factory.mktemp("whole")
    with cli_isolation(root):
        return _fit(root)


@pytest.mark.parametrize("stop", STOPS, ids=["mid-epoch", "epoch-end"])
def test_a_stopped_run_resumed_with_ckpt_path_last_ends_like_the_uninterrupted_run(
    whole: Path, tmp_path: Path, stop: int
) -> None:
    """Before: `--ckpt_path last` started a new version_1, found no checkpoint there, warned and trained from step 0."""
    stopped = _fit(tmp_path / "stopped", f"--trainer.max_steps={stop}")
    last = stopped / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=True)["global_step"] == stop  # the latest state, not the best
    _fit(tmp_path / "stopped", "--ckpt_path", "last")

    assert not (tmp_path / "stopped" / "lcreg" / "version_1").exists()  # the resumed run logs in its own folder
    assert (stopped / "metrics.segment1.csv").is_file()  # the first segment's metrics are kept
    expected = torch.load(whole / "checkpoints" / "last.ckpt", weights_only=True)
    resumed = torch.load(last, weights_only=True)
    assert resumed["global_step"] == expected["global_step"] == 6
    assert expected["state_dict"].keys() == resumed["state_dict"].keys()
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(resumed["state_dict"][key], value, rtol=0, atol=0, msg=key)
    adam, adam_resumed = expected["optimizer_states"][0]["state"], resumed["optimizer_states"][0]["state"]
    for index, state in adam.items():
        torch.testing.assert_close(adam_resumed[index]["exp_avg_sq"], state["exp_avg_sq"], rtol=0, atol=0)
    # The untrained weights (configs/dvds.yaml validates first) and the two epochs; the resumed run adds none.
    assert _val_errors(stopped) == _val_errors(whole) and len(_val_errors(whole)) == 3


# Validations every 2 steps, epochs of 3 (6 or 7 training shapes in batches of 2, the last batch dropped).
EVERY_2 = ["--trainer.val_check_interval=2", "--trainer.check_val_every_n_epoch=null"]
# The queue's runs: a step budget (Lightning always restarts such a run's fit loop), epochs unbounded.
BY_STEPS = ["--trainer.max_epochs=-1", "--trainer.max_steps=6"]
KILLS = {  # the step whose start copies last.ckpt: 3 is the end of the first epoch
    "epoch-end save between validations": (3, EVERY_2),
    "save after a validation": (5, EVERY_2),
    "step budget, epoch-end save between validations": (3, [*EVERY_2, *BY_STEPS]),
    "step budget, save after a validation": (5, [*EVERY_2, *BY_STEPS]),
    "step budget, validation every 2nd epoch": (3, ["--trainer.check_val_every_n_epoch=2", *BY_STEPS]),
    "step budget, validation at every epoch's end by steps": (
        3,
        ["--trainer.val_check_interval=3", *EVERY_2[1:], *BY_STEPS],
    ),
}


def _kill_and_resume(tmp_path: Path, step: int, args: list[str]) -> tuple[dict, dict]:
    """The final ``last.ckpt`` of an uninterrupted run and of one resumed from the file a kill at ``step`` leaves."""
    copy = tmp_path / "killed.ckpt"
    spec = {"class_path": "_cli_runs.CopyLastCheckpointAt", "init_args": {"step": step, "dest": str(copy)}}
    (tmp_path / "whole").mkdir()
    with cli_isolation(tmp_path / "whole"):
        whole = _fit(tmp_path / "whole", *args, f"--trainer.callbacks+={json.dumps(spec)}")
    assert torch.load(copy, weights_only=True)["global_step"] == (3 if step == 3 else 4)
    resumed = _fit(tmp_path / "resumed", *args, "--ckpt_path", str(copy))
    expected = torch.load(whole / "checkpoints" / "last.ckpt", weights_only=True)
    return expected, torch.load(resumed / "checkpoints" / "last.ckpt", weights_only=True)


@pytest.mark.parametrize("train", [6, 7], ids=["full batches", "a leftover object"])
@pytest.mark.parametrize("kill", list(KILLS))
def test_a_run_resumed_from_the_last_checkpoint_a_kill_leaves_ends_like_the_uninterrupted_run(
    tmp_path: Path, kill: str, train: int
) -> None:
    """Session 60 found a DCP-v2 queue run (``max_steps``, validation every 50 steps, epochs of 88) that left its
    uninterrupted trajectory after resuming from the epoch-end save at step 352. Session 61: Lightning ends a
    ``max_steps`` run's resumed epoch again after one more batch when the file was written in ``on_train_epoch_end``
    (a loss_epoch row at step 352, the next epoch one step late); ``LatestCheckpoint`` now saves the end of such an
    epoch at its last batch. The step-budget cases failed before (weights off by up to 7e-5 here, 0.04 on the
    queue's DCP-v2 configuration shrunk to 32 points)."""
    step, args = KILLS[kill]
    expected, final = _kill_and_resume(tmp_path, step, [f"--data.init_args.num_train={train}", *args])
    assert final["global_step"] == expected["global_step"] == 6
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(final["state_dict"][key], value, rtol=0, atol=0, msg=key)


# A plateau scheduler whose state follows the metric: it halves the rate whenever val/loss does not improve.
PLATEAU = (
    '--model.init_args.lr_scheduler={"class_path": "torch.optim.lr_scheduler.ReduceLROnPlateau", '
    '"init_args": {"patience": 0, "factor": 0.5}}'
)
PLATEAU_KILLS = {
    "DeepGMR's schedule: validation at each epoch's last batch by steps": (
        3,
        ["--trainer.val_check_interval=3", *EVERY_2[1:], *BY_STEPS],
    ),
    "validations every 2 steps, the save after a validation": (5, [*EVERY_2, *BY_STEPS]),
    "validations every 2 steps, the epoch-end save": (3, [*EVERY_2, *BY_STEPS]),
    "validation at each epoch's end, epoch budget": (3, ["--trainer.check_val_every_n_epoch=1"]),
}


@pytest.mark.parametrize("kill", list(PLATEAU_KILLS))
def test_a_plateau_scheduler_takes_the_same_steps_in_a_resumed_run(tmp_path: Path, kill: str) -> None:
    """Session 61: Lightning skips plateau steps when it restarts (the metrics are not in checkpoints), so a run
    resumed from the save after a validation ended with its rate one halving behind (3e-5 against 1.5e-5 in the first
    case; 6 of the 15 resumes of the committed DeepGMR runs were such). Since session 62 the model steps its plateau
    scheduler after each validation itself and keeps the step still due in a checkpoint written in a validation;
    without that entry the first two cases fail."""
    step, args = PLATEAU_KILLS[kill]
    expected, final = _kill_and_resume(tmp_path, step, [*args, PLATEAU])
    assert final["lr_schedulers"][0] == expected["lr_schedulers"][0]
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(final["state_dict"][key], value, rtol=0, atol=0, msg=key)


def _multistep(milestones: list[int], interval: str) -> list[str]:
    scheduler = {"class_path": "torch.optim.lr_scheduler.MultiStepLR", "init_args": {"milestones": milestones}}
    return [
        f"--model.init_args.lr_scheduler={json.dumps(scheduler)}",
        f"--model.init_args.lr_scheduler_interval={interval}",
    ]


STEP_SCHEDULE_KILLS = {  # the queue's IDAM runs (milestones in steps) and DCP-v2's and PRNet's configs (in epochs)
    "milestones in steps, the save after a validation": (5, [*EVERY_2, *BY_STEPS, *_multistep([1, 3, 4, 5], "step")]),
    "milestones in epochs, the epoch-end save": (3, [*EVERY_2, *BY_STEPS, *_multistep([1, 2], "epoch")]),
}


@pytest.mark.parametrize("kill", list(STEP_SCHEDULE_KILLS))
def test_a_step_schedule_takes_the_same_steps_in_a_resumed_run(tmp_path: Path, kill: str) -> None:
    """Session 62 probe, kept as a test: a ``MultiStepLR`` (Lightning steps it before the batch's callbacks, so every
    save already holds the batch's step) resumes exactly from each of ``KILLS``' kill points, milestones in steps or
    in epochs."""
    step, args = STEP_SCHEDULE_KILLS[kill]
    expected, final = _kill_and_resume(tmp_path, step, args)
    assert final["lr_schedulers"][0] == expected["lr_schedulers"][0]
    schedule = expected["lr_schedulers"][0]
    assert schedule["_last_lr"][0] < schedule["base_lrs"][0]  # the rate moved (before the kill, too)
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(final["state_dict"][key], value, rtol=0, atol=0, msg=key)


BY_EPOCH_VALIDATIONS = ["--trainer.check_val_every_n_epoch=1", *BY_STEPS]


def _listed(class_path: str, **init_args: Any) -> str:
    """``--trainer.callbacks+=`` for a callback monitoring the default metric."""
    spec = {"class_path": class_path, "init_args": {"monitor": "val/rre_mean_deg", **init_args}}
    return f"--trainer.callbacks+={json.dumps(spec)}"


SAVES_AT_EPOCH_END = _listed("lightning.pytorch.callbacks.ModelCheckpoint", save_on_train_epoch_end=True)
STOPS_AT_EPOCH_END = _listed("lightning.pytorch.callbacks.EarlyStopping", patience=10)


def test_a_step_budget_with_validation_by_epochs_resumes_an_epoch_end_save_exactly(tmp_path: Path) -> None:
    """Session 61 left this schedule inexact (weights off by about 1e-4 here): the default ``ModelCheckpoint`` took
    each validation in at the epoch's end, so ``last.ckpt`` had to be written there, which Lightning resumes one batch
    late. Since session 62 it saves when the validation ends, and ``last.ckpt`` is written at the epoch's last
    batch."""
    expected, final = _kill_and_resume(tmp_path, 3, BY_EPOCH_VALIDATIONS)
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(final["state_dict"][key], value, rtol=0, atol=0, msg=key)


@pytest.mark.xfail(
    strict=True,
    reason="related to Lightning-AI/pytorch-lightning#19617: a max_steps run resumed from an "
    "on_train_epoch_end save ends that epoch again; a listed ModelCheckpoint that takes the validation in at the "
    "epoch's end needs last.ckpt written there",
)
def test_a_listed_checkpoint_saving_at_the_epoch_end_resumes_exactly(tmp_path: Path) -> None:
    """The case left inexact; the next test pins its warning."""
    expected, final = _kill_and_resume(tmp_path, 3, [*BY_EPOCH_VALIDATIONS, SAVES_AT_EPOCH_END])
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(final["state_dict"][key], value, rtol=0, atol=0, msg=key)


@pytest.mark.parametrize(
    ("args", "warns"),
    [
        ([*BY_EPOCH_VALIDATIONS, SAVES_AT_EPOCH_END], True),
        ([*BY_EPOCH_VALIDATIONS, STOPS_AT_EPOCH_END], True),
        (BY_EPOCH_VALIDATIONS, False),
        (["--trainer.check_val_every_n_epoch=1", SAVES_AT_EPOCH_END], False),
        ([*EVERY_2, *BY_STEPS], False),
    ],
    ids=[
        "step budget, validation by epochs, a listed ModelCheckpoint saving at the epoch end",
        "step budget, validation by epochs, a listed EarlyStopping",
        "step budget, validation by epochs, the default callbacks",
        "epoch budget",
        "step budget, validation by steps",
    ],
)
def test_the_schedule_that_does_not_resume_exactly_is_named_at_the_start(
    tmp_path: Path, args: list[str], warns: bool
) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _fit(tmp_path, "--data.init_args.num_train=6", *args)
    named = [w for w in caught if "resumes exactly" in str(w.message) and "val_check_interval=3" in str(w.message)]
    assert len(named) == (1 if warns else 0)


def test_ckpt_path_last_with_nothing_to_resume_is_an_error_naming_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(CheckpointNotFoundError, match=r"nothing to resume") as err:
        _fit(tmp_path / "empty", "--ckpt_path", "last")
    assert str(tmp_path / "empty" / "lcreg") in str(err.value)
    assert not (tmp_path / "empty" / "lcreg").exists()  # nothing was trained


def test_a_listed_latest_checkpoint_sets_the_cadence() -> None:
    from lightning.pytorch.callbacks import ModelCheckpoint

    from lcreg.callbacks import LatestCheckpoint, RngState
    from lcreg.cli import build_cli

    listed = "--trainer.callbacks=[{class_path: lcreg.callbacks.LatestCheckpoint, init_args: {every_n_train_steps: 7}}]"
    callbacks = build_cli([*RUN, listed], run=False).trainer.callbacks
    (latest,) = [c for c in callbacks if isinstance(c, LatestCheckpoint)]
    assert latest.every_n_train_steps == 7 and sum(isinstance(c, RngState) for c in callbacks) == 1
    (best,) = [c for c in callbacks if isinstance(c, ModelCheckpoint)]
    assert best.monitor == "val/rre_mean_deg" and not best.save_last  # LatestCheckpoint alone writes last.ckpt
    # After Lightning's own reordering, last.ckpt is written after the ModelCheckpoint has taken the validation in.
    assert callbacks.index(latest) > callbacks.index(best)
    with pytest.raises(ValueError, match=">= 0"):
        LatestCheckpoint(every_n_train_steps=-1)


def test_ckpt_path_last_follows_the_latest_version_with_a_checkpoint(tmp_path: Path) -> None:
    """last.ckpt follows the latest run of the configured logger that has one (a later `test` run has none)."""
    run = _fit(tmp_path / "runs", "--trainer.max_epochs=1")
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 3
    (tmp_path / "runs" / "lcreg" / "version_1").mkdir()  # e.g. an `lcreg test` run: no checkpoints
    _fit(tmp_path / "runs", "--ckpt_path", "last", "--trainer.max_epochs=2")
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 6
    assert not list((tmp_path / "runs" / "lcreg" / "version_1").iterdir())


def test_rng_state_round_trip_restores_every_stream_when_training_starts() -> None:
    from lcreg.callbacks import RngState

    torch.manual_seed(3)
    np.random.seed(3)
    random.seed(3)
    state = RngState().state_dict()
    expected = (torch.rand(3), np.random.rand(3), random.random())
    torch.manual_seed(0)
    np.random.seed(0)
    random.seed(0)
    callback = RngState()
    callback.load_state_dict(state)
    callback.on_train_start(None, None)  # type: ignore[arg-type]  # the trainer and module are not used
    torch.testing.assert_close(torch.rand(3), expected[0])
    np.testing.assert_array_equal(np.random.rand(3), expected[1])
    assert random.random() == expected[2]


def test_epoch_sampler_order_and_seeds_follow_seed_and_epoch_and_resume_mid_epoch() -> None:
    from lcreg.data.sampling import EpochSampler

    sampler = EpochSampler(6, seed=5)
    epoch0 = list(sampler)
    assert list(sampler) == epoch0 and sorted(i for i, _ in epoch0) == list(range(6))
    sampler.set_epoch(1)
    epoch1 = list(sampler)
    assert epoch1 != epoch0 and {s for _, s in epoch1}.isdisjoint({s for _, s in epoch0})
    resumed = EpochSampler(6, seed=None)
    resumed.load_state_dict({"seed": 5, "epoch": 1, "start": 4})
    assert list(resumed) == epoch1[4:]
    assert list(resumed) == epoch1  # the skip applies to one iteration only
    assert EpochSampler(6, seed=6).seed != sampler.seed and list(EpochSampler(6, seed=6)) != epoch0


def test_ckpt_path_best_tests_the_checkpoint_the_latest_run_chose_on_validation(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: `lcreg test --ckpt_path best` failed (Lightning's `best` needs a fit in the same process)."""
    run = _fit(tmp_path / "runs", "--trainer.max_epochs=2")
    (tmp_path / "runs" / "lcreg" / "version_1").mkdir()  # e.g. an earlier `lcreg test` run: no checkpoints
    state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["callbacks"]
    (recorded,) = [v["best_model_path"] for k, v in state.items() if k.startswith("ModelCheckpoint")]
    assert Path(recorded).is_file() and Path(recorded).parent == run / "checkpoints"
    outputs = [f"--trainer.logger.init_args.save_dir={tmp_path / 'runs'}", f"--trainer.default_root_dir={tmp_path}"]
    with caplog.at_level("INFO"):
        main(["test", *RUN, *outputs, "--ckpt_path", "best"])
    assert f"--ckpt_path best is {recorded} (chosen on validation)" in caplog.text
    assert any((tmp_path / "runs" / "lcreg").glob("version_*/test_per_pair.csv"))
    with pytest.raises(ValueError, match="`fit` resumes with `last`"):
        _fit(tmp_path / "runs", "--ckpt_path", "best")


def test_ckpt_path_best_without_a_recorded_choice_names_the_file(tmp_path: Path) -> None:
    from lcreg.resume import best_checkpoint_of

    last = tmp_path / "last.ckpt"
    torch.save({"state_dict": {}, "callbacks": {"ModelCheckpoint{'monitor': 'x'}": {"best_model_path": ""}}}, last)
    with pytest.raises(CheckpointNotFoundError, match="recorded no checkpoint chosen on validation") as err:
        best_checkpoint_of(last)
    assert str(last) in str(err.value)
    moved = tmp_path / "moved.ckpt"
    moved.write_bytes(b"x")
    torch.save({"state_dict": {}, "callbacks": {"ModelCheckpoint": {"best_model_path": "/gone/moved.ckpt"}}}, last)
    assert best_checkpoint_of(last) == moved  # a run folder moved since: the file of that name beside last.ckpt
    moved.unlink()
    with pytest.raises(CheckpointNotFoundError, match="no longer exists"):
        best_checkpoint_of(last)


@pytest.mark.parametrize("listed", [False, True], ids=["default", "listed"])
def test_last_checkpoint_records_the_best_checkpoint_of_the_same_validation(tmp_path: Path, listed: bool) -> None:
    """Before: last.ckpt was saved before the ModelCheckpoint saw the validation, so it named the previous best
    (deleted once a better one was saved): `--ckpt_path best` then pointed at a missing file, and a resumed run
    compared against a stale best score."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from lcreg.callbacks import LatestCheckpoint
    from lcreg.cli import build_cli

    # A ModelCheckpoint on the step (mode max): every validation is a new best, the last one included, so a last.ckpt
    # saved before the ModelCheckpoint took the last validation in names a deleted file.
    always_better = "{class_path: lightning.pytorch.callbacks.ModelCheckpoint, init_args: {monitor: step, mode: max}}"
    latest = ", {class_path: lcreg.callbacks.LatestCheckpoint}" if listed else ""
    cadence = [f"--trainer.callbacks=[{always_better}{latest}]"]
    outputs = [f"--trainer.logger.init_args.save_dir={tmp_path}", f"--trainer.default_root_dir={tmp_path}"]
    cli = build_cli(["fit", *RUN, *outputs, "--trainer.max_epochs=3", *cadence], run=True)
    callbacks = cli.trainer.callbacks
    order = [type(c) for c in callbacks if isinstance(c, (ModelCheckpoint, LatestCheckpoint))]
    assert order == [ModelCheckpoint, LatestCheckpoint]
    run = tmp_path / "lcreg" / "version_0" / "checkpoints"
    state = torch.load(run / "last.ckpt", weights_only=True)["callbacks"]
    (recorded,) = [v for k, v in state.items() if k.startswith("ModelCheckpoint")]
    checkpoint = cli.trainer.checkpoint_callback
    assert Path(recorded["best_model_path"]) == Path(checkpoint.best_model_path)  # type: ignore[union-attr]
    assert float(recorded["best_model_score"]) == cli.trainer.global_step  # the last validation, at the last step
    assert [p.name for p in run.glob("*.ckpt") if p.name != "last.ckpt"] == [Path(recorded["best_model_path"]).name]


def test_a_run_stopped_by_sigterm_saves_the_step_it_reached_and_resumes_like_the_uninterrupted_run(
    whole: Path, tmp_path: Path
) -> None:
    """Before: a SIGTERM between two saves lost the steps since the last one (up to `every_n_train_steps`: 50 steps
    of a queue run); here step 5 was lost and the run resumed from step 3, the end of the first epoch."""
    with pytest.raises(SystemExit) as stop:
        _fit(tmp_path / "stopped", "--trainer.callbacks+=_cli_runs.SigtermAt", "--trainer.callbacks.step=5")
    assert stop.value.code == 143
    last = tmp_path / "stopped" / "lcreg" / "version_0" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=True)["global_step"] == 5
    _fit(tmp_path / "stopped", "--ckpt_path", "last")
    expected, resumed = (
        torch.load(p / "checkpoints" / "last.ckpt", weights_only=True) for p in (whole, last.parents[1])
    )
    assert resumed["global_step"] == expected["global_step"] == 6
    for key, value in expected["state_dict"].items():
        torch.testing.assert_close(resumed["state_dict"][key], value, rtol=0, atol=0, msg=key)
    assert _val_errors(last.parents[1]) == _val_errors(whole)


def test_lcreg_fit_stopped_by_sigterm_exits_143_and_keeps_its_last_checkpoint(tmp_path: Path) -> None:
    """Before: Lightning ended `fit` on SIGTERM with a SystemExit of code None, so `lcreg fit` exited 0 as if the run
    had finished (a scheduler's preemption or a queue's stop looked like a finished run)."""
    import signal
    import subprocess
    import sys
    import time

    outputs = [f"--trainer.logger.init_args.save_dir={tmp_path}", f"--trainer.default_root_dir={tmp_path}"]
    argv = [sys.executable, "-m", "lcreg", "fit", *RUN, *outputs, "--trainer.max_epochs=10000"]
    process = subprocess.Popen(argv, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    last = tmp_path / "lcreg" / "version_0" / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 240
    while not last.is_file() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, stderr[-2000:]
    assert "training stopped by SIGTERM; `--ckpt_path last` resumes it" in stderr and last.is_file()


def test_a_finished_run_resumed_with_ckpt_path_last_keeps_its_metrics_file(tmp_path: Path) -> None:
    """Before: the resumed run trained no step and logged nothing, so its metrics.csv was left renamed to a segment."""
    done = _fit(tmp_path / "done")
    before = (done / "metrics.csv").read_text(encoding="utf-8")
    _fit(tmp_path / "done", "--ckpt_path", "last")
    assert sorted(path.name for path in done.glob("metrics*.csv")) == ["metrics.csv"]
    assert (done / "metrics.csv").read_text(encoding="utf-8") == before


def test_changed_settings_compares_model_and_data_but_not_machine_keys_or_new_options() -> None:
    saved = {"model": {"init_args": {"lr": 1e-3, "k": 12}}, "data": {"init_args": {"root": "/a", "sigma": 0.0}}}
    same = {
        "model": {"init_args": {"lr": 1e-3, "k": 12, "added": None}},
        "data": {"init_args": {"root": "/b", "sigma": 0.0}},
    }
    assert changed_settings(saved, {**same, "trainer": {"max_steps": 9}}) == []
    other = {"model": {"init_args": {"lr": 2e-4, "k": 12}}, "data": {"init_args": {"root": "/a", "sigma": 0.01}}}
    assert changed_settings(saved, other) == ["data.init_args.sigma", "model.init_args.lr"]
