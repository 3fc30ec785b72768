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
TYPED: tuple[type[Exception], ...] = (ValueError, TypeError, FileNotFoundError)


def _typed() -> tuple[type[Exception], ...]:
    """:data:`TYPED` and lcreg's typed ``RuntimeError``: a training stopped on non-finite values."""
    from lcreg.models.base import NonFiniteTrainingError

    return (*TYPED, NonFiniteTrainingError)


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
        return ("typed" if isinstance(err, _typed()) and named else "cryptic"), text
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


# --- issue 27: geometry contract, internals, DataModules, HDF5 rows, training, CLI values -------------------------
def _propagates(fn: Callable[..., torch.Tensor], *args: torch.Tensor) -> torch.Tensor:
    """1.0 when ``fn`` keeps a NaN/Inf item non-finite and the other items exact (the geometry policy), else NaN."""
    clean = fn(*args)
    for value in (float("nan"), float("inf")):
        bad = args[0].clone()
        bad[1].view(-1)[0] = value
        out = fn(bad, *args[1:])
        if bool(torch.isfinite(out[1]).all()) or not torch.equal(out[[0, 2]], clean[[0, 2]]):
            return torch.tensor(float("nan"))
    return torch.tensor(1.0)


def geometry_cases() -> Iterator[Case]:
    """The element-wise maps propagate NaN/Inf item by item (``ok``); a finite result for a bad item is ``silent``."""
    from lcreg.geometry import euler, neighbors, se3, so3

    gen = torch.Generator().manual_seed(0)
    w = torch.randn(3, 3, generator=gen, dtype=torch.float64) * 0.5
    t = se3.exp(torch.randn(3, 6, generator=gen, dtype=torch.float64) * 0.3)
    p = torch.randn(3, 20, 3, generator=gen, dtype=torch.float64)
    maps: dict[str, tuple[Callable[..., torch.Tensor], tuple[torch.Tensor, ...]]] = {
        "so3.exp": (so3.exp, (w,)),
        "so3.log": (so3.log, (so3.exp(w),)),
        "so3.quaternion_to_matrix": (so3.quaternion_to_matrix, (torch.randn(3, 4, generator=gen, dtype=w.dtype),)),
        "euler.round_trip": (lambda r: euler.euler_zyx_to_matrix(euler.matrix_to_euler_zyx(r)), (so3.exp(w),)),
        "se3.exp": (se3.exp, (torch.randn(3, 6, generator=gen, dtype=w.dtype),)),
        "se3.log": (se3.log, (t,)),
        "se3.inverse": (se3.inverse, (t,)),
        "se3.compose": (se3.compose, (t, t)),
        "se3.transform_points": (se3.transform_points, (t, p)),
        "pairwise_sq_distances": (neighbors.pairwise_sq_distances, (p, p)),
    }
    for label, (fn, args) in maps.items():
        yield Case("geometry", f"{label}/nan_item", lambda f=fn, a=args: _propagates(f, *a), None)


def internal_cases(folder: Path) -> Iterator[Case]:
    """Internals and constructors a user reaches: LK with float64 clouds, gather_points, DataModules, HDF5 rows."""
    import dataclasses

    import h5py

    from lcreg.data.datamodule import ModelNet40DataModule, SyntheticDataModule
    from lcreg.data.modelnet40 import load_modelnet40_h5
    from lcreg.geometry.neighbors import gather_points
    from lcreg.nn.lk import InverseCompositionalLK
    from lcreg.nn.pointnet import PointNetEncoder
    from lcreg.types import RegistrationBatch

    src, ref = _clouds()
    lk, encoder = InverseCompositionalLK(), PointNetEncoder([16, 32]).eval()
    yield Case("nn.lk", "float64_clouds_float32_encoder", lambda: lk(encoder, src.double(), ref.double()), None)
    empty = torch.zeros(2, 0, 3)
    yield Case(
        "geometry",
        "gather_points/empty",
        lambda: gather_points(empty, torch.zeros(2, 4, dtype=torch.long)),
        ("points",),
    )
    yield Case("SyntheticDataModule", "batch_size='2'", lambda: SyntheticDataModule(batch_size="2"), ("batch_size",))  # type: ignore[arg-type]
    yield Case("SyntheticDataModule", "batch_size=2.5", lambda: SyntheticDataModule(batch_size=2.5), ("batch_size",))  # type: ignore[arg-type]
    yield Case("ModelNet40DataModule", "root=None", lambda: ModelNet40DataModule(None).setup("fit"), ("root",))  # type: ignore[arg-type]
    rng = np.random.default_rng(0)
    kinds = {"h5_nan_row": "nan", "h5_identical_row": "identical", "h5_two_points": "few"}
    for name, kind in kinds.items():
        points = rng.normal(size=(4, 2 if kind == "few" else 16, 3)).astype(np.float32)
        if kind == "nan":
            points[2, 1, 0] = np.nan
        elif kind == "identical":
            points[1] = 0.5
        sub = folder / name
        sub.mkdir()
        with h5py.File(sub / f"{name}.h5", "w") as f:
            f["data"], f["label"] = points, np.zeros((4, 1), np.uint8)
        (sub / "train_files.txt").write_text(f"{name}.h5\n")
        yield Case("modelnet40_h5", name, lambda r=sub: load_modelnet40_h5(r, "train")[0], (f"{name}.h5",))
    model = lcreg.DVDs().eval()
    batch = RegistrationBatch(
        src, ref, normals_src=torch.zeros(2, 10, 3), transform_ref_src=torch.eye(4).repeat(2, 1, 1)
    )
    yield Case("DVDs", "validation_step/normals_shape", lambda: model.validation_step(batch, 0), ("normals_src",))
    bad_pose = dataclasses.replace(batch, normals_src=None, transform_ref_src=torch.eye(4).repeat(3, 1, 1))
    yield Case("DVDs", "validation_step/pose_batch", lambda: model.validation_step(bad_pose, 0), ("transform_ref_src",))


