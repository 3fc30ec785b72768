"""The bad-input matrix of issue 14: every public entry point against bad (and a few valid) inputs, classified.

    python benchmarks/bad_input_matrix.py                 # prints the counts and writes nothing
    python benchmarks/bad_input_matrix.py --out docs/results/bad_input_matrix.md --details
    python benchmarks/bad_input_matrix.py --smoke         # a few cases, seconds (the test suite runs it)

Entry points: every model's ``register`` and ``forward`` (8 learned, 3 classical), ``LocalConsistency``,
``PointNetEncoder``, the registration metrics, ICP's initial guess, ``read_points`` on damaged files and the
checkpoint readers. Each case expects either an error or a result:

* ``typed``: the expected error, a ``ValueError``/``TypeError``/``FileNotFoundError`` (lcreg's typed errors derive from
  them) whose message names the argument or the file;
* ``cryptic``: any other exception, or a typed one that names neither (e.g. "mat1 and mat2 must have the same dtype",
  ``RuntimeError('')``, an error blaming an argument the caller never passed);
* ``silent``: a bad input that returned a result, or a result with NaN/Inf;
* ``ok``: a valid input (float64 clouds, large coordinates) that returned a finite result.

The script uses only names that already existed before issue 14, so the same file measures the code before the fix
(``PYTHONPATH=<old checkout>/src python benchmarks/bad_input_matrix.py``).
"""

from __future__ import annotations

import argparse
import os
import struct
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import lcreg

LEARNED = ["DVDs", "DCP", "PRNet", "IDAM", "DeepGMR", "PointNetLK", "FMRNet", "PCRNet"]
CLASSICAL = ["ICP", "RANSAC", "FGR"]
TYPED = (ValueError, TypeError, FileNotFoundError)


@dataclass
class Case:
    """One call: ``run()`` should raise an error naming ``names`` (any of them), or return when ``names`` is None."""

    group: str
    label: str
    run: Callable[[], Any]
    names: tuple[str, ...] | None


def classify(case: Case) -> tuple[str, str]:
    """``(typed|cryptic|silent|ok, short detail)``."""
    try:
        out = case.run()
    except Exception as err:  # the point of the matrix: whatever escapes is classified
        text = f"{type(err).__name__}: {' '.join(str(err).split())[:160]}"
        if case.names is None:
            return "cryptic", "valid input raised " + text
        named = any(name in str(err) for name in case.names)
        return ("typed" if isinstance(err, TYPED) and named else "cryptic"), text
    finite = _finite(out)
    if case.names is None:
        return ("ok", "finite result") if finite else ("silent", "valid input gave NaN/Inf")
    return "silent", "returned a result" + ("" if finite else " with NaN/Inf")


def _finite(out: Any) -> bool:
    if hasattr(out, "transform_ref_src"):
        out = out.transform_ref_src
    if isinstance(out, dict):
        return all(_finite(v) for v in out.values())
    if isinstance(out, (tuple, list)):
        return all(_finite(v) for v in out)
    if isinstance(out, torch.Tensor) and out.is_floating_point():
        return bool(torch.isfinite(out).all())
    if isinstance(out, np.ndarray) and np.issubdtype(out.dtype, np.floating):
        return bool(np.isfinite(out).all())
    return True


