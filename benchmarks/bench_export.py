"""Exported registrars against the eager model: parity on real pairs, and speed (eager, TorchScript, ONNX Runtime).

    python benchmarks/bench_export.py --root ../shared/data/modelnet40_mini --out docs/results/export.md
    python benchmarks/bench_export.py --smoke      # seconds: a tiny DVDs, synthetic pairs

Weights: ``--weights`` (default the shipped ``dvds-modelnet40``), exported by :func:`lcreg.deploy.export_registrar`
with ``--iterations`` fixed (default: the model's). Parity: every ModelNet40 test pair (unseen objects, 1,024 points;
164 pairs in ``modelnet40_mini``), the largest absolute difference of the ``(4, 4)`` transforms and of the rotation
error against the ground truth, for the eager model run for exactly the same iterations (``tolerance`` 0) and for
the eager model as it runs (stopping an item early). Speed: median ms/pair and pairs/s over ``--repeats`` timed
rounds (alternating, after a warm-up) at batch 1 and 16, 1,024 points, one CPU thread (``torch`` and ONNX Runtime).
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lcreg.deploy import DeployedLK, export_registrar
from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    time_calls,
    write_text,
)
from lcreg.metrics.functional import rotation_error_deg


def _model(weights: str, smoke: bool) -> Any:
    if smoke:
        from lcreg.models.dvds import DVDs

        torch.manual_seed(0)
        return DVDs(encoder_channels=[16, 32], lambda_recon=0.0, lambda_normal=0.0).eval()
    import lcreg

    return lcreg.pretrained(weights)


def _weights_line(weights: str) -> str:
    """``<name> (sha256 <first 8 hex digits>…)``: which file the figures belong to (shipped files get replaced)."""
    import hashlib

    from lcreg.weights import resolve

    return f"{weights} (sha256 {hashlib.sha256(resolve(weights).read_bytes()).hexdigest()[:8]}…)"


def _runners(model: Any, folder: Path, points: int, iterations: int | None) -> dict[str, Callable[..., np.ndarray]]:
    """``name -> f(src, ref) -> (B, 4, 4)`` for the eager model and both exported files."""
    import onnxruntime as ort

    ts_path = export_registrar(model, folder / "model.ts", "torchscript", points, iterations)
    onnx_path = export_registrar(model, folder / "model.onnx", "onnx", points, iterations)
    scripted = torch.jit.load(str(ts_path))
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
    steps = iterations or model.eval_iterations or model.solver.max_iterations

    def eager(src: torch.Tensor, ref: torch.Tensor) -> np.ndarray:
        with torch.no_grad():
            return model.solver(model.encoder, src, ref, max_iterations=steps).transform_ref_src.numpy()

    def torchscript(src: torch.Tensor, ref: torch.Tensor) -> np.ndarray:
        with torch.no_grad():
            return scripted(src, ref).numpy()

    def onnxruntime(src: torch.Tensor, ref: torch.Tensor) -> np.ndarray:
        return session.run(None, {"points_src": src.numpy(), "points_ref": ref.numpy()})[0]

    return {"eager": eager, "torchscript": torchscript, "onnxruntime": onnxruntime}


PARITY_TOLERANCE = 1e-4
"""Issue 26's goal: every entry of the exported file's transform within this of eager's."""
PARITY_COLUMNS = [
    "file", "against", "pairs", "max transform diff", "p99", f"pairs within {PARITY_TOLERANCE:g}", "max RRE diff °",
    "mean RRE °",
]  # fmt: skip


