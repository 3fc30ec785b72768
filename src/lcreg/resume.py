"""``--ckpt_path last``: find the latest run's ``last.ckpt`` under the configured logger and resume in its folder.

A run logs under ``<save_dir>/<name>/version_<k>/`` (CSV or TensorBoard logger) and keeps its latest state in
``version_<k>/checkpoints/last.ckpt`` (:class:`lcreg.callbacks.LatestCheckpoint`). ``last`` is the ``last.ckpt`` of
the highest-numbered version that has one (``lcreg test``/``predict`` runs log to versions without checkpoints);
``fit`` then logs to that same version (:class:`lcreg.cli.LcregCLI` sets the logger's ``version``). Without a
logger, ``last`` is ``<default_root_dir>/checkpoints/last.ckpt``; a ``ModelCheckpoint`` with its own ``dirpath`` is
searched there.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcreg.checkpoints import CheckpointNotFoundError

__all__ = [
    "TERMINATED_EXIT_CODE",
    "LastCheckpoint",
    "best_checkpoint_of",
    "changed_settings",
    "find_last_checkpoint",
    "keep_previous_metrics",
    "restore_unlogged_metrics",
    "set_aside_metrics",
    "set_aside_run",
]

LAST = "last.ckpt"
TERMINATED_EXIT_CODE = 143
"""Exit status of training stopped by SIGTERM (128 + 15): ``lcreg fit`` and the benchmark harness's ``fit``.
Lightning ends ``fit`` on SIGTERM with ``SIGTERMException``, a ``SystemExit`` of code ``None`` (exit status 0), so a
scheduler or the training queue would take a preempted run for a finished one; ``last.ckpt`` resumes it."""
_VERSION = re.compile(r"^version_(\d+)$")
_VERSIONED_LOGGERS = ("CSVLogger", "TensorBoardLogger")


@dataclass(frozen=True)
class LastCheckpoint:
    """The checkpoint ``last`` resolves to and, for a versioned logger, the version folder it belongs to."""

    path: Path
    version: int | str | None = None


def _get(node: Any, key: str, default: Any = None) -> Any:
    """``node[key]`` for dicts and jsonargparse Namespaces (``default`` when absent)."""
    if isinstance(node, Mapping):
        return node.get(key, default)
    return getattr(node, key, default) if node is not None else default


def _listed_dirpath(trainer: Any) -> Path | None:
    """The ``dirpath`` of a ``ModelCheckpoint`` listed in the trainer config, if one sets it."""
    for callback in _get(trainer, "callbacks") or []:
        if "ModelCheckpoint" in str(_get(callback, "class_path", "")):
            dirpath = _get(_get(callback, "init_args"), "dirpath")
            if dirpath:
                return Path(dirpath)
    return None


def _version_dirs(root: Path) -> list[tuple[int | str, Path]]:
    """``(version, folder)`` of ``root``'s ``version_<k>`` folders, highest ``k`` first."""
    found = [(int(m.group(1)), p) for p in root.glob("version_*") if (m := _VERSION.match(p.name)) and p.is_dir()]
    return sorted(found, key=lambda item: item[0], reverse=True)


def find_last_checkpoint(trainer: Any) -> LastCheckpoint:
    """The ``last.ckpt`` that ``--ckpt_path last`` means under a trainer config (``trainer`` key of the CLI config).

    Raises:
        CheckpointNotFoundError: No ``last.ckpt`` exists where the configured run would write it (nothing to
            resume), or the configured logger has no version folders to search (pass the file instead).
    """
    listed = _listed_dirpath(trainer)
    if listed is not None:
        return _existing(LastCheckpoint(listed / LAST))
    logger = _get(trainer, "logger")
    root_dir = Path(_get(trainer, "default_root_dir") or ".")
    if logger is None or logger is False:
        return _existing(LastCheckpoint(root_dir / "checkpoints" / LAST))
    if logger is True:
        save_dir, name, version = root_dir, "lightning_logs", None
    else:
        class_path = str(_get(logger, "class_path", ""))
        if not class_path.endswith(_VERSIONED_LOGGERS):
            raise CheckpointNotFoundError(
                LAST,
                f"`--ckpt_path last` is resolved for CSV/TensorBoard loggers only, not {class_path or logger!r}: "
                "pass the checkpoint file (`--ckpt_path <run>/checkpoints/last.ckpt`)",
            )
        args = _get(logger, "init_args")
        save_dir, name, version = Path(_get(args, "save_dir", ".")), _get(args, "name", ""), _get(args, "version")
    root = save_dir / (name or "")
    if version is not None:
        folder = root / (version if isinstance(version, str) else f"version_{version}")
        return _existing(LastCheckpoint(folder / "checkpoints" / LAST, version))
    for number, folder in _version_dirs(root):
        if (folder / "checkpoints" / LAST).is_file():
            return LastCheckpoint(folder / "checkpoints" / LAST, number)
    raise CheckpointNotFoundError(root / "version_*" / "checkpoints" / LAST, "nothing to resume (no such file)")


