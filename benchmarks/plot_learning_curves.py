"""Learning-curve PNGs and a summary table from the ``metrics.csv`` files of ``lcreg fit`` runs.

    python benchmarks/plot_learning_curves.py --run "model D=runs/x/version_0/metrics.csv" \\
        --run "model D=runs/x/version_1/metrics.csv" --run "recipe=runs/y/version_*/metrics.csv" \\
        --out docs/results/curves/ [--smooth 0.6] [--x pairs]
    python benchmarks/plot_learning_curves.py --smoke     # synthetic metrics.csv files (in smoke_runs/ beside the PNGs)

Each ``--run label=path`` adds runs to a label: ``path`` is a ``metrics.csv``, a folder (its ``metrics.csv`` files,
recursively) or a glob (quote it); several runs of one label are its seeds (mean line, min–max shade). Without
``label=`` the label is the run's name (the folder above ``version_<k>``). ``--out`` is a folder (``validation.png``,
``jacobian.png``, ``training.png``, ``other.png`` where their keys were logged, and ``summary.md``) or a ``.md`` file
(the summary there, the PNGs beside it as ``<stem>_<figure>.png``). ``--x pairs`` draws against the training pairs
seen (step × the ``batch_size`` of each run's ``hparams.yaml``), to compare runs of different batch sizes. See
:mod:`lcreg.experiments.benchmarking.curves`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from lcreg.experiments.benchmarking import (
    X_AXES,
    add_smoke_argument,
    load_runs,
    output_path,
    plot_curves,
    run_files,
    summary_table,
    write_synthetic_metrics,
    write_text,
)

SMOKE_RUNS = {"model D": (0, 1, 2), "recipe": (10, 11)}  # label: seeds of the synthetic metrics.csv files


def files_of(pattern: str) -> list[Path]:
    """:func:`run_files` of ``pattern``; nothing found ends the script with the message."""
    try:
        return run_files(pattern)
    except FileNotFoundError as err:
        raise SystemExit(f"--run: {err}") from None


def parse_run(item: str) -> tuple[str, list[Path]]:
    """``"label=path"`` as the label and its ``metrics.csv`` files; a bare path is labelled with its run's name."""
    label, sep, path = item.partition("=")
    if not sep:
        label, path = "", item
    if not path:
        raise SystemExit(f"--run expects [label=]path, got {item!r}")
    files = files_of(path)
    if not label:
        folder = files[0].parent
        label = folder.parent.name if folder.name.startswith("version_") else folder.name
    return label, files


def smoke_runs(root: Path) -> dict[str, list[Path]]:
    """Synthetic Lightning-like ``metrics.csv`` files under ``root``, by label."""
    return {
        label: [write_synthetic_metrics(root / label / f"version_{s}" / "metrics.csv", seed=s) for s in seeds]
        for label, seeds in SMOKE_RUNS.items()
    }


def destinations(out: Path) -> tuple[Path, Path, str]:
    """The PNG folder, the summary file and the PNG name prefix of ``--out``."""
    if out.suffix == ".md":
        return out.parent, out, f"{out.stem}_"
    return out, out / "summary.md", ""


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", default=[], metavar="[LABEL=]PATH", help="repeatable; see above")
    parser.add_argument("--out", default=None, help="folder of the PNGs and summary.md, or the summary's .md file")
    parser.add_argument("--smooth", type=float, default=0.0, help="EMA weight of the training curves (0: raw)")
    parser.add_argument("--x", choices=sorted(X_AXES), default="step", help="x axis (default: step)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    if not args.smoke and not (args.run and args.out):
        parser.error("--run and --out are required (or --smoke)")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    out = output_path(args.out, "curves", args.smoke)
    assert out is not None  # parse() requires --out outside smoke runs
    folder, summary, prefix = destinations(out)
    files = smoke_runs(folder / "smoke_runs") if args.smoke else {}
    for label, paths in map(parse_run, args.run):
        files.setdefault(label, []).extend(paths)
    try:
        metrics = load_runs(files, x=args.x)
    except (FileNotFoundError, ValueError) as err:  # --x pairs: a run without its batch size
        raise SystemExit(f"--x {args.x}: {err}") from None
    table = summary_table(metrics, x=args.x)
    print(table, flush=True)
    sources = [f"- {label}: " + ", ".join(map(str, paths)) for label, paths in files.items()]
    write_text(summary, "\n".join(["Learning curves of", "", *sources, "", table, ""]))
    for path in plot_curves(metrics, folder, prefix, smooth=args.smooth, x=args.x):
        print(f"wrote {path}")
    print(f"wrote {summary}")


if __name__ == "__main__":
    main()
