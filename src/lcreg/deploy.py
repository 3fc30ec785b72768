"""A learned IC-LK registrar as a plain graph for deployment: TorchScript and ONNX files that run without lcreg.

:class:`DeployedLK` re-expresses an IC-LK model (DVDs, PointNetLK, FMR-Net: a
:class:`~lcreg.models.lucas_kanade.LucasKanadeModule`) with export-friendly operations only:

* the PointNet encoder with its eval-mode BatchNorm folded into the linear layers (plain ``matmul``, ``relu``,
  ``amax``);
* the Jacobian as the model computes it (``"analytic"``: the exact derivative at each channel's arg-max point;
  ``"finite_difference"``: six moved copies of the reference), at the centred reference;
* the damped 6x6 normal equations solved by an unrolled Cholesky factorisation (no general ``pinv``/``solve``
  operator), in the model's dtype;
* a fixed number of iterations (the eager solver stops an item early once its update is below ``tolerance``: the one
  documented difference; after convergence further updates are below the tolerance too);
* the model's starts (``eval_start_angles_deg``) stacked along the batch, each item keeping the start with the lowest
  final descriptor residual (or the identity, within ``eval_start_margin``), as the eager solve does.

Input checks stay outside the graph, in :func:`register_exported` and the eager model. The graph maps
``points_src (B, N, 3)``, ``points_ref (B, M, 3)`` (float32) to ``transform_ref_src (B, 4, 4)``; ``unit_scale`` is not
applied (give clouds at the training scale, or scale them as :meth:`RegistrationModule.register` does).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn

from lcreg.geometry import se3
from lcreg.nn.lk import axis_rotation_starts, select_start

__all__ = ["DeployedLK", "ExportFormat", "build_parser", "export_registrar", "main"]

ExportFormat = Literal["torchscript", "onnx"]


class DeployedLK(nn.Module):
    """An IC-LK model's inference with a fixed number of iterations, in export-friendly operations.

    Args:
        model: A :class:`~lcreg.models.lucas_kanade.LucasKanadeModule` (its encoder's weights and eval-mode
            normalisation, its solver's Jacobian mode, damping and finite-difference step are copied).
        iterations: IC-LK iterations (default: the model's ``eval_iterations``, else its solver's
            ``max_iterations``).

    The model's ``eval_start_angles_deg`` and ``eval_start_margin`` are kept (:func:`~lcreg.nn.lk.axis_rotation_starts`,
    :func:`~lcreg.nn.lk.select_start`); a model with a ``voxel_grid`` is exported without it (the whole-cloud solve).

    Raises:
        TypeError: ``model`` is not an IC-LK model.
        ValueError: ``iterations < 1``, or a Jacobian mode without a deployable form (``"autodiff"``).
    """

    def __init__(self, model: nn.Module, iterations: int | None = None) -> None:
        super().__init__()
        from lcreg.models.lucas_kanade import LucasKanadeModule

        if not isinstance(model, LucasKanadeModule):
            raise TypeError(f"DeployedLK needs an IC-LK model (DVDs, PointNetLK, FMR-Net), got {type(model).__name__}")
        solver = model.solver
        steps = iterations or model.eval_iterations or solver.max_iterations
        if steps < 1:
            raise ValueError(f"`iterations` must be >= 1, got {steps}")
        if solver.jacobian not in ("analytic", "finite_difference"):
            raise ValueError(f"Jacobian mode {solver.jacobian!r} has no deployable form; use 'analytic'")
        self.iterations = int(steps)
        self.jacobian = str(solver.jacobian)
        self.damping = float(solver.damping)
        self.fd_step = float(solver.fd_step)
        self.center = bool(solver.center)
        encoder = model.encoder
        folded = [encoder._folded(i) for i in range(len(encoder.linears))]
        for i, (weight, bias) in enumerate(folded):
            self.register_buffer(f"weight{i}", weight.detach().clone())
            self.register_buffer(f"bias{i}", bias.detach().clone())
        self.layers = len(folded)
        starts = axis_rotation_starts(model.eval_start_angles_deg, folded[0][0].dtype)
        self.starts: torch.Tensor
        self.register_buffer("starts", starts)  # (S, 4, 4), the identity first
        self.num_starts = int(starts.shape[0])
        self.start_margin = float(model.eval_start_margin)

    def _layer(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return getattr(self, f"weight{i}"), getattr(self, f"bias{i}")

    def _hidden(self, points: torch.Tensor) -> torch.Tensor:
        h = points
        for i in range(self.layers - 1):
            weight, bias = self._layer(i)
            h = torch.relu(h @ weight.t() + bias)
        return h

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """The descriptor ``psi (B, K)`` of ``points (B, N, 3)``."""
        weight, bias = self._layer(self.layers - 1)
        return torch.relu((self._hidden(points) @ weight.t()).amax(dim=1) + bias)

    def _analytic(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``psi (B, K)`` and ``d psi / d xi (B, K, 6)`` at ``points`` (derivatives through the hidden layers)."""
        b, n, _ = points.shape
        h = points
        dh = torch.eye(3, dtype=points.dtype, device=points.device).expand(b, n, 3, 3)
        for i in range(self.layers - 1):
            weight, bias = self._layer(i)
            z = h @ weight.t() + bias
            mask = (z > 0).to(z.dtype)
            dh = (dh @ weight.t()) * mask[:, :, None, :]
            h = z * mask
        weight, bias = self._layer(self.layers - 1)
        pooled, arg = (h @ weight.t()).max(dim=1)  # (B, K)
        psi = torch.relu(pooled + bias)
        k, c = psi.shape[1], dh.shape[-1]
        dh_arg = torch.gather(dh, 1, arg[:, :, None, None].expand(b, k, 3, c))  # (B, K, 3, C)
        grad = (dh_arg * weight[None, :, None, :]).sum(-1) * (psi > 0).to(psi.dtype)[..., None]  # (B, K, 3)
        p = torch.gather(points, 1, arg[..., None].expand(b, k, 3))  # (B, K, 3)
        return psi, torch.cat([_cross(p, grad), grad], dim=-1)

    def _finite_difference(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = points.shape[0]
        steps = self.fd_step * torch.eye(6, dtype=points.dtype, device=points.device)
        moves = se3.exp(steps)  # (6, 4, 4)
        moved = points[None] @ moves[:, None, :3, :3].transpose(-1, -2) + moves[:, None, None, :3, 3]  # (6, B, N, 3)
        psi = self.encode(points)
        pert = self.encode(moved.reshape(6 * b, -1, 3)).reshape(6, b, -1)
        return psi, ((pert - psi[None]) / self.fd_step).permute(1, 2, 0)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> torch.Tensor:
        """``transform_ref_src (B, 4, 4)`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        if self.center:
            mean_src, mean_ref = points_src.mean(1), points_ref.mean(1)
        else:
            mean_src, mean_ref = points_src[:, 0] * 0, points_ref[:, 0] * 0
        src0, ref0 = points_src - mean_src[:, None], points_ref - mean_ref[:, None]
        feat_ref, jac = self._analytic(ref0) if self.jacobian == "analytic" else self._finite_difference(ref0)
        jt = jac.transpose(1, 2)  # (B, 6, K)
        jtj = jt @ jac
        lam = self.damping * jtj.diagonal(dim1=1, dim2=2).mean(-1) + 1e-30
        eye = torch.eye(6, dtype=jtj.dtype, device=jtj.device)
        pinv = _cholesky_solve(jtj + lam[:, None, None] * eye, jt)  # (B, 6, K)
        b, n = points_src.shape[0], self.num_starts
        if n > 1:  # the starts stacked along the batch, start-major (as the eager solver)
            src0, feat_ref, pinv = src0.repeat(n, 1, 1), feat_ref.repeat(n, 1), pinv.repeat(n, 1, 1)
        g = self.starts.to(src0.dtype)[:, None].expand(n, b, 4, 4).reshape(n * b, 4, 4)
        for _ in range(self.iterations):
            resid = self.encode(_moved(g, src0)) - feat_ref
            dxi = -(pinv @ resid[..., None]).squeeze(-1)
            g = se3.exp(dxi) @ g
        if n > 1:
            final = (self.encode(_moved(g, src0)) - feat_ref).norm(dim=-1).reshape(n, b)
            best = select_start(final, self.start_margin)  # (B,)
            g = g.reshape(n, b, 16).gather(0, best[None, :, None].expand(1, b, 16))[0].reshape(b, 4, 4)
        rot, trans = g[:, :3, :3], g[:, :3, 3]
        trans = trans + mean_ref - (rot @ mean_src[..., None]).squeeze(-1)
        return torch.cat([torch.cat([rot, trans[..., None]], dim=-1), g[:, 3:4]], dim=1)


def _moved(g: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``g (B, 4, 4)`` applied to ``points (B, N, 3)``."""
    return points @ g[:, :3, :3].transpose(1, 2) + g[:, None, :3, 3]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a x b`` over the last axis (written out: exporters lack a cross-product operator)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], dim=-1)


