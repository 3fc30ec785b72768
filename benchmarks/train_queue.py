"""The training queue (``benchmarks/train_queue.toml``): status, run the pending jobs in order, copy their results.

    python benchmarks/train_queue.py status
    python benchmarks/train_queue.py run --section cpu --runs /work/runs/converge    # one thread, nice, in order
    python benchmarks/train_queue.py run --section gpu --max-minutes 9                # resumable chunks on a GPU
    python benchmarks/train_queue.py sync                                             # copy finished rows to commit
    python benchmarks/train_queue.py start --runs /work/runs/converge --commit        # the CPU runners, detached:
                                                                 # each syncs and commits its job every 10 minutes
    python benchmarks/train_queue.py stop --runs /work/runs/converge                  # end them and their training
    python benchmarks/train_queue.py start --runs /work/runs/converge --runner r3     # one runner, the others go on
    python benchmarks/train_queue.py start --runs /work/runs/converge --until 12:25   # the machine goes at 12:25 UTC
    python benchmarks/train_queue.py runs --out docs/results/converge/runs.md         # every finished run's stop
    python benchmarks/train_queue.py progress --runs /work/runs/converge              # the runs training now
    python benchmarks/train_queue.py --smoke                                          # seconds: a tiny queue

Every job is one resumable command (``{runs}``: its run folder under ``--runs``, ``{results}``: its folder under
``--results``). ``run`` starts the pending jobs of a section one at a time with ``OMP_NUM_THREADS=1`` under ``nice``
(on a GPU, ``--max-minutes`` is the time of the whole call: the jobs run in order, the one running at the limit is
stopped and resumes on the next call, so one chunk can finish a short job and go on with the next). When a command
exits 0 its small result files are copied to ``<results>/<id>/`` and ``DONE.json`` (the last call's wall time) is
written there, which marks the job done. ``sync`` copies the result files of unfinished jobs too, so finished runs
of a long job can be committed as they land. Run folders need not outlive a session: before a job starts, the
committed copies of its result logs are restored into an empty run folder, so its finished runs are skipped, and the
runs in progress when a session ended resume from the checkpoints ``sync`` kept in ``<results>/<id>/resume/`` (when
they are small enough, :data:`RESUME_MAX_BYTES`; otherwise they start again). For a job with ``keep_best = true``
``sync`` also writes the slim weights of each finished run's selected checkpoint (or a sweep's tested weights) to
``<results>/<id>/best/`` (the runs whose weights may ship or be probed later). For a job with a ``test_command``
(``{checkpoint}``: a finished run's selected checkpoint, ``{out}``: ``<results>/<id>/test/<variant>-seed<k>``)
``sync`` runs it once per finished run, so that a baseline's test outlives its run folder where its weights are too
large to keep; a ``val_command`` likewise (``{out}``: ``<results>/<id>/val/<variant>-seed<k>``), for the validation
measurement a job's rule reads (e.g. its selected weights at the exact truth). Several runners may share a ``--runs``
folder (one thread each): a job runs in one of them at a time (:func:`job_lock`); the others skip it.
The queue file's ``[[runner]]`` tables name the session's CPU runners (each a ``run --only <its jobs>``): ``start``
launches them in the background from a worktree at the current commit (so that code changed meanwhile does not
disturb them), each logging to ``<runs>/logs/<name>.log``; ``stop`` ends the runners of a ``--runs`` folder and their
training processes (a run resumes from its ``last.ckpt``). ``--runner <names>`` restricts either to the named runners,
the others go on (to pause one runner, or start one whose jobs changed, from a worktree at the current commit; a runner
is known by the name ``start`` gives its command line, :func:`runs_as`, so a job moved to another runner's list does not
make ``stop`` of that runner end its old one). ``runs`` tabulates every
finished run of the committed results: the step at which it stopped, why, and the step its rule selected
(:func:`runs_table`). ``progress`` shows the runs training now: each one's last validation, its best so far and the step
by which it stops unless a validation improves (:func:`progress_table`, :func:`stop_bound`). ``--until`` (``run``,
``start``) is when this machine is expected to go: a ``machine_bound`` job (its checkpoints are too large to keep, so
its runs resume only here) is not begun when its ``wall_hours`` would end after it; the runner goes on with its next
job, and the machine-bound one waits for a session that can finish it (:func:`cannot_finish`).
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import itertools
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import tomllib
import yaml

from lcreg.experiments.benchmarking import (
    CONVERGE_METRIC,
    SELECTION_METRIC,
    ResultLog,
    Series,
    add_smoke_argument,
    machine_line,
    read_metrics,
    training_device,
)
from lcreg.experiments.reproduce.command import REPORT_NOT_WRITTEN_EXIT_CODE
from lcreg.experiments.reproduce.retest import is_retest_output

REPO = Path(__file__).resolve().parents[1]
RESULT_FILES = ("*.jsonl", "metrics*.csv", "hparams.yaml", "*.md", "*.png")
"""Small files copied from a job's run folder (checkpoints only as :func:`keep_resume` and :func:`keep_best` do)."""
RESUME_MAX_BYTES = 8 * 2**20
"""Largest checkpoint folder :func:`keep_resume` keeps: IDAM's (2.4 MB) is kept; DeepGMR's (about 35 MB: 1.5 M
parameters with Adam's state, in ``last.ckpt`` and the selected checkpoint) and DVDs' (23 MB; 40 MB before its frozen
LC metric was left out of checkpoints) are not, as every sync commit would add them to the history; their runs resume
only on a machine that kept the run folder."""
LCREG_MAIN = "import sys; from lcreg.__main__ import main; sys.argv[0] = 'lcreg'; main()"
"""``lcreg`` as a ``python -c`` program (the console script of whichever lcreg the interpreter imports)."""
SMOKE_QUEUE = """
[[job]]
id = "smoke"
section = "cpu"
what = "two-step learning curve on the embedded shapes"
command = "python benchmarks/learning_curves.py --smoke --variants selfsup --patience 2 --val-pairs 2 --run-dir {runs}"
cpu_hours = 0.01
"""


@dataclass(frozen=True)
class Job:
    """One queued command (see ``benchmarks/train_queue.toml``)."""

    id: str
    section: str
    what: str
    command: str
    cpu_hours: float = 0.0
    cap_hours: float | None = None
    gpu_hours: float = 0.0
    keep_best: bool = False
    test_command: str | None = None
    val_command: str | None = None
    machine_bound: bool = False
    """Its checkpoints exceed :data:`RESUME_MAX_BYTES`: a run resumes only on the machine that began it."""
    wall_hours: float | None = None
    """Wall-clock hours from its first step to done with its runner's cores (``machine_bound`` jobs need it)."""

    def follow_up_argv(self, kind: str, checkpoint: Path, out: Path) -> list[str]:
        """The job's ``<kind>_command`` (:data:`FOLLOW_UPS`) for one finished run (``{checkpoint}``, ``{out}``: the path
        stem of its outputs), run by this interpreter as :meth:`executable` runs the job's command."""
        command = getattr(self, f"{kind}_command") or ""
        words = shlex.split(command.format(checkpoint=checkpoint, out=out))
        return [*INTERPRETERS.get(words[0], words[:1]), *words[1:]]

    def argv(self, runs: Path, results: Path) -> list[str]:
        """The command's arguments with ``{runs}``/``{results}`` filled in (``python`` and ``lcreg`` as written)."""
        return shlex.split(self.command.format(runs=runs / self.id, results=results / self.id))

    def executable(self, runs: Path, results: Path, jobs: int = 1) -> list[str]:
        """:meth:`argv` run by this interpreter: ``python`` is it, ``lcreg`` is ``python -c <lcreg.__main__.main>``, so
        the code imported is that of the interpreter's path (the worktree's ``src`` with ``PYTHONPATH``). ``jobs`` > 1
        adds ``--jobs`` to an ``lcreg reproduce`` sweep or a ``learning_curves.py`` job (runs at once, e.g. on a
        GPU)."""
        words = self.argv(runs, results)
        head = INTERPRETERS.get(words[0], words[:1])
        parallel = ["--jobs", str(jobs)] if jobs > 1 and words[:2] in PARALLEL_COMMANDS else []
        return [*head, *words[1:], *parallel]


