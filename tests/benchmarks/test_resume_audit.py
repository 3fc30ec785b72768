"""``benchmarks/resume_audit.py``: which resumes of a run trained one batch more than the uninterrupted run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_smoke import load  # type: ignore[import-not-found]

from _cli_runs import TINY_DVDS, config_args  # type: ignore[import-not-found]

resume_audit = load("resume_audit")


def test_only_a_segment_that_ends_the_last_epoch_again_one_step_later_is_flagged(tmp_path: Path) -> None:
    run = resume_audit.smoke_run(tmp_path)
    found = resume_audit.resumes(run / "metrics.csv")
    assert [(r.segment, r.epoch, r.step, r.extra_batch) for r in found] == [
        ("metrics.segment2.csv", 1, 7, True),  # epoch 1 ended at step 7, ended again at 8
        ("metrics.csv", 1, 8, False),  # a mid-epoch resume: its first row is a step's
    ]
    text = resume_audit.report(resume_audit.audit([tmp_path]), tmp_path)
    assert text.startswith("2 resume boundaries in 1 run; 1 of them, in 1 run, trained one batch more")
    assert "| . | metrics.segment2.csv | 1 | 7 → 8 |" in text


# Epochs of 3 steps, a 6-step budget, validations every 2 steps; Ctrl+C when step 4 starts (last.ckpt holds the
# epoch-end save at step 3), then `--ckpt_path last` in the same folder.
@pytest.mark.usefixtures("isolated_cli")
@pytest.mark.parametrize("before_session_61", [True, False], ids=["epoch end saved in on_train_epoch_end", "now"])
def test_a_real_resume_from_an_epoch_end_is_judged_by_its_trace(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, before_session_61: bool
) -> None:
    from lcreg import callbacks
    from lcreg.cli import main

    if before_session_61:  # LatestCheckpoint then left every epoch end to on_train_epoch_end
        monkeypatch.setattr(callbacks, "_validation_taken_in_at_epoch_end", lambda trainer: True)
    args = [*config_args("dvds.yaml"), *TINY_DVDS, "--data.init_args.num_train=6", "--trainer.limit_train_batches=1.0"]
    args += ["--trainer.max_epochs=-1", "--trainer.max_steps=6", "--trainer.val_check_interval=2"]
    args += ["--trainer.check_val_every_n_epoch=null", f"--trainer.default_root_dir={tmp_path}"]
    args.append(f"--trainer.logger.init_args.save_dir={tmp_path}")
    interrupt = {"class_path": "_cli_runs.InterruptAt", "init_args": {"step": 3}}
    with pytest.raises(SystemExit):
        main(["fit", *args, f"--trainer.callbacks+={json.dumps(interrupt)}"])
    main(["fit", *args, "--ckpt_path", "last"])
    (resume,) = resume_audit.audit([tmp_path])
    assert (resume.segment, resume.epoch, resume.step, resume.extra_batch) == ("metrics.csv", 0, 2, before_session_61)
