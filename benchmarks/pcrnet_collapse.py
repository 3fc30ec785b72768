"""Is an iPCRNet checkpoint's output input-independent? Dead units and the spread of its first update (issue 23).

    python benchmarks/pcrnet_collapse.py --ckpt seed0=/work/runs/.../seed0/checkpoints/last.ckpt \
        seed1=/work/runs/.../seed1/checkpoints/last.ckpt
    python benchmarks/pcrnet_collapse.py --smoke      # seconds, embedded shapes, untrained weights

On the first ``--pairs`` deterministic ModelNet40 validation pairs (clean, ``--num-points``), for every iPCRNet
checkpoint (``identity_init`` on, as the queue trains it): the share of the encoder's pooled features and of the
regressor's last hidden units that are zero on every pair (dead ReLUs), and the standard deviation over the pairs of
the first update's 7 outputs (quaternion and translation) and of the source feature. A network whose output no longer
depends on its input predicts one rotation for every pair: on the DCP-family pairs (Euler U[0, 45 deg] per axis) the
best constant is about the average rotation, the 21.4-22 deg "average-rotation plateau" of the queue's runs. (At
initialisation the first-update spread is 0 by construction: the identity start zeroes the output layer.)
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import torch

from lcreg.baselines.pcrnet import PCRNet
from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    apply_smoke,
    key_values,
    machine_line,
    markdown_table,
    pair_batches,
)
from lcreg.experiments.benchmarking.writers import write_text

SMOKE = {"pairs": 4, "num_points": 64}


def collapse(model: PCRNet, points_src: torch.Tensor, points_ref: torch.Tensor) -> dict[str, float]:
    """Dead-unit shares and output spreads of ``model``'s first update on clouds ``(B, N, 3)`` (B >= 2)."""
    with torch.no_grad():
        src0 = points_src - points_src.mean(1, keepdim=True)
        ref0 = points_ref - points_ref.mean(1, keepdim=True)
        feature_src, feature_ref = model.encoder(src0), model.encoder(ref0)  # (B, K)
        hidden = model.regressor(torch.cat([feature_ref, feature_src], dim=-1))  # (B, H)
        pose = model.pose(hidden)  # (B, 7)
    return {
        "dead encoder features": float((feature_src.abs().amax(0) == 0).float().mean()),
        "dead last hidden units": float((hidden.abs().amax(0) == 0).float().mean()),
        "first-update std": float(pose.std(0).mean()),
        "source-feature std": float(feature_src.std(0).mean()),
    }


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", nargs="*", default=[], metavar="LABEL=PATH", help="Lightning checkpoints of iPCRNet")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--pairs", type=int, default=64)
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument("--out", default=None, help="Markdown file to write the table to")
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    args.ckpt = key_values(args.ckpt, "--ckpt")
    if not args.ckpt and not args.smoke:
        parser.error("give --ckpt LABEL=PATH ...")
    if args.pairs < 2:
        parser.error("--pairs must be >= 2 (a spread over pairs)")
    return args


def load(path: str | None) -> PCRNet:
    """iPCRNet with the identity start, with a Lightning checkpoint's weights (``None``: untrained, seed 0)."""
    torch.manual_seed(0)
    model = PCRNet(identity_init=True)
    if path is not None:
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=False)["state_dict"])
    return model.eval()


def main(argv: Sequence[str] | None = None) -> str:
    args = parse(argv)
    options = {"protocol": "unseen_objects", "noise_sigma": 0.0, "seed": 1234}
    if args.root is not None:
        options["val_pairs_per_object"] = 4
    batches, source = pair_batches(args.root, "val", args.pairs, args.num_points, args.pairs, **options)
    batch = batches[0]
    models = {label: load(path) for label, path in args.ckpt.items()} or {"untrained": load(None)}
    rows = {label: collapse(model, batch.points_src, batch.points_ref) for label, model in models.items()}
    names = list(next(iter(rows.values())))
    lines = [
        f"{source}, {len(batch)} val pairs, {args.num_points} points, {machine_line()}",
        "",
        markdown_table(
            ["checkpoint", *names], ([label, *(f"{v:.4g}" for v in row.values())] for label, row in rows.items())
        ),
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_text(args.out, text)
    return text


if __name__ == "__main__":
    main()
