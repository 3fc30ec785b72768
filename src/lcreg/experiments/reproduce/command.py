"""``lcreg reproduce EXPERIMENT``: rerun a table of the paper, write ours beside the paper's numbers.

``lcreg reproduce ablation --budget cpu --seeds 0 1 2 --out DIR`` trains every variant × seed that ``DIR`` does not
hold yet (:mod:`lcreg.experiments.reproduce.sweep`), then writes ``DIR/<experiment>.md``
(:mod:`lcreg.experiments.reproduce.report`), ``DIR/<experiment>.jsonl`` (every run) and
``DIR/<experiment>_rotation.png``, ``_translation.png`` (:mod:`lcreg.experiments.reproduce.plots`). Dispatched by
:func:`lcreg.cli.main` before LightningCLI, like ``lcreg register``.

Errors print one line on stderr with exit code 2 (arguments); ``LCREG_DEBUG=1`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, NoReturn, get_args

from lcreg.checkpoints import one_line
from lcreg.data.pairs import PartialMode
from lcreg.experiments.benchmarking import ResultLog, write_text
from lcreg.experiments.reproduce.ablation import ABLATION
from lcreg.experiments.reproduce.budgets import DEFAULT_ROOT, PRESETS, DataChoice, Preset
from lcreg.experiments.reproduce.conditions import EvalExperiment, EvalRun, run_conditions
from lcreg.experiments.reproduce.continuation import ContinuationError
from lcreg.experiments.reproduce.lc import LC
from lcreg.experiments.reproduce.parallel import WorkersFailedError, run_workers, worker_runs
from lcreg.experiments.reproduce.plots import plot_sweep
from lcreg.experiments.reproduce.recall_curves import RECALL_CURVES, plot_recall_curves, render_recall_curves
from lcreg.experiments.reproduce.report import render
from lcreg.experiments.reproduce.retest import (
    PRECISIONS,
    RETEST_DATA,
    MissingWeightsError,
    NoFinishedRunsError,
    Retest,
    check_retest_data,
    render_retest,
    retest_path,
    retest_sweep,
)
from lcreg.experiments.reproduce.robustness import ROBUSTNESS, plot_robustness, render_robustness
from lcreg.experiments.reproduce.runtime import (
    RUNTIME,
    RuntimeExperiment,
    RuntimeRun,
    measure_runtime,
    plot_runtime,
    render_runtime,
)
from lcreg.experiments.reproduce.spec import Experiment
from lcreg.experiments.reproduce.stops import plot_learning_curves, with_metrics_files
from lcreg.experiments.reproduce.sweep import (
    KEY_FIELDS,
    Sweep,
    continued_runs,
    failed_runs,
    finished_rows,
    run_sweep,
)

__all__ = [
    "EVALUATIONS",
    "EXPERIMENTS",
    "PLANNED",
    "TIMINGS",
    "ReproduceUsageError",
    "build_parser",
    "main",
    "reproduce",
]

EXPERIMENTS: dict[str, Experiment] = {"ablation": ABLATION, "lc": LC}
"""The experiments ``lcreg reproduce`` runs, by name."""
TIMINGS = {"runtime": RUNTIME}
"""Experiments that time registration instead of training (:mod:`lcreg.experiments.reproduce.runtime`)."""
EVALUATIONS: dict[str, EvalExperiment] = {"robustness": ROBUSTNESS, "recall-curves": RECALL_CURVES}
"""Experiments that evaluate trained models under test conditions (:mod:`lcreg.experiments.reproduce.conditions`)."""
PLANNED: tuple[str, ...] = ()
"""Experiments named by the command but not available yet."""
AVAILABLE = (*EXPERIMENTS, *TIMINGS, *EVALUATIONS)
REPORT_EVERY_S = 60.0
"""Least seconds between two reports written while a sweep trains (the first finished run writes one, the sweep's end
another): a report with its curves takes seconds, many short runs would spend more on reports than on training."""
WRITERS = {
    "robustness": (render_robustness, plot_robustness),
    "recall-curves": (render_recall_curves, plot_recall_curves),
}


REPORT_NOT_WRITTEN_EXIT_CODE = 3
"""Exit status of ``lcreg reproduce`` when every run finished (its row is in the JSONL) but the report at the end
could not be written: the training queue counts the job as done; ``--report-only`` writes the report later."""


class ReproduceUsageError(ValueError):
    """A bad argument of ``lcreg reproduce`` (exit code 2 on the command line)."""


class ReportNotWrittenError(RuntimeError):
    """The report of finished runs could not be written (exit code :data:`REPORT_NOT_WRITTEN_EXIT_CODE`).

    Nothing is lost: every finished run is a row of the JSONL it names, and ``--report-only`` writes the report.
    """

    def __init__(self, log_path: Path, cause: BaseException, report_only: bool = False) -> None:
        self.log_path = log_path
        # Under --report-only the same command would fail the same way: its cause is what to fix.
        then = "fix its cause and rerun this command" if report_only else "rerun the same command with --report-only"
        super().__init__(
            f"report not written ({type(cause).__name__}: {one_line(str(cause), 300)}); the finished runs are kept "
            f"in {log_path}: {then} to write it (LCREG_DEBUG=1 shows the traceback)"
        )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``lcreg reproduce``."""
    parser = argparse.ArgumentParser(
        prog="lcreg reproduce",
        description="Rerun a table of the DVDs paper: train every variant x seed with a budget, choose each\n"
        "checkpoint on the validation pairs, test it, and write a Markdown table (ours, the paper's, the ratio,\n"
        "the paper's claims against the seed spread), a JSONL of every run and PNG plots.\n"
        "A rerun skips finished runs.",
        epilog="experiments:\n  ablation  models A-D, |X1| = 32/64/96, (λ1, λ2): paper objective and self-motion "
        "recipe\n  lc        X vs LC + X for DCP-v2, PRNet, IDAM, DeepGMR\n"
        "  runtime   ms per pair at 500/1000/2000 points of every method (nothing trained; CPU, and GPU if any)\n"
        "  robustness     recall vs Gaussian noise and vs partial visibility, every method on the same pairs\n"
        "  recall-curves  recall vs rotation-error threshold: unseen objects, unseen categories, 7-Scenes, KITTI\n"
        "                 (robustness and recall-curves train the learned methods once, shared in <out>/models.jsonl)"
        "\n\nbudgets: smoke (seconds, synthetic shapes), cpu (about 2 h per "
        "experiment on 2 CPU cores),\n  converge (each run until its validation error stops improving, resumable; "
        "many CPU-hours:\n  benchmarks/train_queue.toml), paper (the paper's 200 epochs, for a GPU); see "
        "docs/reproducing.md",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("experiment", metavar="EXPERIMENT", help=f"one of {', '.join(AVAILABLE)}")
    parser.add_argument("--budget", required=True, choices=PRESETS, help="training budget of every run")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default: %(default)s)")
    parser.add_argument("--out", help="output folder (default: runs/reproduce/<budget>)")
    parser.add_argument("--root", default=DEFAULT_ROOT, help="ModelNet40 folder (default: %(default)s; not smoke)")
    parser.add_argument(
        "--protocol",
        choices=("unseen_objects", "unseen_categories"),
        help="ModelNet40 protocol (default: unseen_objects; runtime: unseen_categories, the paper's)",
    )
    parser.add_argument(
        "--partial",
        choices=get_args(PartialMode),
        default="none",
        help="ablation, lc: crop every cloud (training, validation, test): 'prnet' is PRNet's and IDAM's shared far "
        "anchor (default: %(default)s, full clouds)",
    )
    parser.add_argument(
        "--partial-keep",
        type=_count_or_fraction,
        default=0.75,
        help="points a --partial crop keeps: a fraction of the budget's points or a count (default: %(default)s, "
        "PRNet's and IDAM's 768 of 1024)",
    )
    parser.add_argument(
        "--train-objects",
        type=_count_or_fraction,
        help="ablation, lc: train on a seeded subset of the training objects, a count or a fraction (e.g. 0.5); "
        "validation and test pairs stay the same (default: all; the JSONL key names it)",
    )
    parser.add_argument(
        "--points",
        type=int,
        help="ablation, lc: points per cloud of every run instead of the budget's (e.g. a method's own size where "
        "the budget reduced it); its runs get their own rows and folders (default: the budget's)",
    )
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        type=_setting,
        metavar="KEY=VALUE",
        help="ablation, lc: a config value of every run, after its variant's own: a dotted key as `lcreg fit` takes "
        "it and a YAML value, e.g. --set model.init_args.lr_scheduler.init_args.milestones=[60] (repeatable; part of "
        "each row's budget key and run folder)",
    )
    parser.add_argument(
        "--continue-from",
        metavar="DIR",
        help="ablation, lc (converge budget): an earlier --out whose runs stopped at their step cap; each run here "
        "starts from that run's last state instead of step 0, under a higher --set trainer.max_steps (same budget, "
        "data and other settings; it ends as a run trained from step 0 to the higher cap would)",
    )
    parser.add_argument(
        "--only",
        nargs="+",
        default=[],
        metavar="PATTERN",
        help="variant keys (fnmatch: 'paper/*', 'dcp/*'; runtime: method keys)",
    )
    parser.add_argument(
        "--resume",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="skip runs already in the JSONL (default); --no-resume reruns them (the newest row of a run counts)",
    )
    parser.add_argument("--report-only", action="store_true", help="write the table and plots from the JSONL only")
    parser.add_argument(
        "--retest",
        choices=PRECISIONS,
        metavar="PRECISION",
        help="ablation, lc: train nothing; test every finished run's kept weights again on its own test pairs under "
        f"this trainer.precision ({', '.join(PRECISIONS)}), beside its own test, in <stem>.retest-<PRECISION>.md "
        "and .jsonl (with --report-only: the table from that JSONL only)",
    )
    parser.add_argument(
        "--retest-data",
        dest="retest_data",
        action="append",
        default=[],
        type=_retest_setting,
        metavar="KEY=VALUE",
        help=f"with --retest: a data value of the test only ({', '.join(RETEST_DATA)}), so that the kept weights are "
        "tested on other pairs, e.g. protocol=unseen_categories (labels 20-39; training and validation objects are "
        "the same under both protocols) or noise_sigma=0; repeatable; in the outputs' names "
        "(<stem>.retest-<PRECISION>-<key>-<value>.md)",
    )
    parser.add_argument(
        "--retest-precise-bn",
        dest="retest_precise_bn",
        type=int,
        default=0,
        metavar="N",
        help="with --retest: before each test, recompute every BatchNorm layer's running statistics as their mean over "
        "N training batches of the run's data (the kept weights otherwise unchanged; 'precise BatchNorm'); in the "
        "outputs' names (-precise_bn-N)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="ablation, lc: runs trained at once, each in its own process (default 1; a GPU takes several)",
    )
    parser.add_argument("--no-report", action="store_true", help=argparse.SUPPRESS)  # the workers of --jobs
    return parser


