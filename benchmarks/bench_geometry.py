"""Nearest-neighbour search of ``lcreg.geometry`` (kNN, Chamfer): the expanded-matrix search vs ``torch.cdist``.

    python benchmarks/bench_geometry.py [--batch 16] [--sizes 256 1024 2048] [--k 16] [--dims 3 64] [--repeats 5]
    python benchmarks/bench_geometry.py --smoke      # tiny sizes, one repeat: checks that the script runs

Three searches of the same chunked loop, timed in one process on the same clouds (``B`` clouds of ``N = M`` points,
Gaussian, ``D`` coordinates):

* ``expanded``: the previous implementation, ``|a|^2 - 2 a.b + |b|^2`` after shifting both clouds by the centroid of
  ``a`` (kept here only as the baseline);
* ``cdist-mm``: ``torch.cdist(..., compute_mode="use_mm_for_euclid_dist")`` (the same expansion inside PyTorch);
* ``cdist-exact``: ``torch.cdist(..., compute_mode="donot_use_mm_for_euclid_dist")`` (sums of squared differences).

For each: median milliseconds of the kNN index search (``top-k``) and of Chamfer's two-way nearest neighbours, the
ratio ``expanded / search`` (> 1: faster than the previous code), and the accuracy of the kNN search against a
float64 reference on the same float32 points: the largest relative error of the searched k-th distance and the
fraction of rows whose index set differs. The last table times the library's ``knn`` and ``chamfer_distance``
(forward + backward) end to end against the previous implementation (expanded search, same distance recomputation),
with the number of kNN distances that are not bit-identical (a near-tie resolved differently: the float64 check of the
first table says which search is right) and the largest relative Chamfer difference. The pooling table times the
graph convolutions' maximum over the ``k`` neighbours (forward + backward), :func:`lcreg.geometry.neighbors.
neighbour_max` against the previous ``amax`` on ``(B, N, k, C)`` edge values of DCP-v2's widths (``C`` = 64, 128,
256; ``B`` = 8, ``k`` = 20, ``--pool-points``), and DCP-v2's whole DGCNN embedding with each (same weights and
clouds), with whether the gradients are bit-identical (without ties they are). Numbers depend on the machine
and its load (``--threads 1`` is steadier on a busy machine); the thread count is printed.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Callable
from functools import partial

import torch

from lcreg.geometry import neighbors
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.geometry.neighbors import gather_points, knn, neighbour_max, safe_norm
from lcreg.nn import dgcnn

Search = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def expanded(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Previous search matrix: squared distances ``(B, N, M)`` from the expansion, centroid-shifted, clamped at 0."""
    shift = a.mean(dim=1, keepdim=True)
    a, b = a - shift, b - shift
    d2 = (a * a).sum(-1)[:, :, None] - 2 * (a @ b.transpose(1, 2)) + (b * b).sum(-1)[:, None, :]
    return d2.clamp_min(0)


def cdist_mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.cdist(a, b, compute_mode="use_mm_for_euclid_dist")


