"""How much of each LC + X host's encoder gradient comes from local consistency, at initialisation (issue 23, item 2).

    python benchmarks/lc_gradient_share.py --hosts idam deepgmr dcp prnet --batches 20 \
        --out docs/results/converge/lc_gradient_share.md
    python benchmarks/lc_gradient_share.py --hosts idam deepgmr --batches 20 --adam-steps 20 \
        --out docs/results/converge/lc_adam_share.md
    python benchmarks/lc_gradient_share.py --smoke      # seconds: embedded shapes, 2 batches of DCP-v2

For every host X of ``lcreg reproduce lc`` this builds LC + X (``<host>_lc`` of the registry, seeded with
``--seed``) with the data and sizes of the ``converge`` budget (``lcreg.experiments.reproduce.lc.BUDGETS``: the
DCP-family pairs of ModelNet40 under ``--root``, the budget's points and batch) and, on each of the first
``--batches`` training batches, without any optimiser step, splits the training loss of the shared step
(``training_forward`` + ``training_losses``) into the host's own terms and the LC term. It reports the value of each
and the L2 norm of its gradient on the encoder LC reads (``model.descriptor_encoder()``), as medians over the batches.

The *matched weight* is median(‖∇ own‖ / ‖∇ LC‖): the LC weight at which LC's encoder gradient equals the host's own
(the rule fixed in ``docs/results/converge/history.md`` before any test number, as a fairer second test than the
paper's literal weight 1).

A gradient norm is not what the runs' optimiser (Adam) moves by: Adam scales each coordinate by its own gradient
history, so a term with a small norm steers the coordinates where it is the larger part. ``--adam-steps T`` adds a
second table from the same initialisation and the same first ``T`` training batches, per host:

* *LC-led coordinates*: the share of encoder coordinates where ``|weight * d LC|`` exceeds ``|d own|`` (first batch);
* *LC's change of the trajectory*: ``||theta_LC+X - theta_X|| / ||theta_X - theta_0||`` over the encoder after ``T``
  steps of the host's configured optimiser, X and LC + X on the same batches (and the same random draws);
* the *control*: the same ratio for X trained on the same ``T`` batches in reverse order, the change that the order
  of the data alone makes (what a seed changes is at least that).
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from lcreg.experiments.benchmarking import add_smoke_argument, apply_smoke, build, key_values, machine_line, output_path
from lcreg.experiments.benchmarking.writers import write_text
from lcreg.experiments.reproduce.budgets import DEFAULT_ROOT, LR_KEY, SMOKE_PAIRS, DataChoice
from lcreg.experiments.reproduce.lc import BUDGETS, HOSTS

SMOKE = {"hosts": ["dcp"], "batches": 2, "adam_steps": 2}
LC_TERM = "lc"
"""Name of the LC term in ``training_losses`` (``configs/lc.yaml``)."""


@dataclass(frozen=True)
class Share:
    """One training batch: loss values and encoder-gradient norms of the host's own terms and of LC."""

    own: float
    lc: float
    own_grad: float
    lc_grad: float


def _grad_norm(value: torch.Tensor, params: list[nn.Parameter]) -> float:
    """L2 norm of d value / d params (parameters the value does not reach count 0)."""
    grads = torch.autograd.grad(value, params, retain_graph=True, allow_unused=True)
    return float(torch.sqrt(sum((g.pow(2).sum() for g in grads if g is not None), torch.tensor(0.0))))


def _values(host: str, root: str | None, seed: int) -> dict[str, object]:
    """The ``converge`` budget's data, points, batch and learning rate for ``host`` (``smoke`` without ``root``)."""
    budget = BUDGETS["smoke" if root is None else "converge"][host]
    lr = {} if budget.lr is None else {LR_KEY: budget.lr}  # the rate the runs train at (PRNet: 2.2e-4)
    return {**DataChoice(root).overrides(budget), **lr, "seed_everything": seed}


def _encoder_params(model: nn.Module) -> list[nn.Parameter]:
    """The trainable parameters of the encoder LC reads (``model.descriptor_encoder()``)."""
    encoder = model.descriptor_encoder()
    if not isinstance(encoder, nn.Module):
        raise TypeError(f"{type(model).__name__}: the encoder LC reads is not a module")
    return [p for p in encoder.parameters() if p.requires_grad]