FOLLOW_UPS = ("val", "test")
"""What a job may run on each finished run's selected checkpoint at a sync, in this order (:func:`keep_follow_ups`):
``val_command`` (a validation measurement its rule reads, e.g. the fixed point of ``lk_fixed_point.py``) writes under
``<results>/<id>/val/``, ``test_command`` (the one test) under ``test/``."""
INTERPRETERS = {"python": [sys.executable], "lcreg": [sys.executable, "-c", LCREG_MAIN]}
"""How a command's first word runs: ``python`` is this interpreter, ``lcreg`` its ``lcreg.__main__``."""
REPRODUCE = ["lcreg", "reproduce"]
"""The first two words of an ``lcreg reproduce`` job (its exit code 3: every run finished, the report failed)."""
PARALLEL_COMMANDS = (REPRODUCE, ["python", "benchmarks/learning_curves.py"])
"""Commands that take ``--jobs`` (the first two words of a job's command)."""


@dataclass(frozen=True)
class Runner:
    """One CPU runner of ``start``: ``run --section cpu --only <only>`` (its jobs, in order), and why. ``jobs`` > 1
    adds ``run --jobs <jobs>``: a sweep of its jobs (:data:`PARALLEL_COMMANDS`) trains that many runs at once, each
    on its own thread, so a job of many runs gets that many shares of the cores. ``shares`` sets the runner's CPU
    weight in one-job runners' shares instead (default: ``jobs``): the queue file's priorities, e.g. more for the
    run a session can finish (:func:`runner_nice`). ``threads`` > 1 adds ``run --threads <threads>``: each training
    process of the runner uses that many threads (``OMP_NUM_THREADS``) instead of one, e.g. for a machine-bound run
    that must finish within a session once the other runners are done (it resumes from ``last.ckpt``)."""

    name: str
    only: tuple[str, ...]
    why: str = ""
    jobs: int = 1
    shares: int | None = None
    threads: int = 1


