"""Third-party example: add lcreg's ``LocalConsistency`` loss to your own registration network.

Everything here is ordinary user code (plain PyTorch, no Lightning, nothing subclassed from lcreg): a tiny
PointNet-style per-point encoder, a soft-correspondence + SVD-Procrustes head, random asymmetric point
clouds generated in the script, and a hand-written training loop with a supervised pose loss. The only lcreg
line is ``from lcreg import LocalConsistency``; the loss is ``pose_loss + lc_weight * lc(encoder, src, ref)``.
``lc`` calls the encoder on 64-point (or ``num_points // 4``) subsets, so any ``(B, n, 3) -> (B, n, K)`` or
``(B, K)`` network works.

Run (CPU, a few seconds):
    python examples/third_party_lc.py --steps 200
    python examples/third_party_lc.py --steps 200 --lc-weight 0   # without LC
"""

from __future__ import annotations

import argparse
import math

import torch
from torch import nn

from lcreg import LocalConsistency  # light import: torch only, no Lightning


def random_clouds(batch: int, num_points: int, gen: torch.Generator) -> torch.Tensor:
    """Asymmetric clouds ``(B, N, 3)``: 4 anisotropic Gaussian blobs of unequal size, scaled into the unit ball."""
    centers = torch.randn(batch, 4, 3, generator=gen) * 0.5
    scales = 0.05 + 0.25 * torch.rand(batch, 4, 3, generator=gen)
    probs = torch.tensor([0.4, 0.3, 0.2, 0.1]).expand(batch, 4)
    blob = torch.multinomial(probs, num_points, replacement=True, generator=gen)  # (B, N)
    pick = blob[..., None].expand(-1, -1, 3)
    pts = centers.gather(1, pick) + scales.gather(1, pick) * torch.randn(batch, num_points, 3, generator=gen)
    pts = pts - pts.mean(1, keepdim=True)
    return pts / pts.norm(dim=-1).amax(1)[:, None, None]


def random_rotations(batch: int, max_deg: float, gen: torch.Generator) -> torch.Tensor:
    """Rotations ``(B, 3, 3)`` about random axes by angles uniform in ``[0, max_deg]`` (Rodrigues)."""
    axis = nn.functional.normalize(torch.randn(batch, 3, generator=gen), dim=-1)
    angle = torch.rand(batch, 1, 1, generator=gen) * math.radians(max_deg)
    k = torch.zeros(batch, 3, 3)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(1, 2)
    return torch.eye(3) + angle.sin() * k + (1 - angle.cos()) * k @ k


def make_pairs(batch: int, num_points: int, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    """``src, ref (B, N, 3)``, ``ref = R src + t`` shuffled, and the ground truth ``R (B, 3, 3)``, ``t (B, 3)``."""
    src = random_clouds(batch, num_points, gen)
    rot, trans = random_rotations(batch, 45.0, gen), torch.rand(batch, 3, generator=gen) - 0.5
    perm = torch.argsort(torch.rand(batch, num_points, generator=gen), dim=1)[..., None].expand(-1, -1, 3)
    ref = (src @ rot.transpose(1, 2) + trans[:, None]).gather(1, perm)
    return src, ref, rot, trans


class PointEncoder(nn.Module):
    """Per-point features ``(B, n, 3) -> (B, n, K)``: shared MLP on centred points + max-pooled global context."""

    def __init__(self, dim: int = 64) -> None:
        super().__init__()
        self.local = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU())
        self.context = nn.Sequential(nn.Linear(64, 128), nn.ReLU())
        self.out = nn.Linear(64 + 128, dim)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        h = self.local(points - points.mean(1, keepdim=True))
        g = self.context(h).amax(1, keepdim=True).expand(-1, h.shape[1], -1)
        return self.out(torch.cat([h, g], dim=-1))


