"""The paper's "LC + X" experiment as a script: a front end of ``lcreg reproduce lc``
(:mod:`lcreg.experiments.reproduce`).

    python benchmarks/lc_plus_x.py --budget cpu --seeds 0 1 2 --out docs/results/lc_plus_x.md
    python benchmarks/lc_plus_x.py --hosts idam deepgmr --budget cpu      # a subset of the hosts
    python benchmarks/lc_plus_x.py --smoke      # seconds: DCP-v2 and LC + DCP-v2, 2 steps on synthetic shapes

Every (host, variant, seed) is trained with the budget's steps, points and batch (``cpu``: per host, see
``lcreg.experiments.reproduce.lc.BUDGETS``; ``paper``: 200 epochs), its checkpoint chosen on the validation pairs and
tested once on the deterministic test pairs; rows are appended to ``<out>.jsonl`` as runs finish (a rerun skips them),
and ``<out>`` gets the table beside the paper's (with ``<out stem>_rotation.png`` and ``_translation.png``). The same as
``lcreg reproduce lc --out <folder of out>``, with the files named after ``--out``. The figures of
``docs/results/lc_plus_x.md`` came from the former version of this script (``--host-budget``): per-host step budgets
like those of the ``cpu`` preset.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from lcreg.experiments.benchmarking import add_smoke_argument, output_path
from lcreg.experiments.reproduce.budgets import DEFAULT_ROOT, PRESETS
from lcreg.experiments.reproduce.command import build_parser, reproduce
from lcreg.experiments.reproduce.lc import HOSTS

SMOKE = {"hosts": ["dcp"], "seeds": [0], "budget": "smoke"}


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hosts", nargs="+", default=list(HOSTS), choices=list(HOSTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--budget", default="cpu", choices=PRESETS)
    parser.add_argument("--root", default=DEFAULT_ROOT)
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--out", default=None, help="Markdown table (default docs/results/lc_plus_x.md)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    if args.smoke:
        vars(args).update(SMOKE)
    args.out = output_path(args.out, "lc_plus_x.md", args.smoke) or Path("docs/results/lc_plus_x.md")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    seeds = [str(s) for s in args.seeds]
    only = [f"{host}/*" for host in args.hosts]
    options = ["lc", "--budget", args.budget, "--seeds", *seeds, "--out", str(args.out.parent), "--only", *only]
    options += ["--root", args.root, "--protocol", args.protocol]
    command = f"python benchmarks/lc_plus_x.py {args.command}"
    for path in reproduce(build_parser().parse_args(options), command, stem=args.out.stem):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
