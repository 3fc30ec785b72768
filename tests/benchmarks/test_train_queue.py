"""The training queue: the committed queue file is valid and each command parses; a run marks a job done."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shlex
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch
from tests.benchmarks.test_smoke import BENCHMARKS, load

from lcreg.experiments.benchmarking import Series
from lcreg.experiments.reproduce.command import build_parser

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_committed_queue_jobs_are_valid_and_their_arguments_parse(tmp_path: Path) -> None:
    queue = load("train_queue")
    jobs = queue.load_jobs(BENCHMARKS / "train_queue.toml")
    assert jobs and {job.section for job in jobs} <= {"cpu", "gpu"}
    assert any(job.section == "gpu" for job in jobs) and any(job.section == "cpu" for job in jobs)
    for job in jobs:
        argv = job.argv(tmp_path / "runs", tmp_path / "results")
        assert str(tmp_path / "runs" / job.id) in shlex.join(argv), job.id
        if argv[:2] == ["lcreg", "reproduce"]:  # a typo in a queued command fails here, not hours later
            args = build_parser().parse_args(argv[2:])
            assert args.budget in ("converge", "paper"), f"{job.id}: queued sweeps use converge or paper budgets"
            continue
        script = Path(argv[1])
        assert script.parent.name == "benchmarks" and (BENCHMARKS / script.name).is_file(), job.id
        args = load(script.stem).parse(argv[2:])
        assert args.patience is not None and args.val_pairs > 1, f"{job.id}: queued runs use the converge budget"
        if job.test_command:  # the test of each finished run: on the test split, the selected checkpoint, kept outputs
            words = job.follow_up_argv("test", tmp_path / "best.ckpt", tmp_path / "out")
            test = load(Path(words[1]).stem).parse(words[2:])
            assert test.split == "test" and test.ckpt == [str(tmp_path / "best.ckpt")], job.id
            assert str(test.out) == str(tmp_path / "out") + ".md" and test.pairs_csv, job.id
        if job.val_command:  # what a rule reads: on validation pairs only, never a test look
            words = job.follow_up_argv("val", tmp_path / "best.ckpt", tmp_path / "out")
            val = load(Path(words[1]).stem).parse(words[2:])
            assert val.split == "val" and val.ckpt == [str(tmp_path / "best.ckpt")], job.id
            assert str(val.out) == str(tmp_path / "out") + ".md", job.id


def test_queue_refuses_bad_files(tmp_path: Path) -> None:
    queue = load("train_queue")
    bad = tmp_path / "q.toml"
    bad.write_text('[[job]]\nid = "a"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\nhours = 1\n')
    with pytest.raises(ValueError, match="job 'a'"):
        queue.load_jobs(bad)
    job = '[[job]]\nid = "a"\nsection = "cpu"\nwhat = "x"\ncommand = "{c}"\n'
    bad.write_text(job.format(c="true") * 2)
    with pytest.raises(ValueError, match="unique"):
        queue.load_jobs(bad)


def test_run_marks_only_a_successful_job_done(tmp_path: Path) -> None:
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text(
        '[[job]]\nid = "ok"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c \\"import pathlib; '
        "p = pathlib.Path('{runs}'); p.mkdir(parents=True); (p / 'runs.jsonl').write_text('{{}}\\\\n')\\\"\"\n"
        '[[job]]\nid = "fails"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c \\"raise SystemExit(3)\\""\n'
    )
    args = ["--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    with pytest.raises(SystemExit):
        queue.main(["run", *args])
    done = json.loads((tmp_path / "res" / "ok" / "DONE.json").read_text())
    assert done["files"] == 1 and (tmp_path / "res" / "ok" / "runs" / "runs.jsonl").is_file()
    assert not (tmp_path / "res" / "fails" / "DONE.json").exists()
    queue.main(["run", "--only", "ok", *args])  # a done job is not run again (its folder exists: mkdir would fail)


def test_a_reproduce_job_whose_report_failed_is_done_and_the_runner_goes_on(tmp_path: Path, monkeypatch) -> None:
    queue = load("train_queue")  # exit 3: every run finished, the report was not written (session 54)
    monkeypatch.setitem(queue.INTERPRETERS, "lcreg", [sys.executable, "-c", "raise SystemExit(3)"])
    file = tmp_path / "q.toml"
    file.write_text(
        '[[job]]\nid = "sweep"\nsection = "cpu"\nwhat = "x"\ncommand = "lcreg reproduce lc --budget converge '
        '--out {runs}"\n[[job]]\nid = "next"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c pass"\n'
    )
    queue.main(["run", "--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")])
    done = json.loads((tmp_path / "res" / "sweep" / "DONE.json").read_text())
    assert done["report"] == "not written (exit code 3): rerun the command with --report-only"
    assert "report" not in json.loads((tmp_path / "res" / "next" / "DONE.json").read_text())


def git(repo: Path, *words: str) -> str:
    import subprocess

    return subprocess.run(["git", "-C", str(repo), *words], capture_output=True, text=True, check=True).stdout


def test_a_job_is_synced_and_committed_while_it_trains_and_nothing_else_is_committed(tmp_path: Path) -> None:
    """Session 36 ended with a run 1,760 steps in that no sync had kept (the next machine started it from step 0):
    ``--sync-every`` keeps a training job's rows and resume state meanwhile, and ``--commit`` commits its results
    folder alone, leaving the session's own staged and unstaged edits out of the commits."""
    queue = load("train_queue")
    repo = tmp_path / "repo"
    results = repo / "results"
    results.mkdir(parents=True)
    git(repo, "init", "-q")
    git(repo, "config", "user.email", "t@example.com")
    git(repo, "config", "user.name", "t")
    (repo / "code.py").write_text("x = 1\n")
    git(repo, "add", "code.py")
    git(repo, "commit", "-q", "-m", "code")
    (repo / "code.py").write_text("x = 2\n")  # a session's edit, staged, and one not staged
    git(repo, "add", "code.py")
    (repo / "notes.txt").write_text("draft\n")
    marker = tmp_path / "committed"
    script = tmp_path / "job.py"  # a finished run's row and a run in progress; it ends once a sync has committed them
    script.write_text(
        "import json, pathlib, subprocess, sys, time\n"
        "runs = pathlib.Path(sys.argv[1])\n"
        "(runs / 'a/seed1/checkpoints').mkdir(parents=True)\n"
        "(runs / 'runs.jsonl').write_text(json.dumps({'variant': 'a', 'seed': 0}) + '\\n')\n"
        "(runs / 'a/seed1/checkpoints/last.ckpt').write_bytes(b'state')\n"
        f"git = ['git', '-C', {str(repo)!r}, 'log', '--format=%s']\n"
        "log = lambda: subprocess.run(git, capture_output=True).stdout\n"
        "start = time.monotonic()\n"
        "while b'in training' not in log() and time.monotonic() - start < 60:\n"
        "    time.sleep(0.2)\n"
        f"pathlib.Path({str(marker)!r}).write_bytes(log())\n"
    )
    file = tmp_path / "q.toml"
    file.write_text(f'[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "python {script} {{runs}}"\n')
    args = ["--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(results)]
    queue.main(["run", "--sync-every", "0.02", "--commit", *args])
    assert b"Queue results: j (in training; committed by its runner)" in marker.read_bytes()  # before it ended
    log = git(repo, "log", "--format=%s", "--name-only")
    assert "results/j/runs/runs.jsonl" in log and "results/j/resume/a/seed1/checkpoints/last.ckpt" in log
    assert git(repo, "log", "-1", "--format=%s") == "Queue results: j (done; committed by its runner)\n"
    kept = git(repo, "ls-tree", "-r", "--name-only", "HEAD", "results").split()
    assert kept == ["results/j/DONE.json", "results/j/runs/runs.jsonl"]  # a done job keeps no resume state
    assert git(repo, "log", "--format=%s", "--", "code.py") == "code\n" and "notes.txt" not in log.split()
    assert git(repo, "diff", "--cached", "--name-only") == "code.py\n"  # still staged, not committed
    assert git(repo, "status", "--porcelain", "--", "results") == ""  # every result file is committed
    assert not queue.commit_results(results, "j", "sync")  # nothing new: no empty commit
    assert not queue.commit_results(tmp_path / "not-a-repo", "j", "sync")  # reported, not raised


def test_done_names_the_gpu_that_trained_on_a_gpu_machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Session 17: a job trained on a lent H100 wrote "x86_64 (cpu)" into DONE.json (the default device of the header).
    queue = load("train_queue")
    monkeypatch.setattr("torch.cuda.is_available", lambda: True)
    monkeypatch.setattr("torch.cuda.get_device_name", lambda device=None: "Test GPU 80GB")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "g"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c \\"pass\\""\n')
    queue.main(["run", "--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")])
    done = json.loads((tmp_path / "res" / "g" / "DONE.json").read_text())
    assert done["machine"].startswith("Test GPU 80GB (cuda)")


