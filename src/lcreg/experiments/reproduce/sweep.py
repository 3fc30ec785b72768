"""Run an experiment's variants × seeds: train with the budget, select on validation, test, one JSONL row per run.

Every run goes through the benchmark harness (:func:`lcreg.experiments.benchmarking.fit`): the method is built from its
configs exactly as ``lcreg fit`` builds it, trained with ``seed_everything = seed`` (initialisation and training
order), and validated during training on the validation pairs carved out of the training objects; the checkpoint with
the lowest ``RunBudget.monitor`` (``val/rre_mean_deg``; ``converge``: ``val/rre_clip5_deg`` or the budget's
``metric``) is kept (never the test set) and tested once on the deterministic test pairs (the same in every run: the
data's pair seed is fixed). The row is appended to ``<out>/<experiment>.jsonl`` (flushed) as soon
as the run ends; a rerun skips every (variant, seed) whose row is there for the same budget and data, so an
interrupted sweep resumes with the next unfinished run. A run whose training stops on non-finite losses
(:class:`~lcreg.models.base.NonFiniteTrainingError`) is recorded as failed (a result of that variant, not retried)
and the sweep goes on.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import torch

from lcreg.checkpoints import one_line
from lcreg.experiments.benchmarking import (
    REPORT_COLUMNS,
    ResultLog,
    fit,
    machine_line,
    method,
    peak_memory_mib,
    timed,
    training_device,
)
from lcreg.experiments.reproduce.budgets import LR_KEY, DataChoice, Preset, RunBudget
from lcreg.experiments.reproduce.continuation import (
    CAP_KEY,
    CappedRun,
    ContinuationError,
    capped_run,
    continue_into,
    keeps_resume_state,
)
from lcreg.experiments.reproduce.spec import Experiment, Rows, Variant
from lcreg.models.base import NonFiniteTrainingError
from lcreg.resume import LAST
from lcreg.weights import load_into
from lcreg.weights.export import save

__all__ = [
    "KEY_FIELDS",
    "METRICS",
    "RUN_KEY_FILE",
    "OutputFiles",
    "PresetRun",
    "Sweep",
    "Trainer",
    "claim_folder",
    "failed_runs",
    "finished_rows",
    "folder_owner",
    "pending_runs",
    "run_sweep",
    "run_values",
    "train_and_test",
]

METRICS = (*(key for key, _ in REPORT_COLUMNS), "rte_mean")
"""Test metrics kept in every row (RMSE/MAE of R and t, RRE mean and median, the two recalls, the mean RTE: DeepGMR's
translation figure). Rows written before session 13 lack ``rte_mean``."""
KEY_FIELDS = ("experiment", "variant", "seed", "budget", "data")
"""Fields that identify a run in the JSONL: a row with the same values is a finished run, skipped on a rerun."""

Trainer = Callable[[str, RunBudget, DataChoice, Path, int, Mapping[str, Any]], dict[str, Any]]
"""``train(method, budget, data, run_dir, seed, overrides) -> row fields``: :func:`train_and_test` (tests pass a
fake); ``overrides`` are the variant's config values (:attr:`Variant.overrides`)."""


class OutputFiles:
    """Where an experiment run writes: ``<out>/<stem>`` plus ``.md``, ``.jsonl``, ``.png`` (shared by every run kind).

    Attributes:
        out: The output folder.
        stem: File stem (``""``: the experiment's name).
        experiment: The experiment (its ``name`` is the default stem).
    """

    out: Path
    stem: str
    experiment: Any

    @property
    def file_stem(self) -> Path:
        """``<out>/<stem>``: the report, JSONL and PNGs are this plus a suffix (``stem`` defaults to the experiment)."""
        return self.out / (self.stem or self.experiment.name)

    @property
    def log_path(self) -> Path:
        """``<out>/<stem>.jsonl``."""
        return self.file_stem.with_suffix(".jsonl")


@dataclass(frozen=True)
class PresetRun(OutputFiles):
    """One experiment under one preset, seeds and data (base of the runtime and evaluation runs).

    Attributes:
        experiment: The experiment; its ``budgets`` map every preset to the budget of this run kind.
        preset: The budget preset.
        seeds: Seeds (mean ± std over them).
        data: The data every run reads.
        out: The output folder.
        stem: File stem (``""``: the experiment's name).
    """

    experiment: Any
    preset: Preset
    seeds: tuple[int, ...]
    data: DataChoice
    out: Path
    stem: str = ""

    @property
    def budget(self) -> Any:
        """The preset's budget."""
        return self.experiment.budgets[self.preset]