class SoftProcrustesNet(nn.Module):
    """Soft correspondences from feature similarity, then a closed-form (SVD) rigid fit ``ref ~ R src + t``."""

    def __init__(self, dim: int = 64) -> None:
        super().__init__()
        self.encoder = PointEncoder(dim)

    def forward(self, src: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f_src, f_ref = self.encoder(src), self.encoder(ref)
        attn = torch.softmax(f_src @ f_ref.transpose(1, 2) / math.sqrt(f_src.shape[-1]), dim=-1)  # (B, N, M)
        virtual = attn @ ref  # each source point's soft match in ref
        mu_s, mu_v = src.mean(1, keepdim=True), virtual.mean(1, keepdim=True)
        u, _, vt = torch.linalg.svd((src - mu_s).transpose(1, 2) @ (virtual - mu_v))
        d = torch.ones_like(src[:, 0])
        d[:, 2] = torch.det(vt.transpose(1, 2) @ u.transpose(1, 2)).sign()  # no reflections
        rot = vt.transpose(1, 2) @ torch.diag_embed(d) @ u.transpose(1, 2)
        return rot, (mu_v - mu_s @ rot.transpose(1, 2)).squeeze(1)


def pose_loss(rot: torch.Tensor, trans: torch.Tensor, rot_gt: torch.Tensor, trans_gt: torch.Tensor) -> torch.Tensor:
    """DCP-style ``||R^T R_gt - I||_F^2 + ||t - t_gt||^2``, batch mean."""
    eye = torch.eye(3, device=rot.device)
    return ((rot.transpose(1, 2) @ rot_gt - eye) ** 2).sum((1, 2)).mean() + ((trans - trans_gt) ** 2).sum(1).mean()


def rotation_error_deg(rot: torch.Tensor, rot_gt: torch.Tensor) -> torch.Tensor:
    """Geodesic angle ``(B,)`` in degrees between ``rot`` and ``rot_gt``."""
    cos = ((rot.transpose(1, 2) @ rot_gt).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def train(
    steps: int = 200,
    lc_weight: float = 1.0,
    seed: int = 0,
    num_points: int = 128,
    batch_size: int = 8,
    device: str = "cpu",
    log_every: int = 0,
) -> dict[str, float | None]:
    """Train from scratch; return held-out metrics (``final_lc`` is ``None`` when ``lc_weight == 0``)."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    val_src, val_ref, val_rot, val_trans = (
        x.to(device) for x in make_pairs(16, num_points, torch.Generator().manual_seed(seed + 10_000))
    )  # held-out batch
    model = SoftProcrustesNet().to(device)
    lc = LocalConsistency(feature_dim=64, num_local_points=min(64, num_points // 4)).to(device) if lc_weight else None
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)

    def evaluate() -> tuple[float, float]:
        with torch.no_grad():
            rot, trans = model(val_src, val_ref)
            return pose_loss(rot, trans, val_rot, val_trans).item(), rotation_error_deg(rot, val_rot).mean().item()

    initial_loss, initial_err = evaluate()
    running = torch.zeros(2)  # summed (pose loss, LC) since the last print
    for step in range(1, steps + 1):
        src, ref, rot_gt, trans_gt = (x.to(device) for x in make_pairs(batch_size, num_points, gen))
        rot, trans = model(src, ref)
        loss = pose_loss(rot, trans, rot_gt, trans_gt)
        running[0] += loss.item()
        if lc is not None:  # the one extra line a user adds to their loss
            lc_value = lc(model.encoder, src, ref)
            loss = loss + lc_weight * lc_value
            running[1] += lc_value.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if log_every and step % log_every == 0:
            pose, lc_mean = (running / log_every).tolist()
            print(f"step {step:4d}  pose loss {pose:.4f}  LC {lc_mean:.2e}  total {pose + lc_weight * lc_mean:.4f}")
            running.zero_()
    final_loss, final_err = evaluate()
    final_lc = None
    if lc is not None:
        with torch.no_grad():
            final_lc = lc(model.encoder, val_src, val_ref).item()
    return {
        "initial_loss": initial_loss,
        "final_loss": final_loss,
        "final_lc": final_lc,
        "initial_rotation_error_deg": initial_err,
        "rotation_error_deg": final_err,
    }


def main(argv: list[str] | None = None) -> dict[str, float | None]:
    parser = argparse.ArgumentParser(description="Train a tiny registration net with LocalConsistency.")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--lc-weight", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-points", type=int, default=128)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--log-every", type=int, default=20)
    args = parser.parse_args(argv)
    metrics = train(
        args.steps, args.lc_weight, args.seed, args.num_points, args.batch_size, args.device, args.log_every
    )
    lc_text = "not computed" if metrics["final_lc"] is None else f"{metrics['final_lc']:.2e}"
    print(f"held-out pose loss {metrics['initial_loss']:.4f} -> {metrics['final_loss']:.4f}, final LC {lc_text}")
    print(f"untrained rotation error: {metrics['initial_rotation_error_deg']:.2f} deg")
    print(f"mean rotation error on held-out batch: {metrics['rotation_error_deg']:.2f} deg")
    return metrics


if __name__ == "__main__":
    main()
