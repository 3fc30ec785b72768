"""Every script in benchmarks/ runs end to end in its --smoke mode (tiny synthetic pairs, untrained weights).

The scripts are imported and their ``main(argv)`` called in this process (fast); bench_dvds and kitti_full_pair
still start their fresh measurement processes. No figure is checked: only that the script runs and writes its report.
"""

from __future__ import annotations

import csv
import importlib.util
import statistics
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

from lcreg.data.synthetic import PRIMITIVES

from _shared_data import shared_data  # type: ignore[import-not-found]

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
RUNS = {
    "bad_input_matrix": [],
    "bench_baselines": [],
    "bench_dvds": [],
    "bench_dvds_step": [],
    "bench_dvds_step --recipe": ["--recipe"],
    "bench_runtime": [],
    "bench_export": [],
    "bench_precision": [],
    "compare_methods": [],
    "class_breakdown": [],
    "error_geometry": [],
    "resume_audit": [],
    "compare_rows": [],
    "eval_modelnet40_dvds": [],
    "eval_modelnet40_dvds --split val": ["--split", "val", "--model-args", "eval_iterations=2"],
    "eval_scenes": [],
    "eval_scenes --tune": ["--tune"],
    "kill_resume": [],  # five lcreg processes, about 30 s: the real kill -9 and resume
    "kitti_full_pair": [],
    "lc_gradient_share": [],
    "lc_plus_x": [],
    "lk_fixed_point": [],
    "pcrnet_collapse": [],
    "oracle_floor": [],
    "overfit": [],
    "learning_curves": [],
    "pilot_dvds_variants": [],
    "plot_learning_curves": [],
    "plot_learning_curves --x pairs": ["--x", "pairs"],
    "register_scenes": [],
    "tune_classical": [],
}

# their own test files run their --smoke and check it
CHECKED_ELSEWHERE = {"bench_geometry", "device_payload", "train_queue"}
pytestmark = pytest.mark.usefixtures("isolated_cli")


def load(name: str) -> ModuleType:
    """Import ``benchmarks/<name>.py`` under a private module name."""
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_every_script_has_a_smoke_run() -> None:
    assert {run.split()[0] for run in RUNS} | CHECKED_ELSEWHERE == {p.stem for p in BENCHMARKS.glob("*.py")}


@pytest.mark.parametrize("run", list(RUNS))
def test_smoke(run: str, tmp_path: Path) -> None:
    out = tmp_path / "out" / "report.md"
    load(run.split()[0]).main(["--smoke", "--out", str(out), *RUNS[run]])
    assert out.is_file() and "|---" in out.read_text()


def test_plot_learning_curves_on_pairs_names_a_run_without_its_batch_size(tmp_path: Path) -> None:
    from lcreg.experiments.benchmarking import write_synthetic_metrics

    run = write_synthetic_metrics(tmp_path / "run" / "metrics.csv")
    (run.parent / "hparams.yaml").unlink()
    script = load("plot_learning_curves")
    with pytest.raises(SystemExit, match=r"--x pairs: no hparams\.yaml beside .*run"):
        script.main(["--run", f"D={run}", "--out", str(tmp_path / "curves.md"), "--x", "pairs"])
    script.main(["--run", f"D={run}", "--out", str(tmp_path / "curves.md")])  # steps need no batch size
    assert "first @ step" in (tmp_path / "curves.md").read_text()


def test_bad_input_matrix_smoke_has_no_cryptic_or_silent_case(tmp_path: Path) -> None:
    # Issue 14: before the fixes the full matrix had 133 cryptic and 56 silent cases out of 438; issue 27 added 29
    # cases (9 cryptic and 11 silent before; the smoke subset runs its geometry and internal ones, not training).
    out = tmp_path / "matrix.md"
    load("bad_input_matrix").main(["--smoke", "--out", str(out)])
    assert "cryptic 0, silent 0" in out.read_text().splitlines()[0]


def test_eval_model_args_reach_the_constructor_and_malformed_ones_are_refused() -> None:
    script = load("eval_modelnet40_dvds")
    args = script.parse(["--ckpt", "x.ckpt", "--model-args", "eval_iterations=3"])
    assert script.learned("dvds", None, 0, False, args.model_args).eval_iterations == 3
    assert script.learned("dvds", None, 0, False).eval_iterations is None
    with pytest.raises(SystemExit, match="key=value"):
        script.parse(["--ckpt", "x.ckpt", "--model-args", "eval_iterations"])