def load_runners(path: Path, jobs: Sequence[Job]) -> list[Runner]:
    """The ``[[runner]]`` tables of a queue file, in order.

    Raises:
        ValueError: If a runner lacks a field or has an unknown one, two share a name, one names no job or a job the
            queue does not have, or two list the same job.
    """
    runners = []
    for entry in tomllib.loads(path.read_text(encoding="utf-8")).get("runner", []):
        try:
            runners.append(Runner(**{**entry, "only": tuple(entry.get("only", ()))}))
        except TypeError as err:
            raise ValueError(f"{path}: runner {entry.get('name', '?')!r}: {err}") from None
    known, listed = {job.id for job in jobs}, [job for runner in runners for job in runner.only]
    for runner in runners:
        unknown = set(runner.only) - known
        if not runner.only or unknown:
            raise ValueError(f"{path}: runner {runner.name!r} names no job or unknown ones: {sorted(unknown)}")
        shares = 1 if runner.shares is None else runner.shares
        for field, value in (("jobs", runner.jobs), ("shares", shares), ("threads", runner.threads)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{path}: runner {runner.name!r}: {field} must be an integer >= 1, got {value!r}")
    if len({r.name for r in runners}) != len(runners) or len(set(listed)) != len(listed):
        raise ValueError(f"{path}: runner names and the jobs they list must be unique")
    return runners


def load_jobs(path: Path) -> list[Job]:
    """The jobs of a queue file, in order.

    Raises:
        ValueError: If a job lacks a field, has an unknown one, or two jobs share an id.
    """
    jobs = []
    for entry in tomllib.loads(path.read_text(encoding="utf-8")).get("job", []):
        try:
            jobs.append(Job(**entry))
        except TypeError as err:
            raise ValueError(f"{path}: job {entry.get('id', '?')!r}: {err}") from None
    ids = [job.id for job in jobs]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{path}: job ids must be unique, got {ids}")
    for job in jobs:
        if job.machine_bound and not (isinstance(job.wall_hours, int | float) and job.wall_hours > 0):
            raise ValueError(
                f"{path}: job {job.id!r} is machine_bound: give its wall_hours (> 0), got {job.wall_hours}"
            )
    return jobs


def until_time(text: str, now: datetime | None = None) -> datetime:
    """``--until``: ``HH:MM`` (UTC; the next such time, so ``01:00`` at 23:00 is tomorrow's) or an ISO date and time
    (UTC unless it names a zone).

    Raises:
        argparse.ArgumentTypeError: If ``text`` is neither.
    """
    now = now or datetime.now(UTC)
    try:
        if re.fullmatch(r"\d{1,2}:\d{2}", text):
            hour, minute = map(int, text.split(":"))
            at = now.replace(hour=hour, minute=minute, second=0, microsecond=0)
            return at if at > now else at + timedelta(days=1)
        at = datetime.fromisoformat(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(
            f"--until: expected HH:MM (UTC) or an ISO date and time, got {text!r} ({err})"
        ) from None
    return at if at.tzinfo else at.replace(tzinfo=UTC)


def cannot_finish(job: Job, runs: Path, until: datetime | None, now: datetime | None = None) -> str | None:
    """Why ``run`` does not begin ``job`` here before ``until`` (the machine's expected end), or ``None`` if it may.

    Only a ``machine_bound`` job is held back, and only when none of its runs has begun on this machine (no run folder
    under ``runs``; one that has resumes): a run cut off with the machine starts again from step 0 on the next one,
    so its hours would be lost. Its ``wall_hours`` (from step 0) must end before ``until``.
    """
    if until is None or not job.machine_bound or (runs / job.id).exists():
        return None
    left_h = (until - (now or datetime.now(UTC))).total_seconds() / 3600
    if job.wall_hours is not None and job.wall_hours <= left_h:
        return None
    return (
        f"machine-bound (its runs resume only here), about {job.wall_hours:g} h from step 0, {max(left_h, 0):.2f} h "
        f"left before --until {until:%Y-%m-%d %H:%M} UTC: not begun; it waits for a session that can finish it"
    )


def sync(job: Job, runs: Path, results: Path, done: bool | None = None) -> int:
    """Copy the job's small result files from its run folder to ``results/<id>/runs/``; returns how many.

    A JSONL log already in the results keeps the rows this run folder lacks (:func:`merged_rows`); any other file
    there that is newer than the run folder's (a report rebuilt with ``--report-only``) is kept.

    Also keeps the resume state of the run in progress unless the job is ``done`` (default: its ``DONE.json``
    exists; :func:`keep_resume`), for a ``keep_best`` job the slim weights of every finished run's selected
    checkpoint (:func:`keep_best`), and for a job with a ``val_command`` or ``test_command`` every finished run's
    validation measurement or test (:func:`keep_follow_ups`).
    """
    source, target, count = runs / job.id, results / job.id / "runs", 0
    for pattern in RESULT_FILES:
        for path in source.rglob(pattern) if source.is_dir() else ():
            destination = target / path.relative_to(source)
            destination.parent.mkdir(parents=True, exist_ok=True)
            if path.suffix == ".jsonl" and destination.is_file():  # rows another machine added stay (a GPU chunk)
                destination.write_text(merged_rows(path, destination), encoding="utf-8")
            elif newer(destination, path):  # e.g. a report rebuilt here (--report-only) over the run's older one
                continue
            else:
                shutil.copy2(path, destination)  # keeps the source's mtime, so an unchanged file stays "not newer"
            count += 1
    drop_set_aside(source, target)
    done = (results / job.id / "DONE.json").is_file() if done is None else done
    count += len(keep_resume(source, results / job.id / "resume", done=done))
    for kind in (kind for kind in FOLLOW_UPS if getattr(job, f"{kind}_command")):
        count += len(keep_follow_ups(job, kind, source, results / job.id / kind))
    return count + (len(keep_best(source, results / job.id / "best")) if job.keep_best else 0)


def newer(destination: Path, source: Path) -> bool:
    """Whether ``destination`` exists and was written after ``source`` (modification times, ns)."""
    return destination.is_file() and destination.stat().st_mtime_ns > source.stat().st_mtime_ns


def drop_set_aside(source: Path, target: Path) -> list[Path]:
    """Delete from ``target`` the metrics files that a run started again moved aside in ``source``.

    A run whose checkpoints were lost starts from scratch and moves its folder's old metrics files to
    ``abandoned/<n>/`` (:func:`lcreg.resume.set_aside_metrics`); their copies beside the new ``metrics.csv`` in the
    committed results would otherwise be read as earlier segments of the new curve, and come back on the next
    machine. The moved copies are synced like any result file. Returns the files deleted.
    """
    dropped = []
    for moved in source.rglob("abandoned/*/metrics*.csv") if source.is_dir() else ():
        run_dir = moved.parent.parent.parent
        stale = target / (run_dir / moved.name).relative_to(source)
        if not (run_dir / moved.name).exists() and stale.is_file():
            stale.unlink()
            dropped.append(stale)
    return dropped


def keep_resume(source: Path, target: Path, done: bool = False) -> list[Path]:
    """Keep the resume state of the runs in progress: the checkpoint folder of each ``last.ckpt`` under ``source``
    whose run no JSONL row lists as finished (:func:`finished_runs`; a ``jobs = N`` runner trains N at once), and of
    each finished run whose row says the sweep kept it (:func:`capped_runs`: its step cap cut it off).

    Each such folder's :func:`resume_files` (``last.ckpt`` and the selected checkpoint its callbacks' state names)
    are kept in ``target`` when they are at most :data:`RESUME_MAX_BYTES`, so a run longer than a session resumes on
    the next machine (:func:`restore`) instead of starting again, and a capped run can be continued there under a
    higher cap (``lcreg reproduce --continue-from``); the previous copy goes (its runs have finished since, or are
    kept again). A done job keeps only its capped runs' state; a run folder without any ``last.ckpt`` (a new machine,
    before :func:`restore`) leaves the kept copy alone. Returns the files copied.
    """
    lasts = sorted(source.rglob("last.ckpt")) if source.is_dir() else []
    if not lasts:  # e.g. a new machine before `run` restored the kept copy: keep it
        if done and any(source.rglob("*.jsonl")):  # the job finished here: only its capped runs' state stays
            _prune(target, capped_runs(source))
        return []
    finished, capped = finished_runs(source), capped_runs(source)
    shutil.rmtree(target, ignore_errors=True)
    copied = []
    for folder in (last.parent for last in lasts):
        run = folder.parent.relative_to(source).as_posix()
        if run not in capped and (done or run in finished):
            continue
        last = folder / "last.ckpt"  # too large alone (a DVDs run's): not read for the checkpoints it names
        files = [last] if last.stat().st_size > RESUME_MAX_BYTES else resume_files(folder)
        if sum(f.stat().st_size for f in files) > RESUME_MAX_BYTES:
            print(f"queue: {folder}: checkpoints over {RESUME_MAX_BYTES >> 20} MB, not kept for resuming", flush=True)
            continue
        for path in files:
            destination = target / path.relative_to(source)
            destination.parent.mkdir(parents=True, exist_ok=True)
            copied.append(Path(shutil.copy2(path, destination)))
    return copied


def capped_runs(source: Path) -> set[str]:
    """The run folders, relative to the job's folder ``source``, of the finished runs whose JSONL row says the sweep
    kept their resume state (``kept_resume_state``: a ``converge`` run its step cap cut off, since session 56)."""
    return {folder for row, folder in logged_runs(source) if row.get("kept_resume_state")}


def logged_runs(source: Path) -> Iterator[tuple[dict[str, Any], str]]:
    """Every row of the job's JSONL logs under ``source`` that names its ``metrics_csv``, with its run folder
    relative to ``source``: what follows the job id in ``<runs>/<job id>/<run folder>/metrics.csv``, on whichever
    machine trained it."""
    marker = f"/{source.name}/"
    for log in source.rglob("*.jsonl"):
        for row in ResultLog(log).rows:
            metrics = str(row.get("metrics_csv") or "")
            if marker in metrics:
                yield row, metrics.rsplit(marker, 1)[1].removesuffix("/metrics.csv")


def _prune(target: Path, runs: set[str]) -> None:
    """Delete the files of ``target`` that lie outside the run folders ``runs`` (relative to ``target``)."""
    for path in sorted(target.rglob("*"), reverse=True) if target.is_dir() else ():
        inside = any(path.relative_to(target).as_posix().startswith(f"{run}/") for run in runs)
        if path.is_file() and not inside:
            path.unlink()
        elif path.is_dir() and not any(path.iterdir()):
            path.rmdir()
    if target.is_dir() and not any(target.iterdir()):
        target.rmdir()


def resume_files(folder: Path) -> list[Path]:
    """``folder/last.ckpt`` and the checkpoints its ``ModelCheckpoint`` state names (the selected one): what resumes.

    Other checkpoints in the folder are stale: selected on an earlier machine and restored with its kept copy, they are
    unknown to the callback, which never deletes them (session 30 found two such copies doubling IDAM's resume state).
    An unreadable ``last.ckpt`` keeps every checkpoint of the folder.
    """
    from lcreg.checkpoints import CheckpointError, read_checkpoint

    last = folder / "last.ckpt"
    try:
        callbacks = read_checkpoint(last).get("callbacks") or {}
    except CheckpointError:
        return sorted(folder.glob("*.ckpt"))
    named = set()
    for key, state in callbacks.items():
        if str(key).startswith("ModelCheckpoint") and isinstance(state, dict):
            paths = [
                state.get("best_model_path"),
                state.get("kth_best_model_path"),
                *(state.get("best_k_models") or ()),
            ]
            named |= {Path(str(path)).name for path in paths if path}
    return [last, *sorted(p for name in named - {last.name} if (p := folder / name).is_file())]


def finished_runs(source: Path) -> set[str]:
    """The run folders, relative to the job's folder ``source``, of the finished runs that its JSONL logs list.

    A finished run's row names its ``metrics_csv`` (``<runs>/<job id>/<run folder>/metrics.csv``, on whichever
    machine trained it); what follows the job id is the run folder. A sweep's row (``lcreg reproduce``: its
    ``weights``) does not count where its folder holds a ``last.ckpt`` again: a sweep deletes a finished run's
    checkpoints, so that is a run of another budget or data training in the same folder (session 38: the row of
    PRNet's LC run at lr 1e-3 hid the run at 2.2e-4 from ``progress`` and its resume state from :func:`keep_resume`),
    unless the checkpoint the row selected is there too: that is the run's own resume state, kept while it trained
    and restored on a new machine after it finished (session 49: seed 0 of ``idam_bf16_512`` listed as training, and
    its stale checkpoints kept again at every sync, since a sweep deletes them before it writes the row), or kept by
    the sweep itself for a run its step cap cut off (since session 56, for ``lcreg reproduce --continue-from``).
    """
    folders = set()
    for row, folder in logged_runs(source):
        checkpoints = source / folder / "checkpoints"
        restored = bool(row.get("selected")) and (checkpoints / str(row["selected"])).is_file()
        if not (row.get("weights") and (checkpoints / "last.ckpt").is_file()) or restored:
            folders.add(folder)
    return folders


def keep_best(source: Path, target: Path) -> list[Path]:
    """Export the selected weights of every finished run in the job's logs as ``target/<variant>-seed<k>.pt``.

    The logs are ``source/runs.jsonl`` (``learning_curves.py``: each row's ``best_checkpoint``) and a sweep's
    ``source/<experiment>.jsonl`` (``lcreg reproduce``: each row's ``weights``, the tested ``selected_weights.pt``; a
    variant such as ``idam/X`` is written ``idam_x``; a later row of that variant and seed with another budget or data,
    ``idam_x-seed1-key<hash>``, so that the first run's file does not stand for it). Run folders need not outlive a
    session, so the weights a job may ship or probe later are kept beside its committed logs (slim inference weights,
    :func:`lcreg.weights.export.export_weights`, about 0.6 MB for DVDs). A run whose file exists or whose weights are
    gone is skipped; weights over the file limit are reported and skipped. Returns the files written.
    """
    from lcreg.weights import PretrainedSizeError
    from lcreg.weights.export import export_weights

    written, first_key = [], dict[str, str]()
    logs = (log for log in sorted(source.glob("*.jsonl")) if not is_retest_output(log))
    for row in (row for log in logs for row in ResultLog(log).rows):
        weights = Path(row.get("best_checkpoint") or row.get("weights") or "")
        name = re.sub(r"[^a-z0-9._-]+", "_", f"{row.get('variant')}-seed{row.get('seed')}".lower())
        key = json.dumps([row.get("budget"), row.get("data")])
        if first_key.setdefault(name, key) != key:  # a run of the same variant and seed at a changed budget or data
            name += "-key" + hashlib.sha1(key.encode()).hexdigest()[:8]
        if "variant" not in row or (target / f"{name}.pt").exists() or not weights.is_file():
            continue
        metadata = {"job_row": json.dumps(row, sort_keys=True), "machine": machine_line(training_device())}
        try:
            written.append(export_weights(weights, name, target, metadata=metadata))
        except PretrainedSizeError as error:  # e.g. iPCRNet's 16.9 MB: its test_command tests it instead
            print(f"queue: {weights}: not kept ({error})", flush=True)
    return written


def keep_follow_ups(job: Job, kind: str, source: Path, target: Path) -> list[Path]:
    """Run the job's ``<kind>_command`` (:data:`FOLLOW_UPS`) once for every finished run in ``source/runs.jsonl`` whose
    selected checkpoint exists and whose ``target/<variant>-seed<k>.md`` does not; returns the files the commands wrote
    under ``target``.

    For jobs whose selected weights are too large to keep (:func:`keep_best`; iPCRNet's slim weights are 16.9 MB), the
    test result is what outlives the run folder; a ``val_command`` measures what a job's rule reads as soon as a run
    finishes, without a hand-run watcher. A failing command is reported and leaves no ``.md``, so the next sync tries
    again.
    """
    target.mkdir(parents=True, exist_ok=True)
    before, env = set(target.iterdir()), {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    for row in ResultLog(source / "runs.jsonl").rows if (source / "runs.jsonl").is_file() else ():
        checkpoint = Path(row.get("best_checkpoint") or "")
        out = target / f"{row.get('variant')}-seed{row.get('seed')}".lower()
        report = out.parent / f"{out.name}.md"  # not with_suffix: a variant may hold a dot (recon_mlp_recipe0.1)
        if "variant" not in row or report.exists() or not checkpoint.is_file():
            continue
        argv = ["nice", "-n", "5", *job.follow_up_argv(kind, checkpoint, out)]
        print(f"queue: {job.id}: {kind} {shlex.join(argv)}", flush=True)
        if (code := subprocess.run(argv, cwd=REPO, env=env).returncode) != 0:
            print(f"queue: {job.id}: {kind} of {out.name} exited {code}; tried again at the next sync", flush=True)
            report.unlink(missing_ok=True)
    return sorted(set(target.iterdir()) - before)


def merged_rows(first: Path, second: Path) -> str:
    """The lines of JSONL ``first``, then those of ``second`` that ``first`` lacks (as a multiset), in their order.

    A job may run on this machine and, in chunks, on a lent GPU whose rows come back into the results folder: each
    copy keeps the other's finished runs instead of replacing them. The rows of ``first`` come first, so where both
    machines finished the same run, the newest row (the one that counts) is ``second``'s.
    """
    lines, others = (path.read_text(encoding="utf-8").splitlines() for path in (first, second))
    missing = Counter(others) - Counter(lines)
    extra = []
    for line in others:
        if missing[line] > 0 and line.strip():
            extra.append(line)
            missing[line] -= 1
    rows = lines + extra
    return "\n".join(rows) + "\n" if rows else ""


def restore(job: Job, runs: Path, results: Path) -> int:
    """Copy the committed result files of ``job`` back into its run folder where that folder lacks them (a new
    machine), and add to its JSONL logs the rows they lack (another machine's: :func:`merged_rows`); the scripts
    then skip the runs these logs list as finished, and the run in progress resumes from its kept checkpoints
    (:func:`keep_resume`). Metrics files that a run started again here moved aside stay out
    (:func:`set_aside_here`). Returns how many files were copied or extended."""
    target, count = runs / job.id, 0
    for source in (results / job.id / "runs", results / job.id / "resume"):
        for path in source.rglob("*") if source.is_dir() else ():
            destination = target / path.relative_to(source)
            if path.is_file() and path.suffix == ".jsonl" and destination.is_file():
                rows = merged_rows(destination, path)  # runs another machine finished are not trained again
                if rows != destination.read_text(encoding="utf-8"):
                    destination.write_text(rows, encoding="utf-8")
                    count += 1
            elif path.is_file() and not destination.exists() and not set_aside_here(path, destination):
                destination.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(path, destination)
                count += 1
    return count


def set_aside_here(committed: Path, destination: Path) -> bool:
    """Whether a run started again here moved ``committed``'s bytes aside (``<run>/abandoned/<n>/<name>``).

    Until the next :func:`sync` drops them (:func:`drop_set_aside`), the committed results still hold the lost run's
    metrics files; restored, they would be read as earlier segments of the new curve. A committed file of the same name
    with other bytes (a segment the new run wrote on another machine) is not one of them.
    """
    moved = destination.parent.glob(f"abandoned/*/{destination.name}")
    return committed.name.startswith("metrics") and any(m.read_bytes() == committed.read_bytes() for m in moved)


def status_line(job: Job, results: Path, runs: Path | None = None) -> str:
    """``id  section  done|pending|running (<k> result rows: finished runs, earlier rules' included)  estimate  what``;
    a ``machine_bound`` job's estimate adds its ``wall_hours``.

    ``running`` (with the runner's pid): a runner here holds the job's lock in ``runs`` (:func:`job_lock`).
    """
    done = (results / job.id / "DONE.json").is_file()
    logs = result_logs(results / job.id / "runs")
    finished = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in logs)
    pid = None if done or runs is None else holder(job, runs)
    state = "done" if done else f"{'pending' if pid is None else f'running, pid {pid},'} ({finished} result rows)"
    hours = f"{job.gpu_hours} GPU-h" if job.section == "gpu" else f"{job.cpu_hours} CPU-h (cap {job.cap_hours})"
    hours += f", machine-bound: {job.wall_hours:g} h from step 0" if job.machine_bound else ""
    return f"{job.id:<24} {job.section:<4} {state:<28} {hours:<22} {job.what}"


RUNS_COMMAND = "benchmarks/train_queue.py runs --out docs/results/converge/runs.md"
"""How ``docs/results/converge/runs.md`` is written (:func:`runs_table`)."""
RUNS_PREAMBLE = (
    f"Written by `python {RUNS_COMMAND}` (and by every `sync`) from the committed result rows; do not edit.",
    "",
    "Each heading is a job and the budget its rows were logged under. `converge p<P> v<K>` (`learning_curves.py`):",
    "stop after P validations without a gain, K validation pairs per object; `m<metric>`: stopped and selected on",
    "that metric (else `val/rre_clip5_deg`); `min<M>`: no stop before step M. Seconds: the call that finished a run.",
)
CHECKPOINT_NAME = re.compile(r"step(?P<step>\d+)-(?P<rest>.+)\.ckpt$")
"""A selected checkpoint's file name: ``step<N>-<monitor with / as _><value>.ckpt`` (``lcreg.cli``'s template)."""
RUNS_HEADER = (
    "| run | seed | points | stopped at step | why | selected step | selected on | its value | seconds logged |",
    "|---|---|---|---|---|---|---|---|---|",
)


def result_rows(job: Job, results: Path) -> list[dict]:
    """The rows of the job's committed result logs (``<results>/<id>/runs/*.jsonl``, as :func:`status_line` counts
    them), in file and line order."""
    return [row for log in result_logs(results / job.id / "runs") for row in ResultLog(log).rows]


def result_logs(folder: Path) -> list[Path]:
    """The training rows' JSONL logs in ``folder``, sorted: not the shared models' ``models.jsonl`` (an evaluation
    experiment's) nor a retest's rows (``lcreg reproduce --retest``: the same runs tested again)."""
    return sorted(p for p in folder.glob("*.jsonl") if p.name != "models.jsonl" and not is_retest_output(p))


def selection(row: dict) -> tuple[int | None, str, float | None]:
    """(selected step, monitor, its validation value) of a finished run's row.

    Rows of ``lcreg reproduce`` name the monitor (``selected_on``) and value (``best_val``); rows of
    ``learning_curves.py`` have them only in the checkpoint's file name, whose monitor is the budget's ``m<monitor>``
    or :data:`CONVERGE_METRIC` (:data:`SELECTION_METRIC` for a fixed budget). Unknown parts are ``None`` / ``"?"``.
    """
    name = Path(str(row.get("selected") or row.get("best_checkpoint") or "")).name
    budget = str(row.get("budget") or "")
    other = re.search(r" m(val/\S+)", budget)
    monitor = row.get("selected_on") or (other[1] if other else CONVERGE_METRIC if budget else SELECTION_METRIC)
    if (match := CHECKPOINT_NAME.match(name)) is None:
        return None, str(monitor), row.get("best_val")
    prefix, rest = str(monitor).replace("/", "_"), match["rest"]
    value = row.get("best_val")
    if value is None and rest.startswith(prefix):
        with contextlib.suppress(ValueError):
            value = float(rest[len(prefix) :])
    return int(match["step"]), str(monitor), value


def run_line(row: dict) -> str:
    """One finished run as a row of :data:`RUNS_HEADER` (seconds: of the call that finished it, for a run resumed
    over several calls of ``learning_curves.py``)."""
    from lcreg.experiments.reproduce.stops import stopped_early

    stopped = row.get("stopped_step", row.get("steps"))
    early = row.get("early_stopped", stopped_early(row))
    why = "early stop" if early else "step cap" if early is not None else "fixed budget"
    step, monitor, value = selection(row)
    seconds = row.get("train_s", row.get("seconds"))
    cells = (
        str(row.get("variant", "?")),
        str(row.get("seed", "?")),
        str(row.get("num_points", row.get("points", "?"))),
        "?" if stopped is None else f"{stopped:,}",
        why,
        "?" if step is None else f"{step:,}",
        f"`{monitor}`",
        "?" if value is None else f"{value:.4g}",
        "?" if seconds is None else f"{seconds:,.0f}",
    )
    return "| " + " | ".join(cells) + " |"


def runs_table(jobs: Sequence[Job], results: Path) -> str:
    """Markdown: every finished run of ``jobs`` in the committed results, one table per job and budget (a job's
    rows of an earlier rule are kept under their own budget), with the step at which each run stopped and the step
    its rule selected. Runs in progress are not listed (``status`` shows them)."""
    lines = ["# Finished runs of the training queue", "", *RUNS_PREAMBLE]
    for job in jobs:
        budgets: dict[str, list[dict]] = {}
        for row in result_rows(job, results):
            budgets.setdefault(str(row.get("budget") or "fixed step budget"), []).append(row)
        for budget, rows in budgets.items():
            lines += ["", f"## `{job.id}`: {budget_heading(budget)}", "", *RUNS_HEADER, *map(run_line, rows)]
    return "\n".join(lines) + "\n"


def budget_heading(budget: str) -> str:
    """A row's budget key as a heading: ``lcreg reproduce --set`` values (``"; set k=v, ..."``) after the budget,
    marked as replacing its values (a set ``trainer.max_steps`` is the run's cap, not the budget's steps)."""
    base, sep, settings = budget.partition("; set ")
    return f"{base}; set on every run, replacing the budget's values of these keys: {settings}" if sep else budget


PROGRESS_KEYS = ("val/rre_median_deg", "val/rre_clip5_deg", "val/recall_r2_t0p01", "val/rre_mean_deg")
"""Validation metrics ``progress`` shows (the stopping rules' monitors, the recall of goal (c), the tail)."""


def active_runs(job: Job, runs: Path, hours: float) -> list[Path]:
    """The ``metrics.csv`` files of ``job``'s run folder written in the last ``hours`` (its runs training now; a run
    set aside as lost, under ``abandoned/``, a retest's test, or finished, :func:`finished_runs`, is not one), oldest
    first."""
    folder, since = runs / job.id, time.time() - 3600 * hours
    found = folder.rglob("metrics.csv") if folder.is_dir() else ()
    files = [f for f in found if "abandoned" not in f.parts and not is_retest_output(f)]
    finished = finished_runs(folder) if files else set()
    files = [f for f in files if f.parent.relative_to(folder).as_posix() not in finished]
    return sorted((f for f in files if f.stat().st_mtime >= since), key=lambda f: f.stat().st_mtime)


def progress_cell(key: str, series: Series) -> str:
    """``last @ step (best v @ step)`` of ``key``'s series: higher is better for recalls, lower for the rest."""
    best = int(series.values.argmax() if "recall" in key else series.values.argmin())
    last = f"{series.values[-1]:.4g} @ {series.steps[-1]}"
    return f"{last} (best {series.values[best]:.4g} @ {series.steps[best]})"


def stop_bound(folder: Path, metrics: dict[str, Series]) -> str:
    """The step by which the run in ``folder`` stops unless a validation improves, from its ``config.yaml`` (the
    trainer's ``EarlyStopping`` monitor, mode, ``min_delta`` and patience, ``val_check_interval``, ``min_steps`` and
    ``max_steps``) and its validations so far: ``"<step> (patience <p> after <best step>)"``, or ``"<cap> (cap)"`` when
    the patience would outlast the cap; ``"–"`` without a config or a step cap.

    As Lightning's ``EarlyStopping``: a validation improves on the best when it is better by more than ``min_delta``,
    and the run stops at the ``patience``-th validation after the best (validations at steps ``k *
    val_check_interval - 1``). The validation of the starting weights (step 0) counts, as
    :func:`lcreg.callbacks.keep_initial_weights_as_candidate` makes it the early stopping's first score (runs started
    before session 31 did not have that; for them a step-0 best understates the bound).
    """
    config = folder / "config.yaml"
    trainer = (yaml.safe_load(config.read_text(encoding="utf-8")) or {}).get("trainer", {}) if config.is_file() else {}
    cap, interval = trainer.get("max_steps") or -1, trainer.get("val_check_interval")
    stopping = [
        c.get("init_args", {}) for c in trainer.get("callbacks") or () if "EarlyStopping" in str(c.get("class_path"))
    ]
    series = metrics.get(stopping[0].get("monitor", "")) if stopping else None
    if not isinstance(interval, int) or series is None or not len(series.steps):
        return "–" if cap < 0 else f"{cap} (cap)"
    sign = 1.0 if stopping[0].get("mode", "min") == "min" else -1.0
    delta, patience = float(stopping[0].get("min_delta", 0.0)), int(stopping[0].get("patience", 3))
    best_step, best = None, float("inf")
    for step, value in zip(series.steps, series.values, strict=True):
        if sign * value < best - delta:
            best_step, best = int(step), sign * float(value)
    if best_step is None:
        return "–" if cap < 0 else f"{cap} (cap)"
    first_after = ((best_step + 1) // interval + 1) * interval - 1  # the first validation after the best
    bound = max(first_after + (patience - 1) * interval + 1, trainer.get("min_steps") or 0)
    if 0 <= cap <= bound:
        return f"{cap} (cap)"
    return f"{bound} (patience {patience} after {best_step})"


def progress_table(jobs: Sequence[Job], runs: Path, hours: float = 3.0) -> str:
    """Markdown: every run of ``jobs`` that logged in the last ``hours`` and has not finished (:func:`active_runs`),
    with the runner holding its job, the step of its last validation, the step by which it stops unless a validation
    improves (:func:`stop_bound`) and, for each of :data:`PROGRESS_KEYS`, the last value and the best so far (over the
    segments of a resumed run)."""
    keys = [k.removeprefix("val/") for k in PROGRESS_KEYS]
    header = ["job", "run", "held by", "written", "last validation", "stops by (unless it improves)", *keys]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for job in jobs:
        pid = holder(job, runs)
        for path in active_runs(job, runs, hours):
            metrics = read_metrics(path)
            shown = {key: metrics[key] for key in PROGRESS_KEYS if key in metrics and len(metrics[key].steps)}
            cells = [progress_cell(key, shown[key]) if key in shown else "–" for key in PROGRESS_KEYS]
            last = max((int(series.steps[-1]) for series in shown.values()), default=None)
            run = path.parent.relative_to(runs / job.id).as_posix()
            held = "–" if pid is None else f"pid {pid}"
            step = "none yet" if last is None else f"step {last}"
            written = f"{(time.time() - path.stat().st_mtime) / 60:.0f} min ago"
            stops = stop_bound(path.parent, metrics)
            lines.append("| " + " | ".join([job.id, run, held, written, step, stops, *cells]) + " |")
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def job_lock(job: Job, runs: Path) -> Iterator[int | None]:
    """Hold ``<runs>/<id>.lock`` (an exclusive ``flock``) while ``job`` runs here.

    Yields the lock file's descriptor, or ``None`` when another runner holds it (its pid is in the file). Pass the
    descriptor to the job's process (:func:`run_job`): the kernel releases the lock when the runner and its training
    process have both exited, killed ones included, so a runner killed without its child does not free the job for
    a second runner while the first one's training still writes the run folder.
    """
    import fcntl  # POSIX only, as `nice`

    runs.mkdir(parents=True, exist_ok=True)
    with open(runs / f"{job.id}.lock", "a+", encoding="utf-8") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield None
            return
        file.truncate(0)
        file.write(f"{os.getpid()}\n")
        file.flush()
        yield file.fileno()


def holder(job: Job, runs: Path) -> int | None:
    """The pid of the runner holding ``job``'s lock in ``runs`` (:func:`job_lock`), or ``None`` if none does."""
    import fcntl

    path = runs / f"{job.id}.lock"
    if not path.is_file():
        return None
    with open(path, encoding="utf-8") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            text = file.read().strip()
            return int(text) if text.isdigit() else -1
        return None


@dataclass(frozen=True)
class Keeping:
    """How a runner keeps a job's results while it trains (``run --sync-every``, ``--commit``).

    Attributes:
        sync_every_min: Minutes between two :func:`sync` calls while the job's process runs (``None``: only when it
            ends). Session 36 ended with a run 1,760 steps in whose resume state no sync had kept: a new machine
            started it again from step 0.
        commit: After every sync, commit the job's results folder (:func:`commit_results`), so that a session
            that ends without warning loses at most ``sync_every_min`` of any run.
    """

    sync_every_min: float | None = None
    commit: bool = False


def run_job(
    job: Job,
    runs: Path,
    results: Path,
    max_minutes: float | None,
    jobs: int = 1,
    lock_fd: int | None = None,
    keeping: Keeping = Keeping(),
    threads: int = 1,
) -> bool:
    """Run ``job`` to its end (or ``max_minutes``); on exit 0 copy its results and mark it done. Returns done.

    ``jobs``: runs at once of an ``lcreg reproduce`` or ``learning_curves.py`` job (:meth:`Job.executable`), each on
    one thread. ``lock_fd``: the descriptor of :func:`job_lock`, inherited by the job's process. ``keeping``: the
    syncs (and commits) while it trains and when it ends. ``threads``: the job's ``OMP_NUM_THREADS`` (a runner's
    ``threads``).
    """
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}
    argv = ["nice", "-n", "5", *job.executable(runs, results, jobs)]
    (results / job.id).mkdir(parents=True, exist_ok=True)
    if restored := restore(job, runs, results):
        print(f"queue: {job.id}: {restored} result files restored from {results / job.id / 'runs'}", flush=True)
    print(f"queue: {job.id}: {shlex.join(argv)}", flush=True)
    start = time.monotonic()
    process = subprocess.Popen(argv, cwd=REPO, env=env, pass_fds=() if lock_fd is None else (lock_fd,))
    code = wait_keeping(process, job, runs, results, None if max_minutes is None else start + 60 * max_minutes, keeping)
    if code is None:
        print(f"queue: {job.id}: stopped at the time limit ({max_minutes:.2g} min); resumes next call", flush=True)
        keep(job, runs, results, keeping, "time limit")
        return False
    report_failed = code == REPORT_NOT_WRITTEN_EXIT_CODE and job.argv(runs, results)[:2] == REPRODUCE
    copied = sync(job, runs, results, done=code == 0 or report_failed)
    if code != 0 and not report_failed:
        print(f"queue: {job.id}: exit code {code}; not marked done ({copied} result files copied)", flush=True)
        if keeping.commit:
            commit_results(results, job.id, f"exit code {code}")
        return False
    # The wall time of this last call only (earlier calls of a resumed job are in its rows' own training times).
    machine = machine_line(training_device())
    done = {"last_call_s": round(time.monotonic() - start, 1), "machine": machine, "files": copied}
    if report_failed:  # its runs all finished: running it again would only fail to report again, blocking the runner
        print(f"queue: {job.id}: every run finished, its report was not written: run it with --report-only", flush=True)
        done["report"] = f"not written (exit code {code}): rerun the command with --report-only"
    (results / job.id / "DONE.json").write_text(json.dumps(done) + "\n", encoding="utf-8")
    print(f"queue: {job.id}: done, last call {done['last_call_s']:.0f} s", flush=True)
    if keeping.commit:
        commit_results(results, job.id, "done")
    return True


def wait_keeping(
    process: subprocess.Popen[bytes], job: Job, runs: Path, results: Path, deadline: float | None, keeping: Keeping
) -> int | None:
    """Wait for the job's ``process``, keeping its results every ``keeping.sync_every_min`` meanwhile; returns its
    exit code, or ``None`` when ``deadline`` (``time.monotonic()``) came first (the process is then killed)."""
    every = None if keeping.sync_every_min is None else 60 * keeping.sync_every_min
    while True:
        left = None if deadline is None else deadline - time.monotonic()
        waits = [w for w in (left, every) if w is not None]
        try:
            return process.wait(timeout=max(min(waits), 0) if waits else None)
        except subprocess.TimeoutExpired:
            if deadline is not None and time.monotonic() >= deadline:
                process.kill()
                process.wait()
                return None
            keep(job, runs, results, keeping, "in training")


def keep(job: Job, runs: Path, results: Path, keeping: Keeping, why: str) -> None:
    """:func:`sync` the job, then commit its results folder when ``keeping.commit``."""
    copied = sync(job, runs, results)
    print(f"queue: {job.id}: {copied} result files synced ({why})", flush=True)
    if keeping.commit:
        commit_results(results, job.id, why)


def commit_results(results: Path, job_id: str, why: str) -> bool:
    """Commit ``results/<job_id>`` alone in the git checkout that holds it, when it changed; returns whether it did.

    Only that folder goes into the commit (``git commit -- <folder>``): whatever else is staged or edited in the
    checkout (a session's code) stays as it was. A failure (no git checkout, the index locked by another git
    command at that moment) is reported and the job trains on; the next sync commits again.
    """
    folder = (results / job_id).resolve()
    git = ["git", "-C", str(folder.parent)]

    def call(*words: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*git, *words], capture_output=True, text=True)

    if (added := call("add", "-A", "--", str(folder))).returncode != 0:
        print(f"queue: {job_id}: not committed ({added.stderr.strip() or 'git add failed'})", flush=True)
        return False
    if call("diff", "--cached", "--quiet", "--", str(folder)).returncode == 0:  # nothing new since the last commit
        return False
    message = f"Queue results: {job_id} ({why}; committed by its runner)"
    if (made := call("commit", "-q", "-m", message, "--", str(folder))).returncode != 0:
        print(f"queue: {job_id}: not committed ({made.stderr.strip() or 'git commit failed'})", flush=True)
        return False
    print(f"queue: {job_id}: committed ({why})", flush=True)
    return True


def runner_pids(runs: Path, runners: Sequence[Runner] | None = None) -> list[int]:
    """Pids of this machine's ``train_queue.py run`` processes whose ``--runs`` is ``runs`` (Linux ``/proc``); with
    ``runners``, only theirs (:func:`runs_as`)."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        with contextlib.suppress(OSError):
            argv = cmdline.read_bytes().decode(errors="replace").split("\0")
            if any(a.endswith("train_queue.py") for a in argv[1:2]) and "run" in argv and "--runs" in argv[:-1]:
                if Path(argv[argv.index("--runs") + 1]).resolve() == runs.resolve():
                    if runners is None or any(runs_as(argv, runner) for runner in runners):
                        pids.append(int(cmdline.parent.name))
    return sorted(pids)


def runs_as(argv: Sequence[str], runner: Runner) -> bool:
    """Whether the ``run`` command line ``argv`` is ``runner``'s: ``start`` names it with ``--runner``.

    Not by the jobs it runs: a job moved from one runner's list to another's (session 31) would make ``stop`` of the
    second end the first, which still runs it. A command line without ``--runner`` (started before it was passed) is
    the runner's when its ``--only`` names exactly the runner's jobs.
    """
    if names := option_values(argv, "--runner"):
        return runner.name in names
    return set(option_values(argv, "--only")) == set(runner.only)


def option_values(argv: Sequence[str], option: str) -> list[str]:
    """The values a command line gives ``option`` (``--only a b``: ``["a", "b"]``; none without it)."""
    if option not in argv:
        return []
    values = argv[argv.index(option) + 1 :]
    return list(itertools.takewhile(lambda a: not a.startswith("--"), values))


def descendants(pid: int) -> list[int]:
    """``pid``'s child processes, their children, and so on (Linux ``/proc``)."""
    parents: dict[int, list[int]] = {}
    for status in Path("/proc").glob("[0-9]*/status"):
        with contextlib.suppress(OSError, StopIteration, ValueError):
            line = next(x for x in status.read_text().splitlines() if x.startswith("PPid:"))
            parents.setdefault(int(line.split()[1]), []).append(int(status.parent.name))
    found, todo = [], [pid]
    while todo:
        children = parents.get(todo.pop(), [])
        found += children
        todo += children
    return found


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (exited, not yet reaped by its parent)."""
    with contextlib.suppress(OSError):
        return "\tZ" not in next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x[:6] == "State:")
    return False


def stop_runners(runs: Path, grace_s: float = 60.0, runners: Sequence[Runner] | None = None) -> list[int]:
    """SIGTERM the runners of ``runs`` (with ``runners``: those only) and their training processes (Lightning stops
    at the step, exit 143), SIGKILL what is left after ``grace_s``. Returns the pids signalled."""
    pids = [p for runner in runner_pids(runs, runners) for p in (runner, *descendants(runner))]
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        deadline = time.monotonic() + wait
        while any(map(alive, pids)) and time.monotonic() < deadline:
            time.sleep(0.2)
    return pids


def queue_worktree() -> Path:
    """A worktree of the repository at ``HEAD`` beside it (``wt-queue-<short sha>``), made if missing.

    Two ``start`` calls at once (one per runner) take turns under a lock in the git directory, and the worktree is
    checked out under a ``.partial`` name first and then moved: its path exists only once every file is in it, even
    if a ``start`` is killed while it checks out.
    """
    git = ["git", "-C", str(REPO)]

    def out(*args: str) -> str:
        return subprocess.run([*git, *args], capture_output=True, text=True, check=True).stdout.strip()

    tree = REPO.parent / f"wt-queue-{out('rev-parse', '--short', 'HEAD')}"
    lock = Path(out("rev-parse", "--path-format=absolute", "--git-common-dir")) / "wt-queue.lock"
    with lock.open("a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # released when the file closes
        if not tree.is_dir():
            partial = tree.with_name(tree.name + ".partial")
            if partial.exists():  # left by a killed `start`
                shutil.rmtree(partial)
            out("worktree", "prune")
            out("worktree", "add", "--detach", str(partial), "HEAD")
            out("worktree", "move", str(partial), str(tree))
    return tree


START_SYNC_MIN = 10.0
"""Minutes between a started runner's syncs of the job it trains (``start --sync-every``; :class:`Keeping`)."""
RUNNER_NICE = 10
"""Niceness ``start`` adds to a runner; its training runs 5 nicer still (:func:`run_job`), so that the session's own
work (tests, CI) gets the cores first."""
GROUP_NICE = 19
"""Niceness of a one-job runner's scheduling group (:func:`nice_group`; with ``jobs = N``, :func:`group_nice`)."""
SCHED_WEIGHTS = (1024, 820, 655, 526, 423, 335, 272, 215, 172, 137, 110, 87, 70, 56, 45, 36, 29, 23, 18, 15)
"""CPU weight of niceness 0-19 (Linux ``sched_prio_to_weight``): a group's share of the CPU is its weight's share."""


def group_nice(nice: int, jobs: int) -> int:
    """The niceness (0-19) whose weight is nearest ``jobs`` times that of ``nice``: a runner training ``jobs`` runs at
    once gets ``jobs`` shares of the CPU, as ``jobs`` one-job runners would.

    Its runs share one session, so one autogroup: at ``nice`` the three runs of a ``jobs = 3`` runner shared one
    runner's share (measured in session 28: 50 s of CPU each while every one-job runner's run had 154 s).
    """
    target = jobs * SCHED_WEIGHTS[nice]
    return min(range(len(SCHED_WEIGHTS)), key=lambda n: (abs(SCHED_WEIGHTS[n] - target), -n))


def runner_nice(runner: Runner) -> int:
    """The niceness of ``runner``'s scheduling group: ``shares`` (default ``jobs``) one-job runners' weight."""
    return group_nice(GROUP_NICE, runner.jobs if runner.shares is None else runner.shares)


def nice_group(pid: int, nice: int) -> bool:
    """Set the niceness of the Linux autogroup of session leader ``pid``; returns whether the kernel has one.

    With ``kernel.sched_autogroup_enabled`` (the default on many kernels) the scheduler first shares the CPU equally
    among sessions and applies a process's niceness only within its session. A runner runs in its own session
    (detached), so without this six runners at nice 15 took six shares of the 2 cores against one for a CI run in
    another session (measured in session 26: each training process 28 % of a core, the CI's two pytest workers 11 %
    and 5 %). The group's niceness is what ranks sessions.
    """
    try:
        Path(f"/proc/{pid}/autogroup").write_text(f"{nice}\n", encoding="utf-8")
    except OSError:  # no autogroup (another OS, or a kernel without it): the process niceness is what counts
        return False
    return True


def start_runners(
    runners: Sequence[Runner],
    checkout: Path,
    queue: Path,
    runs: Path,
    results: Path,
    named: bool = False,
    keeping: Keeping = Keeping(),
    until: datetime | None = None,
) -> list[int]:
    """Launch each runner of ``queue`` in the background (its own session, one thread) from ``checkout``; returns
    their pids. Each command line names its runner (``--runner``), by which ``stop`` finds it.

    Args:
        named: ``runners`` are those named by ``start --runner``: refuse only if one of them runs; the others go on.
            Otherwise they are all of the queue's: refuse if any runner of ``runs`` runs. Two runners never train
            one job at once whatever their lists (the job's lock, :func:`holder`).
        keeping: Passed to each runner as ``run --sync-every`` and ``--commit``.
        until: Passed to each runner as ``run --until`` (:func:`cannot_finish`).

    Raises:
        SystemExit: If runners of ``runs`` (of ``runners``, when ``named``) are running already (``stop`` them first),
            or one ended with an error at once (:func:`check_started`).
    """
    if running := runner_pids(runs, runners if named else None):
        raise SystemExit(f"runners of {runs} are running already (pids {running}): `train_queue.py stop` first")
    (runs / "logs").mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(checkout / "src"), "PYTHONUNBUFFERED": "1"}
    started: list[tuple[Runner, subprocess.Popen[bytes]]] = []
    for runner in runners:
        argv = ["nice", "-n", str(RUNNER_NICE), sys.executable, str(checkout / "benchmarks" / "train_queue.py")]
        argv += ["run", "--section", "cpu"]
        argv += ["--queue", str(queue.resolve())]
        argv += ["--only", *runner.only, "--runs", str(runs.resolve()), "--results", str(results.resolve())]
        argv += ["--jobs", str(runner.jobs)] if runner.jobs > 1 else []
        argv += ["--threads", str(runner.threads)] if runner.threads > 1 else []
        argv += ["--runner", runner.name]
        argv += [] if keeping.sync_every_min is None else ["--sync-every", f"{keeping.sync_every_min:g}"]
        argv += ["--commit"] if keeping.commit else []
        argv += [] if until is None else ["--until", until.isoformat()]
        with open(runs / "logs" / f"{runner.name}.log", "a", encoding="utf-8") as log:
            process = subprocess.Popen(
                argv, cwd=checkout, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        nice_group(process.pid, runner_nice(runner))
        runs_at_once = f" ({runner.jobs} runs at once)" if runner.jobs > 1 else ""
        runs_at_once += f" ({runner.threads} threads each)" if runner.threads > 1 else ""
        print(f"queue: runner {runner.name} (pid {process.pid}): {' '.join(runner.only)}{runs_at_once}", flush=True)
        started.append((runner, process))
    check_started(started, runs / "logs")
    return [process.pid for _, process in started]


START_CHECK_S = 3.0
"""Seconds :func:`start_runners` waits before it checks that no runner has failed at once."""


def check_started(started: Sequence[tuple[Runner, subprocess.Popen[bytes]]], logs: Path) -> None:
    """Fail if a runner just started has ended with an error within :data:`START_CHECK_S` (e.g. a checkout without
    ``train_queue.py``: session 56's second ``start`` found a half-made worktree, and its runner died unseen for
    minutes). A runner that ends cleanly (nothing it may begin before ``--until``) is no failure.

    Raises:
        SystemExit: Naming each failed runner, its exit code and the end of its log.
    """
    deadline = time.monotonic() + START_CHECK_S
    while time.monotonic() < deadline and any(process.poll() is None for _, process in started):
        time.sleep(0.1)
    failed = [(runner, process.returncode) for runner, process in started if process.poll() not in (None, 0)]
    if failed:
        tails = [
            f"runner {r.name} ended at once (exit code {code}); {logs / f'{r.name}.log'} ends:\n"
            + "\n".join((logs / f"{r.name}.log").read_text(encoding="utf-8").splitlines()[-5:])
            for r, code in failed
        ]
        raise SystemExit("\n".join(tails))


def selected(job: Job, args: argparse.Namespace) -> bool:
    """Whether ``run`` starts ``job``: the jobs of ``--section``, or the jobs named by ``--only`` whatever their section
    (a GPU session may take over a CPU job, e.g. the PRNet runs that cost 11 s a step on one CPU thread; the job's run
    folder and results are the same, so either machine continues where the other stopped)."""
    return job.id in args.only if args.only is not None else job.section == args.section


def chosen_jobs(jobs: Sequence[Job], only: Sequence[str] | None) -> list[Job]:
    """All ``jobs`` in the queue's order, or the jobs named by ``only`` in the order it names them.

    Raises:
        SystemExit: If ``only`` names a job the queue does not have (a typo would otherwise run nothing).
    """
    if only is None:
        return list(jobs)
    by_id = {job.id: job for job in jobs}
    if unknown := [name for name in only if name not in by_id]:
        raise SystemExit(f"--only: no job {', '.join(map(repr, unknown))} in the queue (ids: {', '.join(by_id)})")
    return [by_id[name] for name in dict.fromkeys(only)]


def named_runners(runners: Sequence[Runner], names: Sequence[str] | None) -> list[Runner]:
    """All ``runners``, or those ``names`` names (``start``/``stop --runner``).

    Raises:
        SystemExit: If ``names`` names a runner the queue does not have.
    """
    if names is None:
        return list(runners)
    known = {runner.name for runner in runners}
    if unknown := [name for name in names if name not in known]:
        names_known = ", ".join(sorted(known))
        raise SystemExit(f"--runner: no runner {', '.join(map(repr, unknown))} in the queue (names: {names_known})")
    return [runner for runner in runners if runner.name in names]


def default_queue(checkout: Path) -> Path:
    """The queue file of a checkout."""
    return checkout / "benchmarks" / "train_queue.toml"


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = ("status", "run", "sync", "start", "stop", "runs", "progress")
    parser.add_argument("action", nargs="?", choices=actions, default="status")
    parser.add_argument("--queue", type=Path, default=default_queue(REPO))
    parser.add_argument("--section", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument(
        "--only", nargs="+", default=None, help="job ids, in the order to run them (run: whatever their section)"
    )
    parser.add_argument("--runs", type=Path, default=REPO / "runs" / "queue", help="run folders (checkpoints)")
    parser.add_argument("--results", type=Path, default=REPO / "docs" / "results" / "converge")
    parser.add_argument(
        "--max-minutes",
        type=float,
        default=None,
        help="the time of the whole call: the jobs run in order, the one running at the limit stops (it resumes)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="runs at once of an `lcreg reproduce` or `learning_curves.py` job (a GPU; a runner's `jobs`; default 1)",
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="run: each training process's OMP_NUM_THREADS (a runner's `threads`)"
    )
    parser.add_argument("--out", type=Path, default=None, help="runs: write the table here (default: print it)")
    parser.add_argument("--hours", type=float, default=3.0, help="progress: runs that logged within these hours")
    parser.add_argument(
        "--runner",
        nargs="+",
        default=None,
        help="start/stop: only these runners (by name); the others go on (default: all). run: the name of the "
        "runner this is (start passes it; stop finds a runner by it)",
    )
    parser.add_argument(
        "--sync-every",
        type=float,
        default=None,
        metavar="MINUTES",
        help="run: sync each job's results every MINUTES while it trains, not only when it ends (start: default "
        f"{START_SYNC_MIN:g})",
    )
    parser.add_argument(
        "--commit",
        action="store_true",
        help="run, sync, start: commit each job's results folder (alone) after every sync that changed it",
    )
    parser.add_argument(
        "--until",
        type=until_time,
        default=None,
        metavar="HH:MM",
        help="run, start: when this machine is expected to go (UTC, or an ISO date and time): a machine_bound job "
        "whose wall_hours end after it is not begun; the runner goes on with its next job",
    )
    parser.add_argument(
        "--checkout",
        type=Path,
        default=None,
        help="start: the checkout the runners run from (default: a worktree at HEAD beside the repository)",
    )
    add_smoke_argument(parser)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    if args.smoke:
        scratch = Path(tempfile.mkdtemp(prefix="lcreg-queue-"))
        (scratch / "train_queue.toml").write_text(SMOKE_QUEUE, encoding="utf-8")
        args.queue, args.runs, args.results = scratch / "train_queue.toml", scratch / "runs", scratch
        args.action = "run"
    if args.action in ("start", "stop"):
        runners = named_runners(load_runners(args.queue, load_jobs(args.queue)), args.runner)
        named = args.runner is not None
        if args.action == "stop":
            stopped = stop_runners(args.runs, runners=runners if named else None)
            print(f"queue: stopped {len(stopped)} processes of the runners of {args.runs}")
            return
        checkout = args.checkout or queue_worktree()
        queue = args.queue if args.queue != default_queue(REPO) else default_queue(checkout)  # the worktree's own
        keeping = Keeping(START_SYNC_MIN if args.sync_every is None else args.sync_every, args.commit)
        start_runners(runners, checkout, queue, args.runs, args.results, named, keeping, args.until)
        return
    jobs = chosen_jobs(load_jobs(args.queue), args.only)
    if args.action == "runs":
        table = runs_table(jobs, args.results)
        if args.out is None:
            print(table, end="")
        else:
            args.out.write_text(table, encoding="utf-8")
        return
    if args.action == "progress":
        print(progress_table(jobs, args.runs, args.hours), end="")
        return
    if args.action == "status":
        for job in jobs:
            print(status_line(job, args.results, args.runs))
        return
    deadline = None if args.max_minutes is None else time.monotonic() + 60 * args.max_minutes
    for job in jobs:
        if args.action == "sync":
            print(f"queue: {job.id}: {sync(job, args.runs, args.results)} result files copied")
            if args.commit:
                commit_results(args.results, job.id, "sync")
        elif selected(job, args) and not (args.results / job.id / "DONE.json").is_file():
            minutes = None if deadline is None else (deadline - time.monotonic()) / 60
            if minutes is not None and minutes <= 0:
                print(f"queue: {job.id}: no time left of --max-minutes; it runs on the next call", flush=True)
                sys.exit(1)
            if why := cannot_finish(job, args.runs, args.until):
                print(f"queue: {job.id}: {why}", flush=True)
                continue
            with job_lock(job, args.runs) as lock_fd:
                if lock_fd is None:
                    print(f"queue: {job.id}: another runner holds {args.runs / job.id}.lock; skipped", flush=True)
                    continue
                keeping = Keeping(args.sync_every, args.commit)
                if not run_job(job, args.runs, args.results, minutes, args.jobs, lock_fd, keeping, args.threads):
                    sys.exit(1)
    if args.action == "sync":
        (args.results / "runs.md").write_text(runs_table(load_jobs(args.queue), args.results), encoding="utf-8")
    if args.smoke:
        print(status_line(jobs[0], args.results))


if __name__ == "__main__":
    main()
