"""benchmarks/learning_curves.py: its variants' values build the models they describe (nothing trained)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from tests.benchmarks.test_smoke import load

from lcreg.cli import LcregCLI
from lcreg.experiments.benchmarking import build_cli_for, machine_line, synthetic_overrides

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_variant_values_build_their_models() -> None:
    variants = load("learning_curves").VARIANTS

    def cli(name: str) -> LcregCLI:
        variant = variants[name]
        return build_cli_for(variant.method, variant.configs, {**synthetic_overrides(), **variant.overrides})

    slow = cli("pcrnet_idinit_lr1e-4").model
    assert slow.hparams.identity_init is True and slow.configure_optimizers().param_groups[0]["lr"] == 1e-4
    stat = cli("selfsup_tw100_stat").model
    assert [type(t).__name__ for t in stat.loss_terms] == [
        "LocalConsistencyLoss",
        "SelfMotionLoss",
        "SelfMotionStationarityLoss",
    ]
    assert [t.translation_weight for t in stat.loss_terms[1:]] == [100.0, 100.0]
    assert cli("selfsup_tw100").config["model"]["init_args"]["loss_terms"][-1]["class_path"].endswith("SelfMotionLoss")
    bn, plain = cli("selfsup_tw100_bn"), cli("selfsup_tw100")  # the same recipe, BatchNorm in the encoder
    assert bn.model.hparams.batch_norm is True and plain.model.hparams.batch_norm is False
    assert bn.config["model"]["init_args"]["loss_terms"] == plain.config["model"]["init_args"]["loss_terms"]
    paper_fmr, paper = cli("model_D_bn_lr1e-3"), cli("model_D")  # model D with FMR-Net's BatchNorm and lr
    assert paper_fmr.model.hparams.batch_norm is True and paper.model.hparams.batch_norm is False
    lrs = [c.model.configure_optimizers().param_groups[0]["lr"] for c in (paper_fmr, paper)]
    assert lrs == [pytest.approx(1e-3), pytest.approx(1e-4)]
    assert paper_fmr.config["model"]["init_args"]["loss_terms"] == paper.config["model"]["init_args"]["loss_terms"]
    assert (paper_fmr.model.hparams.lambda_recon, paper_fmr.model.hparams.lambda_normal) == (0.5, 0.1)
    aux = cli("aux_only_bn_lr1e-3").model  # DVDs' reconstruction and normals alone, FMR-Net's optimiser settings
    assert aux.hparams.batch_norm is True and aux.configure_optimizers().param_groups[0]["lr"] == pytest.approx(1e-3)
    assert aux.hparams.lambda_global == 0 and len(aux.loss_terms) == 0 and aux.decoder is not None
    assert (aux.hparams.lambda_recon, aux.hparams.lambda_normal) == (0.5, 0.1)
    recon, recon_mlp = cli("recon_sq_bn_lr1e-3").model, cli("recon_sq_bn_lr1e-3_mlpdec").model
    assert (recon.hparams.decoder, recon_mlp.hparams.decoder, recon_mlp.hparams.decoder_hidden) == (
        "folding",
        "mlp",
        [1024, 512, 256],
    )
    per_cloud = cli("recon_sq_bn_lr1e-3_mlpdec_percloud").model  # the same, each cloud's batch normalised alone
    assert (recon_mlp.hparams.norm_batch, per_cloud.hparams.norm_batch) == ("joint", "per_cloud")
    assert per_cloud.hparams.decoder == "mlp" and per_cloud.hparams.decoder_hidden == [1024, 512, 256]
    for model in (recon, recon_mlp, per_cloud):  # FMR-Net's objective: its squared reconstruction alone, its optimiser
        assert model.hparams.squared_chamfer and model.hparams.lambda_recon == 1.0 and len(model.loss_terms) == 0
        assert model.hparams.lambda_global == 0 and model.hparams.lambda_normal == 0 and model.hparams.batch_norm
    for scale in (0.1, 0.01):  # the control's objective plus the recipe's terms at a fraction of their weights
        reg = cli(f"recon_mlp_recipe{scale}").model
        assert [(type(t).__name__, t.weight) for t in reg.loss_terms] == [
            ("LocalConsistencyLoss", scale),
            ("SelfMotionLoss", scale),
        ]
        assert reg.loss_terms[1].translation_weight == 100.0 and reg.hparams.decoder == "mlp"
        assert (reg.hparams.lambda_global, reg.hparams.lambda_normal) == (scale, pytest.approx(0.1 * scale))
        assert reg.hparams.squared_chamfer and reg.hparams.lambda_recon == 1.0 and reg.hparams.batch_norm
    for scale in (0.1, 0.01):  # each of the recipe's terms alone at a fraction of its weight (which term biases)
        on = {}
        for name in ("global", "lc", "self_motion", "normal"):
            one = cli(f"recon_mlp_{name}{scale}").model
            assert one.hparams.decoder == "mlp" and one.hparams.squared_chamfer and one.hparams.lambda_recon == 1.0
            weights = {"global": one.hparams.lambda_global, "normal": one.hparams.lambda_normal}
            weights |= {
                "lc" if type(t).__name__ == "LocalConsistencyLoss" else "self_motion": t.weight for t in one.loss_terms
            }
            on[name] = {term: weight for term, weight in weights.items() if weight}
        assert on == {
            "global": {"global": scale},
            "lc": {"lc": scale},
            "self_motion": {"self_motion": scale},
            "normal": {"normal": pytest.approx(0.1 * scale)},
        }
    only = cli("self_motion_only").model
    assert [(type(t).__name__, t.name) for t in only.loss_terms] == [("SelfMotionLoss", "self_motion")]
    assert only.hparams.lambda_global == 0 and only.hparams.lambda_recon == 0
    steplr = cli("selfsup_steplr").config["model"]["init_args"]["lr_scheduler"]
    assert steplr["class_path"] == "torch.optim.lr_scheduler.StepLR" and steplr["init_args"]["step_size"] == 5
    nobn = cli("pointnetlk_nobn")
    assert nobn.model.hparams.batch_norm is False and nobn.model.hparams.jacobian == "analytic"
    assert nobn.trainer.gradient_clip_val == 1.0
    orig = cli("pointnetlk_orig")  # the config as it stands: the original's BatchNorm, Jacobian, lr, no clipping
    assert (orig.model.hparams.batch_norm, orig.model.hparams.jacobian) == (True, "finite_difference")
    assert orig.model.configure_optimizers().param_groups[0]["lr"] == 1e-3 and not orig.trainer.gradient_clip_val
    lever = cli("pointnetlk_nobn_steplr")
    assert lever.model.hparams.batch_norm is False and lever.trainer.gradient_clip_val == 1.0
    scheduler = lever.model.configure_optimizers()["lr_scheduler"]["scheduler"]
    assert isinstance(scheduler, torch.optim.lr_scheduler.StepLR) and (scheduler.step_size, scheduler.gamma) == (5, 0.5)
    assert scheduler.optimizer.param_groups[0]["lr"] == 0.0001
    for name, lr in (("prnet", 1e-3), ("prnet_lr2.2e-4", 2.2e-4)):  # as `lcreg reproduce lc`: DCP-family pairs
        prnet = cli(name)
        assert type(prnet.model).__name__ == "PRNet" and prnet.datamodule.hparams.noise_sigma == 0.01
        optimizer = prnet.model.configure_optimizers()["optimizer"]
        assert optimizer.param_groups[0]["lr"] == pytest.approx(lr)
    assert cli("pcrnet").model.hparams.identity_init is False
    assert cli("pcrnet_idinit").model.hparams.identity_init is True
    assert cli("fmr").model.hparams.pose_weight == 0 and cli("fmr_semi").model.hparams.pose_weight == 1.0
    hybrid = cli("fmr_tw100").model  # FMR-Net's own config and loss, plus selfsup_tw100's self-motion term
    tw100_terms = cli("selfsup_tw100").config["model"]["init_args"]["loss_terms"]
    assert cli("fmr_tw100").config["model"]["init_args"]["loss_terms"] == tw100_terms[-1:]
    assert type(hybrid).__name__ == "FMRNet" and hybrid.hparams.pose_weight == 0
    assert [(type(t).__name__, t.translation_weight, t.max_angle_deg) for t in hybrid.loss_terms] == [
        ("SelfMotionLoss", 100.0, 45.0)
    ]


def test_recipe_levers_change_only_their_self_motion_argument() -> None:
    """``recipe_with`` rebuilds the recipe's loss terms (LC as configs/lc.yaml, the self-motion term as
    configs/self_motion.yaml) and changes only the named argument."""
    module = load("learning_curves")

    def terms(variant: object) -> list[list[tuple[str, str, dict[str, object]]]]:
        """Every loss term's modules (LC's LocalConsistency included) with their public attributes."""
        model = build_cli_for(variant.method, variant.configs, {**synthetic_overrides(), **variant.overrides}).model
        return [
            [
                (name, type(m).__name__, {k: v for k, v in vars(m).items() if not k.startswith("_")})
                for name, m in term.named_modules()
            ]
            for term in model.loss_terms
        ]

    recipe = terms(module.VARIANTS["selfsup"])
    assert terms(module.recipe_with()) == recipe
    assert [term[0][1] for term in recipe] == ["LocalConsistencyLoss", "SelfMotionLoss"]
    assert recipe[0][1][1] == "LocalConsistency" and recipe[0][1][2]["num_local_points"] == 64
    levers = {f"selfsup_tw{w}": {"translation_weight": float(w)} for w in (25, 100, 400)}
    for name, changed in {**levers, "selfsup_frac50": {"sample_fraction": 0.5}}.items():
        lever = terms(module.VARIANTS[name])
        assert lever[0] == recipe[0]
        assert lever[1][0][2] == {**recipe[1][0][2], **changed} != recipe[1][0][2]
    fine = terms(module.VARIANTS["selfsup_tw100_fine"])  # selfsup_tw100 and a second term on small motions
    assert fine[:2] == terms(module.VARIANTS["selfsup_tw100"]) and fine[2][0][1] == "SelfMotionLoss"
    small = {"name": "self_motion_fine", "max_angle_deg": 2.0, "max_translation": 0.02, "translation_weight": 100.0}
    assert fine[2][0][2] == {**recipe[1][0][2], **small}


def test_report_joins_the_finished_runs_of_other_run_folders(tmp_path: Path) -> None:
    """``--also-runs``: a lever job's runs reported beside an earlier job's (committed copies: moved folders)."""
    module = load("learning_curves")
    first, other = tmp_path / "first", tmp_path / "other"
    module.main(["--smoke", "--run-dir", str(first)])  # model_D and selfsup, seed 0, a fixed 2-step budget
    rows = (first / "runs.jsonl").read_text().splitlines()
    assert len(rows) == 2 and '"model_D"' in rows[0] and '"selfsup"' in rows[1]
    (first / "runs.jsonl").write_text(rows[0] + "\n")
    other.mkdir()
    (other / "runs.jsonl").write_text(rows[1] + "\n")
    shutil.move(first / "selfsup", other / "selfsup")  # the recorded metrics path is gone: found under `other`
    out = tmp_path / "report.md"
    report = [
        "--report-only",
        "--steps",
        str(module.SMOKE["steps"]),
        "--seeds",
        "0",
        "--variants",
        "selfsup",
        "model_D",
    ]
    module.main([*report, "--run-dir", str(first), "--out", str(out)])
    assert "| selfsup |" not in out.read_text() and "| model_D |" in out.read_text()
    module.main([*report, "--run-dir", str(first), "--also-runs", str(other), "--out", str(out)])
    text = out.read_text()
    assert str(other) in text.splitlines()[0]
    # The header names the machine that trained the rows (a GPU's, for rows a lent GPU wrote), not the one writing it.
    assert f"; {machine_line('cpu')}: 2 runs; runs: " in text.splitlines()[0]
    assert text.index("| val/rre_mean_deg | selfsup |") < text.index(
        "| val/rre_mean_deg | model_D |"
    )  # --variants order


def test_a_converge_run_on_the_pose_monitor_selects_on_it_and_is_keyed_apart(tmp_path: Path) -> None:
    """``--monitor val/pose_clip_r2_t0p01``: checkpoints named and chosen on it; its rows do not count as the clip5
    rule's runs (the same variants and seed train again under the default monitor)."""
    module = load("learning_curves")
    common = ["--smoke", "--run-dir", str(tmp_path), "--patience", "2", "--val-pairs", "1"]
    pose = "converge p2 v1 mval/pose_clip_r2_t0p01"
    module.main([*common, "--monitor", "val/pose_clip_r2_t0p01"])
    rows = [json.loads(line) for line in (tmp_path / "runs.jsonl").read_text().splitlines()]
    assert [r["budget"] for r in rows] == [pose] * len(module.SMOKE["variants"])
    for row in rows:
        assert "val_pose_clip_r2_t0p01" in Path(row["best_checkpoint"]).name
        logged = Path(row["metrics_csv"]).read_text().splitlines()[0].split(",")
        assert "val/pose_clip_r2_t0p01" in logged and "val/rre_clip5_deg" in logged
    module.main(common)
    rows = [json.loads(line) for line in (tmp_path / "runs.jsonl").read_text().splitlines()]
    assert [r["budget"] for r in rows[2:]] == ["converge p2 v1"] * 2
    assert all("val_rre_clip5_deg" in Path(r["best_checkpoint"]).name for r in rows[2:])