def test_a_jobs_training_process_gets_the_runners_threads(tmp_path: Path) -> None:
    # Session 45: a machine-bound run that must finish within the session gets both cores once the other runners are
    # done; until then every job ran with OMP_NUM_THREADS=1 whatever the machine had free.
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    write = "import os, sys; open(sys.argv[1], 'w').write(os.environ['OMP_NUM_THREADS'])"
    jobs = [
        f'[[job]]\nid = "{n}"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c \\"{write}\\" {{results}}/t"\n'
        for n in "ab"
    ]
    file.write_text("".join(jobs))
    args = ["--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    queue.main(["run", "--only", "a", *args])
    queue.main(["run", "--only", "b", "--threads", "2", *args])
    assert [(tmp_path / "res" / n / "t").read_text() for n in "ab"] == ["1", "2"]


def test_a_section_runs_its_jobs_and_only_names_jobs_of_any_section(tmp_path: Path) -> None:
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    job = '[[job]]\nid = "{id}"\nsection = "{section}"\nwhat = "x"\ncommand = "python -c \\"pass\\""\n'
    file.write_text(job.format(id="c", section="cpu") + job.format(id="g", section="gpu"))
    args = ["--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]

    def done() -> set[str]:
        return {p.parent.name for p in (tmp_path / "res").glob("*/DONE.json")}

    queue.main(["run", "--section", "gpu", *args])
    assert done() == {"g"}
    queue.main(["run", "--section", "gpu", "--only", "c", *args])  # a GPU session takes over a CPU job
    assert done() == {"c", "g"}
    jobs = queue.load_jobs(file)
    assert [job.id for job in queue.chosen_jobs(jobs, ["g", "c"])] == ["g", "c"]  # the order --only names them
    with pytest.raises(SystemExit, match="no job 'typo'"):
        queue.main(["run", "--only", "c", "typo", *args])


def test_max_minutes_is_the_time_of_the_whole_call(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A job that ends early leaves the rest of ``--max-minutes`` to the next one, which is stopped at the call's
    limit (not a full limit of its own); a job left without time is not started."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    job = (
        '[[job]]\nid = "{id}"\nsection = "gpu"\nwhat = "x"\ncommand = "python -c \\"import time; time.sleep({s})\\""\n'
    )
    file.write_text(job.format(id="short", s=3) + job.format(id="long", s=30) + job.format(id="third", s=0))
    args = ["--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    start = time.monotonic()
    with pytest.raises(SystemExit):
        queue.main(["run", "--section", "gpu", "--max-minutes", "0.1", *args])
    assert time.monotonic() - start < 8  # 6 s in all; a limit per job would stop "long" after 3 + 6 s
    assert (tmp_path / "res" / "short" / "DONE.json").is_file()
    assert "queue: long: stopped at the time limit" in capsys.readouterr().out
    assert not (tmp_path / "res" / "long" / "DONE.json").exists() and not (tmp_path / "res" / "third").exists()
    with pytest.raises(SystemExit):
        queue.main(["run", "--section", "gpu", "--max-minutes", "0", "--only", "third", *args])
    assert "queue: third: no time left" in capsys.readouterr().out


def test_smoke_runs_a_converge_learning_curve_through_the_queue(capsys: pytest.CaptureFixture[str]) -> None:
    load("train_queue").main(["--smoke"])
    out = capsys.readouterr().out
    assert "smoke" in out and " done " in out


def _queue(folder: Path, command: str) -> Path:
    file = folder / "other.toml"
    file.write_text(f'[[job]]\nid = "o"\nsection = "cpu"\nwhat = "x"\ncommand = "{command}"\n')
    return file


def test_an_lcreg_job_runs_the_interpreters_lcreg_and_its_results_are_copied(tmp_path: Path) -> None:
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    command = "lcreg reproduce ablation --budget smoke --seeds 0 --only paper/model_A --out {runs}"
    file.write_text(f'[[job]]\nid = "abl"\nsection = "cpu"\nwhat = "x"\ncommand = "{command}"\n')
    (job,) = queue.load_jobs(file)
    assert job.executable(tmp_path, tmp_path)[:2] == [sys.executable, "-c"]
    assert job.executable(tmp_path, tmp_path, jobs=4)[-2:] == ["--jobs", "4"]  # several runs at once (a GPU)
    (curves,) = queue.load_jobs(_queue(tmp_path, "python benchmarks/learning_curves.py --smoke"))
    assert curves.executable(tmp_path, tmp_path, jobs=4)[-2:] == ["--jobs", "4"]
    (other,) = queue.load_jobs(_queue(tmp_path, "python benchmarks/lc_gradient_share.py --smoke"))
    assert "--jobs" not in other.executable(tmp_path, tmp_path, jobs=4)  # only the sweeps and learning curves
    queue.main(["run", "--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")])
    copied = tmp_path / "res" / "abl" / "runs"
    assert (copied / "ablation.jsonl").is_file() and (copied / "ablation.md").is_file()
    assert not list(copied.rglob("*.pt")) and not list(copied.rglob("*.ckpt"))  # weights stay in the run folder


def test_copied_results_are_not_ignored_by_git() -> None:
    """Before: `.gitignore`'s `runs/` hid every copied result folder, so nothing the queue copied could be committed."""
    import shutil
    import subprocess

    repo = BENCHMARKS.parent
    if shutil.which("git") is None or not (repo / ".git").exists():
        pytest.skip("not a git checkout")
    copied = [
        "docs/results/converge/job/runs/runs.jsonl",
        "docs/results/converge/job/runs/runs/converge/lc/idam_LC/seed0/run/metrics.csv",  # a reproduce sweep's rows
    ]
    result = subprocess.run(["git", "check-ignore", *copied], cwd=repo, capture_output=True, text=True)
    assert result.returncode == 1 and not result.stdout, f"ignored: {result.stdout}"
    weights = subprocess.run(["git", "check-ignore", "docs/results/converge/job/runs/x/best.ckpt"], cwd=repo)
    assert weights.returncode == 0  # checkpoints stay out


def test_a_new_machine_restores_finished_runs_from_the_committed_results(tmp_path: Path) -> None:
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    # The job appends one row per call to its runs.jsonl, as the scripts do for each finished run.
    append = "import pathlib; p = pathlib.Path('{runs}'); p.mkdir(parents=True, exist_ok=True); "
    append += "f = p / 'runs.jsonl'; f.write_text((f.read_text() if f.exists() else '') + 'row\\\\n'); "
    append += "raise SystemExit(1)"
    file.write_text(f'[[job]]\nid = "long"\nsection = "cpu"\nwhat = "x"\ncommand = "python -c \\"{append}\\""\n')
    args = ["--queue", str(file), "--results", str(tmp_path / "res")]
    for machine in ("first", "second"):  # each session's run folders are new; the results folder is committed
        with pytest.raises(SystemExit):
            queue.main(["run", "--runs", str(tmp_path / machine), *args])
    assert (tmp_path / "second" / "long" / "runs.jsonl").read_text() == "row\nrow\n"
    assert (tmp_path / "res" / "long" / "runs" / "runs.jsonl").read_text() == "row\nrow\n"


def test_a_job_on_two_machines_keeps_the_rows_of_both(tmp_path: Path) -> None:
    """A job running here and, in chunks, on a lent GPU: the GPU's rows, unpacked into the results, survive this
    machine's next sync, and come back into this run folder when the job restarts (not trained again)."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    here, committed = runs / "j" / "lc.jsonl", res / "j" / "runs" / "lc.jsonl"
    here.parent.mkdir(parents=True)
    here.write_text('{"run": "cpu 0"}\n{"run": "both"}\n')
    committed.parent.mkdir(parents=True)
    committed.write_text('{"run": "both"}\n{"run": "gpu 0"}\n{"run": "gpu 1"}\n')  # the GPU chunk's, unpacked
    queue.sync(job, runs, res)
    rows = '{"run": "cpu 0"}\n{"run": "both"}\n{"run": "gpu 0"}\n{"run": "gpu 1"}\n'
    assert committed.read_text() == rows
    here.write_text('{"run": "cpu 0"}\n')  # e.g. the run folder of a session that began before the GPU's rows
    assert queue.restore(job, runs, res) == 1
    assert here.read_text() == '{"run": "cpu 0"}\n{"run": "both"}\n{"run": "gpu 0"}\n{"run": "gpu 1"}\n'
    assert queue.restore(job, runs, res) == 0  # nothing new: the file is left alone
    assert queue.merged_rows(here, here) == here.read_text()


def test_a_keep_best_job_keeps_the_selected_weights_of_each_finished_run(tmp_path: Path) -> None:
    """Run folders need not outlive a session: ``keep_best`` exports each finished run's selected checkpoint beside
    the committed logs, once, loadable by ``lcreg.pretrained`` with the checkpoint's weights."""
    import torch

    import lcreg
    from lcreg.checkpoints import read_checkpoint
    from lcreg.weights import read_weights

    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text(queue.SMOKE_QUEUE.replace("cpu_hours = 0.01", "cpu_hours = 0.01\nkeep_best = true"))
    (job,) = queue.load_jobs(file)
    assert job.keep_best
    runs, res = tmp_path / "runs", tmp_path / "res"
    queue.main(["run", "--queue", str(file), "--runs", str(runs), "--results", str(res)])
    rows = [json.loads(line) for line in (runs / "smoke" / "runs.jsonl").read_text().splitlines()]
    kept_files = sorted(p.name for p in (res / "smoke" / "best").iterdir())
    assert kept_files == sorted(f"{r['variant']}-seed{r['seed']}.pt".lower() for r in rows) and len(rows) >= 1
    (row,) = [r for r in rows if r["variant"] == "selfsup"]
    kept = res / "smoke" / "best" / "selfsup-seed0.pt"
    assert not (res / "smoke" / "resume").exists()  # a finished job keeps no resume state
    model = lcreg.pretrained(kept)
    state = read_checkpoint(row["best_checkpoint"])["state_dict"]
    for key, value in model.state_dict().items():
        torch.testing.assert_close(value, state[key], rtol=0, atol=0, msg=key)
    assert json.loads(read_weights(kept).metadata["job_row"]) == row
    before = kept.stat().st_mtime_ns
    Path(row["best_checkpoint"]).unlink()  # a lost run folder: nothing to export, no error, the kept file stays
    assert queue.keep_best(runs / "smoke", res / "smoke" / "best") == []
    assert kept.stat().st_mtime_ns == before


def test_keep_best_keeps_a_sweeps_selected_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An ``lcreg reproduce`` sweep logs each finished run's tested ``selected_weights.pt`` as ``weights``; session 30
    found IDAM's partial-cloud seed 0 gone with its machine before any probe could use it. Kept as
    ``<variant>-seed<k>.pt`` with a file-safe name and the same tensors; weights over the file limit are skipped."""
    import torch

    import lcreg
    from lcreg.baselines.idam import IDAM
    from lcreg.weights.export import save

    queue = load("train_queue")
    source, target = tmp_path / "runs" / "j", tmp_path / "best"
    model = IDAM(emb_dims=8, gnn_channels=(8,), hidden=4, num_iters=1)
    weights = save(model, source / "runs" / "idam_X" / "seed1" / "selected_weights.pt")
    rows = [{"variant": "idam/X", "seed": 1, "weights": str(weights)}, {"variant": "idam/X", "seed": 2}]
    (source / "lc.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    assert queue.keep_best(source, target) == [target / "idam_x-seed1.pt"]
    kept = lcreg.pretrained(target / "idam_x-seed1.pt")
    for key, value in model.state_dict().items():
        torch.testing.assert_close(kept.state_dict()[key], value, rtol=0, atol=0, msg=key)
    assert queue.keep_best(source, target) == []  # kept once
    # Session 53: a later run of the same variant and seed at another budget (a changed lr) was never kept, since the
    # first run's file had its name.
    later = save(model, source / "runs" / "idam_X_key1" / "seed1" / "selected_weights.pt")
    rows.append({"variant": "idam/X", "seed": 1, "budget": "lr 0.0003", "weights": str(later)})
    (source / "lc.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    (kept_later,) = queue.keep_best(source, target)
    assert kept_later.name.startswith("idam_x-seed1-key") and queue.keep_best(source, target) == []
    (target / "idam_x-seed1.pt").unlink()
    kept_later.unlink()
    import lcreg.weights.export as export_module

    monkeypatch.setattr(export_module, "MAX_FILE_BYTES", 100)
    assert queue.keep_best(source, target) == [] and not (target / "idam_x-seed1.pt").exists()


@pytest.mark.parametrize("kind", ["val", "test"])
def test_a_job_with_a_follow_up_command_runs_it_on_each_finished_run_once(tmp_path: Path, kind: str) -> None:
    """Weights too large to keep (iPCRNet's) are lost with the run folder, and a rule reads a measurement of each run's
    selected weights (its fixed point): ``test_command`` / ``val_command`` runs once per finished run at a sync, on its
    selected checkpoint, and what it writes under ``test/`` / ``val/`` is kept; a failing command is retried."""
    queue = load("train_queue")
    writer = "import sys, pathlib; pathlib.Path(sys.argv[2] + '.md').write_text(sys.argv[1])"
    file = tmp_path / "q.toml"
    file.write_text(
        queue.SMOKE_QUEUE.replace(
            "cpu_hours = 0.01", f'cpu_hours = 0.01\n{kind}_command = """python -c "{writer}" {{checkpoint}} {{out}}"""'
        )
    )
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    queue.main(["run", "--queue", str(file), "--runs", str(runs), "--results", str(res)])
    rows = [json.loads(line) for line in (runs / "smoke" / "runs.jsonl").read_text().splitlines()]
    outputs = res / "smoke" / kind
    expected = sorted(f"{r['variant']}-seed{r['seed']}.md".lower() for r in rows)
    assert sorted(p.name for p in outputs.iterdir()) == expected
    assert not (res / "smoke" / ({"val", "test"} - {kind}).pop()).exists()
    (row,) = [r for r in rows if r["variant"] == "selfsup"]
    assert (outputs / "selfsup-seed0.md").read_text() == row["best_checkpoint"]
    before = (outputs / "selfsup-seed0.md").stat().st_mtime_ns
    assert queue.keep_follow_ups(job, kind, runs / "smoke", outputs) == []  # run once
    assert (outputs / "selfsup-seed0.md").stat().st_mtime_ns == before
    failing = dataclasses.replace(job, **{f"{kind}_command": 'python -c "import sys; sys.exit(3)" {checkpoint} {out}'})
    (outputs / "selfsup-seed0.md").unlink()
    assert queue.keep_follow_ups(failing, kind, runs / "smoke", outputs) == []
    assert not (outputs / "selfsup-seed0.md").exists()
    assert queue.keep_follow_ups(job, kind, runs / "smoke", outputs) == [outputs / "selfsup-seed0.md"]  # tried again
    # A variant whose name holds a dot (session 33: recon_mlp_recipe0.1 was measured again at every sync).
    dotted = {**row, "variant": "recon_x0.1"}
    with (runs / "smoke" / "runs.jsonl").open("a") as log:
        log.write(json.dumps(dotted) + "\n")
    assert queue.keep_follow_ups(job, kind, runs / "smoke", outputs) == [outputs / "recon_x0.1-seed0.md"]
    (outputs / "recon_x0.1-seed0.md").write_text("kept")
    assert queue.keep_follow_ups(job, kind, runs / "smoke", outputs) == []
    assert (outputs / "recon_x0.1-seed0.md").read_text() == "kept"  # not measured again


def test_sync_keeps_the_run_in_progress_so_that_a_new_machine_resumes_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The folders of the runs in progress are kept (not a finished run's: its row names it; session 30 found that
    only the newest was kept while a ``jobs = 2`` runner trained two), they replace the previous copy, they come back
    into an empty run folder before the job starts, and a done job or an oversized folder keeps nothing."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    for seed in range(3):
        folder = runs / "j" / "a" / f"seed{seed}" / "checkpoints"
        folder.mkdir(parents=True)
        for name in ("last.ckpt", "step000100-val.ckpt"):
            (folder / name).write_bytes(f"{name} {seed}".encode())
    row = {"variant": "a", "seed": 0, "metrics_csv": "/elsewhere/runs/j/a/seed0/metrics.csv"}  # another machine's
    (runs / "j" / "runs.jsonl").write_text(json.dumps(row) + "\n")
    queue.sync(job, runs, res)
    kept = res / "j" / "resume"
    assert sorted(p.relative_to(kept).as_posix() for p in kept.rglob("*.ckpt")) == [
        f"a/seed{seed}/checkpoints/{name}" for seed in (1, 2) for name in ("last.ckpt", "step000100-val.ckpt")
    ]
    fresh = tmp_path / "fresh"  # a new machine: an empty run folder
    queue.sync(job, fresh, res)  # a sync there before `run` must not drop the kept copy
    assert queue.restore(job, fresh, res) == 5  # four checkpoints and the JSONL log
    assert (fresh / "j" / "a" / "seed2" / "checkpoints" / "last.ckpt").read_bytes() == b"last.ckpt 2"
    monkeypatch.setattr(queue, "RESUME_MAX_BYTES", 40)  # seed 1: 32 bytes
    (runs / "j" / "a" / "seed2" / "checkpoints" / "last.ckpt").write_bytes(b"x" * 20)  # seed 2's folder grows
    queue.sync(job, runs, res)  # too large (e.g. DeepGMR): not kept, where seed 1's small folder still is
    assert sorted(p.relative_to(kept).as_posix() for p in kept.rglob("*.ckpt")) == [
        "a/seed1/checkpoints/last.ckpt",
        "a/seed1/checkpoints/step000100-val.ckpt",
    ]
    monkeypatch.setattr(queue, "RESUME_MAX_BYTES", 10)
    # Every last.ckpt alone is over the limit now: none is read (a DVDs last.ckpt is 11 MB against 8 MB).
    monkeypatch.setattr(queue, "resume_files", lambda folder: pytest.fail(f"read {folder}"))
    queue.sync(job, runs, res)  # no folder small enough: the earlier copy goes
    assert not kept.exists()
    monkeypatch.undo()
    queue.sync(job, runs, res)
    (res / "j" / "DONE.json").write_text("{}\n")
    queue.sync(job, runs, res)
    assert not kept.exists()


def test_a_done_job_keeps_the_resume_state_of_the_runs_its_cap_cut_off(tmp_path: Path) -> None:
    """Session 56: a capped run's state (kept by the sweep, its row says so) is committed and restored, so that a higher
    cap can continue it on a new machine (`lcreg reproduce --continue-from`); nothing else of a done job is kept."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    for seed in (0, 2):  # seed 0 reached its cap, seed 2 trains
        folder = runs / "j" / "a" / f"seed{seed}" / "run" / "checkpoints"
        folder.mkdir(parents=True)
        for name in ("last.ckpt", "step000100-val.ckpt"):
            (folder / name).write_bytes(f"{name} {seed}".encode())
    rows = [
        {"seed": seed, "metrics_csv": f"/elsewhere/runs/j/a/seed{seed}/run/metrics.csv", "weights": "w.pt"}
        | ({"selected": "step000100-val.ckpt", "kept_resume_state": True} if seed == 0 else {})
        for seed in (0, 1)  # seed 1 stopped early: no checkpoints
    ]
    (runs / "j" / "lc.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    kept = res / "j" / "resume"

    def kept_runs() -> list[str]:
        return sorted({p.relative_to(kept).parent.parent.as_posix() for p in kept.rglob("*.ckpt")})

    queue.sync(job, runs, res)
    assert kept_runs() == ["a/seed0/run", "a/seed2/run"]
    (runs / "j" / "a" / "seed2" / "run" / "checkpoints" / "last.ckpt").unlink()  # seed 2 done (stopped early)
    (res / "j" / "DONE.json").write_text("{}\n")
    queue.sync(job, runs, res)
    assert kept_runs() == ["a/seed0/run"]
    for path in (runs / "j" / "a" / "seed0" / "run" / "checkpoints").iterdir():  # a sync after the state went
        path.unlink()
    queue.sync(job, runs, res)
    assert kept_runs() == ["a/seed0/run"]  # the row still says it was kept: the copy stays
    fresh = tmp_path / "fresh"
    queue.sync(job, fresh, res)  # a new machine before restore
    queue.restore(job, fresh, res)
    assert (fresh / "j" / "a" / "seed0" / "run" / "checkpoints" / "last.ckpt").read_bytes() == b"last.ckpt 0"


def test_sync_drops_the_committed_copies_of_metrics_a_restarted_run_set_aside(tmp_path: Path) -> None:
    """A run whose checkpoints were lost starts again and moves its old metrics to ``abandoned/1/``; the committed
    copies of the moved files go too, else the next report (or machine) reads them as segments of the new curve."""
    from lcreg.resume import set_aside_metrics

    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    run_dir = runs / "j" / "a" / "seed2"
    run_dir.mkdir(parents=True)
    for name in ("metrics.segment1.csv", "metrics.csv"):
        (run_dir / name).write_text(f"old {name}\n")
    queue.sync(job, runs, res)  # the committed state of the lost run
    committed = res / "j" / "runs" / "a" / "seed2"
    assert (committed / "metrics.segment1.csv").is_file()
    assert set_aside_metrics(run_dir) == run_dir / "abandoned" / "1"
    (run_dir / "metrics.csv").write_text("new\n")  # the run started again
    queue.sync(job, runs, res)
    assert sorted(p.relative_to(committed).as_posix() for p in committed.rglob("*.csv")) == [
        "abandoned/1/metrics.csv",
        "abandoned/1/metrics.segment1.csv",
        "metrics.csv",
    ]
    assert (committed / "metrics.csv").read_text() == "new\n"
    assert (committed / "abandoned" / "1" / "metrics.segment1.csv").read_text() == "old metrics.segment1.csv\n"
    assert set_aside_metrics(tmp_path / "empty") is None


def test_only_the_checkpoints_the_run_resumes_from_are_kept(tmp_path: Path) -> None:
    """``last.ckpt`` and the selected checkpoint its callback state names; a checkpoint selected on an earlier machine
    and restored with the kept copy is unknown to the callback and stays behind (session 30: two such copies)."""
    import torch

    queue = load("train_queue")
    folder = tmp_path / "runs" / "j" / "a" / "seed0" / "checkpoints"
    folder.mkdir(parents=True)
    state = {"best_model_path": "/another/machine/runs/j/a/seed0/checkpoints/step000200-val.ckpt"}
    callbacks = {"EarlyStopping{'monitor': 'val/x'}": {}, "ModelCheckpoint{'monitor': 'val/x'}": state}
    torch.save({"state_dict": {}, "callbacks": callbacks}, folder / "last.ckpt")
    for name in ("step000100-val.ckpt", "step000200-val.ckpt"):  # the first: an earlier machine's selection
        (folder / name).write_bytes(b"weights")
    assert queue.resume_files(folder) == [folder / "last.ckpt", folder / "step000200-val.ckpt"]
    kept = tmp_path / "res" / "resume"
    assert sorted(p.name for p in queue.keep_resume(tmp_path / "runs" / "j", kept)) == [
        "last.ckpt",
        "step000200-val.ckpt",
    ]
    (folder / "last.ckpt").write_bytes(b"damaged")  # unreadable: every checkpoint is kept, as before
    assert len(queue.resume_files(folder)) == 3


def test_a_sweep_run_training_again_in_a_finished_runs_folder_is_in_progress(tmp_path: Path) -> None:
    """A sweep's row for another budget names the same folder (variant and seed), but a finished sweep run leaves
    no checkpoint: with a ``last.ckpt`` there, the folder's run is training and its resume state is kept."""
    import torch

    queue = load("train_queue")
    source = tmp_path / "runs" / "j"
    run = source / "runs" / "converge" / "lc" / "prnet_LC" / "seed0" / "run"
    row = {"variant": "prnet/LC", "seed": 0, "weights": f"{run.parent}/selected_weights.pt"}
    (source / "runs").mkdir(parents=True)
    (source / "runs" / "lc.jsonl").write_text(
        json.dumps({**row, "metrics_csv": f"/elsewhere/j/{run.relative_to(source)}/metrics.csv"}) + "\n"
    )
    folder = run.relative_to(source).as_posix()
    assert queue.finished_runs(source) == {folder}  # finished: its checkpoints are gone
    (run / "checkpoints").mkdir(parents=True)
    torch.save({"callbacks": {}}, run / "checkpoints" / "last.ckpt")  # the run of the new budget, in training
    assert queue.finished_runs(source) == set()
    assert [p.name for p in queue.keep_resume(source, tmp_path / "kept")] == ["last.ckpt"]
    (source / "runs" / "curves.jsonl").write_text(
        json.dumps({"best_checkpoint": "x", "metrics_csv": f"/m/j/{folder}/metrics.csv"}) + "\n"
    )
    assert queue.finished_runs(source) == {folder}  # a learning_curves.py row keeps its checkpoints: finished


def test_a_finished_sweep_runs_restored_resume_state_does_not_make_it_a_run_in_progress(tmp_path: Path) -> None:
    """Session 49: a sync kept a sweep run's resume state while it trained; it finished (its row written, its
    checkpoints deleted) on that machine, and a new machine restored the kept copy. With the row's selected checkpoint
    among them, the folder's checkpoints are that finished run's: it is not training, and no sync keeps them again."""
    import torch

    queue = load("train_queue")
    source = tmp_path / "runs" / "j"
    run = source / "runs" / "converge" / "lc" / "idam_X" / "seed0" / "run"
    selected = "step004400-val_rre_clip5_deg1.4251.ckpt"
    row = {"variant": "idam/X", "seed": 0, "weights": f"{run.parent}/selected_weights.pt", "selected": selected}
    (run / "checkpoints").mkdir(parents=True)
    (source / "lc.jsonl").write_text(json.dumps({**row, "metrics_csv": f"/m/j/{run.relative_to(source)}/metrics.csv"}))
    torch.save({"callbacks": {}}, run / "checkpoints" / "last.ckpt")
    assert queue.finished_runs(source) == set()  # another budget's run training in the folder (session 38)
    torch.save({"callbacks": {}}, run / "checkpoints" / selected)  # the restored copy of the run's own state
    assert queue.finished_runs(source) == {run.relative_to(source).as_posix()}
    kept = tmp_path / "kept"
    (kept / "old").mkdir(parents=True)
    assert queue.keep_resume(source, kept) == [] and not (kept / "old").exists()  # the stale copy goes


def test_restore_does_not_bring_back_metrics_a_restarted_run_set_aside(tmp_path: Path) -> None:
    """Session 30: a new machine restarted a run from scratch (its old metrics moved to ``abandoned/1/``), then the
    runner was restarted before any sync; ``restore`` copied the committed old files back beside the new run's, so
    its curve began with the lost run's steps. A committed file equal to a set-aside copy stays out; a committed
    file of the same name with other bytes (a later segment of the new run, from another machine) comes back."""
    from lcreg.resume import set_aside_metrics

    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    committed = res / "j" / "runs" / "a" / "seed1"
    committed.mkdir(parents=True)
    for name in ("metrics.segment1.csv", "metrics.csv"):
        (committed / name).write_text(f"lost run's {name}\n")
    assert queue.restore(job, runs, res) == 2  # a new machine: the lost run's files come back ...
    run_dir = runs / "j" / "a" / "seed1"
    set_aside_metrics(run_dir)  # ... and the run, without checkpoints, starts again and moves them aside
    (run_dir / "metrics.csv").write_text("new run\n")
    assert queue.restore(job, runs, res) == 0  # the runner restarts before a sync
    assert sorted(p.name for p in run_dir.glob("metrics*.csv")) == ["metrics.csv"]
    (committed / "metrics.segment1.csv").write_text("new run, first segment, from another machine\n")
    assert queue.restore(job, runs, res) == 1
    assert (run_dir / "metrics.segment1.csv").read_text() == "new run, first segment, from another machine\n"


def test_sync_keeps_a_report_regenerated_here_over_the_run_folders_older_copy(tmp_path: Path) -> None:
    """A report rebuilt in the results (``--report-only``, with the rows another machine added) is newer than the one
    the run folder wrote earlier; sync keeps it (session 19 found an 18-run report replaced by a stale 9-run one),
    and copies the run folder's files again once they change."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    runs, res = tmp_path / "runs", tmp_path / "res"
    (runs / "j" / "a").mkdir(parents=True)
    stale, metrics = runs / "j" / "lc.md", runs / "j" / "a" / "metrics.csv"
    stale.write_text("4 of 9 runs\n")
    metrics.write_text("step\n1\n")
    queue.sync(job, runs, res)
    report = res / "j" / "runs" / "lc.md"
    report.write_text("18 of 18 runs\n")  # regenerated here, later
    later = stale.stat().st_mtime_ns + 10**9
    os.utime(report, ns=(later, later))
    queue.sync(job, runs, res)
    assert report.read_text() == "18 of 18 runs\n"
    metrics.write_text("step\n1\n2\n")  # the run goes on: its newer file is copied
    os.utime(metrics, ns=(later + 10**9, later + 10**9))
    queue.sync(job, runs, res)
    assert (res / "j" / "runs" / "a" / "metrics.csv").read_text() == "step\n1\n2\n"


def test_a_job_held_by_another_runner_is_skipped_and_the_next_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: two runners whose `--only` lists shared a job could both train it into one run folder."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    jobs = [f'[[job]]\nid = "{name}"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n' for name in ("held", "free")]
    file.write_text("\n".join(jobs))
    held, _ = queue.load_jobs(file)
    args = ["run", "--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    with queue.job_lock(held, tmp_path / "runs") as fd:
        assert fd is not None
        with queue.job_lock(held, tmp_path / "runs") as second:
            assert second is None  # one holder at a time, within a process too
        assert queue.holder(held, tmp_path / "runs") == os.getpid()
        assert f"running, pid {os.getpid()}," in queue.status_line(held, tmp_path / "res", tmp_path / "runs")
        queue.main(args)
    assert "queue: held: another runner holds" in capsys.readouterr().out
    assert not (tmp_path / "res" / "held" / "DONE.json").exists()
    assert (tmp_path / "res" / "free" / "DONE.json").is_file()
    assert queue.holder(held, tmp_path / "runs") is None
    assert "pending (0 result rows)" in queue.status_line(held, tmp_path / "res", tmp_path / "runs")
    queue.main(args)  # released: the next runner takes it
    assert (tmp_path / "res" / "held" / "DONE.json").is_file()


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc to find the runner's job")
def test_the_lock_outlives_a_killed_runner_while_its_job_runs(tmp_path: Path) -> None:
    """The job's process inherits the lock: a runner killed without its child does not free the job."""
    import signal
    import subprocess

    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "slow"\nsection = "cpu"\nwhat = "x"\ncommand = "sleep 30"\n')
    (job,) = queue.load_jobs(file)
    folders = ["--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "res")]
    argv = [sys.executable, str(BENCHMARKS / "train_queue.py"), "run", "--queue", str(file), *folders]
    runner = subprocess.Popen(argv, start_new_session=True)
    try:
        for _ in range(1200):  # the runner has started its job
            if queue.descendants(runner.pid):
                break
            time.sleep(0.1)
        else:
            pytest.fail("the runner did not start its job")
        assert (tmp_path / "runs" / "slow.lock").read_text().strip() == str(runner.pid)
        runner.kill()
        runner.wait()
        with queue.job_lock(job, tmp_path / "runs") as fd:
            assert fd is None  # `sleep 30`, orphaned, still holds it
    finally:
        os.killpg(runner.pid, signal.SIGKILL)
    for _ in range(300):
        with queue.job_lock(job, tmp_path / "runs") as fd:
            if fd is not None:
                break
        time.sleep(0.1)
    assert fd is not None  # released once the job's process is gone


def test_committed_runners_list_known_jobs_once() -> None:
    queue = load("train_queue")
    file = BENCHMARKS / "train_queue.toml"
    jobs = queue.load_jobs(file)
    runners = queue.load_runners(file, jobs)
    assert runners and all(runner.why for runner in runners)
    sections = {job.id: job.section for job in jobs}
    assert all(sections[job] == "cpu" for runner in runners for job in runner.only)  # `start` runs the CPU section


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        ('[[runner]]\nname = "a"\nonly = ["nope"]\n', "unknown ones"),
        ('[[runner]]\nname = "a"\nonly = []\n', "names no job"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\n[[runner]]\nname = "b"\nonly = ["j"]\n', "must be unique"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\ncores = 2\n', "unexpected keyword"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\nthreads = 0\n', "threads must be an integer >= 1"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\njobs = 0\n', "jobs must be an integer >= 1"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\njobs = "2"\n', "jobs must be an integer >= 1"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\nshares = 0\n', "shares must be an integer >= 1"),
        ('[[runner]]\nname = "a"\nonly = ["j"]\nshares = 2.5\n', "shares must be an integer >= 1"),
    ],
)
def test_bad_runner_tables_are_refused(tmp_path: Path, tables: str, message: str) -> None:
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n' + tables)
    with pytest.raises(ValueError, match=message):
        queue.load_runners(file, queue.load_jobs(file))


def test_a_runner_of_n_runs_at_once_gets_n_shares_of_the_cpu() -> None:
    queue = load("train_queue")
    weight = dict(enumerate(queue.SCHED_WEIGHTS))
    assert [queue.group_nice(19, n) for n in (1, 2, 3, 4)] == [19, 16, 14, 13]
    for jobs in (2, 3, 4):  # within the kernel table's step (about 1.25x a niceness) of jobs one-job runners
        assert 0.8 < weight[queue.group_nice(19, jobs)] / (jobs * weight[19]) < 1.25
    assert queue.group_nice(1, 2) == 0  # never below 0
    assert queue.group_nice(5, 1) == 5
    # A runner's shares (the queue file's priorities) replace its jobs as the weight: 22 shares is niceness 5.
    assert queue.runner_nice(queue.Runner("r", ("j",), jobs=3)) == queue.group_nice(19, 3)
    assert queue.runner_nice(queue.Runner("r", ("j",), jobs=3, shares=22)) == 5
    assert queue.runner_nice(queue.Runner("r", ("j",), shares=1)) == 19


def sleeping_runners(tmp_path: Path, two_jobs: int) -> tuple[Path, Path, list[str]]:
    """A queue of three sleeping jobs: runner "one" runs a then b, runner "two" (``jobs = two_jobs``, twice as many
    shares, two threads) runs c.

    Returns:
        The queue file, the runs folder and the arguments of ``start``/``stop`` for them.
    """
    file = tmp_path / "q.toml"
    sleep = "python -c 'import time; time.sleep(900)'"  # outlives a slow start on a busy machine; stopped by the test
    jobs = [f'[[job]]\nid = "{n}"\nsection = "cpu"\nwhat = "x"\ncommand = "{sleep}"\n' for n in ("a", "b", "c")]
    runners = '[[runner]]\nname = "one"\nonly = ["a", "b"]\n'
    runners += f'[[runner]]\nname = "two"\nonly = ["c"]\njobs = {two_jobs}\nshares = {2 * two_jobs}\nthreads = 2\n'
    file.write_text("\n".join(jobs) + runners)
    runs, res = tmp_path / "runs", tmp_path / "res"
    args = ["--queue", str(file), "--runs", str(runs), "--results", str(res), "--checkout", str(BENCHMARKS.parent)]
    return file, runs, args


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc to find the runners")
def test_start_launches_the_runners_and_stop_ends_them_with_their_jobs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`start` runs each runner detached from this process (its own log); `stop` ends runner and training process."""
    queue = load("train_queue")
    monkeypatch.setattr(queue, "GROUP_NICE", 1)  # set, but not so low that a busy test machine starves the runners
    file, runs, args = sleeping_runners(tmp_path, two_jobs=2)
    queue.main(["start", *args])
    try:
        own = os.getpriority(os.PRIO_PROCESS, 0)

        def niceness(pid: int) -> int | None:
            with contextlib.suppress(ProcessLookupError):
                return os.getpriority(os.PRIO_PROCESS, pid)
            return None  # exited meanwhile

        def started(pid: int) -> bool:  # its training process exists and `nice -n 5` has applied (a busy machine
            children = queue.descendants(pid)  # may show it between the fork and the exec of `nice`)
            return bool(children) and all(niceness(c) in (min(own + 15, 19), None) for c in children)

        for _ in range(1200):  # both runners have started their first job
            pids = queue.runner_pids(runs)
            if len(pids) == 2 and all(map(started, pids)):
                break
            time.sleep(0.1)
        else:
            nice = {pid: [niceness(c) for c in queue.descendants(pid)] for pid in queue.runner_pids(runs)}
            logs = [p.read_text() for p in runs.glob("logs/*")]
            pytest.fail(f"runners and their children's niceness: {nice}; logs: {logs}")
        assert {p.name for p in (runs / "logs").iterdir()} == {"one.log", "two.log"}
        argvs = [Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") for pid in pids]
        assert sorted(b"--jobs" in argv for argv in argvs) == [False, True]  # runner "two" runs 2 runs at once
        assert all(argv[argv.index(b"--jobs") + 1] == b"2" for argv in argvs if b"--jobs" in argv)
        assert [argv[argv.index(b"--threads") + 1] if b"--threads" in argv else None for argv in argvs] in (
            [None, b"2"],
            [b"2", None],
        ) and all((b"--threads" in argv) == (b"--jobs" in argv) for argv in argvs)  # runner "two" only
        assert all(argv[argv.index(b"--sync-every") + 1] == b"10" and b"--commit" not in argv for argv in argvs)
        for pid, argv in zip(pids, argvs, strict=True):  # the runner nice 10, its training 5 more: the session's
            assert os.getpriority(os.PRIO_PROCESS, pid) == min(own + queue.RUNNER_NICE, 19)  # own work comes first
            assert all(niceness(c) in (min(own + 15, 19), None) for c in queue.descendants(pid))
            if Path("/proc/self/autogroup").is_file():  # sessions are shared first: the runner's session is niced too,
                group = str(queue.group_nice(1, 4) if b"--jobs" in argv else 1)  # two runs at once, four shares
                assert Path(f"/proc/{pid}/autogroup").read_text().split()[-1] == group
        assert {queue.holder(job, runs) for job in queue.load_jobs(file)} == {*pids, None}  # a and c run, b waits
        with pytest.raises(SystemExit, match="running already"):
            queue.main(["start", *args])
    finally:
        signalled = queue.stop_runners(runs, grace_s=10)
    assert len(signalled) >= 4  # two runners and their two training processes
    assert queue.runner_pids(runs) == [] and not any(map(queue.alive, signalled))
    assert all(queue.holder(job, runs) is None for job in queue.load_jobs(file))


def test_start_fails_when_a_runner_ends_with_an_error_at_once(tmp_path: Path) -> None:
    """Session 56: a runner started from a half-made worktree died at once, unseen until `progress` 8 minutes later."""
    queue = load("train_queue")
    _, runs, args = sleeping_runners(tmp_path, two_jobs=1)
    args[args.index("--checkout") + 1] = str(tmp_path / "empty")  # no benchmarks/train_queue.py there
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match=r"runner one ended at once \(exit code 2\)") as err:
        queue.main(["start", *args])
    assert "can't open file" in str(err.value) and "runner two ended at once" in str(err.value)
    assert queue.runner_pids(runs) == []


def test_two_starts_at_once_both_get_the_whole_worktree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A second `start` while the first checks out the worktree waits for it, not runs a half-made tree."""
    queue = load("train_queue")
    repo = tmp_path / "repo"
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / "benchmarks").mkdir()
    (repo / "benchmarks" / "train_queue.py").write_text("print()\n")
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "queue"], check=True)
    sha = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True).stdout
    (tmp_path / f"wt-queue-{sha.strip()}.partial").mkdir()  # a killed `start`'s leftover
    (tmp_path / f"wt-queue-{sha.strip()}.partial" / "junk").write_text("")
    monkeypatch.setattr(queue, "REPO", repo)
    checking_out, go = threading.Event(), threading.Event()
    real_run = subprocess.run

    def slow_checkout(cmd: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
        if cmd[3:5] == ["worktree", "add"]:  # git makes the folder, then fills it
            Path(cmd[-2]).mkdir()
            checking_out.set()
            go.wait(30)
        return real_run(cmd, **kwargs)  # type: ignore[call-overload]

    monkeypatch.setattr(queue.subprocess, "run", slow_checkout)
    got: list[tuple[Path, bool]] = []

    def start() -> None:
        tree = queue.queue_worktree()
        got.append((tree, (tree / "benchmarks" / "train_queue.py").is_file()))

    first, second = threading.Thread(target=start), threading.Thread(target=start)
    first.start()
    assert checking_out.wait(30)
    second.start()
    second.join(1.0)  # it must not return while the first checks out
    go.set()
    first.join(30)
    second.join(30)
    assert got == [(tmp_path / f"wt-queue-{sha.strip()}", True)] * 2
    assert not (tmp_path / f"wt-queue-{sha.strip()}.partial").exists()


def test_runs_tabulates_each_finished_runs_stop_and_selected_step_under_its_budget(tmp_path: Path) -> None:
    """Both row schemas: ``learning_curves.py`` (stop in ``stopped_step``, the selection only in the checkpoint's
    name, its monitor in the budget) and ``lcreg reproduce`` (``steps``, ``selected_on``, ``best_val``); a job's rows
    of an earlier rule keep their own table. ``sync`` writes the same table to ``<results>/runs.md``."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text(
        '[[job]]\nid = "curves"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n'
        '[[job]]\nid = "sweep"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n'
    )
    res = tmp_path / "res"
    curves = [
        {"variant": "fmr", "seed": 1, "points": 1024, "steps": 3000, "budget": "converge p12 v4 mval/rre_median_deg",
         "best_checkpoint": "/gone/step002350-val_rre_median_deg0.3769.ckpt", "seconds": 19722.4,
         "stopped_step": 2950, "early_stopped": True},
        {"variant": "pcr", "seed": 0, "points": 1024, "steps": 3000, "budget": "converge p6 v4 min3000",
         "best_checkpoint": "/gone/step003000-val_rre_clip5_deg10.5000.ckpt", "seconds": 5.0,
         "stopped_step": 3000, "early_stopped": False},
    ]  # fmt: skip
    sweep = [
        {"variant": "prnet/X", "seed": 0, "budget": "B1", "steps": 650, "stopped_early": True, "train_s": 270.0,
         "selected": "step000050-val_rre_median_deg3.3750.ckpt", "selected_on": "val/rre_median_deg",
         "best_val": 3.375, "num_points": 256},
        {"variant": "prnet/X", "seed": 0, "budget": "B1, lr 0.00022", "steps": 3000, "stopped_early": False,
         "train_s": 900.0, "selected": "step002900-val_rre_median_deg1.6800.ckpt",
         "selected_on": "val/rre_median_deg", "best_val": 1.68, "num_points": 256},
        {"variant": "idam/X", "seed": 0, "budget": "5016 steps × 8 pairs; set trainer.max_steps=2508", "steps": 1848,
         "stopped_early": True, "train_s": 3411.5, "selected": "step001496-val_rre_clip5_deg3.9651.ckpt",
         "selected_on": "val/rre_clip5_deg", "best_val": 3.965, "num_points": 512},
    ]  # fmt: skip
    for job, name, rows in (("curves", "runs.jsonl", curves), ("sweep", "lc.jsonl", sweep)):
        (res / job / "runs").mkdir(parents=True)
        (res / job / "runs" / name).write_text("".join(json.dumps(row) + "\n" for row in rows))
    table = queue.runs_table(queue.load_jobs(file), res)
    sections = table.split("\n## ")[1:]
    assert [s.splitlines()[0] for s in sections] == [
        "`curves`: converge p12 v4 mval/rre_median_deg",
        "`curves`: converge p6 v4 min3000",
        "`sweep`: B1",
        "`sweep`: B1, lr 0.00022",
        "`sweep`: 5016 steps × 8 pairs; set on every run, replacing the budget's values of these keys: "
        "trainer.max_steps=2508",
    ]
    rows = [s.splitlines()[-1] for s in sections]
    assert rows[0] == "| fmr | 1 | 1024 | 2,950 | early stop | 2,350 | `val/rre_median_deg` | 0.3769 | 19,722 |"
    assert rows[1] == "| pcr | 0 | 1024 | 3,000 | step cap | 3,000 | `val/rre_clip5_deg` | 10.5 | 5 |"
    assert rows[2] == "| prnet/X | 0 | 256 | 650 | early stop | 50 | `val/rre_median_deg` | 3.375 | 270 |"
    assert rows[3] == "| prnet/X | 0 | 256 | 3,000 | step cap | 2,900 | `val/rre_median_deg` | 1.68 | 900 |"
    queue.main(["sync", "--queue", str(file), "--runs", str(tmp_path / "runs"), "--results", str(res)])
    assert (res / "runs.md").read_text() == table
    out = tmp_path / "runs.md"
    queue.main(["runs", "--queue", str(file), "--results", str(res), "--out", str(out)])
    assert out.read_text() == table


def test_runs_reads_a_raised_step_cap_from_the_rows_overrides() -> None:
    """``--set trainer.max_steps=7040``: a run stopped at 6,776 stopped early (its row, of before session 44, says
    not: it compared with the budget's 5,016 steps)."""
    queue = load("train_queue")
    row = {"variant": "idam/X", "seed": 1, "num_points": 512, "steps": 6776, "stopped_early": False,
           "overrides": {"trainer.max_steps": 7040}, "selected": "step006072-val_rre_clip5_deg2.8104.ckpt",
           "selected_on": "val/rre_clip5_deg", "best_val": 2.8104, "train_s": 5253.4}  # fmt: skip
    line = "| idam/X | 1 | 512 | 6,776 | early stop | 6,072 | `val/rre_clip5_deg` | 2.81 | 5,253 |"
    assert queue.run_line(row) == line
    assert "| 7,040 | step cap |" in queue.run_line({**row, "steps": 7040})


def test_progress_shows_each_run_training_now_with_its_last_and_best_validation(tmp_path: Path) -> None:
    """Over the segments of a resumed run: the last validation and the best so far (the highest recall, the lowest
    errors); a run that has not logged within ``hours``, a run set aside as lost and a finished run (its row in the
    job's log; session 30 saw runs restored from the committed results listed as training) are left out."""
    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    runs = tmp_path / "runs"
    head = "epoch,step,val/rre_median_deg,val/recall_r2_t0p01,train/loss\n"
    live = runs / "j" / "v" / "seed1"
    live.mkdir(parents=True)
    (live / "metrics.segment1.csv").write_text(head + "0,0,2.0,0.5,\n0,10,,,9.0\n0,49,0.5,0.75,\n")
    (live / "metrics.csv").write_text(head + "1,99,0.8,0.7,\n")
    for old in (runs / "j" / "v" / "seed0", runs / "j" / "v" / "seed1" / "abandoned" / "1"):
        old.mkdir(parents=True)
        (old / "metrics.csv").write_text(head + "0,0,9.0,0.0,\n")
    os.utime(runs / "j" / "v" / "seed0" / "metrics.csv", (time.time() - 4 * 3600,) * 2)
    (runs / "j" / "v" / "seed2").mkdir()
    (runs / "j" / "v" / "seed2" / "metrics.csv").write_text(head + "0,0,1.0,0.9,\n")  # restored, recent, finished
    (runs / "j" / "runs.jsonl").write_text(json.dumps({"metrics_csv": "/old/runs/j/v/seed2/metrics.csv"}) + "\n")
    table = queue.progress_table(queue.load_jobs(file), runs, hours=3.0)
    rows = [line for line in table.splitlines()[2:] if line]
    assert len(rows) == 1, table
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[:3] == ["j", "v/seed1", "–"] and cells[4:6] == ["step 99", "–"]  # no config.yaml: no bound
    assert cells[6] == "0.8 @ 99 (best 0.5 @ 49)"  # median RRE: lowest is best
    assert cells[7] == "–"  # clip5 not logged
    assert cells[8] == "0.7 @ 99 (best 0.75 @ 49)"  # recall: highest is best


def test_a_retests_rows_and_logs_are_not_runs_of_the_job(tmp_path: Path) -> None:
    """``lcreg reproduce --retest`` writes ``<stem>.retest-<precision>.jsonl`` beside the sweep's rows (each naming the
    run's weights) and a test log in each run's ``retest-<precision>/`` folder: neither is a finished or a training
    run of the job (status, runs.md, keep_best, progress)."""
    from lcreg.baselines.idam import IDAM
    from lcreg.weights.export import save

    queue = load("train_queue")
    file = tmp_path / "q.toml"
    file.write_text('[[job]]\nid = "j"\nsection = "cpu"\nwhat = "x"\ncommand = "true"\n')
    (job,) = queue.load_jobs(file)
    results, runs = tmp_path / "results", tmp_path / "runs"
    seed = runs / "j" / "runs" / "converge" / "lc" / "idam_X" / "seed0"
    weights = save(IDAM(emb_dims=8, gnn_channels=(8,), hidden=4, num_iters=1), seed / "selected_weights.pt")
    row = {"variant": "idam/X", "seed": 0, "metrics_csv": f"/m/j/{seed.relative_to(runs / 'j')}/run/metrics.csv"}
    retest = {"variant": "idam/X", "seed": 0, "precision": "32-true", "weights": str(weights)}
    for folder in (results / "j" / "runs", runs / "j"):
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "lc.jsonl").write_text(json.dumps(row) + "\n")
        (folder / "lc.retest-32-true.jsonl").write_text(json.dumps(retest) + "\n")
    (seed / "retest-32-true" / "version_0").mkdir(parents=True)
    (seed / "retest-32-true" / "version_0" / "metrics.csv").write_text("epoch,step,test/rmse_r_deg\n0,0,3.0\n")
    assert queue.result_rows(job, results) == [row]
    assert "(1 result rows)" in queue.status_line(job, results)
    assert queue.keep_best(runs / "j", tmp_path / "best") == []  # the sweep's row names no weights here
    assert queue.active_runs(job, runs, hours=3.0) == []


def test_stop_bound_is_where_lightnings_early_stopping_ends_the_run(tmp_path: Path) -> None:
    """The step by which a run stops unless it improves, checked against Lightning's own ``EarlyStopping`` fed the
    same validations: the step-0 validation of the starting weights is its first score
    (``keep_initial_weights_as_candidate``), ``min_delta`` counts, the step cap bounds it."""
    from lightning.pytorch.callbacks import EarlyStopping

    queue = load("train_queue")
    trained = {49: 0.9, 99: 0.7, 149: 0.65, 199: 0.8, 249: 0.66, 299: 0.75, 349: 0.9, 399: 0.9}

    def series(values: dict[int, float], mode: str, delta: float, cap: int) -> dict[str, Series]:
        stopping = {"monitor": "val/m", "mode": mode, "min_delta": delta, "patience": 3}
        callbacks = [{"class_path": "lightning.pytorch.callbacks.EarlyStopping", "init_args": stopping}]
        trainer = {"max_steps": cap, "val_check_interval": 50, "callbacks": callbacks}
        (tmp_path / "config.yaml").write_text(json.dumps({"trainer": trainer}))  # JSON is YAML
        sign = 1.0 if mode == "min" else -1.0
        return {"val/m": Series(np.array(list(values)), sign * np.array(list(values.values())))}

    def lightning_stop(values: dict[int, float], mode: str, delta: float) -> int:
        stop = EarlyStopping("val/m", min_delta=delta, patience=3, mode=mode)
        sign = 1.0 if mode == "min" else -1.0
        steps = [
            step for step, value in values.items() if stop._evaluate_stopping_criteria(torch.tensor(sign * value))[0]
        ]
        return steps[0] + 1

    cases = [  # (step-0 value, mode, min_delta, the best step)
        (0.95, "min", 0.0, 149),
        (0.95, "max", 0.0, 149),
        (0.95, "min", 0.06, 99),  # 0.65 is not better than 0.7 by more than 0.06
        (0.1, "min", 0.0, 0),  # the starting weights stay the best: stop at the third validation, step 149
    ]
    for start, mode, delta, best in cases:
        values = {0: start, **trained}
        expected = lightning_stop(values, mode, delta)
        assert expected == (150 if best == 0 else best + 3 * 50 + 1)
        assert queue.stop_bound(tmp_path, series(values, mode, delta, 3000)) == f"{expected} (patience 3 after {best})"
    assert queue.stop_bound(tmp_path, series({0: 0.95, **trained}, "min", 0.0, 260)) == "260 (cap)"
    assert queue.stop_bound(tmp_path / "none", {}) == "–"


def wait_for_runners(queue: ModuleType, runs: Path, count: int) -> list[int]:
    """The pids of ``count`` runners of ``runs``, once each has started its job (a busy machine starts them slowly)."""
    for _ in range(1200):
        if len(pids := queue.runner_pids(runs)) == count and all(map(queue.descendants, pids)):
            return pids
        time.sleep(0.1)
    pytest.fail(f"expected {count} runners with their jobs, found {queue.runner_pids(runs)}")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc to find the runners")
def test_start_and_stop_runner_act_on_the_named_runners_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--runner` pauses or starts one runner while the others train on; a runner is known by its name."""
    queue = load("train_queue")
    # Session 30: at the default niceness, beside training runners given more CPU, the runners started so slowly
    # that runner "two"'s 60 s job had ended before runner "one" was up.
    monkeypatch.setattr(queue, "GROUP_NICE", 1)
    file, runs, args = sleeping_runners(tmp_path, two_jobs=1)

    with pytest.raises(SystemExit, match="no runner 'three'"):
        queue.main(["start", *args, "--runner", "three"])
    queue.main(["start", *args, "--runner", "two"])
    try:
        (two,) = wait_for_runners(queue, runs, 1)
        one_runner, two_runner = queue.load_runners(file, queue.load_jobs(file))
        assert queue.runner_pids(runs, [two_runner]) == [two] and queue.runner_pids(runs, [one_runner]) == []
        with pytest.raises(SystemExit, match="running already"):
            queue.main(["start", *args, "--runner", "two"])
        with pytest.raises(SystemExit, match="running already"):  # all runners: refused while one runs
            queue.main(["start", *args])
        queue.main(["start", *args, "--runner", "one"])  # the other one starts beside it
        (one,) = set(wait_for_runners(queue, runs, 2)) - {two}
        queue.main(["stop", *args, "--runner", "two"])
        assert queue.runner_pids(runs) == [one] and not queue.alive(two)
        assert queue.holder(queue.load_jobs(file)[0], runs) == one  # "one" trains on
    finally:
        queue.stop_runners(runs, grace_s=10)
    assert queue.runner_pids(runs) == []


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc to find the runners")
def test_stop_runner_spares_a_runner_whose_job_moved_to_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Session 31: job "a" moves from runner "one"'s list to "two"'s while "one" still runs it; `stop --runner two`
    must end "two" only (it ended "one" too when runners were known by their jobs)."""
    queue = load("train_queue")
    monkeypatch.setattr(queue, "GROUP_NICE", 1)
    file, runs, args = sleeping_runners(tmp_path, two_jobs=1)
    queue.main(["start", *args])
    try:
        wait_for_runners(queue, runs, 2)
        text = file.read_text(encoding="utf-8")
        file.write_text(text.replace('only = ["a", "b"]', 'only = ["b"]').replace('only = ["c"]', 'only = ["c", "a"]'))
        one_runner, two_runner = queue.load_runners(file, queue.load_jobs(file))
        (one,) = queue.runner_pids(runs, [one_runner])  # still known by the name that `start` gave it
        (two,) = queue.runner_pids(runs, [two_runner])
        queue.main(["stop", *args, "--runner", "two"])
        assert queue.runner_pids(runs) == [one] and queue.alive(one) and not queue.alive(two)
    finally:
        queue.stop_runners(runs, grace_s=10)
    assert queue.runner_pids(runs) == []


def test_a_runner_is_known_by_the_name_start_gives_it_or_else_by_exactly_its_jobs() -> None:
    queue = load("train_queue")
    runner = queue.Runner("r4", ("x", "y"))
    run = ["python", "train_queue.py", "run", "--only", "y", "x", "--runs", "/r"]
    assert queue.runs_as([*run, "--runner", "r4"], runner)
    assert not queue.runs_as([*run, "--runner", "r2"], runner)  # its jobs match, its name does not
    assert queue.runs_as(run, runner)  # started before `start` named runners: the same jobs
    assert not queue.runs_as(["train_queue.py", "run", "--only", "x", "z", "--runs", "/r"], runner)
    assert queue.option_values(["a", "--only", "x", "y", "--jobs", "2"], "--only") == ["x", "y"]
    assert queue.option_values(["a"], "--runner") == []


def _machine_bound_queue(folder: Path, wall_hours: float) -> Path:
    """Job "big" (machine-bound, ``wall_hours``), then "small" (resumable); each makes its run folder and exits."""
    file = folder / "q.toml"
    make = "python -c \\\"import pathlib; pathlib.Path('{runs}').mkdir(parents=True, exist_ok=True)\\\""
    big = f'[[job]]\nid = "big"\nsection = "cpu"\nwhat = "x"\ncommand = "{make}"\nmachine_bound = true\n'
    small = f'[[job]]\nid = "small"\nsection = "cpu"\nwhat = "x"\ncommand = "{make}"\n'
    file.write_text(f"{big}wall_hours = {wall_hours}\n{small}")
    return file


def test_a_machine_bound_job_that_cannot_finish_before_until_waits_and_the_next_job_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Session 49's lesson: a DCP-v2 run begun too late ends with the machine and starts again from step 0 on the
    next one. Before, a runner began its next job whatever the time left."""
    queue = load("train_queue")
    file = _machine_bound_queue(tmp_path, wall_hours=2.0)
    runs, res = tmp_path / "runs", tmp_path / "res"
    args = ["run", "--queue", str(file), "--runs", str(runs), "--results", str(res)]
    soon = (datetime.now(UTC) + timedelta(hours=1)).isoformat()
    queue.main([*args, "--until", soon])
    assert "queue: big: machine-bound (its runs resume only here), about 2 h from step 0" in capsys.readouterr().out
    assert not (runs / "big").exists() and not (res / "big" / "DONE.json").exists()
    assert (res / "small" / "DONE.json").is_file()  # the runner went on with its next job
    assert "pending (0 result rows)" in (line := queue.status_line(queue.load_jobs(file)[0], res, runs))
    assert "machine-bound: 2 h from step 0" in line
    queue.main([*args, "--until", (datetime.now(UTC) + timedelta(hours=2.5)).isoformat()])
    assert (res / "big" / "DONE.json").is_file()  # time enough: it runs


def test_a_machine_bound_job_begun_here_resumes_whatever_the_time_left(tmp_path: Path) -> None:
    queue = load("train_queue")
    big, _ = queue.load_jobs(_machine_bound_queue(tmp_path, wall_hours=2.0))
    until, now = datetime(2026, 12, 6, 12, 25, tzinfo=UTC), datetime(2026, 12, 6, 11, 0, tzinfo=UTC)
    assert queue.cannot_finish(big, tmp_path / "runs", until, now) is not None
    assert queue.cannot_finish(big, tmp_path / "runs", until, now - timedelta(hours=1)) is None  # 2.4 h left
    assert queue.cannot_finish(big, tmp_path / "runs", None, now) is None  # no --until: as before
    (tmp_path / "runs" / "big").mkdir(parents=True)
    assert queue.cannot_finish(big, tmp_path / "runs", until, now) is None  # its runs resume here
    resumable = dataclasses.replace(big, machine_bound=False)
    assert queue.cannot_finish(resumable, tmp_path / "other", until, until) is None  # a new machine resumes it


def test_until_is_the_next_such_utc_time_or_an_iso_time_and_start_passes_it_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    queue = load("train_queue")
    late = datetime(2026, 12, 6, 23, 0, tzinfo=UTC)
    assert queue.until_time("23:30", late) == datetime(2026, 12, 6, 23, 30, tzinfo=UTC)
    assert queue.until_time("01:00", late) == datetime(2026, 12, 7, 1, 0, tzinfo=UTC)  # past midnight: tomorrow's
    assert queue.until_time("2026-12-07T02:00", late) == datetime(2026, 12, 7, 2, 0, tzinfo=UTC)
    for bad in ("noon", "25:00"):
        with pytest.raises(argparse.ArgumentTypeError, match="--until: expected HH:MM"):
            queue.until_time(bad, late)
    *_, args = sleeping_runners(tmp_path, two_jobs=1)
    launched: list[list[str]] = []

    class Launched:  # a runner that runs on
        pid = -1
        returncode = None

        def poll(self) -> None:
            return None

    def popen(argv: list[str], **_: object) -> Launched:
        launched.append(argv)
        return Launched()

    monkeypatch.setattr(queue.subprocess, "Popen", popen)
    monkeypatch.setattr(queue, "nice_group", lambda pid, nice: True)
    queue.main(["start", *args, "--until", "2026-12-06T12:25"])
    assert len(launched) == 2 and all(
        argv[argv.index("--until") + 1] == "2026-12-06T12:25:00+00:00" for argv in launched
    )
    with pytest.raises(ValueError, match="'big' is machine_bound: give its wall_hours"):
        queue.load_jobs(_machine_bound_queue(tmp_path, wall_hours=0))