def best_checkpoint_of(last: Path) -> Path:
    """The checkpoint chosen on validation by the run whose latest state is ``last`` (``--ckpt_path best``).

    It is the ``best_model_path`` that the run's first ``ModelCheckpoint`` recorded in ``last`` (the default one
    monitors ``val/rre_mean_deg``); a run folder moved since is followed (the file of that name beside ``last``).

    Raises:
        CheckpointNotFoundError: ``last`` records no best checkpoint (no validation ran yet), or its file is gone.
        lcreg.checkpoints.CheckpointError: ``last`` itself cannot be read.
    """
    from lcreg.checkpoints import read_checkpoint

    states = read_checkpoint(last).get("callbacks") or {}
    recorded = [
        str(state.get("best_model_path") or "")
        for key, state in states.items()
        if str(key).startswith("ModelCheckpoint") and isinstance(state, dict)
    ]
    if not recorded or not recorded[0]:
        raise CheckpointNotFoundError(last, "the run recorded no checkpoint chosen on validation (did it validate?)")
    for candidate in (Path(recorded[0]), last.parent / Path(recorded[0]).name):
        if candidate.is_file():
            return candidate
    raise CheckpointNotFoundError(recorded[0], f"the best checkpoint recorded in {last} no longer exists")


def _existing(last: LastCheckpoint) -> LastCheckpoint:
    if not last.path.is_file():
        raise CheckpointNotFoundError(last.path, "nothing to resume (no such file)")
    return last


def keep_previous_metrics(log_dir: Path) -> Path | None:
    """Rename ``log_dir/metrics.csv`` to ``metrics.segment<n>.csv`` (first free ``n``) before a resumed run logs.

    Lightning's CSV logger deletes an existing ``metrics.csv`` when it logs into a used folder; the renamed file
    keeps the earlier segment's rows (including any logged after its last checkpoint).

    Returns:
        The new path, or ``None`` when there was no ``metrics.csv``.
    """
    metrics = log_dir / "metrics.csv"
    if not metrics.is_file():
        return None
    n = 1
    while (target := log_dir / f"metrics.segment{n}.csv").exists():
        n += 1
    metrics.rename(target)
    return target


def restore_unlogged_metrics(kept: Path | None, loggers: Sequence[Any] = ()) -> None:
    """Undo :func:`keep_previous_metrics` when the resumed run logged nothing (no new ``metrics.csv``).

    A run resumed at its step cap (or stopped before its first log) trains no step: the renamed file goes back to
    ``metrics.csv`` instead of leaving the run without one and a segment that duplicates the earlier file.

    Args:
        kept: What :func:`keep_previous_metrics` returned.
        loggers: The trainer's loggers, if it logs on (e.g. a test): each ``CSVLogger`` (or subclass) appends to the
            file put back; other loggers are left alone.
    """
    if kept is not None and kept.is_file() and not (metrics := kept.parent / "metrics.csv").exists():
        kept.rename(metrics)
        for logger in loggers:
            _append_to(logger, metrics)


