"""Which resumes of finished runs trained one batch more than an uninterrupted run would have.

    python benchmarks/resume_audit.py docs/results/converge [--out docs/results/converge/resume_audit.md]
    python benchmarks/resume_audit.py --smoke      # seconds: a made-up run with two resumes

Until session 61 :class:`lcreg.callbacks.LatestCheckpoint` wrote the end of an epoch in ``on_train_epoch_end``. A
``max_steps`` run resumed from such a file ends that epoch again after one more batch (Lightning 2.6 always restarts an
iteration-based run's fit loop; a related report: Lightning-AI/pytorch-lightning#19617), so the resumed run is one
step ahead of the uninterrupted one from there on, the next epoch's first batch trained twice. Its trace in the
metrics: the first epoch-end row of the resumed segment ends the epoch the previous segment had ended already, one
step later (e.g. ``train/loss_epoch`` of epoch 3 at step 351, then again at 352; a validation due at the extra step
comes before it).

The script reads every ``metrics.csv`` under the folders given, with the ``metrics.segment<n>.csv`` of its earlier
segments (:func:`lcreg.experiments.benchmarking.curves.segments`), and lists each resume boundary with that trace.
A resume without it can still differ for other reasons (another machine, thread count or library version).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lcreg.experiments.benchmarking import add_smoke_argument, markdown_table, write_or_print
from lcreg.experiments.benchmarking.curves import segments

EPOCH_END_COLUMN = "train/loss_epoch"


@dataclass(frozen=True)
class Resume:
    """One resume boundary of a run: the segment it started and whether it trained one batch more.

    Attributes:
        run: The run's folder.
        segment: File name of the segment the resume started (``metrics.segment<n>.csv`` or ``metrics.csv``).
        epoch: Epoch of the previous segment's last epoch-end row.
        step: Step of that row.
        extra_batch: Whether the new segment starts by ending that epoch again one step later.
    """

    run: Path
    segment: str
    epoch: int | None
    step: int | None
    extra_batch: bool


def _epoch_ends(path: Path) -> list[tuple[int, int]]:
    """``(epoch, step)`` of every epoch-end row of one metrics file, in file order."""
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    return [(int(r["epoch"]), int(float(r["step"]))) for r in rows if r.get(EPOCH_END_COLUMN)]


def resumes(metrics: Path) -> list[Resume]:
    """The resume boundaries of the run whose last segment is ``metrics`` (a ``metrics.csv``)."""
    found = []
    parts = segments(metrics)
    for before, after in itertools.pairwise(parts):
        ends, later = _epoch_ends(before), _epoch_ends(after)
        epoch, step = ends[-1] if ends else (None, None)
        extra = step is not None and bool(later) and later[0] == (epoch, step + 1)
        found.append(Resume(metrics.parent, after.name, epoch, step, extra))
    return found


def audit(folders: Sequence[Path]) -> list[Resume]:
    """Every resume boundary of the runs under ``folders`` (a retest's folder is not a training run)."""
    files = sorted({p for folder in folders for p in folder.rglob("metrics.csv") if "retest" not in str(p)})
    return [resume for path in files for resume in resumes(path)]


def report(found: Sequence[Resume], root: Path | None = None) -> str:
    """Markdown: the count, then one row per boundary that trained one batch more."""
    extra = [r for r in found if r.extra_batch]
    lines = [
        f"{len(found)} resume boundaries in {_runs(found)}; {len(extra)} of them, in {_runs(extra)}, trained one "
        "batch more (the resumed segment ends the previous segment's last epoch again, one step later).",
        "",
    ]
    rows = [[_name(r.run, root), r.segment, r.epoch, f"{r.step} → {(r.step or 0) + 1}"] for r in extra]
    lines.append(markdown_table(["run", "segment", "epoch ended again", "its end step"], rows))
    return "\n".join(lines) + "\n"


def _runs(found: Sequence[Resume]) -> str:
    count = len({r.run for r in found})
    return f"{count} run" if count == 1 else f"{count} runs"


def _name(run: Path, root: Path | None) -> str:
    if root is not None and run.is_relative_to(root):
        return str(run.relative_to(root))
    return str(run)


def smoke_run(folder: Path) -> Path:
    """A made-up run: epochs of 4 steps, resumed once at an epoch end with the trace and once mid-epoch without."""
    header = ["epoch", "step", EPOCH_END_COLUMN, "train/loss_step"]
    parts = {
        "metrics.segment1.csv": [[0, 1, "", 1.0], [0, 3, 0.9, ""], [1, 5, "", 0.8], [1, 7, 0.7, ""]],
        "metrics.segment2.csv": [[1, 8, 0.1, ""], [2, 9, "", 0.6]],
        "metrics.csv": [[2, 10, "", 0.5], [2, 12, 0.5, ""]],
    }
    for name, rows in parts.items():
        with (folder / name).open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
    return folder


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", type=Path, help="folders searched for runs' metrics.csv")
    parser.add_argument("--out", help="write the report here (default: print it)")
    add_smoke_argument(parser)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    with tempfile.TemporaryDirectory(prefix="lcreg-resume-audit-") as scratch:
        folders = [smoke_run(Path(scratch))] if args.smoke else args.folders
        if not folders:
            sys.exit("resume_audit: give the folders to search (or --smoke)")
        missing = [str(f) for f in folders if not f.is_dir()]
        if missing:
            sys.exit(f"resume_audit: not a folder: {', '.join(missing)}")
        text = report(audit(folders), folders[0] if len(folders) == 1 else None)
    write_or_print(text, args.out, "resume_audit.md", args.smoke)


if __name__ == "__main__":
    main()