def cdist_exact(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


SEARCHES: dict[str, Search] = {"expanded": expanded, "cdist-mm": cdist_mm, "cdist-exact": cdist_exact}


def chunk_rows(batch: int, num_b: int) -> int:
    return max(1, neighbors._CHUNK_ELEMENTS // (batch * num_b))


def knn_search(search: Search, query: torch.Tensor, points: torch.Tensor, k: int) -> torch.Tensor:
    """``(B, Q, k)`` indices, chunked over queries like the library."""
    chunk = chunk_rows(query.shape[0], points.shape[1])
    parts = [torch.topk(search(q, points), k, dim=-1, largest=False).indices for q in query.split(chunk, dim=1)]
    return torch.cat(parts, dim=1)


def both_ways_search(search: Search, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest ``a -> b`` and ``b -> a`` indices from one chunked pass, like the library's Chamfer."""
    batch, num_b = b.shape[:2]
    chunk = chunk_rows(batch, num_b)
    idx_ab, best = [], b.new_full((batch, num_b), float("inf"))
    idx_ba = torch.zeros(batch, num_b, dtype=torch.long)
    for start, part in zip(range(0, a.shape[1], chunk), a.split(chunk, dim=1)):
        d = search(part, b)
        idx_ab.append(d.argmin(dim=2))
        val, arg = d.min(dim=1)
        better = val < best
        best, idx_ba = torch.where(better, val, best), torch.where(better, arg + start, idx_ba)
    return torch.cat(idx_ab, dim=1), idx_ba


def median_ms(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median milliseconds of each callable, called in turn ``repeats`` times after a warm-up (cancels drift)."""
    runs: dict[str, list[float]] = {name: [] for name in fns}
    for r in range(repeats + 1):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            if r:
                runs[name].append(1000 * (time.perf_counter() - start))
    return {name: statistics.median(times) for name, times in runs.items()}


def accuracy(search: Search, query: torch.Tensor, points: torch.Tensor, k: int) -> tuple[float, float]:
    """Largest relative error of the k-th neighbour distance and fraction of rows with another index set."""
    idx = knn_search(search, query, points, k)
    ref = torch.cdist(query.double(), points.double(), compute_mode="donot_use_mm_for_euclid_dist")
    ref_d, ref_i = torch.topk(ref, k, dim=-1, largest=False)
    got_d = ref.gather(-1, idx).amax(-1)  # true distance of the farthest returned neighbour
    rel = ((got_d - ref_d[..., -1]).abs() / ref_d[..., -1].clamp_min(1e-300)).max().item()
    differs = (idx.sort(-1).values != ref_i.sort(-1).values).any(-1).double().mean().item()
    return rel, differs


def search_table(batch: int, sizes: list[int], dims: list[int], k: int, repeats: int, offset: float) -> None:
    print(f"\n### Search only (no autograd), B={batch}, k={k}, float32, clouds offset by {offset} from the origin\n")
    print("| D | N=M | search | kNN ms | ratio | Chamfer NN ms | ratio | max rel err k-th dist | rows differing |")
    print("|---|---|---|---|---|---|---|---|---|")
    for dim in dims:
        for n in sizes:
            gen = torch.Generator().manual_seed(n + dim)
            a = torch.randn(batch, n, dim, generator=gen) + offset
            b = torch.randn(batch, n, dim, generator=gen) + offset
            with torch.no_grad():
                t_knn = median_ms({m: partial(knn_search, s, a, b, k) for m, s in SEARCHES.items()}, repeats)
                t_cd = median_ms({m: partial(both_ways_search, s, a, b) for m, s in SEARCHES.items()}, repeats)
                for name, search in SEARCHES.items():
                    rel, differs = accuracy(search, a, b, k)
                    print(
                        f"| {dim} | {n} | {name} | {t_knn[name]:.2f} | {t_knn['expanded'] / t_knn[name]:.2f} | "
                        f"{t_cd[name]:.2f} | {t_cd['expanded'] / t_cd[name]:.2f} | {rel:.1e} | {differs:.4f} |"
                    )


def previous_knn(query: torch.Tensor, points: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The previous ``knn``: expanded search, then the same exact, differentiable distances as the library."""
    with torch.no_grad():
        idx = knn_search(expanded, query.detach(), points.detach(), k)
    dists, order = safe_norm(query[:, :, None, :] - gather_points(points, idx), dim=-1).sort(dim=-1)
    return dists, idx.gather(-1, order)


def previous_chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The previous ``chamfer_distance``: expanded two-way search, then the same distances as the library."""
    with torch.no_grad():
        idx_ab, idx_ba = both_ways_search(expanded, a.detach(), b.detach())
    return safe_norm(a - gather_points(b, idx_ab)).mean(1) + safe_norm(b - gather_points(a, idx_ba)).mean(1)


Tensor = torch.Tensor


def knn_backward(fn: Callable[..., tuple[Tensor, Tensor]], a: Tensor, b: Tensor, k: int) -> None:
    fn(a, b, k)[0].sum().backward()


def chamfer_backward(fn: Callable[[Tensor, Tensor], Tensor], a: Tensor, b: Tensor) -> None:
    fn(a, b).sum().backward()


def library_table(batch: int, sizes: list[int], k: int, repeats: int) -> None:
    print(f"\n### Library (this checkout) vs the previous implementation, forward + backward, B={batch}, k={k}, D=3\n")
    print("| N=M | knn previous ms | knn ms | ratio | CD previous ms | CD ms | ratio | knn differing | CD rel diff |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        gen = torch.Generator().manual_seed(n)
        a = torch.randn(batch, n, 3, generator=gen).requires_grad_(True)
        b = torch.randn(batch, n, 3, generator=gen).requires_grad_(True)
        fns = {
            "knn old": partial(knn_backward, previous_knn, a, b, k),
            "knn new": partial(knn_backward, knn, a, b, k),
            "cd old": partial(chamfer_backward, previous_chamfer, a, b),
            "cd new": partial(chamfer_backward, chamfer_distance, a, b),
        }
        t = median_ms(fns, repeats)
        with torch.no_grad():
            knn_differs = int((knn(a, b, k)[0] != previous_knn(a, b, k)[0]).sum())
            cd_new, cd_old = chamfer_distance(a, b), previous_chamfer(a, b)
            cd_rel = float(((cd_new - cd_old).abs() / cd_old).max())
        print(
            f"| {n} | {t['knn old']:.2f} | {t['knn new']:.2f} | {t['knn old'] / t['knn new']:.2f} | "
            f"{t['cd old']:.2f} | {t['cd new']:.2f} | {t['cd old'] / t['cd new']:.2f} | "
            f"{knn_differs} of {batch * n * k} | {cd_rel:.1e} |"
        )


def previous_max(values: Tensor) -> Tensor:
    """The previous pooling, ``amax`` over the neighbour axis (kept here only as the baseline)."""
    return values.amax(dim=2)


def pool_backward(pool: Callable[[Tensor], Tensor], values: Tensor, grad: Tensor) -> Tensor:
    values.grad = None
    pool(values).backward(grad)
    assert values.grad is not None
    return values.grad


def embedding_backward(model: dgcnn.DGCNN, pool: Callable[[Tensor], Tensor], points: Tensor) -> list[Tensor]:
    """Weight gradients of ``model(points).sum()`` with ``pool`` as DGCNN's neighbour maximum."""
    saved, dgcnn.neighbour_max = dgcnn.neighbour_max, pool
    try:
        model.zero_grad()
        model(points).sum().backward()
    finally:
        dgcnn.neighbour_max = saved
    return [p.grad.clone() for p in model.parameters() if p.grad is not None]


def pooling_table(batch: int, points: int, k: int, repeats: int) -> None:
    print(
        f"\n### Neighbour maximum, forward + backward: amax (previous) vs neighbour_max, B={batch}, N={points}, k={k}\n"
    )
    print("| values | amax ms | neighbour_max ms | ratio | gradients identical |")
    print("|---|---|---|---|---|")
    gen = torch.Generator().manual_seed(points)
    for channels in (64, 128, 256):
        values = torch.randn(batch, points, k, channels, generator=gen).requires_grad_(True)
        grad = torch.randn(batch, points, channels, generator=gen)
        fns = {
            name: partial(pool_backward, pool, values, grad)
            for name, pool in (("old", previous_max), ("new", neighbour_max))
        }
        t = median_ms(fns, repeats)
        same = torch.equal(fns["old"](), fns["new"]())
        print(
            f"| {batch} x {points} x {k} x {channels} | {t['old']:.1f} | {t['new']:.1f} | "
            f"{t['old'] / t['new']:.2f} | {'yes' if same else 'no'} |"
        )
    torch.manual_seed(0)
    model = dgcnn.DGCNN(k=k).train()
    cloud = torch.randn(batch, points, 3, generator=gen)
    fns = {
        name: partial(embedding_backward, model, pool, cloud)
        for name, pool in (("old", previous_max), ("new", neighbour_max))
    }
    t = median_ms(fns, repeats)
    same = all(torch.equal(a, b) for a, b in zip(fns["old"](), fns["new"](), strict=True))
    print(
        f"| DCP-v2's DGCNN, {batch} x {points} points | {t['old']:.1f} | {t['new']:.1f} | "
        f"{t['old'] / t['new']:.2f} | {'yes' if same else 'no'} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024, 2048])
    parser.add_argument("--dims", type=int, nargs="+", default=[3, 64], help="coordinate widths (64: DGCNN features)")
    parser.add_argument("--k", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pool-points", type=int, default=256, help="points per cloud of the pooling table")
    parser.add_argument("--offset", type=float, default=0.0, help="added to every coordinate (far-from-origin test)")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--smoke", action="store_true", help="B=2, N=64, one repeat: checks that the script runs")
    args = parser.parse_args()
    if args.smoke:
        args.batch, args.sizes, args.dims, args.k, args.repeats, args.pool_points = 2, [64], [3], 4, 1, 32
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads")
    search_table(args.batch, args.sizes, args.dims, args.k, args.repeats, args.offset)
    pool_batch, pool_k = (2, 4) if args.smoke else (8, 20)  # DCP-v2's batch and graph
    pooling_table(pool_batch, args.pool_points, pool_k, args.repeats)
    library_table(args.batch, args.sizes, args.k, args.repeats)


if __name__ == "__main__":
    main()
