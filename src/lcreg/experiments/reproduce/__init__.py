"""``lcreg reproduce``: the paper's tables rerun with a budget, ours beside the paper's numbers.

* :mod:`~lcreg.experiments.reproduce.paper`: the paper's numbers (ablation and LC + X tables);
* :mod:`~lcreg.experiments.reproduce.budgets`: :class:`RunBudget` (steps or epochs, points, batch, validations) and the
data;
* :mod:`~lcreg.experiments.reproduce.claims`: the paper's claims as comparisons judged against the seed spread;
* :mod:`~lcreg.experiments.reproduce.spec`: :class:`Experiment` (variants, table cells, claims, budgets per preset);
* :mod:`~lcreg.experiments.reproduce.ablation`, :mod:`~lcreg.experiments.reproduce.lc`: the experiments, thin specs
over the registry;
* :mod:`~lcreg.experiments.reproduce.sweep`: train, select on validation, test, one resumable JSONL row per run
  (:func:`lcreg.experiments.benchmarking.fit`); :mod:`~lcreg.experiments.reproduce.retest`: the kept weights of finished
  runs tested again under another precision (``--retest``);
* :mod:`~lcreg.experiments.reproduce.runtime`: the runtime table (nothing trained: ms per pair per method, points,
seed);
* :mod:`~lcreg.experiments.reproduce.conditions`: evaluation experiments (models trained once, shared; every method ×
  seed × test condition on the same pairs, per-pair errors in the JSONL); :mod:`~lcreg.experiments.reproduce.robustness`
  (recall vs noise and partial visibility) and :mod:`~lcreg.experiments.reproduce.recall_curves` (recall vs rotation
  threshold, scenes);
* :mod:`~lcreg.experiments.reproduce.report`, :mod:`~lcreg.experiments.reproduce.plots`: the Markdown table and the
PNGs;
* :mod:`~lcreg.experiments.reproduce.command`: the command line (dispatched by :func:`lcreg.cli.main`).
"""

from __future__ import annotations

from lcreg.experiments.reproduce.budgets import PRESETS, DataChoice, RunBudget
from lcreg.experiments.reproduce.claims import Claim, ClaimResult, Comparison, judge
from lcreg.experiments.reproduce.command import EXPERIMENTS, PLANNED, main
from lcreg.experiments.reproduce.spec import Cell, Experiment, Variant
from lcreg.experiments.reproduce.sweep import Sweep, run_sweep

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