def parity(model: Any, runners: dict[str, Callable[..., np.ndarray]], batches: list[Any]) -> list[list[Any]]:
    """Rows: exported file vs eager (same iterations, and as it runs), largest transform and RRE differences.

    A third reference row runs the same graph in float64 (:class:`lcreg.deploy.DeployedLK`, in torch): how far the
    float32 eager result is from a more exact evaluation of the same algorithm, the floor no runtime can beat.
    """
    tolerance = model.solver.tolerance
    exact = DeployedLK(model).double().eval()
    outs: dict[str, list[np.ndarray]] = {name: [] for name in (*runners, "eager (early stop)", "float64 graph")}
    gts = []
    for batch in batches:
        model.solver.tolerance = 0.0
        for name, run in runners.items():
            outs[name].append(run(batch.points_src, batch.points_ref))
        model.solver.tolerance = tolerance
        outs["eager (early stop)"].append(runners["eager"](batch.points_src, batch.points_ref))
        with torch.no_grad():
            outs["float64 graph"].append(exact(batch.points_src.double(), batch.points_ref.double()).numpy())
        gts.append(batch.transform_ref_src.numpy())
    gt = torch.from_numpy(np.concatenate(gts)).double()
    rre = {k: rotation_error_deg(torch.from_numpy(np.concatenate(v)).double(), gt) for k, v in outs.items()}
    pairs = [(n, r) for n in ("torchscript", "onnxruntime") for r in ("eager", "eager (early stop)")]
    rows = []
    for name, ref in [*pairs, ("float64 graph", "eager")]:
        diff = np.abs(np.concatenate(outs[name]) - np.concatenate(outs[ref])).reshape(len(gt), -1).max(axis=1)
        rre_diff = float((rre[name] - rre[ref]).abs().max())
        within = int((diff <= PARITY_TOLERANCE).sum())
        rows.append(
            [name, ref, len(gt), f"{diff.max():.2e}", f"{np.quantile(diff, 0.99):.2e}", within, f"{rre_diff:.2e}",
             f"{float(rre[name].mean()):.3f}"]
        )  # fmt: skip
    return rows


def speed(runners: dict[str, Callable[..., np.ndarray]], batch: Any, sizes: Sequence[int], repeats: int) -> list[Any]:
    """Rows: ms/pair and pairs/s of each runner at each batch size (the first pairs of ``batch``, tiled)."""
    rows = []
    for size in sizes:
        reps = -(-size // len(batch))
        src = batch.points_src.repeat(reps, 1, 1)[:size].contiguous()
        ref = batch.points_ref.repeat(reps, 1, 1)[:size].contiguous()
        calls = {k: (lambda f=f, a=src, b=ref: f(a, b)) for k, f in runners.items()}
        timings = time_calls(calls, repeats)
        base = timings["eager"].median_s
        for name, timing in timings.items():
            ms = 1000 * timing.median_s / size
            rows.append([name, size, f"{ms:.1f}", f"{size / timing.median_s:.1f}", f"{base / timing.median_s:.2f}"])
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini", help="ModelNet40 folder")
    parser.add_argument("--weights", default="dvds-modelnet40", help="a shipped name, a .pt or a .ckpt")
    parser.add_argument("--iterations", type=int, help="fixed IC-LK iterations of the files (default: the model's)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", help="Markdown file to write")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    points = 64 if args.smoke else 1024
    batches, source = pair_batches(None if args.smoke else args.root, "test", 4 if args.smoke else None, points)
    model = _model(args.weights, args.smoke)
    with tempfile.TemporaryDirectory() as folder:
        runners = _runners(model, Path(folder), points, args.iterations)
        table = parity(model, runners, batches)
        speed_rows = speed(runners, batches[0], (1, 4) if args.smoke else (1, 16), 2 if args.smoke else args.repeats)
    text = (
        f"Machine: {machine_line()}; one CPU thread. Pairs: {source}, {points} points. Weights: "
        f"{'tiny untrained DVDs' if args.smoke else _weights_line(args.weights)}.\n\n"
        + markdown_table(PARITY_COLUMNS, table)
        + "\n\n"
        + markdown_table(["runner", "batch", "ms/pair", "pairs/s", "x eager"], speed_rows)
        + "\n"
    )
    print(text)
    if args.out or not args.smoke:
        write_text(output_path(args.out, "export.md", args.smoke), text)


if __name__ == "__main__":
    main()