@dataclass(frozen=True)
class Sweep(PresetRun):
    """An experiment under one preset, seeds and data, writing ``<out>/<stem>.{md,jsonl}`` and PNGs.

    Its :attr:`budget` maps budget groups to :class:`RunBudget`; :meth:`Experiment.budget` gives a variant's.
    """

    experiment: Experiment
    points: int | None = None
    """Points per cloud of every run instead of its budget's (``None``: the budget's); set at construction, it
    resizes :attr:`experiment`'s budgets (:meth:`Experiment.with_points`) and gives the runs their own folders."""

    settings: tuple[tuple[str, Any], ...] = ()
    """``(dotted key, value)`` config values of every run, applied after its variant's own (``--set``): part of each
    row's budget key (:meth:`key`) and of its run folder, so such runs never stand for or resume the budget's own."""

    continues: Path | None = None
    """An earlier output folder whose runs, cut off by their step cap, these runs continue under their higher cap
    (``--continue-from``; :mod:`lcreg.experiments.reproduce.continuation`); ``None``: every run starts at step 0."""

    def __post_init__(self) -> None:
        if self.points is not None:
            object.__setattr__(self, "experiment", self.experiment.with_points(self.points))

    def overrides(self, variant: Variant) -> dict[str, Any]:
        """The config values of ``variant``'s runs: its own, then :attr:`settings`."""
        return {**variant.overrides, **dict(self.settings)}

    def settings_text(self) -> str:
        """``"; set key=value, ..."`` (JSON values) for the budget key, ``""`` without :attr:`settings`."""
        return "; set " + ", ".join(f"{k}={json.dumps(v)}" for k, v in self.settings) if self.settings else ""

    def step_cap(self, variant: Variant) -> int | None:
        """The step cap of ``variant``'s runs: a ``trainer.max_steps`` value, else its budget's steps."""
        return self.overrides(variant).get(CAP_KEY, self.experiment.budget(self.preset, variant).steps)

    def continued_run(self, variant: Variant, seed: int) -> CappedRun | None:
        """The earlier run in :attr:`continues` that the run of ``variant`` and ``seed`` continues (``None``: none).

        Raises:
            ContinuationError: :attr:`continues` is set but holds no run this one can continue (the message says
                why), or the budget is not a ``converge`` one.
        """
        if self.continues is None:
            return None
        budget = self.experiment.budget(self.preset, variant)
        if not budget.converge:
            raise ContinuationError(f"{variant.key}: the {self.preset} budget has no early stop; nothing to continue")
        log = ResultLog(self.continues / self.log_path.name, KEY_FIELDS)
        return capped_run(log, self.key(variant, seed), self.overrides(variant), int(self.step_cap(variant) or 0))

    def run_dir(self, variant: Variant, seed: int, log: ResultLog | None = None) -> Path:
        """Logs and checkpoints of one run: ``<out>/runs/<preset>/<experiment>/<variant>/seed<k>``.

        With :attr:`points` the variant's folder is ``<variant>_<points>pts``, with a ``train_objects`` subset of the
        data ``<variant>_train<n>`` (e.g. ``idam_X_train0.5``), with :attr:`settings` ``..._set<hash>`` (8 hex digits
        of :meth:`settings_text`): a run of another size, on other training objects or with other settings never
        resumes from the checkpoint of an unfinished run of the budget's own. A folder that holds another key's run
        (:func:`folder_owner`: a budget whose lr or steps changed since, other data) is not reused, since the new
        run would overwrite that run's ``selected_weights.pt`` and take over its row's logs: the run then trains in
        ``<variant>..._key<hash>/seed<k>`` (8 hex digits of its key).

        Args:
            variant: The run's variant.
            seed: Its seed.
            log: The sweep's JSONL log if already open (default: opened here).
        """
        size = "" if self.points is None else f"_{self.points}pts"
        subset = "" if self.data.train_objects is None else f"_train{self.data.train_objects:g}"
        settings = f"_set{_digest(self.settings_text())}" if self.settings else ""
        folder = variant.key.replace("/", "_") + size + subset + settings
        base = self.out / "runs" / self.preset / self.experiment.name / folder / f"seed{seed}"
        key = self.key(variant, seed)
        owner = folder_owner(base, log or self.open_log())
        if owner is None or owner == key:
            return base
        return base.parent.with_name(f"{folder}_key{_digest(json.dumps(key, sort_keys=True))}") / base.name

    def key(self, variant: Variant, seed: int) -> dict[str, Any]:
        """The :data:`KEY_FIELDS` of a run.

        A ``--set`` of the learning rate (:data:`LR_KEY`) replaces the budget's own, so the key names only the set one:
        a run keeps its key when its budget later adopts an lr that runs had been given by ``--set``.
        """
        budget = self.experiment.budget(self.preset, variant)
        if LR_KEY in dict(self.settings):
            budget = replace(budget, lr=None)
        budget_text = budget.describe() + self.settings_text()
        name = self.experiment.name
        return {
            "experiment": name,
            "variant": variant.key,
            "seed": seed,
            "budget": budget_text,
            "data": self.data.describe(),
        }

    def open_log(self) -> ResultLog:
        """The sweep's JSONL (finished runs of every budget and data; rows are told apart by their key)."""
        return ResultLog(self.log_path, KEY_FIELDS)