def test_jobs_train_each_run_in_its_own_process_as_the_sequential_loop_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--jobs 2``: one worker process per unfinished (variant, seed), rows in the shared ``runs.jsonl``; a run's
    validation curve equals the one the in-process loop trains from the same seed; a rerun starts nothing."""
    module = load("learning_curves")
    # The workers inherit the environment: one torch thread, as this process (conftest), so that both sum in the same
    # order. With the machine's default (2 threads on a 2-core CPU) a curve differed in its 7th digit (session 22).
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    common = ["--root", "", "--points", "64", "--batch", "2", "--steps", "2", "--val-every", "1", "--seeds", "0"]
    parallel, sequential = tmp_path / "parallel", tmp_path / "sequential"
    module.main([*common, "--variants", "model_D", "selfsup", "--jobs", "2", "--run-dir", str(parallel)])
    started = [line for line in capsys.readouterr().out.splitlines() if ": started (" in line]
    assert sorted(line.split(":")[0] for line in started) == ["model_D seed 0", "selfsup seed 0"]
    rows = {r["variant"]: r for r in map(json.loads, (parallel / "runs.jsonl").read_text().splitlines())}
    assert sorted(rows) == ["model_D", "selfsup"] and all(r["stopped_step"] == 2 for r in rows.values())
    # Each worker records the device that trained it and its own peak memory (the GPU queue's step costs and memory).
    cpu = machine_line("cpu").split(", torch")[0]  # the worker's thread count is its own
    assert all(r["machine"].startswith(f"{cpu}, torch ") for r in rows.values())
    assert all(r["peak_mib"] is None or r["peak_mib"] > 0 for r in rows.values())
    assert (parallel / "selfsup" / "seed0" / "worker.log").is_file()
    module.main([*common, "--variants", "selfsup", "--run-dir", str(sequential)])
    (twin,) = map(json.loads, (sequential / "runs.jsonl").read_text().splitlines())

    def curve(row: dict[str, object]) -> list[str]:
        lines = Path(str(row["metrics_csv"])).read_text().splitlines()
        column = lines[0].split(",").index("val/rre_mean_deg")
        return [cells[column] for cells in (line.split(",") for line in lines[1:]) if cells[column]]

    assert len(curve(twin)) == 3 and curve(rows["selfsup"]) == curve(twin)  # steps 0, 1, 2
    module.main([*common, "--variants", "model_D", "selfsup", "--jobs", "2", "--run-dir", str(parallel)])
    assert ": started (" not in capsys.readouterr().out


def test_min_steps_resumes_an_early_stopped_run_to_its_floor_and_is_keyed_apart(tmp_path: Path) -> None:
    """``--min-steps``: a run that stopped early (patience 1) is not finished under the floor's key; the rerun
    resumes it from its ``last.ckpt`` (the same trajectory up to the stop) and trains on to the floor; a bad floor is
    refused."""
    module = load("learning_curves")
    common = ["--root", "", "--points", "64", "--batch", "2", "--steps", "8", "--val-every", "1", "--seeds", "0"]
    common += ["--variants", "model_D", "--run-dir", str(tmp_path), "--patience", "1"]
    module.main(common)
    module.main([*common, "--min-steps", "8"])
    early, floored = map(json.loads, (tmp_path / "runs.jsonl").read_text().splitlines())
    assert early["budget"] == "converge p1 v1" and early["early_stopped"] and early["stopped_step"] < 8
    assert floored["budget"] == "converge p1 v1 min8" and floored["stopped_step"] == 8
    assert not floored["early_stopped"] and floored["metrics_csv"] == early["metrics_csv"]  # one folder, resumed
    segments = sorted(Path(early["metrics_csv"]).parent.glob("metrics*.csv"))
    steps = {int(row.split(",")[1]) for path in segments for row in path.read_text().splitlines()[1:]}
    assert max(steps) >= 7 and len(segments) == 2  # the first run's file kept as a segment of the resumed curve
    for bad in (["--min-steps", "9"], ["--min-steps", "0"]):
        with pytest.raises(SystemExit):
            module.parse([*common, *bad])
    with pytest.raises(SystemExit):
        module.parse(["--smoke", "--min-steps", "2"])  # no --patience: a fixed budget has no early stop
