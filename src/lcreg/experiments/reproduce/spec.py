"""What an experiment of ``lcreg reproduce`` is: trained variants, the cells of the paper's table, claims, budgets.

An :class:`Experiment` is data only; :mod:`lcreg.experiments.reproduce.sweep` trains and tests its variants through the
benchmark harness, :mod:`lcreg.experiments.reproduce.report` and :mod:`lcreg.experiments.reproduce.plots` write the
table and the figures. The table has *rows* (grouped in *blocks*) and *series* (column groups): the ablation's rows are
the paper's rows and its series the two objectives; the LC table's rows are the hosts and its series X and LC + X.
Every (row, series) :class:`Cell` names the variant whose runs fill it and the paper row it is compared with; several
cells may share a variant (the paper repeats model D as |X1| = 64 and (λ1, λ2) = (0.5, 0.1); it is trained once).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from lcreg.experiments.reproduce.budgets import Preset, RunBudget
from lcreg.experiments.reproduce.claims import Claim
from lcreg.experiments.reproduce.paper import PaperTable

__all__ = ["Cell", "Experiment", "Variant"]


@dataclass(frozen=True)
class Variant:
    """A trained configuration: a method of :data:`lcreg.experiments.benchmarking.METHODS` and its budget group.

    Attributes:
        key: Name in the JSONL, in claims and in ``--only`` (e.g. ``"paper/A"``, ``"dcp/LC"``).
        method: Registry name of the method (its configs are what is trained).
        budget_group: Key of the experiment's budgets (variants of one group get the same budget).
        overrides: Config values by dotted key applied after the method's configs (e.g. another LC weight:
            ``{"model.init_args.loss_terms": [...]}``; a list replaces the configs' list).
    """

    key: str
    method: str
    budget_group: str
    overrides: Mapping[str, Any] = field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class Cell:
    """One entry of the reproduced table: the runs of ``variant`` beside the paper's row ``paper``."""

    block: str
    row: str
    series: str
    variant: str
    paper: str | None


Rows = Mapping[str, Sequence[Mapping[str, Any]]]
"""Finished JSONL rows by variant key (one per seed)."""


@dataclass(frozen=True)
class Experiment:
    """One experiment of ``lcreg reproduce``.

    Attributes:
        name: Command-line name (``lcreg reproduce <name>``) and stem of the output files.
        title: Heading of the report.
        paper_table: The paper table reproduced (its caption's start and LaTeX label).
        paper: The paper's numbers by row (:mod:`lcreg.experiments.reproduce.paper`).
        variants: Everything trained.
        cells: The table: one cell per (row, series).
        claims: The paper's claims, judged on the seeds.
        budgets: Preset -> budget group -> budget.
        series: What each series is (one line each, in the report's header).
        notes: How the experiment differs from the paper (report bullets).
        extra: Further report lines computed from the finished rows (e.g. the size of the LC term).
    """

    name: str
    title: str
    paper_table: str
    paper: PaperTable
    variants: tuple[Variant, ...]
    cells: tuple[Cell, ...]
    claims: tuple[Claim, ...]
    budgets: Mapping[Preset, Mapping[str, RunBudget]]
    series: Mapping[str, str]
    notes: tuple[str, ...] = ()
    extra: Callable[[Rows], list[str]] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        keys = [v.key for v in self.variants]
        if len(set(keys)) != len(keys):
            raise ValueError(f"{self.name}: variant keys repeat: {keys}")
        unknown = {c.variant for c in self.cells} - set(keys)
        unknown |= {k for claim in self.claims for c in claim.comparisons for k in (c.better, c.worse)} - set(keys)
        if unknown:
            raise ValueError(f"{self.name}: cells or claims name unknown variants {sorted(unknown)}")
        if missing := {c.paper for c in self.cells if c.paper is not None} - set(self.paper):
            raise ValueError(f"{self.name}: cells name rows the paper table lacks: {sorted(missing)}")
        groups = {v.budget_group for v in self.variants}
        for preset, budgets in self.budgets.items():
            if lacking := groups - set(budgets):
                raise ValueError(f"{self.name}: preset {preset} has no budget for {sorted(lacking)}")

    def variant(self, key: str) -> Variant:
        """The variant named ``key``."""
        return next(v for v in self.variants if v.key == key)

    def budget(self, preset: Preset, variant: Variant) -> RunBudget:
        """The budget of ``variant`` under ``preset``."""
        return self.budgets[preset][variant.budget_group]

    def with_points(self, points: int) -> Experiment:
        """The experiment with every budget of every preset at ``points`` points per cloud.

        The budgets' descriptions (and so the JSONL keys of the runs) name the new size, so these runs never count
        as runs of the budgets' own size.

        Raises:
            ValueError: If ``points`` is not an integer of at least 3 (the fewest a rigid pose can be solved from).
        """
        if isinstance(points, bool) or not isinstance(points, int) or points < 3:
            raise ValueError(f"points per cloud must be an integer of at least 3, got {points!r}")
        budgets = {p: {g: replace(b, points=points) for g, b in groups.items()} for p, groups in self.budgets.items()}
        return replace(self, budgets=budgets)

    def select(self, patterns: Sequence[str]) -> Experiment:
        """The experiment restricted to the variants whose key matches a pattern (``fnmatch``; none: all).

        The variants come in the order of the first pattern each matches (the experiment's order within a pattern),
        so ``--only`` also sets the order a sweep runs them in. Cells of other variants are dropped, and so are
        claims that compare them.

        Raises:
            ValueError: If a pattern matches no variant (the message lists the keys).
        """
        if not patterns:
            return self
        keys = [v.key for v in self.variants]
        for pattern in patterns:
            if not fnmatch.filter(keys, pattern):
                raise ValueError(f"--only {pattern!r} matches no variant of {self.name}; known: {', '.join(keys)}")
        first = {
            v.key: next((i for i, p in enumerate(patterns) if fnmatch.fnmatchcase(v.key, p)), None)
            for v in self.variants
        }
        kept = {k for k, i in first.items() if i is not None}
        claims = tuple(c for c in self.claims if all({x.better, x.worse} <= kept for x in c.comparisons))
        return replace(
            self,
            variants=tuple(sorted((v for v in self.variants if v.key in kept), key=lambda v: first[v.key] or 0)),
            cells=tuple(c for c in self.cells if c.variant in kept),
            claims=claims,
        )

    def blocks(self) -> list[str]:
        """Block names in table order."""
        return list(dict.fromkeys(c.block for c in self.cells))

    def rows(self, block: str) -> list[str]:
        """Row names of ``block`` in table order."""
        return list(dict.fromkeys(c.row for c in self.cells if c.block == block))

    def series_names(self) -> list[str]:
        """Series in column order."""
        return list(dict.fromkeys(c.series for c in self.cells))

    def cell(self, block: str, row: str, series: str) -> Cell | None:
        """The cell at (``block``, ``row``, ``series``), if the table has one."""
        return next((c for c in self.cells if (c.block, c.row, c.series) == (block, row, series)), None)