def _lc_weight(model: nn.Module) -> float:
    return float(next(t.weight for t in model.injected_terms if t.name == LC_TERM))


def batch_shares(host: str, root: str | None, batches: int, seed: int, checkpoint: str | None = None) -> list[Share]:
    """The :class:`Share` of the first ``batches`` training batches of LC + ``host``, at initialisation or with the
    weights of ``checkpoint`` (a ``.ckpt`` of an LC + ``host`` run: how the shares stand after training)."""
    model, datamodule = build(f"{host}_lc", checkpoint, values=_values(host, root, seed), with_data=True)
    params, weight = _encoder_params(model), _lc_weight(model)
    datamodule.setup("fit")
    model.train()
    torch.manual_seed(seed)
    shares = []
    for i, batch in enumerate(datamodule.train_dataloader()):
        if i == batches:
            break
        losses = model.training_losses(model.training_forward(batch), batch)
        own = losses["loss"] - weight * losses[LC_TERM]
        lc = losses[LC_TERM]
        shares.append(Share(float(own.detach()), float(lc.detach()), _grad_norm(own, params), _grad_norm(lc, params)))
    return shares


def _host_and_lc(host: str, root: str | None, seed: int) -> tuple[nn.Module, nn.Module, list[object]]:
    """X and LC + X with the same initial weights, and the batches of the shared stream (training mode)."""
    values = _values(host, root, seed)
    plain, datamodule = build(host, None, values=values, with_data=True)
    with_lc = build(f"{host}_lc", None, values=values)
    datamodule.setup("fit")
    torch.manual_seed(seed)
    return plain.train(), with_lc.train(), list(datamodule.train_dataloader())


def _encoder_vector(model: nn.Module) -> torch.Tensor:
    """The encoder LC reads, its trainable parameters as one flat vector (a copy)."""
    return torch.cat([p.detach().flatten() for p in _encoder_params(model)]).clone()


def _train(model: nn.Module, batches: Sequence[object], seed: int) -> torch.Tensor:
    """``len(batches)`` steps of the model's own optimiser (its ``configure_optimizers``); the encoder after them."""
    config = model.configure_optimizers()
    optimizer = config["optimizer"] if isinstance(config, dict) else config
    for i, batch in enumerate(batches):
        torch.manual_seed(seed + i)  # the same random draws (samplers, dropout) in every copy
        optimizer.zero_grad()
        model.training_losses(model.training_forward(batch), batch)["loss"].backward()
        optimizer.step()
    return _encoder_vector(model)


def lc_led_share(model: nn.Module, batch: object, seed: int) -> float:
    """Share of encoder coordinates where ``|weight * d LC|`` exceeds ``|d own|`` on ``batch``."""
    params, weight = _encoder_params(model), _lc_weight(model)
    torch.manual_seed(seed)
    losses = model.training_losses(model.training_forward(batch), batch)
    own = losses["loss"] - weight * losses[LC_TERM]
    grads = {}
    for name, value in (("own", own), ("lc", weight * losses[LC_TERM])):
        parts = torch.autograd.grad(value, params, retain_graph=True, allow_unused=True)
        grads[name] = torch.cat(
            [(g if g is not None else torch.zeros_like(p)).flatten() for g, p in zip(parts, params)]
        )
    return float((grads["lc"].abs() > grads["own"].abs()).double().mean())


def adam_row(host: str, root: str | None, steps: int, seed: int) -> str:
    """One Markdown row of the Adam table (module docstring): LC-led share, trajectory change and its control."""
    plain, with_lc, batches = _host_and_lc(host, root, seed)
    start = _encoder_vector(plain)
    if not torch.equal(start, _encoder_vector(with_lc)):
        raise RuntimeError(f"{host}: X and LC + X do not start from the same encoder weights")
    batches = batches[:steps]
    led = lc_led_share(with_lc, batches[0], seed)
    reversed_plain = copy.deepcopy(plain)
    moved = _train(plain, batches, seed)
    change = float((_train(with_lc, batches, seed) - moved).norm() / (moved - start).norm())
    control = float((_train(reversed_plain, batches[::-1], seed) - moved).norm() / (moved - start).norm())
    return f"| LC + {HOSTS[host]} | {len(batches)} | {100 * led:.2g} % | {change:.3g} | {control:.3g} |"