def train_and_test(
    name: str, budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: Mapping[str, Any]
) -> dict[str, Any]:
    """Train method ``name`` under ``budget`` on ``data``, test the checkpoint chosen on validation.

    Args:
        name: Registry name of the method.
        budget: Steps, sizes and validation schedule.
        data: The dataset.
        run_dir: Logs and checkpoints of the run.
        seed: ``seed_everything`` of the run.
        overrides: The variant's own config values (:attr:`Variant.overrides`), applied last.

    Returns:
        Row fields: the test metrics (:data:`METRICS`), the selected checkpoint (its name; its weights are kept
        as ``selected_weights.pt``; the Lightning checkpoints are deleted, but for the resume state of a run that
        reached its cap) and its validation error, the steps run, the pair counts, the sizes, the times, the machine
        that trained it and the training's peak memory (:func:`~lcreg.experiments.benchmarking.peak_memory_mib`;
        ``overrides`` when the variant has any).
    """
    recorded = copy.deepcopy(dict(overrides))  # parsing turns the dicts it is given into Namespaces, in place
    values = run_values(budget, data, run_dir, seed, recorded)
    device = training_device()
    result, peak_mib = peak_memory_mib(
        lambda: fit(name, values, monitor=budget.monitor, resume=budget.converge), device
    )
    best_val = getattr(result.trainer.checkpoint_callback, "best_model_score", None)
    load_into(result.model, result.best_checkpoint)
    test = partial(result.trainer.test, result.model, datamodule=result.datamodule, verbose=False)
    results, test_s = timed(test)
    tested = results[0]
    steps, cap = int(result.trainer.global_step), _step_cap(result.trainer, budget)
    capped = keeps_resume_state(budget.converge, steps, cap)
    weights = _keep_weights_only(result.model, result.best_checkpoint, run_dir, keep_resume=capped)
    dm: Any = result.datamodule
    return {
        "method": name,
        "configs": list(method(name).config_files()),
        "steps": steps,
        "epochs": int(result.trainer.current_epoch),
        "train_s": round(result.seconds, 1),
        "test_s": round(test_s, 1),
        "machine": machine_line(result.trainer.strategy.root_device),  # the model is back on the CPU after fit
        "peak_mib": None if peak_mib is None else round(peak_mib, 1),
        "selected": result.best_checkpoint.name,
        "weights": str(weights),
        "best_val_rre_mean_deg": None if best_val is None or budget.converge else float(best_val),
        "selected_on": budget.monitor,
        "best_val": None if best_val is None else float(best_val),
        "stopped_early": budget.converge and steps < cap,
        "metrics_csv": str(Path(result.trainer.log_dir or run_dir) / "metrics.csv"),
        "num_val_pairs": len(dm.val_set),
        "num_test_pairs": len(dm.test_set),
        "num_points": dm.hparams.num_points,
        **({"points_per_cloud": dm.points_per_cloud} if dm.points_per_cloud != dm.hparams.num_points else {}),
        "batch_size": dm.hparams.batch_size,
        **({"overrides": recorded} if recorded else {}),
        **({"kept_resume_state": True} if capped else {}),  # last.ckpt kept: --continue-from, the queue's sync
        **{key: float(tested[f"test/{key}"]) for key in METRICS},
    }