def _count_or_fraction(text: str) -> int | float:
    """``--partial-keep``, ``--train-objects``: ``"768"`` is a count, ``"0.75"`` a fraction (checked downstream)."""
    try:
        return int(text)
    except ValueError:
        return float(text)


_KEY = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)+$")


def _setting(text: str) -> tuple[str, Any]:
    """``--set KEY=VALUE``: a dotted config key and its YAML-parsed value (``"[60]"`` is a list, ``"1e-4"`` a float).

    Raises:
        argparse.ArgumentTypeError: No ``=``, a key that is not dotted words, or a value YAML cannot read.
    """
    import yaml

    key, sep, value = text.partition("=")
    if not sep or not _KEY.match(key.strip()):
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE with a dotted key (model.init_args.x=1), got {text!r}")
    try:
        return key.strip(), yaml.safe_load(value)
    except yaml.YAMLError as err:
        raise argparse.ArgumentTypeError(
            f"{key.strip()}: the value {value!r} is not YAML ({one_line(str(err))})"
        ) from None


def _retest_setting(text: str) -> tuple[str, Any]:
    """``--retest-data KEY=VALUE``: a data key of :data:`RETEST_DATA` and its checked YAML value.

    Raises:
        argparse.ArgumentTypeError: No ``=``, a key outside :data:`RETEST_DATA`, or a value the key cannot take.
    """
    import yaml

    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE (e.g. protocol=unseen_categories), got {text!r}")
    try:
        return key.strip(), check_retest_data(key.strip(), yaml.safe_load(value))
    except (ValueError, yaml.YAMLError) as err:
        raise argparse.ArgumentTypeError(one_line(str(err))) from None