def _append_to(logger: Any, metrics: Path) -> None:
    """Let a ``CSVLogger`` that has written nothing yet append to ``metrics``, an earlier segment's file.

    Lightning's CSV writer rewrites its file with the columns it has logged itself whenever a new column comes: on a
    file it did not write, the earlier columns made it fail (session 56: a converge run resumed at its cap and then
    tested, ``ValueError: dict contains fields not in fieldnames``). It learns the file's columns first.
    """
    from lightning.fabric.loggers import CSVLogger  # lazy: this module stays free of Lightning at import

    writer = logger.experiment if isinstance(logger, CSVLogger) else None  # subclasses too
    keys = getattr(writer, "metrics_keys", None)
    if not isinstance(keys, list) or not metrics.is_file():
        return
    with metrics.open(newline="", encoding="utf-8") as file:
        header = next(csv.reader(file), [])
    keys.extend(key for key in header if key not in keys)
    keys.sort()  # as the writer keeps them


SETTING_SECTIONS = ("model", "data")
"""The sections of a run's ``config.yaml`` that define what it trains (the trainer's may change between segments)."""
MACHINE_KEYS = frozenset({"root", "num_workers"})
"""Keys whose values differ between machines, not between runs (the data folder, the loader's processes)."""


def changed_settings(saved: Mapping[str, Any], current: Mapping[str, Any]) -> list[str]:
    """Dotted keys of :data:`SETTING_SECTIONS` whose values differ between two configs (as ``config.yaml`` holds them).

    For a run folder's ``config.yaml`` (the segment trained last) against the run about to resume there: a change
    (a learning rate, the crop, the training objects) makes it another run, which must not continue that state. Keys
    present in one config only (an option added to the code since) and :data:`MACHINE_KEYS` do not count.

    Returns:
        The differing keys, sorted (``[]``: the same run).
    """

    def walk(a: Any, b: Any, key: str) -> list[str]:
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            shared = sorted(k for k in a.keys() & b.keys() if k not in MACHINE_KEYS)
            return [found for k in shared for found in walk(a[k], b[k], f"{key}.{k}" if key else str(k))]
        return [] if a == b else [key]

    return walk(
        {k: saved[k] for k in SETTING_SECTIONS if k in saved},
        {k: current[k] for k in SETTING_SECTIONS if k in current},
        "",
    )


def set_aside_run(log_dir: Path) -> Path:
    """Move a run's state out of ``log_dir`` to ``log_dir/superseded/<n>/`` (first free ``n``), to start afresh there.

    That is ``checkpoints/``, ``config.yaml``, ``hparams.yaml`` and the metrics files.
    For an unfinished run whose settings differ from the run now started in its folder (:func:`changed_settings`):
    nothing of it is deleted. Returns the new folder.
    """
    names = ("checkpoints", "config.yaml", "hparams.yaml", "metrics.csv")
    moving = [log_dir / name for name in names if (log_dir / name).exists()] + sorted(
        log_dir.glob("metrics.segment*.csv")
    )
    return _move_into_new(log_dir / "superseded", moving)


def _move_into_new(parent: Path, paths: list[Path]) -> Path:
    """Move ``paths`` into ``parent/<n>/``, the first ``n`` (1, 2, ...) not taken; returns that folder."""
    n = 1
    while (target := parent / str(n)).exists():
        n += 1
    target.mkdir(parents=True)
    for path in paths:
        path.rename(target / path.name)
    return target


def set_aside_metrics(log_dir: Path) -> Path | None:
    """Move a lost run's ``metrics.csv`` and ``metrics.segment<n>.csv`` to ``log_dir/abandoned/<n>/`` (first free n).

    For a run that starts from scratch in a used folder, e.g. on a new machine that restored the committed logs of a
    run whose checkpoints were lost: left in place, those files would be read as earlier segments of the new curve
    (:func:`lcreg.experiments.benchmarking.curves.segments`). Moved, they keep the lost run's record.

    Returns:
        The new folder, or ``None`` when there was nothing to move.
    """
    stale = sorted(log_dir.glob("metrics.segment*.csv")) + [p for p in [log_dir / "metrics.csv"] if p.is_file()]
    return _move_into_new(log_dir / "abandoned", stale) if stale else None
