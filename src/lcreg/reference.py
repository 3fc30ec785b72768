"""Reference mode: run the straightforward implementations that the optimised training step replaced.

Several hot spots of the DVDs training step have a fast implementation (the default) and the plain one it was
derived from, kept as private ``_..._reference`` functions beside it. Both compute the same mathematics; they differ
only in float rounding (summation order) and in time and memory. Inside ``with reference_mode():`` every such spot
takes its reference implementation, so a test can compare the whole step's losses and gradients with the plain code
and a benchmark can time both on the same weights and batch in one process (``benchmarks/bench_dvds_step.py``).

This is a verification and benchmarking tool, not a setting: no constructor or config exposes it. The switch is a
:class:`contextvars.ContextVar`, so it is local to the thread (and asyncio task) that enters it; autograd's backward
pass replays whatever graph the forward pass built, so it needs no switch of its own.

Example:
    >>> with reference_mode():
    ...     reference_active()
    True
    >>> reference_active()
    False
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

__all__ = ["reference_active", "reference_mode"]

_REFERENCE: ContextVar[bool] = ContextVar("lcreg_reference_mode", default=False)


@contextmanager
def reference_mode() -> Iterator[None]:
    """Run the reference (unoptimised) implementations inside the ``with`` block; nests and restores on exit."""
    token = _REFERENCE.set(True)
    try:
        yield
    finally:
        _REFERENCE.reset(token)


def reference_active() -> bool:
    """Whether the calling code runs inside :func:`reference_mode`."""
    return _REFERENCE.get()