def _experiment(name: str, only: Sequence[str]) -> Experiment | RuntimeExperiment | EvalExperiment:
    if name in PLANNED:
        raise ReproduceUsageError(f"experiment {name!r} is not available yet; available: {', '.join(AVAILABLE)}")
    if name not in AVAILABLE:
        raise ReproduceUsageError(f"unknown experiment {name!r}; available: {', '.join(AVAILABLE)}")
    try:
        if name in TIMINGS:
            return TIMINGS[name].select(only)
        return EVALUATIONS[name].select(only) if name in EVALUATIONS else EXPERIMENTS[name].select(only)
    except ValueError as err:
        raise ReproduceUsageError(str(err)) from None


def _data(
    preset: Preset,
    root: str,
    protocol: str | None,
    partial: str = "none",
    partial_keep: int | float = 0.75,
    train_objects: int | float | None = None,
) -> DataChoice:
    if preset == "smoke":
        return DataChoice(None, partial=partial, partial_keep=partial_keep, train_objects=train_objects)
    if not Path(root).expanduser().is_dir():
        raise ReproduceUsageError(
            f"ModelNet40 not found at {root!r}: pass --root DIR (official modelnet40_ply_hdf5_2048 layout)"
        )
    workers = None if preset == "paper" else 0  # the GPU machine of `paper` has cores to spare for loading
    resolved = str(Path(root).expanduser().resolve())
    return DataChoice(resolved, protocol or "unseen_objects", workers, partial, partial_keep, train_objects)


