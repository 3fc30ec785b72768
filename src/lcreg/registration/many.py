"""``lcreg register --pairs FILE``: register every pair of a list, write a results CSV and score the estimates.

Pair lists (:func:`lcreg.data.pairlists.read_pair_list`): a CSV of ``src,ref[,gt]`` rows, a 3DMatch scene (its
``gt.log``) or benchmark folder (all scenes), or a KITTI json pair list. Each file is read, its voxel size chosen and
its features computed once per run (fragments appear in many pairs), so ``ms/pair`` is amortised over the run.

Scores, where the list has a ground truth:

* RRE (geodesic rotation error, degrees), RTE (translation error, cloud units) and their recall at ``--rre`` /
  ``--rte`` (defaults by kind: 3DMatch 15° / 0.3 m, KITTI 5° / 2 m, CSV 5° and no translation threshold);
* 3DMatch pairs (``gt.info`` present): the official registration recall, the share of the scored pairs (fragments
  ``j - i > 1``) whose ground-truth correspondences have an RMSE below ``--rmse`` (0.2 m), computed from the
  ``gt.info`` covariance (:func:`lcreg.metrics.functional.correspondence_rmse_sq`); per scene and its mean over
  scenes (the number papers report) and over all scored pairs.

The results CSV gets one row per pair as soon as it is done (a killed run keeps them; ``--resume`` runs only the
missing pairs); a ``<results>.summary.json`` holds the scores.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import math
import sys
import time
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lcreg.checkpoints import CheckpointError, one_line
from lcreg.checks import MissingDependencyError
from lcreg.data.pairlists import ListedPair, read_pair_list
from lcreg.registration.api import LowFitnessWarning, Registration, register_clouds, resolve_methods
from lcreg.registration.inputs import Cloud, as_cloud
from lcreg.registration.methods import Method, PreparedCache, threads
from lcreg.registration.voxel import TARGET_POINTS, cloud_voxel_size, round_voxel_size

__all__ = ["COLUMNS", "PairRow", "Thresholds", "default_thresholds", "register_pairs", "run_pairs", "summarize"]

COLUMNS = (
    "name", "group", "source", "reference", "method", "voxel_size", "fitness", "inlier_rmse", "time_ms",
    "rre_deg", "rte", "success", "rmse", "scored", *(f"t{i}{j}" for i in range(4) for j in range(4)),
    "coarse_time_ms", "coarse_rre_deg", "coarse_rte", "coarse_success", "coarse_rmse", "error", "fallback",
)  # fmt: skip
"""Columns of the results CSV; ``coarse_*`` hold the coarse step of a pipeline (``ransac`` of ``ransac+icp``):
its time and errors, so one run also scores the coarse method alone (the same computation, its time included).
``error`` is empty for a registered pair; for a pair that could not be registered (a damaged, empty or missing file)
it holds the reason, the pair counts as failed (a 3DMatch-scored pair too) and the run goes on. ``fallback`` is
empty unless ``--fallback`` ran on the pair (its fitness was below ``--min-fitness``): then it names the method whose
result was kept. ``method`` is always the method asked for."""


@dataclass(frozen=True)
class Thresholds:
    """Recall thresholds: rotation (degrees), translation (cloud units; ``inf``: none), 3DMatch RMSE (units)."""

    rre_deg: float
    rte: float
    rmse: float = 0.2


def default_thresholds(pairs: Sequence[ListedPair]) -> Thresholds:
    """The standard thresholds of the list's kind: 3DMatch 15° / 0.3 m, KITTI 5° / 2 m, CSV 5° / none.

    The scene values are those ``lcreg test`` logs (the DataModules' ``recall_thresholds``): one source of truth.
    """
    from lcreg.data.kitti import KITTIOdometryDataModule
    from lcreg.data.threedmatch import SevenScenesDataModule

    if any(p.info is not None for p in pairs):
        return Thresholds(*SevenScenesDataModule.recall_thresholds[0])
    if pairs and all(p.path_src.suffix.lower() == ".bin" for p in pairs):
        return Thresholds(*KITTIOdometryDataModule.recall_thresholds[0])
    return Thresholds(5.0, math.inf)


@dataclass
class PairRow:
    """One pair's result: the registration and its errors (NaN without ground truth), or why it failed."""

    pair: ListedPair
    result: Registration | None
    rre_deg: float
    rte: float
    rmse: float
    success: bool | None
    coarse: tuple[float, float, float, bool | None] | None = None
    error: str = ""
    time_s: float = 0.0
    method: str = ""

    @classmethod
    def failed(cls, pair: ListedPair, method: Method, error: str, time_s: float, label: str | None = None) -> PairRow:
        """The row of a pair that could not be registered: a failure wherever it is scored."""
        has_gt = pair.transform_ref_src is not None
        rmse = math.inf if pair.info is not None else math.nan  # scored pairs count as failed
        coarse = (math.nan, math.nan, rmse, False if has_gt else None) if method.refine is not None else None
        success = False if has_gt else None
        return cls(pair, None, math.nan, math.nan, rmse, success, coarse, error, time_s, label or method.name)

    def as_csv(self) -> dict[str, Any]:
        """The CSV row (:data:`COLUMNS`)."""
        result = self.result
        out = {
            "name": self.pair.name,
            "group": self.pair.group,
            "source": str(self.pair.path_src),
            "reference": str(self.pair.path_ref),
            "method": self.method,
            "voxel_size": "" if result is None else f"{result.voxel_size:.6g}",
            "fitness": "" if result is None else f"{result.fitness:.6f}",
            "inlier_rmse": "" if result is None else f"{result.inlier_rmse:.6g}",
            "time_ms": f"{1000 * (self.time_s if result is None else result.time_s):.1f}",
            "rre_deg": f"{self.rre_deg:.6g}",
            "rte": f"{self.rte:.6g}",
            "success": "" if self.success is None else int(self.success),
            "rmse": f"{self.rmse:.6g}",
            "scored": int(self.pair.scored),
            "error": self.error,
            "fallback": "" if result is None else result.extra.get("fallback", {}).get("kept", ""),
        }
        transform = np.full((4, 4), np.nan) if result is None else result.transform
        out |= {f"t{i}{j}": f"{transform[i, j]:.10g}" for i in range(4) for j in range(4)}
        coarse_time = self.time_s if result is None else result.coarse_time_s
        rre, rte, rmse, success = self.coarse or (math.nan, math.nan, math.nan, None)
        return out | {
            "coarse_time_ms": "" if coarse_time is None or self.coarse is None else f"{1000 * coarse_time:.1f}",
            "coarse_rre_deg": "" if self.coarse is None else f"{rre:.6g}",
            "coarse_rte": "" if self.coarse is None else f"{rte:.6g}",
            "coarse_success": "" if success is None else int(success),
            "coarse_rmse": "" if self.coarse is None else f"{rmse:.6g}",
        }


def _errors(pair: ListedPair, transform: np.ndarray) -> tuple[float, float, float]:
    """``(RRE degrees, RTE, 3DMatch correspondence RMSE)`` of one estimate (NaN where not defined)."""
    if pair.transform_ref_src is None:
        return math.nan, math.nan, math.nan
    from lcreg.metrics import functional as F

    pred = torch.from_numpy(np.array(transform, dtype=np.float64))[None]
    gt = torch.from_numpy(np.array(pair.transform_ref_src, dtype=np.float64))[None]
    rre = float(F.rotation_error_deg(pred, gt)[0])
    rte = float(F.translation_error(pred, gt)[0])
    rmse = math.nan
    if pair.info is not None:
        info = torch.from_numpy(np.array(pair.info, dtype=np.float64))[None]
        rmse = math.sqrt(max(float(F.correspondence_rmse_sq(pred, gt, info)[0]), 0.0))
    return rre, rte, rmse


def _success(pair: ListedPair, rre: float, rte: float, thresholds: Thresholds) -> bool | None:
    if pair.transform_ref_src is None:
        return None
    return bool(rre < thresholds.rre_deg and rte < thresholds.rte)


class _Clouds:
    """Files read once and their automatic voxel sizes computed once per run."""

    def __init__(self, target_points: int) -> None:
        self.target = target_points
        self.read = functools.lru_cache(maxsize=32)(self._read)
        self.voxel = functools.lru_cache(maxsize=4096)(self._voxel)

    def _read(self, path: Path, name: str) -> Cloud:
        return as_cloud(path, name)

    def _voxel(self, path: Path) -> float:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return cloud_voxel_size(self.read(path, "points").points, self.target)


def register_pairs(
    pairs: Iterable[ListedPair],
    method: Method,
    thresholds: Thresholds,
    *,
    weights: str | None = None,
    voxel_size: float | None = None,
    target_points: int = TARGET_POINTS,
    seed: int = 0,
    fallback: Method | None = None,
    min_fitness: float | None = None,
    small: Method | None = None,
    label: str | None = None,
) -> Iterable[PairRow]:
    """Register each pair (files read, voxel sizes and features computed once per file), yielding its row.

    Args:
        pairs: Pairs of :func:`lcreg.data.pairlists.read_pair_list`.
        method: Parsed method.
        thresholds: Recall thresholds (for :attr:`PairRow.success`).
        weights: Learned methods' weights.
        voxel_size: One ``v`` for every pair (``None``: automatic per pair, rounded to the ``2^(k/4)`` grid).
        target_points: Points per cloud after downsampling.
        seed: Seed of the networks' point samples.
        fallback: Method run on a pair whose result's fitness is below ``min_fitness`` (:func:`register_clouds`).
        min_fitness: Fitness below which a result counts as failed.
        small: Method for pairs of clouds with at most ``target_points`` points each.
        label: The ``method`` of the rows (default: ``method``'s name; ``"default"`` for the default pipeline).

    Yields:
        One :class:`PairRow` per pair, in order.
    """
    clouds, cache = _Clouds(target_points), PreparedCache(size=64)
    for pair in pairs:
        start = time.perf_counter()
        try:
            src, ref = clouds.read(pair.path_src, "points_src"), clouds.read(pair.path_ref, "points_ref")
            v = voxel_size or round_voxel_size(max(clouds.voxel(pair.path_src), clouds.voxel(pair.path_ref)))
            with warnings.catch_warnings(record=True) as caught:  # one line per run, not per pair (run_pairs)
                warnings.simplefilter("always", LowFitnessWarning)
                result = register_clouds(
                    src, ref, method, weights=weights, voxel_size=v, target_points=target_points, seed=seed,
                    cache=cache, fallback=fallback, min_fitness=min_fitness, small=small,
                )  # fmt: skip
            for warning in caught:
                if not issubclass(warning.category, LowFitnessWarning):
                    warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
            if any(issubclass(w.category, LowFitnessWarning) for w in caught):
                result.extra["warned"] = True
        except (CheckpointError, MissingDependencyError):
            raise  # the run's weights or method, not this pair: nothing else would register either
        except (OSError, ValueError) as err:  # this pair's files: damaged, empty, missing, too small
            reason = f"{type(err).__name__}: {one_line(str(err))}"
            yield PairRow.failed(pair, method, reason, time.perf_counter() - start, label)
            continue
        rre, rte, rmse = _errors(pair, result.transform)
        coarse = None
        if result.coarse_transform is not None:
            c_rre, c_rte, c_rmse = _errors(pair, result.coarse_transform)
            coarse = (c_rre, c_rte, c_rmse, _success(pair, c_rre, c_rte, thresholds))
        success = _success(pair, rre, rte, thresholds)
        yield PairRow(pair, result, rre, rte, rmse, success, coarse, method=label or method.name)


def _median(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def _recall(rows: list[dict[str, Any]], thresholds: Thresholds, p: str) -> float:
    """Share of ``rows`` with RRE and RTE below ``thresholds`` (from the errors: a resumed run may set others)."""
    return float(np.mean([float(r[f"{p}rre_deg"]) < thresholds.rre_deg and float(r[f"{p}rte"]) < thresholds.rte
                          for r in rows]))  # fmt: skip


def _group_scores(
    rows: list[dict[str, Any]], thresholds: Thresholds, p: str = "", standard: Thresholds | None = None
) -> dict[str, Any]:
    """Scores of CSV rows (values as read back): counts, recall, medians, 3DMatch recall, ms/pair.

    ``p="coarse_"`` scores the coarse step of a pipeline from its ``coarse_*`` columns; ``standard`` adds
    ``recall_standard``, the recall at the list kind's standard thresholds (when the user set others).
    """
    with_gt = [r for r in rows if r[f"{p}success"] != ""]
    out: dict[str, Any] = {
        "pairs": len(rows),
        "failed": sum(1 for r in rows if r["error"]),
        "pairs_with_gt": len(with_gt),
        "ms_per_pair": float(np.mean([float(r[f"{p}time_ms"]) for r in rows])) if rows else math.nan,
    }
    if with_gt:
        out |= {"recall": _recall(with_gt, thresholds, p)}
        if standard is not None:
            out |= {"recall_standard": _recall(with_gt, standard, p)}
        out |= {
            "rre_median_deg": _median([float(r[f"{p}rre_deg"]) for r in with_gt]),
            "rte_median": _median([float(r[f"{p}rte"]) for r in with_gt]),
            "rre_mean_deg": float(np.nanmean([float(r[f"{p}rre_deg"]) for r in with_gt])),
        }
    scored = [r for r in rows if r["scored"] == "1" and r[f"{p}rmse"] not in ("", "nan")]
    if scored:
        ok = [float(r[f"{p}rmse"]) <= thresholds.rmse for r in scored]  # <=: the official test
        out |= {"scored_pairs": len(scored), "threedmatch_recall": float(np.mean(ok))}
    return out


def _scores(
    rows: list[dict[str, Any]], thresholds: Thresholds, p: str = "", standard: Thresholds | None = None
) -> dict[str, Any]:
    """``{"overall": ..., "groups": ...}`` (3DMatch: also the mean of the scenes' recalls)."""
    groups = sorted({r["group"] for r in rows})
    per_group = {g: _group_scores([r for r in rows if r["group"] == g], thresholds, p, standard) for g in groups}
    overall = _group_scores(rows, thresholds, p, standard)
    recalls = [s["threedmatch_recall"] for s in per_group.values() if "threedmatch_recall" in s]
    if recalls and len(per_group) > 1:
        overall["threedmatch_recall_scene_mean"] = float(np.mean(recalls))
    return {"overall": overall, "groups": per_group}


def _thresholds_dict(thresholds: Thresholds) -> dict[str, float | None]:
    rte = thresholds.rte if math.isfinite(thresholds.rte) else None
    return {"rre_deg": thresholds.rre_deg, "rte": rte, "rmse": thresholds.rmse}


def summarize(rows: list[dict[str, Any]], thresholds: Thresholds, standard: Thresholds | None = None) -> dict[str, Any]:
    """Scores of the results CSV rows; a pipeline's coarse step under ``"coarse"`` (same keys).

    Args:
        rows: Rows of the results CSV (strings, as read back).
        thresholds: The run's recall thresholds (``recall``).
        standard: The list kind's standard thresholds, scored too (``recall_standard``) when they differ.
    """
    if standard is not None and (standard.rre_deg, standard.rte) == (thresholds.rre_deg, thresholds.rte):
        standard = None
    out: dict[str, Any] = {"thresholds": _thresholds_dict(thresholds)}
    if standard is not None:
        out["standard_thresholds"] = _thresholds_dict(standard)
    out |= _scores(rows, thresholds, "", standard)
    if rows and all(r["coarse_time_ms"] != "" for r in rows):
        out["coarse"] = _scores(rows, thresholds, "coarse_", standard)
    return out


def _read_done(path: Path, method: str) -> list[dict[str, Any]]:
    """Rows of an existing results CSV of the same method (for ``--resume``)."""
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is not None and list(reader.fieldnames) == list(COLUMNS[:-2]):
            raise ValueError(
                f"--resume: {str(path)!r} was written by an older lcreg (no 'error' and 'fallback' columns); start a "
                "new --results file"
            )
        if reader.fieldnames is None or list(reader.fieldnames) != list(COLUMNS):
            raise ValueError(f"--resume: {str(path)!r} is not a results CSV of lcreg register (other columns)")
        rows = list(reader)
    other = {r["method"] for r in rows} - {method}
    if other:
        raise ValueError(f"--resume: {str(path)!r} holds results of {sorted(other)}, not of {method!r}")
    return rows


def _thresholds(args: argparse.Namespace, pairs: Sequence[ListedPair]) -> Thresholds:
    base = default_thresholds(pairs)
    for option in ("rre", "rte", "rmse"):
        value = getattr(args, option)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"--{option} must be a finite number > 0, got {value}")
    return Thresholds(args.rre or base.rre_deg, args.rte or base.rte, args.rmse or base.rmse)


def run_pairs(args: argparse.Namespace) -> dict[str, Any]:
    """The ``--pairs`` mode of ``lcreg register``: register, write the CSV and summary, print the scores."""
    method, fallback, min_fitness, small = resolve_methods(
        args.method, args.refine, args.fallback, args.min_fitness, args.ransac_iterations
    )
    label = "default" if args.method == "default" else method.name  # the CSV's and summary's method: as asked
    pairs = read_pair_list(args.pairs)
    if args.limit is not None:
        pairs = pairs[: max(args.limit, 0)]
    thresholds = _thresholds(args, pairs)
    results = Path(args.results or "register_results.csv").expanduser()
    done = _read_done(results, label) if args.resume and results.is_file() else []
    if results.exists() and not args.resume:
        raise FileExistsError(f"{str(results)!r} exists: pass --resume to continue it, or another --results file")
    names = {r["name"] for r in done}
    todo = [p for p in pairs if p.name not in names]
    print(f"{len(pairs)} pairs from {args.pairs} ({len(done)} already in {results}), method {label}")
    rows = list(done)
    with results.open("a" if done else "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        if not done:
            writer.writeheader()
        bar = _progress(todo, args.no_progress)
        with threads(args.threads):
            _write_rows(bar, writer, fh, rows, (method, fallback, min_fitness, small), thresholds, args)
    summary = summarize(rows, thresholds, default_thresholds(pairs))
    summary |= {"method": label, "pairs_file": str(args.pairs)}
    summary_path = results.with_suffix(".summary.json")
    summary_path.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    _print_summary(summary)
    print(f"wrote {results} and {summary_path}")
    return summary


def _write_rows(
    bar: Any,
    writer: csv.DictWriter,
    fh: Any,
    rows: list[dict[str, Any]],
    methods: tuple[Method, Method | None, float | None, Method | None],
    thresholds: Thresholds,
    args: argparse.Namespace,
) -> None:
    """Register the pairs of ``bar``, writing (and flushing) each row as it comes, appending it to ``rows``."""
    method, fallback, min_fitness, small = methods
    label = "default" if args.method == "default" else method.name
    warned: list[str] = []
    for row in register_pairs(
        bar,
        method,
        thresholds,
        weights=args.weights,
        voxel_size=args.voxel_size,
        target_points=args.target_points,
        seed=args.seed,
        fallback=fallback,
        min_fitness=min_fitness,
        small=small,
        label=label,
    ):
        record = row.as_csv()
        writer.writerow(record)
        fh.flush()
        rows.append({k: str(v) for k, v in record.items()})
        if row.result is not None and row.result.extra.get("warned"):
            warned.append(row.pair.name)
        _postfix(bar, rows)
    if warned:
        print(
            f"lcreg register: warning: {len(warned)} pairs ({warned[0]}, ...): {method.name} found no solution or its "
            "fitness says it failed; --fallback ransac+icp reruns such pairs",
            file=sys.stderr,
        )


def _progress(pairs: list[ListedPair], disabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(pairs, unit="pair", mininterval=0.5, disable=disabled, file=sys.stderr, dynamic_ncols=True)


def _postfix(bar: Any, rows: list[dict[str, Any]]) -> None:
    scored = [r for r in rows if r["success"] != ""]
    if scored and hasattr(bar, "set_postfix_str"):
        bar.set_postfix_str(f"recall {np.mean([int(r['success']) for r in scored]):.3f}", refresh=False)


def _format(value: Any, percent: bool = False) -> str:
    if isinstance(value, float):
        return f"{100 * value:.1f} %" if percent else f"{value:.4g}"
    return str(value)


def _print_summary(summary: dict[str, Any]) -> None:
    t = summary["thresholds"]
    rte = "none" if t["rte"] is None else f"{t['rte']:g}"
    print(f"recall: RRE < {t['rre_deg']:g} deg and RTE < {rte}; 3DMatch recall: correspondence RMSE < {t['rmse']:g}")
    if "standard_thresholds" in summary:
        st = summary["standard_thresholds"]
        print(
            f"standard recall of this kind of list (recall_standard): RRE < {st['rre_deg']:g} deg and RTE < {st['rte']}"
        )
    header = (
        "group",
        "pairs",
        "recall",
        "standard recall",
        "3DMatch recall",
        "median RRE deg",
        "median RTE",
        "ms/pair",
    )
    print(" | ".join(header))
    items = (
        [*summary["groups"].items(), ("all", summary["overall"])]
        if len(summary["groups"]) > 1
        else [("all", summary["overall"])]
    )
    for name, s in items:
        cells = [
            name or "all", s["pairs"], _format(s.get("recall", "-"), True),
            _format(s.get("recall_standard", "-"), True),
            _format(s.get("threedmatch_recall", "-"), True), _format(s.get("rre_median_deg", "-")),
            _format(s.get("rte_median", "-")), f"{s['ms_per_pair']:.0f}",
        ]  # fmt: skip
        print(" | ".join(str(c) for c in cells))
    if summary["overall"]["failed"]:
        print(f"{summary['overall']['failed']} pairs could not be registered (counted as failed): see the error column")
    if "threedmatch_recall_scene_mean" in summary["overall"]:
        print(f"3DMatch recall, mean over scenes: {100 * summary['overall']['threedmatch_recall_scene_mean']:.1f} %")
