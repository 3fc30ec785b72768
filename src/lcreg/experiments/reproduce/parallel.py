"""``lcreg reproduce ... --jobs N``: train the unfinished runs of a sweep N at a time, each in its own process.

One run (variant, seed) is one ``python -m lcreg reproduce <experiment> --only <variant> --seeds <seed>
--no-report`` process with the sweep's budget, data and output folder; it appends its row to the shared JSONL (one
line written at once, in append mode) and logs to ``<run folder>/worker.log``. On a GPU the runs of a small-batch
sweep leave most of the device idle, so several at once finish sooner; on a CPU each run keeps its one thread. On
Linux a worker is ended (SIGTERM, so it keeps its ``last.ckpt``) when the command that started it dies, e.g. when the
training queue stops a chunk.
"""

from __future__ import annotations

import ctypes
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from lcreg.experiments.reproduce.sweep import Sweep, pending_runs
from lcreg.resume import TERMINATED_EXIT_CODE

__all__ = ["WorkerRun", "WorkersFailedError", "run_workers", "worker_runs"]

POLL_S = 0.5
"""Seconds between checks of the running workers."""


class WorkersFailedError(RuntimeError):
    """Some worker processes of ``--jobs`` exited with an error (their runs have no row).

    Attributes:
        exit_code: :data:`~lcreg.resume.TERMINATED_EXIT_CODE` when a worker was stopped by a signal (the run
            resumes), else 1.
    """

    def __init__(self, failed: Sequence[tuple[str, int]]) -> None:
        stopped = (TERMINATED_EXIT_CODE, -signal.SIGTERM, -signal.SIGKILL)
        self.exit_code = TERMINATED_EXIT_CODE if any(code in stopped for _, code in failed) else 1
        names = ", ".join(f"{name} (exit {code})" for name, code in failed)
        super().__init__(f"{len(failed)} run(s) did not finish: {names}; see worker.log in their run folders")


@dataclass(frozen=True)
class WorkerRun:
    """One unfinished run of a sweep and the process that trains it.

    Attributes:
        name: ``"<variant> seed <k>"``.
        argv: The worker's command line.
        log: Its output file (``<run folder>/worker.log``).
    """

    name: str
    argv: tuple[str, ...]
    log: Path


def worker_runs(sweep: Sweep, options: Sequence[str], rerun: bool) -> list[WorkerRun]:
    """The worker command of every pending run.

    Args:
        sweep: The sweep.
        options: Arguments every worker repeats (``--budget``, ``--root``, ``--out``, ``--protocol``).
        rerun: Rerun finished runs too (``--no-resume``).
    """
    head = [sys.executable, "-m", "lcreg", "reproduce", sweep.experiment.name, *options, "--no-report"]
    log = sweep.open_log()
    return [
        WorkerRun(
            f"{variant.key} seed {seed}",
            (*head, "--only", _escape(variant.key), "--seeds", str(seed), *(["--no-resume"] if rerun else [])),
            sweep.run_dir(variant, seed, log) / "worker.log",
        )
        for variant, seed in pending_runs(sweep, rerun, log)
    ]


def run_workers(
    runs: Sequence[WorkerRun],
    jobs: int,
    progress: Callable[[str], None] = print,
    on_finish: Callable[[], object] | None = None,
) -> None:
    """Run ``runs`` at most ``jobs`` at a time and wait for all of them.

    ``on_finish`` is called after each worker that exits 0 (its row is in the JSONL), e.g. to write the report of
    what has finished so far while the others train.

    Raises:
        ValueError: If ``jobs`` < 1.
        WorkersFailedError: If a worker exited with a non-zero status (after all of them ended).
    """
    if jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {jobs}")
    queue, failed = list(runs), []
    running: dict[WorkerRun, subprocess.Popen[bytes]] = {}
    while queue or running:
        while queue and len(running) < jobs:
            run = queue.pop(0)
            run.log.parent.mkdir(parents=True, exist_ok=True)
            with run.log.open("ab") as out:
                running[run] = subprocess.Popen(
                    run.argv, stdout=out, stderr=subprocess.STDOUT, preexec_fn=_end_with_parent
                )
            progress(f"{run.name}: started ({len(running)} running, {len(queue)} waiting)")
        time.sleep(POLL_S)
        for run, process in list(running.items()):
            if (code := process.poll()) is not None:
                del running[run]
                progress(f"{run.name}: {'finished' if code == 0 else f'exit {code}'}")
                failed += [(run.name, code)] if code else []
                if code == 0 and on_finish is not None:
                    on_finish()
    if failed:
        raise WorkersFailedError(failed)


def _escape(key: str) -> str:
    """``key`` as an fnmatch pattern that matches only itself (``--only`` takes patterns)."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in key)


def _end_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM this process when its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere nothing."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