def _seeds(seeds: Sequence[int]) -> tuple[int, ...]:
    if any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise ReproduceUsageError(f"--seeds must be distinct non-negative integers, got {list(seeds)}")
    return tuple(seeds)


def reproduce(
    args: argparse.Namespace, command: str, progress: Callable[[str], None] = print, stem: str = ""
) -> list[Path]:
    """Run (or, with ``report_only``, only report) the sweep that parsed ``args`` describe.

    Args:
        args: Parsed arguments of :func:`build_parser`.
        command: The command line written in the report.
        progress: Called with one line per run.
        stem: File stem of the outputs in ``--out`` (default: the experiment's name).

    Returns:
        The written files: the Markdown report, the JSONL (if any run finished) and the PNGs.

    Raises:
        ReproduceUsageError: Unknown or planned experiment, ``--only`` matching nothing, bad seeds or ``--jobs``,
            missing data.
        WorkersFailedError: With ``--jobs``, some runs ended with an error (after the report of the others).
        ReportNotWrittenError: Every run ended, but writing the report failed.
    """
    experiment = _experiment(args.experiment, args.only)
    if args.jobs < 1 or (args.jobs > 1 and not isinstance(experiment, Experiment)):
        raise ReproduceUsageError(f"--jobs must be >= 1 (above 1 only for {', '.join(EXPERIMENTS)}), got {args.jobs}")
    out = Path(args.out or f"runs/reproduce/{args.budget}")
    chosen = (
        ("--partial", args.partial != "none"),
        ("--points", args.points is not None),
        ("--train-objects", args.train_objects is not None),
        ("--set", bool(args.settings)),
        ("--retest", args.retest is not None),
        ("--retest-data", bool(args.retest_data)),
        ("--retest-precise-bn", bool(args.retest_precise_bn)),
        ("--continue-from", args.continue_from is not None),
    )
    for option, value in chosen:
        if value and not isinstance(experiment, Experiment):
            raise ReproduceUsageError(
                f"{option} applies to {', '.join(EXPERIMENTS)} (training sweeps); {args.experiment} sets its own data"
            )
    if isinstance(experiment, RuntimeExperiment):
        data = _data(args.budget, args.root, args.protocol or "unseen_categories")
        return _time(RuntimeRun(experiment, args.budget, _seeds(args.seeds), data, out, stem), args, command, progress)
    if isinstance(experiment, EvalExperiment):
        data = _data(args.budget, args.root, "unseen_categories")
        run = EvalRun(experiment, args.budget, _seeds(args.seeds), data, out, stem)
        return _evaluate(run, args, command, progress)
    for option, given in (("--retest-data", bool(args.retest_data)), ("--retest-precise-bn", args.retest_precise_bn)):
        if given and args.retest is None:
            raise ReproduceUsageError(f"{option} changes the test of --retest PRECISION: give --retest too")
    if args.retest_precise_bn < 0:
        raise ReproduceUsageError(f"--retest-precise-bn must be a number of batches >= 1, got {args.retest_precise_bn}")
    data = _data(args.budget, args.root, args.protocol, args.partial, args.partial_keep, args.train_objects)
    seeds = _seeds(args.seeds)
    settings = tuple(dict(args.settings).items())  # a key set twice: the last value
    try:
        sweep = Sweep(experiment, args.budget, seeds, data, out, stem, points=args.points, settings=settings)
    except ValueError as err:  # Experiment.with_points owns the bound on --points
        raise ReproduceUsageError(f"--points: {err}") from None
    if args.continue_from is not None:
        sweep = _continuing(sweep, Path(args.continue_from), not args.resume or args.retest is not None)
    if args.retest is None and not args.report_only:
        _check_step_cap(sweep)
    if args.retest is not None:
        return _retest(sweep, args, command, progress)
    failure = None
    written_at = -REPORT_EVERY_S

    def refresh(*_: object) -> None:  # after a finished run: a sweep cut off later keeps its report
        nonlocal written_at
        if args.no_report or time.monotonic() - written_at < REPORT_EVERY_S:
            return
        try:
            progress(f"report of the runs finished so far: {_report(sweep, sweep.open_log(), command, out)[0]}")
        except Exception as err:  # a side product: training goes on, and the sweep's end reports again
            progress(f"report not written ({type(err).__name__}: {err}); training goes on, rows in {sweep.log_path}")
        written_at = time.monotonic()

    if args.report_only:
        log = sweep.open_log()
    elif args.jobs > 1:
        try:
            runs = worker_runs(sweep, _worker_options(args, out), not args.resume)
            run_workers(runs, args.jobs, progress, on_finish=refresh)
        except WorkersFailedError as err:  # the finished runs are reported first
            failure = err
        log = sweep.open_log()
    else:
        log = run_sweep(sweep, progress=progress, rerun=not args.resume, on_row=refresh)
    if args.no_report:
        return []
    try:
        written = _guarded(lambda: _report(sweep, log, command, out), sweep.log_path, args.report_only)
    except ReportNotWrittenError as err:
        if failure is None:
            raise
        progress(str(err))  # the workers' failure, and its exit code (resume or not), wins over the report's
        raise failure from err
    if failure is not None:
        raise failure
    return written


