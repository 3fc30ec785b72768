"""DVDs training step: the reference implementation against the fast one, side by side in one process.

    python benchmarks/bench_dvds_step.py [--root ../shared/data/modelnet40_mini] [--batch 16] [--points 1024]
                                         [--repeats 5] [--threads N] [--breakdown] [--device cpu|cuda] [--recipe]
    python benchmarks/bench_dvds_step.py --smoke     # seconds, tiny embedded synthetic pairs (checks the script runs)

The model is ``configs/dvds_modelnet40.yaml`` (DVDs with the local-consistency term, the paper objective), or with
``--recipe`` ``configs/dvds_selfsup_modelnet40.yaml`` (plus the self-motion term, which trains through an eval-mode
IC-LK solve: the shipped weights' recipe), with seeded random weights (the work of a step does not depend on them: IC-LK
always runs its 10 iterations). The batch is the first ``--batch`` validation pairs of ModelNet40 at ``--points`` points
(``--root``, unseen objects; carved out of the training objects) when the data is present, otherwise the embedded
synthetic shapes. One step is what the training loop runs: gradients zeroed, ``model.training_forward(batch)``,
``model.training_losses(result, batch)["loss"]``, ``.backward()``.

* ``reference``: the step inside :func:`lcreg.reference.reference_mode`, i.e. the straightforward implementations
  (dense last encoder layer with a dense backward, in training mode and through the eval-mode solve the self-motion
  term differentiates, full ``(B, N, K)`` Jacobian pooling, the folding grid copied per cloud, Chamfer on the
  ``torch.cdist`` matrix);
* ``fast``: the default code path.

Both run on the same weights and batch; time per step is the median of ``--repeats`` alternating rounds after
``--warmup`` rounds (:func:`lcreg.experiments.benchmarking.time_calls`). Memory: on CPU the peak resident-set increase
during one step (:func:`lcreg.experiments.benchmarking.peak_rss_increase_mib`: high-water mark after the step minus the
resident set before it, freed heap returned first; everything resident at the peak counts: saved activations,
temporaries, library workspaces); on CUDA the peak of ``torch.cuda.max_memory_allocated`` above the allocation before
the step. A check line gives the largest differences of the loss terms and of the parameter gradients between the two
paths (relative to each gradient's largest entry); ``--breakdown`` adds the time of each component of the step in both
modes.

Threads: PyTorch's intra-op thread count (``--threads``; default: PyTorch's own) changes both paths; it is printed
with the machine. On a machine shared with other jobs, each multi-threaded op waits for its threads to be scheduled,
so run the comparison at the thread count you train with.
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    apply_smoke,
    build,
    cli_args,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    peak_rss_increase_mib,
    synchronize,
    time_calls,
    write_text,
)
from lcreg.geometry import se3
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.models.dvds import DVDs
from lcreg.reference import reference_mode
from lcreg.types import RegistrationBatch

SMOKE = {"batch": 2, "points": 96, "repeats": 1, "warmup": 0, "breakdown": True}
MODES = ("reference", "fast")


@contextlib.contextmanager
def mode(name: str) -> Iterator[None]:
    """``reference_mode()`` for ``"reference"``, nothing for ``"fast"``."""
    with reference_mode() if name == "reference" else contextlib.nullcontext():
        yield


def in_mode(name: str, fn: Callable[[], object]) -> Callable[[], object]:
    """``fn`` run in mode ``name``."""

    def run() -> object:
        with mode(name):
            return fn()

    return run


def training_step(model: DVDs, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
    """One training step's forward and backward (gradients zeroed first); the detached loss terms."""
    model.zero_grad(set_to_none=True)
    losses = model.training_losses(model.training_forward(batch), batch)
    losses["loss"].backward()
    return {name: value.detach() for name, value in losses.items()}


def step_memory_mib(model: DVDs, batch: RegistrationBatch, device: torch.device) -> float | None:
    """Peak memory added by one step: resident set on CPU, allocated CUDA memory on a GPU (MiB)."""
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        training_step(model, batch)
        synchronize(device)
        return (torch.cuda.max_memory_allocated(device) - before) / 2**20
    return peak_rss_increase_mib(lambda: training_step(model, batch))[1]


def agreement(model: DVDs, batch: RegistrationBatch) -> str:
    """Largest loss-term difference and largest relative gradient difference between the two paths."""
    results = {}
    for name in MODES:
        torch.manual_seed(0)  # the same self-generated pairs in both paths (self-motion term)
        with mode(name):
            losses = training_step(model, batch)
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        results[name] = (losses, grads)
    (loss_ref, grad_ref), (loss_fast, grad_fast) = results["reference"], results["fast"]
    loss_diff = max(float((loss_ref[k] - loss_fast[k]).abs()) for k in loss_ref)
    rel = [float((grad_ref[n] - grad_fast[n]).abs().max() / grad_ref[n].abs().max().clamp_min(1e-30)) for n in grad_ref]
    return (
        f"check: loss terms {', '.join(f'{k} {float(v):.6g}' for k, v in loss_ref.items())}; largest loss-term "
        f"difference {loss_diff:.2e}, largest relative gradient difference {max(rel):.2e} over {len(rel)} tensors"
    )


