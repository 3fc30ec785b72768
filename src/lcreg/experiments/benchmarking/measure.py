"""Timing (synchronised on CUDA), registration speed, peak memory and fresh-process measurements.

:func:`timed` is the one timing primitive: every benchmark and :func:`lcreg.experiments.evaluation.evaluate` time
through it. Clocks are injectable (``clock``), so the bookkeeping is tested without sleeping.
"""

from __future__ import annotations

import ctypes
import gc
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import torch

from lcreg.types import RegistrationResult

if TYPE_CHECKING:
    from lcreg.models.base import RegistrationModule

__all__ = [
    "Clock",
    "RegistrationSpeed",
    "Timing",
    "device_of",
    "peak_memory_mib",
    "peak_rss_increase_mib",
    "peak_rss_mib",
    "registration_speed",
    "run_fresh_process",
    "synchronize",
    "time_call",
    "time_calls",
    "timed",
]

T = TypeVar("T")
Clock = Callable[[], float]
"""A monotonic clock in seconds (``time.perf_counter`` by default)."""
DeviceLike = torch.device | str | None


def synchronize(device: DeviceLike) -> None:
    """Wait for queued kernels on ``device`` (CUDA only; a no-op elsewhere and for ``None``)."""
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def device_of(module: torch.nn.Module) -> torch.device:
    """Device of a module's first parameter or buffer; the CPU for modules without any (Open3D methods)."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


def timed(fn: Callable[[], T], device: DeviceLike = None, clock: Clock = time.perf_counter) -> tuple[T, float]:
    """Call ``fn()`` once and measure its wall time, synchronising ``device`` before and after.

    Args:
        fn: The work to time (no arguments; bind them with ``functools.partial`` or a closure).
        device: Device whose queued work belongs to the measurement (CUDA is asynchronous).
        clock: Clock in seconds.

    Returns:
        ``(fn's result, seconds)``.
    """
    synchronize(device)
    start = clock()
    out = fn()
    synchronize(device)
    return out, clock() - start


@dataclass(frozen=True)
class Timing:
    """Seconds of the timed repeats of one function (warm-up runs excluded)."""

    runs_s: tuple[float, ...]

    @property
    def median_s(self) -> float:
        """Median of the repeats, seconds."""
        return statistics.median(self.runs_s)


def time_calls(
    fns: Mapping[str, Callable[[], object]],
    repeats: int,
    warmup: int = 1,
    device: DeviceLike = None,
    clock: Clock = time.perf_counter,
) -> dict[str, Timing]:
    """Time several functions in alternating rounds (each round calls every function once, in order).

    Alternating spreads slow drifts (thermal, other jobs) evenly over the functions being compared.

    Args:
        fns: Functions by name.
        repeats: Timed rounds (>= 1).
        warmup: Rounds run first and discarded (allocator, caches, lazy initialisation).
        device: Device synchronised around every call (see :func:`timed`).
        clock: Clock in seconds.

    Returns:
        The :class:`Timing` of every function.

    Raises:
        ValueError: If ``repeats < 1`` or ``warmup < 0``.
    """
    if repeats < 1 or warmup < 0:
        raise ValueError(f"need repeats >= 1 and warmup >= 0, got {repeats} and {warmup}")
    runs: dict[str, list[float]] = {name: [] for name in fns}
    for round_index in range(warmup + repeats):
        for name, fn in fns.items():
            seconds = timed(fn, device, clock)[1]
            if round_index >= warmup:
                runs[name].append(seconds)
    return {name: Timing(tuple(values)) for name, values in runs.items()}


def time_call(
    fn: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    device: DeviceLike = None,
    clock: Clock = time.perf_counter,
) -> Timing:
    """:func:`time_calls` for one function: ``warmup`` discarded calls, then ``repeats`` timed ones."""
    return time_calls({"fn": fn}, repeats, warmup, device, clock)["fn"]


@dataclass(frozen=True)
class RegistrationSpeed:
    """Median ms per pair of registering a set of pairs, and the mean iterations the method ran."""

    ms_per_pair: float
    mean_iterations: float


def registration_speed(
    model: RegistrationModule,
    points_src: torch.Tensor,
    points_ref: torch.Tensor,
    batch_size: int = 1,
    repeats: int = 3,
    clock: Clock = time.perf_counter,
) -> RegistrationSpeed:
    """Time ``model.register`` over all pairs in chunks of ``batch_size`` on the model's device.

    One untimed warm-up pass (its iteration counts are reported), then ``repeats`` timed passes.

    Args:
        model: A registration module (Open3D methods run on the CPU).
        points_src: Source clouds ``(P, N, 3)``, moved to the model's device.
        points_ref: Reference clouds ``(P, M, 3)``.
        batch_size: Pairs per ``register`` call.
        repeats: Timed passes (median reported).
        clock: Clock in seconds.

    Returns:
        Median ms per pair and mean iterations per pair.
    """
    device = device_of(model)
    src, ref = points_src.to(device), points_ref.to(device)

    def run() -> list[RegistrationResult]:
        chunks = range(0, len(src), batch_size)
        return [model.register(src[i : i + batch_size], ref[i : i + batch_size]) for i in chunks]

    warm, _ = timed(run, device, clock)
    timing = time_call(run, repeats, warmup=0, device=device, clock=clock)
    iterations = torch.cat([r.num_iters.reshape(-1).float().cpu() for r in warm])
    return RegistrationSpeed(1000 * timing.median_s / len(src), float(iterations.mean()))


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports ``ru_maxrss`` in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _status_mib(field: str) -> float:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``; reported in KiB), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key == field:
            return int(value.split()[0]) / 1024
    raise OSError(f"/proc/self/status has no {field}")


def peak_rss_increase_mib(fn: Callable[[], T]) -> tuple[T, float | None]:
    """Call ``fn()`` once and measure how far this process's resident set rose above its level before the call.

    Linux only: freed heap memory is first returned to the system (glibc ``malloc_trim``), the high-water mark is
    reset to the current resident set (``/proc/self/clear_refs``), and the figure is ``VmHWM`` after the call minus
    ``VmRSS`` before it. Unlike ``ru_maxrss`` (the peak over the process's whole life) it can be taken for several
    functions in one process; it covers every allocation (tensors, autograd buffers, library workspaces) that was
    resident at the peak.

    Returns:
        ``(fn's result, MiB)``; the MiB are ``None`` where the kernel offers no resettable high-water mark.
    """
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        before = _status_mib("VmRSS")
    except OSError:
        return fn(), None
    out = fn()
    return out, _status_mib("VmHWM") - before


def peak_memory_mib(fn: Callable[[], T], device: str | torch.device) -> tuple[T, float | None]:
    """Call ``fn()`` once and measure the peak memory it took on ``device``, MiB.

    CUDA: ``torch.cuda.max_memory_allocated`` after resetting the peak (tensors held by PyTorch's allocator, not the
    allocator's cache or the CUDA context). Otherwise: :func:`peak_rss_increase_mib` (the process's resident set).

    Returns:
        ``(fn's result, MiB)``; the MiB are ``None`` where the CPU figure cannot be taken.
    """
    device = torch.device(device)
    if device.type != "cuda":
        return peak_rss_increase_mib(fn)
    torch.cuda.reset_peak_memory_stats(device)
    out = fn()
    return out, torch.cuda.max_memory_allocated(device) / 2**20


def run_fresh_process(args: Sequence[str]) -> dict[str, Any]:
    """Run ``python <args>`` in a new process (own peak memory) and parse the last JSON line it prints.

    The child imports the same ``lcreg`` as this process (its source folder is put first on ``PYTHONPATH``).

    Raises:
        RuntimeError: If the child fails or prints no JSON line (the message holds its stderr tail).
    """
    import lcreg

    src = str(Path(lcreg.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH")) if p)}
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True, check=False, env=env)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"`python {' '.join(args)}` failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(lines[-1])
    return result