def _continuing(sweep: Sweep, earlier: Path, refused: bool) -> Sweep:
    """``sweep`` continuing the capped runs of ``earlier`` (``--continue-from``), each checked before any run trains.

    Raises:
        ReproduceUsageError: With ``--no-resume`` or ``--retest`` (``refused``), a missing folder, or a pending run
            without an earlier run to continue (the message names it and why).
    """
    if refused:
        raise ReproduceUsageError(
            "--continue-from trains runs on from their earlier state: not with --no-resume or --retest"
        )
    if not earlier.is_dir():
        raise ReproduceUsageError(f"--continue-from: no folder {earlier}")
    continuing = replace(sweep, continues=earlier)
    try:
        continued_runs(continuing, rerun=False)
    except ContinuationError as err:
        raise ReproduceUsageError(f"--continue-from: {err}") from None
    return continuing


def _check_step_cap(sweep: Sweep) -> None:
    """A ``--set trainer.max_steps`` that ends runs before their first validation (no checkpoint to choose) is refused.

    Raises:
        ReproduceUsageError: Names the variant, its first validation step and the value given.
    """
    cap = dict(sweep.settings).get("trainer.max_steps")
    if not isinstance(cap, int) or cap < 0:  # -1 (Lightning's "no cap") and non-integers: Lightning's own checks
        return
    for variant in sweep.experiment.variants:
        first = sweep.experiment.budget(sweep.preset, variant).val_every
        if first is not None and cap < first:
            raise ReproduceUsageError(
                f"--set trainer.max_steps={cap}: {variant.key}'s runs would end before their first validation, at step "
                f"{first} of the {sweep.preset} budget, and have no checkpoint to choose; give at least {first}"
            )


def _guarded(write: Callable[[], list[Path]], log_path: Path, report_only: bool) -> list[Path]:
    """Call ``write`` (a report of rows already in ``log_path``); any error in it is a :class:`ReportNotWrittenError`.

    The report is written after the runs have finished: a plotting or rendering failure must neither hide that they
    finished (the training queue would run the job again forever) nor look like a failed run. ``report_only``: the
    command was ``--report-only`` already, so the error's hint names the cause instead of that option.
    """
    try:
        return write()
    except Exception as err:
        raise ReportNotWrittenError(log_path, err, report_only) from err


def _worker_options(args: argparse.Namespace, out: Path) -> list[str]:
    """The arguments every ``--jobs`` worker repeats."""
    protocol = ["--protocol", args.protocol] if args.protocol else []
    crop = ["--partial", args.partial, "--partial-keep", str(args.partial_keep)] if args.partial != "none" else []
    size = [] if args.points is None else ["--points", str(args.points)]
    subset = [] if args.train_objects is None else ["--train-objects", str(args.train_objects)]
    settings = [f"--set={key}={json.dumps(value)}" for key, value in dict(args.settings).items()]
    settings += [] if args.continue_from is None else ["--continue-from", str(args.continue_from)]
    options = ["--budget", args.budget, "--root", str(args.root), "--out", str(out), *protocol, *crop, *size]
    return [*options, *subset, *settings]