def components(model: DVDs, batch: RegistrationBatch) -> dict[str, Callable[[], object]]:
    """The parts of one step, each with its backward where the step has one (for ``--breakdown``)."""
    x, y = batch.points_src, batch.points_ref
    result = model.training_forward(batch)
    moved = se3.transform_points(result.transform_ref_src.detach(), x)
    with torch.no_grad():
        f_x, f_y = model.encoder(torch.cat([x, y])).split(x.shape[0])
    codes = (f_x.clone().requires_grad_(), f_y.clone().requires_grad_())
    normals = (batch.normals_src, batch.normals_ref)

    def eval_encoder(fn: Callable[[], object]) -> Callable[[], object]:
        def run() -> object:
            model.encoder.eval()
            try:
                with torch.no_grad():
                    return fn()
            finally:
                model.encoder.train()

        return run

    def backward(fn: Callable[[], torch.Tensor]) -> Callable[[], object]:
        def run() -> object:
            model.zero_grad(set_to_none=True)
            fn().backward()
            return None

        return run

    centred = (y - y.mean(1, keepdim=True), x - x.mean(1, keepdim=True))
    out: dict[str, Callable[[], object]] = {
        "IC-LK solve (training_forward)": lambda: model.training_forward(batch),
        "- Jacobian (psi(Y0) and d psi / d xi)": eval_encoder(lambda: model.encoder.twist_jacobian(centred[0])),
        "- one eval encoder pass (x iterations)": eval_encoder(lambda: model.encoder(centred[1])),
        "encoder training pass on [X, Y, W(X)], fwd+bwd": backward(
            lambda: model.encoder(torch.cat([x, y, moved])).square().sum()
        ),
        "reconstruction term (decoder + Chamfer, both sets), fwd+bwd": backward(
            lambda: sum(chamfer_distance(model.decoder(c), p).mean() for c, p in zip(codes, (x, y)))
        ),
        "normal term (both sets), fwd+bwd": backward(
            lambda: sum(model._normal_loss(p, n, c) for c, p, n in zip(codes, (x, y), normals))
        ),
    }
    for term in model.injected_terms:
        out[f"{term.name} term, fwd+bwd"] = backward(lambda term=term: term(model, result, batch))
    return out


def breakdown_table(model: DVDs, batch: RegistrationBatch, args: argparse.Namespace, device: torch.device) -> str:
    """Median ms of every component in both modes (alternating rounds)."""
    rows = []
    for name, fn in components(model, batch).items():
        timing = time_calls({m: in_mode(m, fn) for m in MODES}, args.repeats, args.warmup, device)
        ref, fast = (1000 * timing[m].median_s for m in MODES)
        rows.append([name, f"{ref:.1f}", f"{fast:.1f}", f"{ref / fast:.2f}"])
    return markdown_table(["component", "reference ms", "fast ms", "ratio"], rows)


def step_table(model: DVDs, batch: RegistrationBatch, args: argparse.Namespace, device: torch.device) -> str:
    """Median time per step and peak memory of both paths, and their ratio."""
    timing = time_calls(
        {m: in_mode(m, lambda: training_step(model, batch)) for m in MODES}, args.repeats, args.warmup, device
    )
    memory: dict[str, Any] = {}
    for name in MODES:
        with mode(name):
            memory[name] = step_memory_mib(model, batch, device)
    rows = []
    for name in MODES:
        runs = ", ".join(f"{s:.3f}" for s in timing[name].runs_s)
        mib = "n/a" if memory[name] is None else f"{memory[name]:.0f}"
        rows.append([name, f"{timing[name].median_s:.3f}", runs, mib])
    ratio = timing["reference"].median_s / timing["fast"].median_s
    table = markdown_table(["step", "median s/step", "runs (s)", "peak memory increase (MiB)"], rows)
    return table + f"\n\nratio reference / fast: {ratio:.2f}x"


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini", help="ModelNet40 folder (else synthetic)")
    parser.add_argument("--batch", type=int, default=16, help="pairs per batch")
    parser.add_argument("--points", type=int, default=1024, help="points per cloud")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds (median reported)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed rounds first")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: PyTorch's)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0, help="weight initialisation")
    parser.add_argument("--breakdown", action="store_true", help="also time each component of the step")
    parser.add_argument("--recipe", action="store_true", help="the self-motion recipe (dvds_selfsup_modelnet40.yaml)")
    parser.add_argument("--out", default=None, help="also write the report (Markdown) here")
    add_smoke_argument(parser)
    return apply_smoke(parser.parse_args(argv), SMOKE)


def setup(args: argparse.Namespace) -> tuple[DVDs, RegistrationBatch, str]:
    """The configured DVDs model (train mode, seeded weights) and the benchmark batch (no pose: self-supervised)."""
    torch.manual_seed(args.seed)
    model = build("dvds_selfsup" if args.recipe else "dvds", values=cli_args("model", {"diagnostics_every_n_steps": 0}))
    if not isinstance(model, DVDs):  # pragma: no cover - the registry builds DVDs
        raise TypeError(f"expected DVDs, got {type(model).__name__}")
    batches, source = pair_batches(args.root, "val", pairs=args.batch, num_points=args.points, batch_size=args.batch)
    batch = move_data_to_device(batches[0], args.device)
    batch.transform_ref_src = None
    return model.to(args.device).train(), batch, source


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    model, batch, source = setup(args)
    device = torch.device(args.device)
    config = "configs/dvds_selfsup_modelnet40.yaml" if args.recipe else "configs/dvds_modelnet40.yaml"
    head = (
        f"DVDs training step ({config}, LC included), batch {len(batch)} x {args.points} points "
        f"from {source}; device {args.device}: {machine_line(args.device)}; median of {args.repeats} after "
        f"{args.warmup} warm-up"
    )
    print(head, flush=True)
    parts = [head, step_table(model, batch, args, device), agreement(model, batch)]
    print("\n\n".join(parts[1:]), flush=True)
    if args.breakdown:
        parts.append(breakdown_table(model, batch, args, device))
        print("\n" + parts[-1])
    out = output_path(args.out, "bench_dvds_step.md", args.smoke)
    if out:
        write_text(out, "\n\n".join(parts) + "\n")


if __name__ == "__main__":
    main()