# --- clouds --------------------------------------------------------------------------------------------------------
def _clouds(n: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    src = torch.rand(2, n, 3, generator=gen) - 0.5
    return src, src + 0.02


def cloud_cases(n: int) -> Iterator[tuple[str, Any, Any, tuple[str, ...] | None]]:
    """``(label, src, ref, names)``: bad pairs of clouds, then valid ones (``names`` None)."""
    src, ref = _clouds(n)
    nan, inf = src.clone(), ref.clone()
    nan[1, 3, 0] = float("nan")
    inf[0, 2, 2] = float("inf")
    yield "nan_src", nan, ref, ("points_src",)
    yield "inf_ref", src, inf, ("points_ref",)
    yield "empty_src", src[:, :0], ref, ("points_src",)
    yield "zero_batch", src[:0], ref[:0], ("points_src",)
    yield "two_points_ref", src, ref[:, :2], ("points_ref",)
    yield "unbatched", src[0], ref[0], ("points_src",)
    yield "two_columns", src[..., :2], ref[..., :2], ("points_src",)
    yield "four_columns", torch.cat([src, src[..., :1]], -1), torch.cat([ref, ref[..., :1]], -1), ("points_src",)
    yield "int_dtype", src.long(), ref.long(), ("points_src",)
    yield "float16", src.half(), ref.half(), ("points_src",)
    yield "numpy_array", src.numpy(), ref.numpy(), ("points_src",)
    yield "batch_mismatch", src, ref[:1], ("points_ref",)
    yield "dtype_mismatch", src, ref.double(), ("points_ref", "points_src")
    yield "one_location", torch.ones(2, n, 3), torch.ones(2, n, 3), ("points_src", "points_ref")
    yield "float64", src.double(), ref.double(), None
    yield "scale_1e6", src.double() * 1e6, ref.double() * 1e6, None
    yield "scale_1e-3", src.double() * 1e-3, ref.double() * 1e-3, None


def model_cases(names: list[str], n: int) -> Iterator[Case]:
    for name in names:
        torch.manual_seed(0)
        model = getattr(lcreg, name)().eval()
        for label, src, ref, expect in cloud_cases(n):
            yield Case(name, f"register/{label}", lambda m=model, s=src, r=ref: m.register(s, r), expect)
            yield Case(name, f"forward/{label}", lambda m=model, s=src, r=ref: _no_grad(m, s, r), expect)


def _no_grad(model: Any, src: Any, ref: Any) -> Any:
    with torch.no_grad():
        return model(src, ref)


def module_cases(n: int) -> Iterator[Case]:
    """LocalConsistency, PointNetEncoder, metrics, ICP's initial guess."""
    encoder = lcreg.PointNetEncoder()
    lc = lcreg.LocalConsistency()
    lc_est = lcreg.LocalConsistency(pairing="estimate")
    big = _clouds(512)
    for label, src, ref, expect in cloud_cases(512):
        expect = None if label == "one_location" else expect  # a descriptor of one location is defined
        yield Case("LocalConsistency", label, lambda s=src, r=ref: lc(encoder, s, r), expect)
    for label, src, _, expect in cloud_cases(n):
        if label not in ("batch_mismatch", "dtype_mismatch", "two_points_ref", "inf_ref"):
            expect = None if label == "one_location" else expect and ("points",)
            yield Case("PointNetEncoder", label, lambda s=src: encoder(s), expect)
    scaled = torch.eye(4).repeat(2, 1, 1)
    scaled[:, 0, 0] = 2.0
    nan_t = torch.eye(4).repeat(2, 1, 1)
    nan_t[0, 1, 3] = float("nan")
    yield Case(
        "LocalConsistency",
        "estimate/non_rigid",
        lambda: lc_est(encoder, big[0], transform_ref_src=scaled),
        ("transform_ref_src",),
    )
    yield Case(
        "LocalConsistency",
        "estimate/nan",
        lambda: lc_est(encoder, big[0], transform_ref_src=nan_t),
        ("transform_ref_src",),
    )
    src, ref = _clouds(n)
    icp = lcreg.ICP()
    yield Case("ICP", "init/non_rigid", lambda: icp(src, ref, init=scaled), ("init",))
    yield Case("ICP", "init/nan", lambda: icp(src, ref, init=nan_t), ("init",))
    yield Case("ICP", "init/batch", lambda: icp(src, ref, init=scaled[:1]), ("init",))
    yield from metric_cases(scaled, nan_t)


def metric_cases(scaled: torch.Tensor, nan_t: torch.Tensor) -> Iterator[Case]:
    from lcreg.metrics.registration import registration_metrics

    eye = torch.eye(4).repeat(2, 1, 1)

    def update_then_compute(pred: torch.Tensor, gt: torch.Tensor) -> Any:
        metrics = registration_metrics()
        metrics.update(transform_pred=pred, transform_gt=gt)
        return metrics.compute()

    yield Case("metrics", "zero_pairs", lambda: registration_metrics().compute(), ("pairs", "update"))
    yield Case("metrics", "gt_nan", lambda: update_then_compute(eye, nan_t), ("transform_gt",))
    yield Case("metrics", "gt_non_rigid", lambda: update_then_compute(eye, scaled), ("transform_gt",))
    yield Case("metrics", "gt_shape", lambda: update_then_compute(eye, eye[:, :3]), ("transform_gt",))


# --- files ---------------------------------------------------------------------------------------------------------
def _ply(points: np.ndarray, declared: int | None = None, fmt: str = "binary_little_endian") -> bytes:
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {declared or len(points)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode()
    if fmt == "ascii":
        return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()
    return head + points.astype("<f4").tobytes()


def _pcd(points: np.ndarray, declared: int, data: str = "ascii", payload: bool = True) -> bytes:
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {declared}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {declared}\nDATA {data}\n"
    ).encode()
    if not payload:
        return head
    if data == "ascii":
        return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()
    return head + points.astype("<f4").tobytes()


def _npy(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def file_cases(folder: Path) -> Iterator[Case]:
    """``read_points`` on damaged, lying and valid files."""
    from lcreg.data.io import read_points

    pts = np.random.default_rng(0).random((64, 3)).astype(np.float32)
    npy = _npy(pts)
    files: dict[str, tuple[bytes, bool]] = {
        "ply_truncated.ply": (_ply(pts)[:136], False),
        "ply_lying_count.ply": (_ply(pts, declared=10_000_000), False),
        "ply_ascii_short.ply": (_ply(pts, declared=100, fmt="ascii"), False),
        "ply_header_only.ply": (_ply(pts)[: _ply(pts).index(b"end_header\n") + 11], False),
        "pcd_header_only.pcd": (_pcd(pts, 2_000_000, payload=False), False),
        "pcd_binary_truncated.pcd": (_pcd(pts, 64, "binary")[:-100], False),
        "pcd_ascii_lying.pcd": (_pcd(pts, 1000), False),
        "npy_1e39.npy": (_npy(np.full((4, 3), 1e39)), False),
        "npy_complex.npy": (_npy(pts.astype(np.complex64)), False),
        "npy_garbled_header.npy": (
            npy[:10] + b"{'descr': '<f4', 'fortran_order': False, 'shape': (64, 3" + npy[60:],
            False,
        ),
        "npy_huge_shape.npy": (npy.replace(b"(64, 3)", b"(99999999999, 3)"[: len(b"(64, 3)")]), False),
        "npy_truncated.npy": (npy[:-40], False),
        "bin_odd_size.bin": (struct.pack("<5f", *range(5)), False),
        "empty.ply": (b"", False),
        "random.pcd": (os.urandom(300), False),
        "valid.ply": (_ply(pts), True),
        "valid_ascii.ply": (_ply(pts, fmt="ascii"), True),
        "valid.npy": (npy, True),
        "valid.pcd": (_pcd(pts, 64), True),
    }
    for name, (data, valid) in files.items():
        path = folder / name
        path.write_bytes(data)
        yield Case(
            "read_points", name, lambda p=path, v=valid: _read_exact(read_points, p, pts, v), None if valid else (name,)
        )
    yield Case("read_points", "missing.ply", lambda: read_points(folder / "missing.ply"), ("missing.ply",))


def _read_exact(read: Callable[[Path], np.ndarray], path: Path, pts: np.ndarray, valid: bool) -> np.ndarray:
    out = read(path)
    if valid and not np.allclose(out, pts, atol=1e-6):
        return np.full(3, np.nan)  # a valid file read wrongly counts as silent
    return out


def checkpoint_cases(folder: Path) -> Iterator[Case]:
    from lcreg.weights import load_into

    model = lcreg.PointNetLK()
    files = {"ckpt_empty.ckpt": b"", "ckpt_random.ckpt": os.urandom(512)}
    good = folder / "ckpt_good.ckpt"
    torch.save({"state_dict": model.state_dict()}, good)
    files["ckpt_truncated.ckpt"] = good.read_bytes()[:200]
    torch.save({"weights": 1}, folder / "ckpt_no_state_dict.ckpt")
    for name, data in files.items():
        (folder / name).write_bytes(data)
    for name in [*files, "ckpt_no_state_dict.ckpt", "ckpt_missing.ckpt"]:
        yield Case("load_into", name, lambda p=folder / name: load_into(model, str(p)), (name,))


# --- driver --------------------------------------------------------------------------------------------------------
def all_cases(folder: Path, smoke: bool) -> Iterator[Case]:
    n = 64
    yield from model_cases(LEARNED[:1] if smoke else LEARNED, n)
    yield from model_cases(CLASSICAL[:1] if smoke else CLASSICAL, n)
    if not smoke:
        yield from module_cases(n)
    yield from file_cases(folder)
    yield from checkpoint_cases(folder)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", help="write the counts (and with --details every case) as Markdown")
    parser.add_argument("--details", action="store_true", help="list every case that is not typed/ok")
    parser.add_argument("--smoke", action="store_true", help="one learned and one classical model: seconds")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows: list[tuple[str, str, str, str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in all_cases(Path(tmp), args.smoke):
            verdict, detail = classify(case)
            rows.append((case.group, case.label, verdict, detail))
    counts = Counter(r[2] for r in rows)
    by_group: dict[str, Counter[str]] = {}
    for group, _, verdict, _ in rows:
        by_group.setdefault(group, Counter())[verdict] += 1
    lines = [f"{len(rows)} cases: " + ", ".join(f"{k} {counts[k]}" for k in ("typed", "ok", "cryptic", "silent")), ""]
    lines += ["| entry point | typed | ok | cryptic | silent |", "|---|---|---|---|---|"]
    lines += [f"| {g} | {c['typed']} | {c['ok']} | {c['cryptic']} | {c['silent']} |" for g, c in by_group.items()]
    bad = [r for r in rows if r[2] in ("cryptic", "silent")]
    if args.details and bad:
        lines += ["", "| entry point | case | verdict | what happened |", "|---|---|---|---|"]
        lines += [f"| {g} | {c} | {v} | {d.replace('|', '/')} |" for g, c, v, d in bad]
    text = "\n".join(lines)
    print(text, flush=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