def _cholesky_solve(a: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """``a^{-1} rhs`` for symmetric positive definite ``a (B, n, n)`` (small, fixed ``n``) and ``rhs (B, n, K)``.

    An unrolled Cholesky factorisation and two triangular substitutions: elementwise operations only.
    """
    n = a.shape[-1]
    low: list[list[torch.Tensor]] = [[a[:, 0, 0] * 0 for _ in range(n)] for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = a[:, i, j]
            for k in range(j):
                acc = acc - low[i][k] * low[j][k]
            low[i][j] = torch.sqrt(acc.clamp_min(1e-30)) if i == j else acc / low[j][j]
    ys: list[torch.Tensor] = []
    for i in range(n):  # L y = rhs
        acc = rhs[:, i]
        for k in range(i):
            acc = acc - low[i][k][:, None] * ys[k]
        ys.append(acc / low[i][i][:, None])
    xs: list[torch.Tensor] = [ys[0]] * n
    for i in reversed(range(n)):  # L^T x = y
        acc = ys[i]
        for k in range(i + 1, n):
            acc = acc - low[k][i][:, None] * xs[k]
        xs[i] = acc / low[i][i][:, None]
    return torch.stack(xs, dim=1)


def export_registrar(
    model: nn.Module, out: str | Path, fmt: ExportFormat, points: int = 1024, iterations: int | None = None
) -> Path:
    """Write ``model``'s inference as a TorchScript (``.pt``) or ONNX (``.onnx``) file; returns the path.

    Args:
        model: An IC-LK model (DVDs, PointNetLK, FMR-Net), e.g. ``lcreg.pretrained("dvds-modelnet40")``.
        out: The file to write.
        fmt: ``"torchscript"`` (``torch.jit.load`` runs it) or ``"onnx"`` (ONNX Runtime runs it; needs the
            ``export`` extra: onnx, onnxscript).
        points: Points per cloud of the example input (the batch size and point counts stay dynamic).
        iterations: Fixed IC-LK iterations (see :class:`DeployedLK`).

    Raises:
        TypeError, ValueError: See :class:`DeployedLK`; an unknown ``fmt``.
    """
    graph = DeployedLK(model, iterations).eval()
    example = (torch.randn(2, points, 3), torch.randn(2, points, 3))  # batch 2: a batch of 1 would be specialised
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "torchscript":
        with torch.no_grad():
            traced: Any = torch.jit.trace(graph, example)
        traced.save(str(path))
    elif fmt == "onnx":
        from torch.export import Dim

        batch = Dim("batch")
        torch.onnx.export(
            graph,
            example,
            str(path),
            input_names=["points_src", "points_ref"],
            output_names=["transform_ref_src"],
            dynamic_shapes={"points_src": {0: batch, 1: Dim("n", min=8)}, "points_ref": {0: batch, 1: Dim("m", min=8)}},
            dynamo=True,  # torch.export + onnxscript (the `export` extra)
        )
    else:
        raise ValueError(f"unknown export format {fmt!r}; expected 'torchscript' or 'onnx'")
    return path


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``lcreg export``."""
    parser = argparse.ArgumentParser(
        prog="lcreg export",
        description="Write a learned IC-LK registrar (DVDs, PointNetLK, FMR-Net) as a file that registers a pair "
        "without lcreg: TorchScript (torch.jit.load) or ONNX (ONNX Runtime; pip install 'lcreg[export]').",
        epilog="example: lcreg export dvds-modelnet40 --format onnx --out dvds.onnx\n"
        "inputs points_src (B, N, 3), points_ref (B, M, 3) float32 at the training scale; output transform_ref_src "
        "(B, 4, 4); a fixed number of iterations (the eager solver may stop earlier)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("weights", help="a shipped name (lcreg.pretrained_names()), an exported .pt or a .ckpt")
    parser.add_argument("--format", choices=("onnx", "torchscript"), required=True, dest="fmt")
    parser.add_argument("--out", required=True, help="the file to write (.onnx, .pt)")
    parser.add_argument("--points", type=int, default=1024, help="points per cloud of the example (default: 1024)")
    parser.add_argument("--iterations", type=int, help="fixed IC-LK iterations (default: the model's)")
    return parser


def main(argv: Sequence[str] | None = None) -> Path:
    """``lcreg export``: one line on stderr and exit code 1 (2 for arguments) for a user error."""
    from lcreg.checkpoints import CheckpointError
    from lcreg.checks import MissingDependencyError
    from lcreg.weights import pretrained

    args = build_parser().parse_args(argv)
    try:
        if args.fmt == "onnx":
            _require_onnx()
        path = export_registrar(pretrained(args.weights), args.out, args.fmt, args.points, args.iterations)
    except (CheckpointError, MissingDependencyError, TypeError, ValueError, OSError) as err:
        sys.stderr.write(f"lcreg export: error: {err}\n")
        raise SystemExit(1) from err
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB, {args.fmt})")
    return path


def _require_onnx() -> None:
    """Raise :class:`~lcreg.checks.MissingDependencyError` unless onnx and onnxscript import."""
    from lcreg.checks import MissingDependencyError

    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as err:
        raise MissingDependencyError(
            f"ONNX export needs onnx and onnxscript ({err.name} is missing): pip install 'lcreg[export]'"
        ) from err