def run_values(
    budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: Mapping[str, Any]
) -> dict[str, Any]:
    """The ``lcreg fit`` values of one run: its budget's (logs under ``run_dir``), its data's, then ``overrides``.

    ``overrides`` is copied: parsing turns the dicts it is given into Namespaces, in place.
    """
    return {**budget.fit_overrides(run_dir, seed), **data.overrides(budget), **copy.deepcopy(dict(overrides))}


def _step_cap(trainer: Any, budget: RunBudget) -> int:
    """The run's step cap: the trainer's ``max_steps`` (a ``--set trainer.max_steps`` included), else the budget's."""
    return int(trainer.max_steps) if int(trainer.max_steps) > 0 else int(budget.steps or 0)


def _keep_weights_only(model: torch.nn.Module, best: Path, run_dir: Path, keep_resume: bool = False) -> Path:
    """Save the tested (selected) weights as ``<run_dir>/selected_weights.pt`` and delete the run's checkpoints.

    A finished run needs no training state: the Lightning checkpoints (optimiser moments, ``last.ckpt``) are up to
    three times the weights (about 70 MB for DCP-v2 or PRNet), times every run of a sweep. ``keep_resume``: a run its
    step cap cut off keeps ``last.ckpt`` and ``best`` (the state a higher cap continues,
    :mod:`lcreg.experiments.reproduce.continuation`).
    """
    path = save(model, run_dir / "selected_weights.pt")  # the one weights format: lcreg.pretrained reads it
    kept = {LAST, best.name} if keep_resume else set()
    for checkpoint in best.parent.glob("*.ckpt"):
        if checkpoint.name not in kept:
            checkpoint.unlink()
    return path


def run_sweep(
    sweep: Sweep,
    train: Trainer | None = None,
    progress: Callable[[str], None] = lambda _: None,
    rerun: bool = False,
    on_row: Callable[[ResultLog], object] | None = None,
) -> ResultLog:
    """Train and test every unfinished (variant, seed) of ``sweep``, appending each row as it ends.

    Args:
        sweep: What to run.
        train: The run itself (``None``: :func:`train_and_test`).
        progress: Called with one line per run (skipped or finished).
        rerun: Run finished runs again too (their new rows are appended; the newest row of a run counts).
        on_row: Called with the log after each appended row, e.g. to write the report of what has finished so far
            (a sweep cut off later keeps a report of its finished runs).

    Returns:
        The JSONL log with every finished row.
    """
    log = sweep.open_log()
    pending = {(variant.key, seed) for variant, seed in pending_runs(sweep, rerun, log)}
    sources = continued_runs(sweep, rerun, log)  # checked before any run trains
    for variant in sweep.experiment.variants:
        budget = sweep.experiment.budget(sweep.preset, variant)
        for seed in sweep.seeds:
            if (variant.key, seed) not in pending:
                progress(f"{variant.key} seed {seed}: finished before, skipped")
                continue
            run_dir = sweep.run_dir(variant, seed, log)
            claim_folder(run_dir, sweep.key(variant, seed))
            source = sources.get((variant.key, seed))
            if source is not None and continue_into(source, run_dir / source.log_dir.relative_to(source.run_dir)):
                progress(f"{variant.key} seed {seed}: continues {source.run_dir} from step {source.steps}")
            continued = {} if source is None else {"continues": str(source.run_dir), "continued_from": source.steps}
            run = partial(train or train_and_test, variant.method, budget, sweep.data, run_dir)
            try:
                fields = run(seed, sweep.overrides(variant))
            except NonFiniteTrainingError as err:  # a diverged run is a result: recorded, not retried on resume
                fields = {"failed": one_line(str(err), 300)}
            row = log.append({**sweep.key(variant, seed), "preset": sweep.preset, **fields, **continued})
            progress(f"{variant.key} seed {seed}: {_outcome(row)}")
            if on_row is not None:
                on_row(log)
    return log


def _digest(text: str) -> str:
    """8 hex digits of ``text``'s SHA-1: the suffix of a run folder that ``--set`` values or a key tell apart."""
    return hashlib.sha1(text.encode()).hexdigest()[:8]


RUN_KEY_FILE = "run_key.json"
"""The key (:data:`KEY_FIELDS`) of the run a sweep trains in a run folder, written there as the run starts."""


