# Ad-hoc probe of session 16 (goal (b)): which of several IC-LK starts to keep. Collect, then judge:
#   PYTHONPATH=src python docs/results/converge/multistart/probes/judge_probe.py collect NAME SPLIT OUT.pt [P A]
#   PYTHONPATH=src python docs/results/converge/multistart/probes/judge_probe.py judge OUT.pt [OUT.pt ...]
#   PYTHONPATH=src python docs/results/converge/multistart/probes/judge_probe.py compare TRAINED.pt UNTRAINED.pt ...
# (P: validation pairs per object, 4 as the converge budget; A: comma-separated start angles, default 30,60)
"""Per-start IC-LK solves of a shipped LK file on the ModelNet40 pairs, and start-selection judges on them.

``collect`` runs each start of ``axis_rotation_starts([30, 60])`` (13: the identity, then +-30 deg and +-60 deg
about x, y, z) as its own solve and saves every start's final transform and residual with the ground truth and the
pair classes. ``judge`` scores the judges fixed before any of it ran (session 16):

* ``identity``: start 0 (the shipped behaviour);
* ``residual``: the lowest final residual (``InverseCompositionalLK(starts=...)`` today);
* ``margin m``: the identity unless another start's residual is below ``(1 - m)`` times the identity's;
* ``consensus``: the start whose final rotation has the most starts within 2 deg of it (ties: the lowest residual).

each on the first 7 starts (+-30 deg) and on all 13.
"""

import sys

import torch

from lcreg import pretrained
from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.experiments.benchmarking import split_batches
from lcreg.metrics.functional import registration_recall, rotation_error_deg, translation_error
from lcreg.nn.lk import axis_rotation_starts, select_start
from lcreg.weights import read_weights, resolve_class

ROOT = "../shared/data/modelnet40_mini"
SYMMETRIC = {"bowl", "flower_pot", "vase", "cup", "bottle", "cone"}  # an axis of rotational symmetry


def collect(name: str, split: str, out: str, pairs: int = 4, angles: tuple[float, ...] = (30, 60)) -> None:
    """Save every start's final transform and residual, the ground truth and the classes of ``split``'s pairs.

    ``NAME@untrainedK``: the file's network untrained, initialised with seed K (as the shipped-weights test does).
    """
    torch.set_num_threads(1)
    if "@untrained" in name:
        file, seed = name.split("@untrained")
        weights = read_weights(file)
        torch.manual_seed(int(seed))
        model = resolve_class(weights.class_path)(**weights.init_args).eval()
    else:
        model = pretrained(name)
    dm = ModelNet40DataModule(ROOT, num_points=1024, batch_size=52, val_pairs_per_object=pairs)
    batches = split_batches(dm, split)  # type: ignore[arg-type]
    starts = axis_rotation_starts(angles)
    rows: dict[str, list[torch.Tensor]] = {"transform": [], "residual": [], "gt": []}
    classes: list[str] = []
    with torch.no_grad():
        for b in batches:
            per_start = [
                model.solver(
                    model.encoder, b.points_src, b.points_ref, max_iterations=model.eval_iterations, starts=s[None]
                )
                for s in starts
            ]
            shipped = model.register(b.points_src, b.points_ref).transform_ref_src
            assert torch.allclose(per_start[0].transform_ref_src, shipped, atol=1e-5), "start 0 != shipped solve"
            rows["transform"].append(torch.stack([r.transform_ref_src for r in per_start], 1))  # (B, S, 4, 4)
            rows["residual"].append(torch.stack([r.aux["final_residual"] for r in per_start], 1))  # (B, S)
            rows["gt"].append(b.transform_ref_src)
            classes += dm.pair_classes(split, b.index) or []  # type: ignore[arg-type]
            print(f"{len(classes)} pairs", flush=True)
    torch.save({**{k: torch.cat(v) for k, v in rows.items()}, "classes": classes, "name": name, "split": split}, out)


