"""``lcreg reproduce``: the paper's tables rerun with a budget, ours beside the paper's numbers.

* :mod:`~lcreg.reproduce.paper`: the paper's numbers (ablation and LC + X tables);
* :mod:`~lcreg.reproduce.budgets`: :class:`RunBudget` (steps or epochs, points, batch, validations) and the data;
* :mod:`~lcreg.reproduce.claims`: the paper's claims as comparisons judged against the seed spread;
* :mod:`~lcreg.reproduce.spec`: :class:`Experiment` (variants, table cells, claims, budgets per preset);
* :mod:`~lcreg.reproduce.ablation`, :mod:`~lcreg.reproduce.lc`: the experiments, thin specs over the registry;
* :mod:`~lcreg.reproduce.sweep`: train, select on validation, test, one resumable JSONL row per run
  (:func:`lcreg.benchmarking.fit`);
* :mod:`~lcreg.reproduce.runtime`: the runtime table (nothing trained: ms per pair per method, points, seed);
* :mod:`~lcreg.reproduce.conditions`: evaluation experiments (models trained once, shared; every method × seed ×
  test condition on the same pairs, per-pair errors in the JSONL); :mod:`~lcreg.reproduce.robustness` (recall vs
  noise and partial visibility) and :mod:`~lcreg.reproduce.recall_curves` (recall vs rotation threshold, scenes);
* :mod:`~lcreg.reproduce.report`, :mod:`~lcreg.reproduce.plots`: the Markdown table and the PNGs;
* :mod:`~lcreg.reproduce.command`: the command line (dispatched by :func:`lcreg.cli.main`).
"""

from __future__ import annotations

from lcreg.reproduce.budgets import PRESETS, DataChoice, RunBudget
from lcreg.reproduce.claims import Claim, ClaimResult, Comparison, judge
from lcreg.reproduce.command import EXPERIMENTS, PLANNED, main
from lcreg.reproduce.spec import Cell, Experiment, Variant
from lcreg.reproduce.sweep import Sweep, run_sweep

__all__ = [
    "EXPERIMENTS",
    "PLANNED",
    "PRESETS",
    "Cell",
    "Claim",
    "ClaimResult",
    "Comparison",
    "DataChoice",
    "Experiment",
    "RunBudget",
    "Sweep",
    "Variant",
    "judge",
    "main",
    "run_sweep",
]