def _assigned_refiner() -> torch.Tensor:
    """1.0 when ``model.refiner = ICP()`` after construction takes effect (or refuses), NaN when silently ignored."""
    model = lcreg.DVDs().eval()
    icp = lcreg.ICP()
    try:
        model.refiner = icp
    except (TypeError, ValueError, AttributeError) as err:
        return torch.tensor(1.0 if "refiner" in str(err) else float("nan"))
    return torch.tensor(1.0 if model.refiner is icp else float("nan"))


def _all_pretrained_load() -> torch.Tensor:
    """1.0 when every name of ``pretrained_names()`` loads, NaN when one is listed but cannot be loaded."""
    try:
        for name in lcreg.pretrained_names():
            lcreg.pretrained(name)
    except Exception:
        return torch.tensor(float("nan"))
    return torch.tensor(1.0)


class _ExitError(ValueError):
    """The command line ended with a short report (at most two lines on stderr): a typed error."""


def _cli(args: list[str]) -> Any:
    """``python -m lcreg ARGS`` as a user runs it (from the repository root), classified by what it printed.

    Raises:
        _ExitError: A non-zero exit with at most two lines on stderr (its first line).
        RuntimeError: A non-zero exit with a longer report (a traceback: cryptic whatever it names).
    """
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        [sys.executable, "-m", "lcreg", *args], cwd=repo, capture_output=True, text=True, timeout=600, check=False
    )
    if proc.returncode == 0:
        return None
    lines = [
        line for line in proc.stderr.splitlines() if line.strip() and "Warning" not in line and "warn(" not in line
    ]
    lines = [line for line in lines if line.startswith(("lcreg: error", "hint:", "usage:"))] or lines
    if len(lines) <= 2:
        raise _ExitError(lines[0] if lines else f"exit code {proc.returncode}")
    raise RuntimeError(f"exit code {proc.returncode} after a {len(lines)}-line report ending {lines[-1][:120]!r}")


TINY = [
    "--config=configs/dvds.yaml",
    "--model.init_args.encoder_channels=[16,32]",
    "--model.init_args.decoder_grid_size=8",
    "--model.init_args.decoder_hidden=[32]",
    "--model.init_args.normal_hidden=[16]",
    "--data.init_args.num_points=64",
    "--data.init_args.points_per_shape=128",
    "--data.init_args.num_train=4",
    "--data.init_args.num_val=2",
    "--data.init_args.num_test=2",
    "--data.init_args.batch_size=2",
    "--trainer.max_steps=4",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
]


def training_cases(folder: Path) -> Iterator[Case]:
    """Training on the embedded shapes: a diverging run, NaN weights; CLI values; assignment and listing."""
    root = [f"--trainer.default_root_dir={folder / 'runs'}", f"--trainer.logger.init_args.save_dir={folder / 'runs'}"]
    yield Case(
        "fit",
        "adam_lr_1e12",
        lambda: _cli(["fit", *TINY, *root, "--model.init_args.optimizer.init_args.lr=1e12"]),
        ("diverged", "non-finite"),
    )
    good = folder / "good.ckpt"
    _cli(["fit", *TINY, *root, "--trainer.max_steps=1"])
    last = next((folder / "runs").rglob("last.ckpt"))
    content = torch.load(last, map_location="cpu", weights_only=False)
    key = next(k for k, v in content["state_dict"].items() if v.is_floating_point() and v.numel() > 1)
    content["state_dict"][key].view(-1)[0] = float("nan")
    torch.save(content, good.with_name("nan_weight.ckpt"))
    nan_ckpt = str(good.with_name("nan_weight.ckpt"))
    yield Case(
        "fit",
        "ckpt_path_nan_weight",
        lambda: _cli(["fit", *TINY, *root, f"--ckpt_path={nan_ckpt}"]),
        ("nan_weight.ckpt",),
    )
    yield Case(
        "fit", "weights_nan_weight", lambda: _cli(["fit", *TINY, *root, f"--weights={nan_ckpt}"]), ("nan_weight.ckpt",)
    )
    notes = folder / "notes.txt"
    notes.write_text("my notes\n")
    values = {
        "batch_size_-4": (["--data.init_args.batch_size=-4"], ("batch_size",)),
        "max_iterations_-1": (["--model.init_args.max_iterations=-1"], ("max_iterations",)),
        "max_epochs_abc": (["--trainer.max_epochs=abc"], ("max_epochs",)),
        "ckpt_path_text_file": ([f"--ckpt_path={notes}"], ("notes.txt",)),
    }
    for label, (extra, names) in values.items():
        yield Case("cli", label, lambda e=extra: _cli(["fit", *TINY, *root, *e]), names)
    yield Case("RegistrationModule", "assign_refiner", _assigned_refiner, None)
    yield Case("pretrained", "every_listed_name_loads", _all_pretrained_load, None)


# --- driver --------------------------------------------------------------------------------------------------------
def all_cases(folder: Path, smoke: bool) -> Iterator[Case]:
    n = 64
    yield from model_cases(LEARNED[:1] if smoke else LEARNED, n)
    yield from model_cases(CLASSICAL[:1] if smoke else CLASSICAL, n)
    if not smoke:
        yield from module_cases(n)
    yield from file_cases(folder)
    yield from checkpoint_cases(folder)
    yield from geometry_cases()
    yield from internal_cases(folder)
    if not smoke:
        yield from training_cases(folder)


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
