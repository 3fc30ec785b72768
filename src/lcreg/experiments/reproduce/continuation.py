"""Continue a ``converge`` run that its step cap cut off, under a higher cap (``lcreg reproduce --continue-from``).

A ``converge`` run stops when its validation stops improving or at its step cap (``trainer.max_steps``, the budget's
``steps`` or a ``--set`` of it). A run that reached the cap was still improving, so the sweep keeps its ``last.ckpt``
and its selected checkpoint beside ``selected_weights.pt`` (:func:`keeps_resume_state`). A sweep with a higher cap
and ``--continue-from <earlier --out>`` starts each of its runs from that state instead of from step 0: the earlier
run's checkpoints and metrics files are copied into the new run's folder (the ``ModelCheckpoint`` paths inside
``last.ckpt`` moved with them), and the run resumes there as a cut-off run does
(:func:`lcreg.experiments.benchmarking.fit` with ``resume=True``): same weights, optimiser, scheduler, early-stopping
and checkpoint-selection state, random numbers and position in the training stream, so it ends where a run trained
from step 0 to the higher cap ends, and its selection and curve cover both segments.

The earlier run is the newest row of ``<earlier out>/<stem>.jsonl`` with the new run's experiment, variant, seed,
data, budget and config values apart from ``trainer.max_steps``.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lcreg.checkpoints import read_checkpoint
from lcreg.experiments.benchmarking import ResultLog
from lcreg.experiments.reproduce.stops import recorded_file, stopped_early
from lcreg.resume import LAST, set_aside_metrics

CAP_KEY = "trainer.max_steps"
"""The config key of a run's step cap: the one value a continued run may change."""
SETTINGS_MARK = "; set "
"""Where the ``--set`` values begin in a row's budget text (``Sweep.settings_text``)."""


class ContinuationError(ValueError):
    """No earlier run to continue: none matches, it stopped early, its cap is not lower, or its state is gone."""


@dataclass(frozen=True)
class CappedRun:
    """An earlier run that reached its step cap, with the state it resumes from.

    Attributes:
        row: Its JSONL row.
        run_dir: Its run folder (``selected_weights.pt``).
        log_dir: Its log folder (``metrics.csv``, ``config.yaml`` and ``checkpoints/``).
    """

    row: dict[str, Any]
    run_dir: Path
    log_dir: Path

    @property
    def steps(self) -> int:
        """The steps it trained: its cap."""
        return int(self.row["steps"])


def keeps_resume_state(converge: bool, steps: int, cap: int) -> bool:
    """Whether a finished run keeps ``last.ckpt`` and its selected checkpoint: a ``converge`` run that hit its cap."""
    return converge and steps >= cap