def claim_folder(run_dir: Path, key: Mapping[str, Any]) -> None:
    """Write ``key`` to ``run_dir/``:data:`RUN_KEY_FILE` (the folder's owner, :func:`folder_owner`)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / RUN_KEY_FILE).write_text(json.dumps(dict(key), indent=1) + "\n", encoding="utf-8")


def folder_owner(run_dir: Path, log: ResultLog) -> dict[str, Any] | None:
    """The key of the run trained in ``run_dir``, ``None`` if none is known.

    Its :data:`RUN_KEY_FILE`; for a folder without one (runs started before session 53), the key of the newest row
    of ``log`` whose ``weights`` or ``metrics_csv`` lie in a folder of the same ``<preset>/<experiment>/<variant>/
    seed<k>`` (the row's absolute path may be another machine's).

    Raises:
        ValueError: The key file is not a JSON object (damaged); names the file.
    """
    marker = run_dir / RUN_KEY_FILE
    if marker.is_file():
        try:
            owner = json.loads(marker.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"{marker}: not a run key ({err}); delete it if no run of this folder is kept") from err
        if not isinstance(owner, dict):
            raise ValueError(f"{marker}: not a run key (a JSON object); delete it if no run of this folder is kept")
        return owner
    tail = run_dir.parts[-4:]
    recorded = [row for row in log.rows if any(_lies_in(row.get(f), tail) for f in ("weights", "metrics_csv"))]
    return {field: recorded[-1].get(field) for field in KEY_FIELDS} if recorded else None


def _lies_in(path: object, tail: tuple[str, ...]) -> bool:
    """Whether the recorded file ``path`` lies in a folder whose path ends with the parts ``tail``."""
    if not isinstance(path, str):
        return False
    parts = Path(path).parts
    return any(parts[i : i + len(tail)] == tail for i in range(len(parts) - len(tail) + 1))


def pending_runs(sweep: Sweep, rerun: bool, log: ResultLog | None = None) -> list[tuple[Variant, int]]:
    """The (variant, seed) pairs of ``sweep`` without a row for its budget and data (all of them with ``rerun``).

    Args:
        sweep: The sweep.
        rerun: Every run is pending (``--no-resume``).
        log: Its JSONL log if already open (default: opened here).
    """
    log = log or sweep.open_log()
    runs = [(v, s) for v in sweep.experiment.variants for s in sweep.seeds]
    return [(v, s) for v, s in runs if rerun or not log.done(**sweep.key(v, s))]


def continued_runs(sweep: Sweep, rerun: bool, log: ResultLog | None = None) -> dict[tuple[str, int], CappedRun]:
    """The earlier run each pending run of ``sweep`` continues, by (variant key, seed) (empty without ``continues``).

    Raises:
        ContinuationError: A pending run has no earlier run to continue (:meth:`Sweep.continued_run`).
    """
    if sweep.continues is None:
        return {}
    pending = pending_runs(sweep, rerun, log)
    return {(variant.key, seed): source for variant, seed in pending if (source := sweep.continued_run(variant, seed))}


def _outcome(row: dict[str, Any]) -> str:
    if "failed" in row:
        return f"failed ({row['failed']})"
    return f"RMSE(R) {row['rmse_r_deg']:.3f}°, {row['train_s']:.0f} s"


def _rows_of(sweep: Sweep, log: ResultLog) -> dict[str, list[dict[str, Any]]]:
    """The newest row of every (variant, seed) of ``sweep`` in ``log`` (its budget and data), by variant key."""
    found = {v.key: [log.find(**sweep.key(v, seed)) for seed in sweep.seeds] for v in sweep.experiment.variants}
    return {key: [row for row in rows if row is not None] for key, rows in found.items()}


def finished_rows(sweep: Sweep, log: ResultLog) -> Rows:
    """The successful runs of ``sweep`` in ``log`` by variant key (failed runs left out: see :func:`failed_runs`)."""
    return {key: [r for r in rows if "failed" not in r] for key, rows in _rows_of(sweep, log).items()}


def failed_runs(sweep: Sweep, log: ResultLog) -> list[str]:
    """``"<variant> seed <k>: <why>"`` for every run of ``sweep`` whose training diverged (non-finite losses)."""
    rows = _rows_of(sweep, log)
    return [f"{key} seed {r['seed']}: {r['failed']}" for key, runs in rows.items() for r in runs if "failed" in r]
