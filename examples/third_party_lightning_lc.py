"""Third-party example: give your own LightningModule lcreg's local-consistency loss through a mixin.

The network, data and supervised loss are ordinary user code (a LightningModule not derived from lcreg); the lcreg
lines are the import, ``LocalConsistencyMixin`` among the base classes (either order works), and
``attach_local_consistency`` in ``__init__``. The mixin wraps ``training_step`` when the class is created, so the
loss it returns gets ``lc_weight * LocalConsistency(self.encoder, src, ref)`` added and ``train/lc`` is logged.

Run (CPU, a few seconds):
    python examples/third_party_lightning_lc.py --steps 60
    python examples/third_party_lightning_lc.py --steps 60 --lc-weight 0   # without LC
"""

from __future__ import annotations

import argparse

import lightning as L
import torch

# Reuse the plain-PyTorch example's network, data and loss: only the training wrapper differs.
from third_party_lc import SoftProcrustesNet, make_pairs, pose_loss, rotation_error_deg
from torch.utils.data import DataLoader, IterableDataset

from lcreg import LocalConsistency
from lcreg.models.mixins import LocalConsistencyMixin


class RandomPairs(IterableDataset):
    """Endless batches ``(src, ref, R, t)`` of random asymmetric clouds."""

    def __init__(self, batch_size: int, num_points: int, seed: int) -> None:
        self.batch_size, self.num_points, self.seed = batch_size, num_points, seed

    def __iter__(self):  # type: ignore[no-untyped-def]
        gen = torch.Generator().manual_seed(self.seed)
        while True:
            yield make_pairs(self.batch_size, self.num_points, gen)


class PoseNet(L.LightningModule, LocalConsistencyMixin):  # the order that used to drop LC silently: now fine
    def __init__(self, lc_weight: float = 1.0, num_points: int = 128) -> None:
        super().__init__()
        self.net = SoftProcrustesNet()
        self.encoder = self.net.encoder  # what LC compares (default name; or override lc_encoder())
        lc = LocalConsistency(num_local_points=min(64, num_points // 4)) if lc_weight else None
        self.attach_local_consistency(lc, lc_weight)

    def training_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> torch.Tensor:
        src, ref, rot_gt, trans_gt = batch  # lc_clouds() takes the first two items as (src, ref)
        rot, trans = self.net(src, ref)
        loss = pose_loss(rot, trans, rot_gt, trans_gt)
        self.log("train/pose", loss)
        return loss  # the mixin adds lc_weight * LC to this

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=1e-3)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description="A user LightningModule with lcreg's LC through the mixin.")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--lc-weight", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-points", type=int, default=128)
    args = parser.parse_args(argv)
    L.seed_everything(args.seed, verbose=False)
    model = PoseNet(args.lc_weight, args.num_points)
    loader = DataLoader(RandomPairs(8, args.num_points, args.seed), batch_size=None)
    trainer = L.Trainer(
        max_steps=args.steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(model, loader)
    src, ref, rot_gt, _ = make_pairs(16, args.num_points, torch.Generator().manual_seed(args.seed + 10_000))
    with torch.no_grad():
        error = float(rotation_error_deg(model.net(src, ref)[0], rot_gt).mean())
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    metrics["rotation_error_deg"] = error
    lc = metrics.get("train/lc_epoch", metrics.get("train/lc"))
    print(f"held-out mean rotation error {error:.2f} deg; last LC {lc if lc is not None else 'off'}")
    return metrics


if __name__ == "__main__":
    main()