def table_row(host: str, shares: list[Share], weights: str = "initialisation") -> str:
    """One Markdown row: medians over the batches and the matched weight; ``weights`` names where they come from."""
    med = {f: statistics.median(getattr(s, f) for s in shares) for f in ("own", "lc", "own_grad", "lc_grad")}
    matched = statistics.median(s.own_grad / s.lc_grad for s in shares if s.lc_grad > 0)
    share = 100 * med["lc"] / (med["own"] + med["lc"])
    return (
        f"| LC + {HOSTS[host]} | {weights} | {len(shares)} | {med['own']:.4g} | {med['lc']:.4g} | {share:.2g} % | "
        f"{med['own_grad']:.4g} | {med['lc_grad']:.4g} | {matched:.3g} |"
    )


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hosts", nargs="+", default=list(HOSTS), choices=list(HOSTS))
    parser.add_argument("--batches", type=int, default=20, help="training batches per host (medians over them)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initialisation and of the batches")
    parser.add_argument(
        "--adam-steps", type=int, default=0, help="also the Adam table after this many steps (0: the norms only)"
    )
    parser.add_argument(
        "--ckpt",
        nargs="+",
        default=[],
        metavar="HOST=PATH",
        help="also measure the first table with the weights of an LC + HOST run's checkpoint (one per host)",
    )
    parser.add_argument("--root", default=DEFAULT_ROOT)
    parser.add_argument("--out", default=None, help="Markdown table to write")
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    args.checkpoints = list(key_values(args.ckpt, "--ckpt").items())
    if unknown := [host for host, _ in args.checkpoints if host not in HOSTS]:
        parser.error(f"--ckpt: unknown host(s) {', '.join(unknown)}; one of {', '.join(HOSTS)}")
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    args.out = output_path(args.out, "lc_gradient_share.md", args.smoke)
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    data = DataChoice(args.root).describe() if args.root else f"embedded shapes ({SMOKE_PAIRS} pairs; smoke)"
    lines = [
        f"`python benchmarks/lc_gradient_share.py {args.command}`: {data}, DCP-family pairs, the `converge` budget's "
        f"points and batch, seed {args.seed} (initialisation and batches); {machine_line()}",
        "",
        "| host | weights | batches | own loss | LC | LC share of the loss | ‖∇ own‖ on the encoder | ‖∇ LC‖ on the "
        "encoder | matched LC weight |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for host in args.hosts:
        lines.append(table_row(host, batch_shares(host, args.root, args.batches, args.seed)))
        print(lines[-1], flush=True)
    for host, path in args.checkpoints:
        shares = batch_shares(host, args.root, args.batches, args.seed, checkpoint=path)
        lines.append(table_row(host, shares, weights=f"`{Path(path).name}`"))
        print(lines[-1], flush=True)
    if args.adam_steps > 0:
        lines += [
            "",
            f"After {args.adam_steps} steps of each host's optimiser (its config: Adam) from the same initialisation "
            "on the same batches: LC-led coordinates (first batch), ‖θ(LC + X) − θ(X)‖ / ‖θ(X) − θ₀‖ over the "
            "encoder, and the control ‖θ(X, batches reversed) − θ(X)‖ / ‖θ(X) − θ₀‖ (module docstring)",
            "",
            "| host | steps | encoder coordinates led by LC | LC's change of the trajectory | control: order of "
            "the batches |",
            "|---|---|---|---|---|",
        ]
        for host in args.hosts:
            lines.append(adam_row(host, args.root, args.adam_steps, args.seed))
            print(lines[-1], flush=True)
    if args.out:
        print(f"wrote {write_text(args.out, chr(10).join(lines) + chr(10))}")


if __name__ == "__main__":
    main()