def _without_cap(values: Mapping[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in values.items() if key != CAP_KEY}


def _matches(row: Mapping[str, Any], key: Mapping[str, Any], overrides: Mapping[str, Any]) -> bool:
    """Whether ``row`` is the run of ``key`` with the config values ``overrides``, apart from the step cap."""
    same = all(row.get(field) == value for field, value in key.items() if field != "budget")
    budget = str(row.get("budget", "")).split(SETTINGS_MARK)[0] == str(key["budget"]).split(SETTINGS_MARK)[0]
    return same and budget and _without_cap(row.get("overrides") or {}) == _without_cap(overrides)


def capped_run(log: ResultLog, key: Mapping[str, Any], overrides: Mapping[str, Any], cap: int) -> CappedRun:
    """The earlier run that a run of ``key`` continues (the newest matching row of ``log``).

    Args:
        log: The earlier sweep's JSONL (``<earlier out>/<stem>.jsonl``; its files are looked for under that folder
            too, :func:`~lcreg.experiments.reproduce.stops.recorded_file`).
        key: The new run's key (experiment, variant, seed, budget, data).
        overrides: The new run's config values (its variant's and ``--set``'s).
        cap: The new run's step cap.

    Raises:
        ContinuationError: No such row, a failed run, a run that stopped early, a cap not below ``cap``, or a run
            folder without its ``last.ckpt`` or selected checkpoint; the message names the run and the file.
    """
    name = f"{key['variant']} seed {key['seed']}"
    rows = [row for row in log.rows if _matches(row, key, overrides)]
    if not rows:
        raise ContinuationError(
            f"{name}: {log.path} has no run of this budget, data and config apart from {CAP_KEY} to continue"
        )
    row = rows[-1]
    if "failed" in row:
        raise ContinuationError(f"{name}: the run in {log.path} failed ({row['failed']}); nothing to continue")
    steps = int(row["steps"])
    if stopped_early(row):  # rows before session 44 compared a raised cap's steps with the budget's own
        raise ContinuationError(
            f"{name}: the run in {log.path} stopped early at step {steps} (its validation stopped improving), "
            "not at its cap: a higher cap does not continue it"
        )
    if steps >= cap:
        raise ContinuationError(f"{name}: the run in {log.path} trained {steps} steps; {CAP_KEY} {cap} is not above")
    weights = recorded_file(row, "weights", log.path.parent)
    metrics = recorded_file(row, "metrics_csv", log.path.parent)
    if weights is None or metrics is None:
        raise ContinuationError(f"{name}: the run folder of the row in {log.path} is not there (another machine's?)")
    checkpoints = metrics.parent / "checkpoints"
    for needed in (checkpoints / LAST, checkpoints / str(row.get("selected"))):
        if not needed.is_file():
            raise ContinuationError(
                f"{name}: {needed} is missing: the run cannot be continued (runs that finished before the sweep "
                "kept the state of capped runs deleted it)"
            )
    return CappedRun(dict(row), weights.parent, metrics.parent)


def _moved(value: Any, old: str, new: str) -> Any:
    """``value`` with a leading ``old`` folder replaced by ``new`` in strings and dict keys (nested)."""
    if isinstance(value, str):
        return new + value[len(old) :] if value == old or value.startswith(old + "/") else value
    if isinstance(value, dict):
        return {_moved(k, old, new): _moved(v, old, new) for k, v in value.items()}
    return value


def _moved_callback(name: Any, state: Any, checkpoints: Path) -> Any:
    """A ``ModelCheckpoint``'s state with its folder (``dirpath``, as it was recorded) moved to ``checkpoints``."""
    if not str(name).startswith("ModelCheckpoint") or not isinstance(state, dict) or not state.get("dirpath"):
        return state
    return _moved(state, str(state["dirpath"]), str(checkpoints))


def continue_into(source: CappedRun, log_dir: Path) -> bool:
    """Start the run logging to ``log_dir`` from ``source``'s state, unless it has its own ``last.ckpt`` already.

    Copies ``source``'s metrics files (its curve so far), ``config.yaml``, ``last.ckpt`` (its ``ModelCheckpoint``
    paths moved to ``log_dir``) and selected checkpoint. Metrics files of a lost continuation in ``log_dir`` (no
    checkpoint) are set aside first (:func:`lcreg.resume.set_aside_metrics`).

    Returns:
        Whether the state was copied (``False``: the continuation resumes from its own checkpoint).
    """
    checkpoints = log_dir / "checkpoints"
    if (checkpoints / LAST).is_file():
        return False
    set_aside_metrics(log_dir)
    checkpoints.mkdir(parents=True, exist_ok=True)
    for path in [*sorted(source.log_dir.glob("metrics*.csv")), source.log_dir / "config.yaml"]:
        if path.is_file():
            shutil.copy2(path, log_dir / path.name)
    shutil.copy2(source.log_dir / "checkpoints" / str(source.row["selected"]), checkpoints)
    state = read_checkpoint(source.log_dir / "checkpoints" / LAST)
    callbacks = state.get("callbacks") or {}
    state["callbacks"] = {name: _moved_callback(name, value, checkpoints) for name, value in callbacks.items()}
    partial = checkpoints / f"{LAST}.partial"
    torch.save(state, partial)
    partial.replace(checkpoints / LAST)  # whole or absent: a run killed here starts the copy again
    return True