def test_eval_choose_starts_reports_each_setting_and_the_rules_choice(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--choose-starts``: per checkpoint one row with one start and one per angle, each built with that setting,
    and the choice of :func:`~lcreg.experiments.evaluation.choose_start_angle` on the rows' mean RRE."""
    from lcreg.experiments.evaluation import choose_start_angle

    script = load("eval_modelnet40_dvds")
    out, pairs = tmp_path / "starts.md", tmp_path / "pairs.csv"
    script.main(
        ["--smoke", "--split", "val", "--choose-starts", "30", "90", "--out", str(out), "--pairs-csv", str(pairs)]
    )
    means: dict[str, list[float]] = {}
    for line in csv.DictReader(pairs.open()):
        means.setdefault(line["row"], []).append(float(line["rre_deg"]))
    names = {"one start": None, "starts ±30°": 30.0, "starts ±90°": 90.0}
    assert sorted(row.rsplit(", ", 1)[1] for row in means) == sorted(names)  # only the trained rows, no ICP
    mean_rre = {names[row.rsplit(", ", 1)[1]]: statistics.fmean(v) for row, v in means.items()}
    best = choose_start_angle(mean_rre)
    chosen = out.read_text().split("smaller angle):")[1].strip()
    assert chosen.startswith("- ") and ("one start" if best is None else f"eval_start_angles_deg=[{best:g}]") in chosen
    args = script.parse(["--smoke", "--split", "val", "--choose-starts", "30"])
    model = script.learned("dvds", None, 0, False, {**args.model_args, "eval_start_angles_deg": "[30]"})
    assert model.eval_start_angles_deg == (30.0,)
    with pytest.raises(SystemExit):
        script.parse(["--ckpt", "x.ckpt", "--choose-starts", "30"])
    assert "add --split val" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.parse(
            [
                "--ckpt",
                "x.ckpt",
                "--split",
                "val",
                "--choose-starts",
                "30",
                "--model-args",
                "eval_start_angles_deg=[45]",
            ]
        )
    assert "leave it out of --model-args" in capsys.readouterr().err


@pytest.mark.data
def test_eval_val_pairs_draws_the_converge_budgets_validation_pairs() -> None:
    # 4 pairs per validation object: the 312 pairs the converge budget ranks checkpoints on (78 objects)
    root = shared_data("modelnet40_mini")
    script = load("eval_modelnet40_dvds")
    sizes = {}
    for per_object in (1, 4):
        args = script.parse(["--ckpt", "x.ckpt", "--root", str(root), "--split", "val", "--val-pairs", str(per_object)])
        batches, _, _ = script.evaluation_pairs(args, 0.0)
        sizes[per_object] = sum(b.points_src.shape[0] for b in batches)
    assert sizes == {1: 78, 4: 312}


def test_eval_pairs_csv_holds_each_rows_per_pair_errors_that_make_its_table_values(tmp_path: Path) -> None:
    """``--pairs-csv``: one line per row and pair; each row's mean of ``rre_deg`` is its table's mean RRE."""
    script = load("eval_modelnet40_dvds")
    out, pairs = tmp_path / "t.md", tmp_path / "pairs.csv"
    script.main(["--smoke", "--out", str(out), "--pairs-csv", str(pairs), "--noise-sigma", "0", "0.01"])
    errors: dict[tuple[str, str], list[float]] = {}
    offsets: dict[str, set[tuple[str, str, str]]] = {}
    for line in csv.DictReader(pairs.open()):
        errors.setdefault((line["sigma"], line["row"]), []).append(float(line["rre_deg"]))
        offsets.setdefault(line["sigma"], set()).add((line["pair"], line["centroid_offset"], line["class"]))
    # One offset and one class per pair, in every row; the class is the datamodule's for the pair's object.
    assert all(len(pairs_of_sigma) == 2 for pairs_of_sigma in offsets.values())
    _, _, classes = script.evaluation_pairs(script.parse(["--smoke"]), 0.0)
    assert classes is not None and len(classes) == 2 and set(classes) <= set(PRIMITIVES)  # the synthetic kinds
    assert {(pair, cls) for pair, _, cls in offsets["0.0"]} == {(str(i), c) for i, c in enumerate(classes)}
    table, sigma, column = {}, "", 0
    for line in out.read_text().splitlines():
        if "noise sigma" in line:
            sigma = line.split("noise sigma ")[1].split(",")[0]
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if "mean RRE °" in cells:
            column = cells.index("mean RRE °")
        elif len(cells) > column > 0 and not cells[0].startswith("---") and "mean ± std" not in cells[0]:
            table[(sigma, cells[0])] = float(cells[column])
    assert set(errors) == set(table) and {s for s, _ in table} == {"0.0", "0.01"}
    assert len(table) == 2 * 7  # per sigma: trained, 2 untrained, each ± ICP refinement; one ICP gate
    for key, values in errors.items():
        assert len(values) == 2, key  # the smoke budget's pairs
        assert statistics.fmean(values) == pytest.approx(table[key], rel=1e-3, abs=1e-3), key


def test_eval_same_points_draws_both_clouds_from_one_sampling() -> None:
    """``--same-points``: the reference is the transformed source point for point set (nearest neighbours at 0);
    by default the samplings differ."""
    from lcreg.geometry.chamfer import chamfer_distance
    from lcreg.geometry.se3 import transform_points

    script = load("eval_modelnet40_dvds")
    for flags, same in (([], False), (["--same-points"], True)):
        args = script.parse(["--smoke", *flags])
        batch = script.evaluation_pairs(args, 0.0)[0][0]
        moved = transform_points(batch.transform_ref_src, batch.points_src)
        gap = chamfer_distance(moved, batch.points_ref)
        assert bool((gap < 1e-5).all()) == same, (flags, gap)
        # The pairs CSV's centroid offsets: 0 for one sampling, and the per-pair norm of the centroid gap otherwise.
        offsets = torch.tensor(script.centroid_offsets([batch]))
        expected = (moved.mean(dim=1) - batch.points_ref.mean(dim=1)).norm(dim=-1)
        torch.testing.assert_close(offsets, expected, rtol=1e-4, atol=1e-6)
        assert bool((offsets < 1e-5).all()) == same, (flags, offsets)


def test_eval_from_truth_starts_every_solve_at_the_true_pose(tmp_path: Path) -> None:
    """``--from-truth``: each source moved by its ground truth, whose transform becomes the identity; with one
    sampling and no noise that pose is ICP's exact fixed point (errors 0)."""
    from lcreg.geometry.se3 import transform_points

    script = load("eval_modelnet40_dvds")
    plain = script.evaluation_pairs(script.parse(["--smoke"]), 0.0)[0][0]
    moved = script.evaluation_pairs(script.parse(["--smoke", "--from-truth"]), 0.0)[0][0]
    torch.testing.assert_close(moved.points_src, transform_points(plain.transform_ref_src, plain.points_src))
    torch.testing.assert_close(moved.transform_ref_src, torch.eye(4).expand(len(plain), 4, 4))
    torch.testing.assert_close(moved.points_ref, plain.points_ref)
    pairs, out = tmp_path / "pairs.csv", tmp_path / "t.md"
    script.main(["--smoke", "--same-points", "--from-truth", "--pairs-csv", str(pairs), "--out", str(out)])
    rows = list(csv.DictReader(pairs.open()))
    icp = [float(r["rre_deg"]) + float(r["rte"]) for r in rows if r["row"].startswith("Open3D ICP")]
    assert icp and max(icp) < 1e-3, icp
    assert all(float(r["centroid_offset"]) < 1e-5 for r in rows)


def test_lk_fixed_point_stays_at_an_exact_fixed_point_and_reports_both_starts(tmp_path: Path) -> None:
    """``lk_fixed_point.py``: two rows per model (its solve, and updates from the exact truth); started at the true
    pose of one sampling (a fixed point) the updates do not move; a model without an IC-LK solve is refused."""
    from lcreg.experiments.benchmarking import build, pair_batches

    script = load("lk_fixed_point")
    out = tmp_path / "f.md"
    text = script.main(["--smoke", "--out", str(out)])
    assert text.count("| untrained, seed 0 |") == 2 and out.read_text() == text
    model = build("dvds_selfsup", None, values={"seed_everything": 0}).eval()
    for same, moved in ((True, False), (False, True)):
        batch = pair_batches(None, "test", 2, num_points=64, independent_sampling=not same)[0][0]
        with torch.no_grad():
            pose = script.from_truth(model, batch, 3)
        gap = float((pose - batch.transform_ref_src).abs().max())
        assert (gap > 1e-4) == moved, (same, gap)
    with pytest.raises(TypeError, match="step_from"):
        script.from_truth(build("icp"), batch, 1)


def test_pcrnet_collapse_sees_dead_units_and_an_input_independent_output() -> None:
    """``pcrnet_collapse.py``: with a live output layer the first update varies over pairs; with the regressor's last
    hidden layer killed (every unit below zero) all its units are dead and the update is one constant."""
    from lcreg.experiments.benchmarking import pair_batches

    script = load("pcrnet_collapse")
    batch = pair_batches(None, "val", 4, num_points=64, batch_size=4)[0][0]
    model = script.load(None)
    torch.manual_seed(1)
    with torch.no_grad():
        model.pose.weight.normal_(0.0, 0.1)
    live = script.collapse(model, batch.points_src, batch.points_ref)
    assert live["first-update std"] > 1e-6 and live["dead last hidden units"] < 1
    with torch.no_grad():
        model.regressor.linears[-1].bias.fill_(-1e4)
    dead = script.collapse(model, batch.points_src, batch.points_ref)
    assert dead["dead last hidden units"] == 1.0 and dead["first-update std"] == 0.0