def _report(sweep: Sweep, log: ResultLog, command: str, out: Path) -> list[Path]:
    """Write the sweep's Markdown report, JSONL and PNGs; returns the written files."""
    rows = with_metrics_files(finished_rows(sweep, log), out)  # also from a copy of <out> made elsewhere
    curves = plot_learning_curves(sweep.experiment, rows, out, sweep.file_stem.name)
    report = render(sweep, rows, command, failed_runs(sweep, log), curves)
    written = [write_text(sweep.file_stem.with_suffix(".md"), report)]
    written += [sweep.log_path] if sweep.log_path.is_file() else []
    return written + plot_sweep(sweep, rows) + curves


def _retest(sweep: Sweep, args: argparse.Namespace, command: str, progress: Callable[[str], None]) -> list[Path]:
    """Test the sweep's kept weights again under ``--retest`` (or, with ``--report-only``, only report them)."""
    if args.jobs > 1:
        raise ReproduceUsageError("--retest tests one run after another; leave out --jobs")
    given = dict(args.retest_data)  # a key given twice: the last value; the tag lists keys in RETEST_DATA's order
    retest = Retest(
        args.retest, tuple((key, given[key]) for key in RETEST_DATA if key in given), args.retest_precise_bn
    )
    if sweep.data.root is None and "protocol" in dict(retest.data):
        raise ReproduceUsageError(
            "--retest-data protocol: the smoke budget's embedded synthetic shapes have no ModelNet40 protocol"
        )
    if args.report_only:
        log = ResultLog(retest_path(sweep, retest, ".jsonl"), KEY_FIELDS)
    else:
        try:
            log = retest_sweep(sweep, retest, progress)
        except (MissingWeightsError, NoFinishedRunsError) as err:
            raise ReproduceUsageError(str(err)) from None
    md = retest_path(sweep, retest, ".md")

    def write() -> list[Path]:
        return [write_text(md, render_retest(sweep, log, retest, command))]

    written = _guarded(write, log.path, args.report_only)
    return written + ([log.path] if log.path.is_file() else [])


def _time(run: RuntimeRun, args: argparse.Namespace, command: str, progress: Callable[[str], None]) -> list[Path]:
    """Measure (or only report) the runtime experiment; the Markdown report, the JSONL and the PNG."""
    log = run.open_log() if args.report_only else measure_runtime(run, progress=progress, rerun=not args.resume)

    def write() -> list[Path]:
        written = [write_text(run.file_stem.with_suffix(".md"), render_runtime(run, log, command))]
        return written + ([run.log_path] if run.log_path.is_file() else []) + plot_runtime(run, log)

    return _guarded(write, run.log_path, args.report_only)


def _evaluate(run: EvalRun, args: argparse.Namespace, command: str, progress: Callable[[str], None]) -> list[Path]:
    """Train and evaluate (or only report) an evaluation experiment; the Markdown report, the JSONL and the PNG."""
    log = run.open_log() if args.report_only else run_conditions(run, progress=progress, rerun=not args.resume)
    render_report, plot = WRITERS[run.experiment.name]

    def write() -> list[Path]:
        written = [write_text(run.file_stem.with_suffix(".md"), render_report(run, log, command))]
        return written + ([run.log_path] if run.log_path.is_file() else []) + plot(run, log)

    return _guarded(write, run.log_path, args.report_only)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``lcreg reproduce`` (exit code 2 for arguments)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    command = "lcreg reproduce " + " ".join(argv)
    if os.environ.get("LCREG_DEBUG", "") not in ("", "0"):
        written = reproduce(args, command)
    else:
        try:
            written = reproduce(args, command)
        except ReproduceUsageError as err:
            _fail(str(err))
        except WorkersFailedError as err:
            sys.stderr.write(f"lcreg reproduce: {err}\n")
            raise SystemExit(err.exit_code) from None
        except ReportNotWrittenError as err:
            sys.stderr.write(f"lcreg reproduce: {err}\n")
            raise SystemExit(REPORT_NOT_WRITTEN_EXIT_CODE) from None
    for path in written:
        print(f"wrote {path}")


def _fail(message: str) -> NoReturn:
    sys.stderr.write(f"lcreg reproduce: error: {message}\n")
    raise SystemExit(2)
