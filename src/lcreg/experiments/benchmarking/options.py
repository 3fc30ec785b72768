"""Command-line pieces shared by the benchmark scripts: ``key=value`` lists, config options, budgets, ``--smoke``."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["Budget", "add_smoke_argument", "apply_smoke", "config_values", "key_values"]


def key_values(items: Sequence[str], option: str) -> dict[str, str]:
    """``["dvds=a.ckpt", "dcp=b.ckpt"]`` as a dict.

    Raises:
        SystemExit: If an item has no ``=`` or an empty side (the message names ``option``).
    """
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if not key or not value:
            raise SystemExit(f"{option} expects key=value, got {item!r}")
        out[key] = value
    return out


def config_values(args: Sequence[str]) -> dict[str, Any]:
    """A script's extra options ``--data.init_args.test_split=train`` (or ``--key value``) as values by dotted key.

    The values stay text: :func:`lcreg.cli.instantiate` types them as ``lcreg`` types its command line (``"5"`` for
    an int, ``"null"``, ``"[1, 2]"``).

    Raises:
        SystemExit: If an item is not ``--key=value`` or ``--key value`` (the message names it).
    """
    out: dict[str, Any] = {}
    items = iter(args)
    for item in items:
        key, sep, text = item.partition("=")
        value = text if sep else next(items, None)
        if not key.startswith("--") or len(key) < 3 or value is None or (not sep and value.startswith("--")):
            raise SystemExit(f"expected config options --key=value (e.g. --data.init_args.root=DIR), got {item!r}")
        out[key[2:]] = value
    return out


@dataclass(frozen=True)
class Budget:
    """A training budget: optimiser steps, points per cloud and pairs per batch."""

    steps: int
    points: int
    batch: int

    @classmethod
    def parse(cls, text: str, option: str = "budget") -> Budget:
        """``"steps,points,batch"`` (e.g. ``"200,512,16"``).

        Raises:
            SystemExit: If ``text`` is not three positive integers.
        """
        try:
            steps, points, batch = (int(v) for v in text.split(","))
        except ValueError:
            raise SystemExit(f"{option} expects steps,points,batch (three integers), got {text!r}") from None
        if min(steps, points, batch) < 1:
            raise SystemExit(f"{option} values must be positive, got {text!r}")
        return cls(steps, points, batch)

    def __str__(self) -> str:
        return f"{self.steps},{self.points},{self.batch}"


def add_smoke_argument(parser: argparse.ArgumentParser) -> None:
    """``--smoke``: run in seconds on tiny embedded synthetic pairs, untrained weights allowed (checks, no figures)."""
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="check that the script runs: a few seconds on tiny embedded synthetic pairs (no data files, untrained "
        "weights allowed, output under --out or a temporary folder); the figures mean nothing",
    )


def apply_smoke(args: argparse.Namespace, smoke: Mapping[str, Any]) -> argparse.Namespace:
    """Apply a script's ``--smoke`` settings, and use the embedded shapes when ``args.root`` is not a folder.

    Args:
        args: Parsed arguments with ``smoke`` and ``root``.
        smoke: The script's smoke settings (tiny sizes, one seed, ...).

    Returns:
        ``args``, updated in place.
    """
    if args.smoke:
        vars(args).update(smoke)
    if args.smoke or not (args.root and Path(args.root).is_dir()):
        args.root = None  # the embedded synthetic shapes
    return args