def pick(transform: torch.Tensor, residual: torch.Tensor, judge: str) -> torch.Tensor:
    """Index of the kept start of every pair ``(B,)`` for ``transform (B, S, 4, 4)``, ``residual (B, S)``."""
    b, s = residual.shape
    if judge == "identity":
        return torch.zeros(b, dtype=torch.long)
    if judge == "residual":
        return select_start(residual.T)
    if judge.startswith("margin"):  # the library's eval_start_margin
        return select_start(residual.T, float(judge.split()[1]))
    if judge == "consensus":
        ti = transform[:, :, None].expand(b, s, s, 4, 4).reshape(-1, 4, 4)
        tj = transform[:, None, :].expand(b, s, s, 4, 4).reshape(-1, 4, 4)
        near = (rotation_error_deg(ti, tj).reshape(b, s, s) < 2.0).sum(-1).double()  # (B, S) support
        score = near - residual.double() / (residual.double().max() + 1)  # ties: the lower residual
        return score.argmax(1)
    raise ValueError(judge)


def judge(paths: list[str]) -> None:
    """Print each judge's errors on the collected pairs: all of them and those of non-symmetric classes."""
    for path in paths:
        data = torch.load(path)
        cls = data["classes"]
        keep_sym = torch.tensor([c not in SYMMETRIC for c in cls])
        print(
            f"\n{data['name']} {data['split']} ({len(cls)} pairs; without {sorted(SYMMETRIC & set(cls))}: "
            f"{int(keep_sym.sum())})"
        )
        for n_starts in sorted({7, data["transform"].shape[1]}):
            t, r = data["transform"][:, :n_starts], data["residual"][:, :n_starts]
            for j in ("identity", "residual", "margin 0.1", "margin 0.25", "consensus"):
                k = pick(t, r, j)
                chosen = t[torch.arange(len(k)), k]
                rre, rte = rotation_error_deg(chosen, data["gt"]), translation_error(chosen, data["gt"])
                cells = []
                for mask in (torch.ones_like(keep_sym), keep_sym):
                    a, e = rre[mask], rte[mask]
                    rec = float(registration_recall(a, e, 2.0, 0.01))
                    cells.append(
                        f"mean {a.mean():.3f} median {a.median():.3f} >5: {int((a > 5).sum())} recall {100 * rec:.1f}"
                    )
                print(
                    f"  {n_starts:2d} starts {j:12s} | all: {cells[0]} | non-sym: {cells[1]} | "
                    f"moved {int((k != 0).sum())}"
                )


def summary(data: dict, judge_name: str) -> dict[str, float]:  # type: ignore[type-arg]
    """Mean and median RRE (deg) and recall (2 deg, 0.01) of ``judge_name``'s kept starts on the ±30 deg starts."""
    t, r = data["transform"][:, :7], data["residual"][:, :7]
    k = pick(t, r, judge_name)
    chosen = t[torch.arange(len(k)), k]
    rre, rte = rotation_error_deg(chosen, data["gt"]), translation_error(chosen, data["gt"])
    recall = float(registration_recall(rre, rte, 2.0, 0.01))
    return {"mean RRE": float(rre.mean()), "median RRE": float(rre.median()), "recall (2°, 0.01)": recall}


def compare(trained: str, untrained: list[str]) -> None:
    """The shipped-weights test's comparison (trained against untrained seeds, beyond mean +- std) per judge."""
    mine, seeds = torch.load(trained), [torch.load(u) for u in untrained]
    print(f"{mine['name']} {mine['split']}: {len(mine['classes'])} pairs, {len(seeds)} untrained seeds")
    for j in ("identity", "residual", "margin 0.1", "margin 0.25"):
        cells, fails = [], []
        for stat, value in summary(mine, j).items():
            values = torch.tensor([summary(u, j)[stat] for u in seeds], dtype=torch.float64)
            mean, std = float(values.mean()), float(values.std())
            better = value > mean + std if stat.startswith("recall") else value < mean - std
            cells.append(f"{stat} {value:.4g} vs {mean:.4g} ± {std:.4g}")
            fails += [] if better else [stat]
        print(f"  {j:12s} | " + " | ".join(cells) + f" | not beyond: {fails or 'none'}")


if __name__ == "__main__":
    if sys.argv[1] == "compare":
        compare(sys.argv[2], sys.argv[3:])
    elif sys.argv[1] == "collect":
        extra = sys.argv[5:]
        angles = tuple(float(a) for a in extra[1].split(",")) if len(extra) > 1 else (30.0, 60.0)
        collect(sys.argv[2], sys.argv[3], sys.argv[4], int(extra[0]) if extra else 4, angles)
    else:
        judge(sys.argv[2:])
