"""The benchmark harness (lcreg.experiments.benchmarking): registry, build, checkpoints, timing bookkeeping, training,
writers."""

from __future__ import annotations

import itertools
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
import yaml
from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint

import lcreg
import lcreg.experiments.evaluation
from lcreg.cli import expand_configs
from lcreg.config import ConfigValueError
from lcreg.data.synthetic import PRIMITIVES
from lcreg.experiments.benchmarking import (
    CONVERGE_METRIC,
    DATA_CONFIGS,
    METHODS,
    REFINE_CONFIG,
    VOXELIZE_CONFIG,
    Budget,
    FitResult,
    ResultLog,
    build,
    cli_args,
    config_dir,
    config_path,
    config_values,
    converge_overrides,
    fit,
    fit_overrides,
    format_mean_std,
    key_values,
    last_checkpoint,
    markdown_table,
    method,
    method_layers,
    output_path,
    pair_batches,
    pair_batches_and_classes,
    peak_memory_mib,
    peak_rss_increase_mib,
    read_metrics,
    registration_speed,
    significant,
    synthetic_overrides,
    time_call,
    time_calls,
    timed,
    training_loss,
    voxelize_overrides,
)
from lcreg.experiments.evaluation import evaluate
from lcreg.methods import METHODS as LIBRARY_METHODS
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationResult
from lcreg.weights import training_only
from lcreg.weights.export import save

from _shared_data import shared_data  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")


def _lc_terms(num_local_points: int) -> list[dict]:
    """configs/lc.yaml's term with a smaller |X1|, as a ``model.init_args.loss_terms`` value."""
    lc = {
        "class_path": "lcreg.nn.local_consistency.LocalConsistency",
        "init_args": {"num_local_points": num_local_points},
    }
    return [{"class_path": "lcreg.models.loss_terms.LocalConsistencyLoss", "init_args": {"local_consistency": lc}}]


TINY_DVDS = cli_args(
    "model",
    {
        "encoder_channels": [8, 16],
        "loss_terms": _lc_terms(16),
        "decoder_grid_size": 4,
        "decoder_hidden": [8],
        "normal_hidden": [8],
        "diagnostics_every_n_steps": 0,
    },
)


class FakeClock:
    """A clock that advances by the given steps, one per reading."""

    def __init__(self, steps: list[float]) -> None:
        self.now = 0.0
        self.steps = iter(steps)

    def __call__(self) -> float:
        self.now += next(self.steps)
        return self.now


def _model_class(spec_configs: tuple[str, ...]) -> str:
    """The ``model.class_path`` of the last config of a method that has a model block."""
    files = expand_configs([arg for c in spec_configs for arg in ("--config", str(config_path(c)))])[1::2]
    paths = [(yaml.safe_load(Path(f).read_text()) or {}).get("model", {}).get("class_path") for f in files]
    return [p for p in paths if p][-1]


# --- registry ------------------------------------------------------------------------------------------------------
def test_every_registered_config_exists() -> None:
    assert config_dir().name == "configs" and config_dir().is_dir()
    for spec in METHODS.values():
        for name in spec.config_files():
            assert config_path(name).is_file()
    for name in (*DATA_CONFIGS.values(), REFINE_CONFIG, VOXELIZE_CONFIG):
        assert config_path(name).is_file()


def test_registry_links_point_to_registered_methods() -> None:
    for spec in METHODS.values():
        assert spec.weights_from in (None, *METHODS) and spec.lc_variant in (None, *METHODS)
        if spec.lc_variant:
            assert METHODS[spec.lc_variant].learned and spec.learned
    assert METHODS["ransac_icp"].config_files() == ("models/ransac.yaml", "data/modelnet40.yaml", REFINE_CONFIG)
    assert set(LIBRARY_METHODS) <= set(METHODS)  # every library method is benchmarked under its own name
    with pytest.raises(KeyError, match="unknown method 'nope'; known: dvds"):
        method("nope")
    with pytest.raises(FileNotFoundError, match=r"missing\.yaml"):
        config_path("missing.yaml")


@pytest.mark.parametrize("name", list(METHODS))
def test_build_without_checkpoint_gives_the_configured_class(name: str) -> None:
    model = build(name)
    module, _, cls = _model_class(METHODS[name].config_files()).rpartition(".")
    assert isinstance(model, RegistrationModule)
    assert type(model).__module__ == module and type(model).__name__ == cls
    assert model.has_loss == METHODS[name].learned
    library = LIBRARY_METHODS[METHODS[name].method]  # each row builds the library method it names
    assert f"{module}.{cls}" == library.class_path and library.learned == METHODS[name].learned


def test_build_passes_configs_and_values_like_lcreg_test() -> None:
    files, values = method_layers("dvds_icp", ["data/kitti.yaml"], {"seed_everything": 3})
    names = [path.relative_to(config_dir()).as_posix() for path in files]
    assert names == ["dvds_modelnet40.yaml", REFINE_CONFIG, "data/kitti.yaml"] and values == {"seed_everything": 3}
    _, dm = build("icp", values={"data.init_args.num_points": 512}, with_data=True)
    assert type(dm).__name__ == "ModelNet40DataModule" and dm.hparams.num_points == 512
    _, dm = build("icp", values=synthetic_overrides(pairs=3), with_data=True)
    assert type(dm).__name__ == "SyntheticDataModule" and dm.num_test == 3 and dm.hparams.num_workers == 0


def test_build_takes_typed_values_over_the_method_configs() -> None:
    model, dm = build("dvds", values={"data.init_args.num_points": 96}, with_data=True)
    assert f"{type(model).__module__}.{type(model).__name__}" == LIBRARY_METHODS["dvds"].class_path
    assert type(dm).__name__ == "ModelNet40DataModule" and dm.hparams.num_points == 96
    model = build("dvds", values={"model.init_args.encoder_channels": [8, 16], "model.init_args.batch_norm": False})
    assert model.hparams.encoder_channels == [8, 16] and model.hparams.batch_norm is False


def test_a_further_config_wins_over_the_method_values_it_sets(tmp_path: Path) -> None:
    # DCP's own value is its original batch size (32); a data add-on after it brings its own (KITTI: 1), as it did
    # when the method's value came before the add-on on the command line. An add-on that does not set it keeps 32.
    assert dict(METHODS["dcp"].overrides) == {"data.init_args.batch_size": 32}
    _, dm = build("dcp", with_data=True)
    assert dm.batch_size == 32
    _, dm = build("dcp", configs=["data/kitti.yaml"], with_data=True)
    assert type(dm).__name__ == "KITTIOdometryDataModule" and dm.batch_size == 1
    _, values = method_layers("dcp", ["data/kitti.yaml"])
    assert "data.init_args.batch_size" not in values
    points_only = tmp_path / "points.yaml"
    points_only.write_text("data:\n  init_args:\n    num_points: 96\n")
    _, dm = build("dcp", configs=[points_only], with_data=True)
    assert dm.batch_size == 32 and dm.hparams.num_points == 96
    composing = tmp_path / "composing.yaml"  # a composed file's keys count too
    (tmp_path / "batch.yaml").write_text("data:\n  init_args:\n    batch_size: 5\n")
    composing.write_text("compose: [batch.yaml]\n")
    _, dm = build("dcp", configs=[composing], with_data=True)
    assert dm.batch_size == 5
    caller = {"data.init_args.num_points": 512, "data.init_args.batch_size": 7}
    _, dm = build("dcp", configs=["data/kitti.yaml"], values=caller, with_data=True)
    assert dm.batch_size == 7  # the caller's values come last


def test_a_malformed_value_key_is_a_config_error() -> None:
    with pytest.raises(ConfigValueError, match=r"data\.\.batch_size"):
        build("icp", values={"data..batch_size": 2})
    for key in (".seed_everything", "trainer."):
        with pytest.raises(ConfigValueError, match="expected dotted names"):
            build("icp", values={key: 1})


def test_cli_args_are_values_by_dotted_key_without_none() -> None:
    values = {"a": 1, "b": None, "c": [1, 2], "d": True, "e": "x"}
    assert cli_args("model", values) == {
        "model.init_args.a": 1,
        "model.init_args.c": [1, 2],
        "model.init_args.d": True,
        "model.init_args.e": "x",
    }
    assert voxelize_overrides(normalize=False) == {"model.init_args.voxel_grid.init_args.normalize": False}
    assert synthetic_overrides(pairs=3)["data"]["class_path"] == "lcreg.data.datamodule.SyntheticDataModule"
    assert config_values(["--data.init_args.test_split=train", "--trainer.max_steps", "5", "--x.y="]) == {
        "data.init_args.test_split": "train",
        "trainer.max_steps": "5",
        "x.y": "",
    }
    for bad in (["data.x=1"], ["--x"], ["--x", "--y=1"]):
        with pytest.raises(SystemExit, match="--key=value"):
            config_values(bad)


# --- checkpoints ---------------------------------------------------------------------------------------------------
def test_build_loads_weights_of_the_one_format(tmp_path: Path) -> None:
    """A model saved by the harness is an exported weights file: build() and lcreg.pretrained read it alike."""
    source = build("dvds", values={"seed_everything": 1, **TINY_DVDS})
    path = save(source, tmp_path / "w" / "tiny.pt")
    target = build("dvds", path, values={"seed_everything": 2, **TINY_DVDS})
    inference = [k for k in source.state_dict() if not training_only(source, k)]
    shipped_like = lcreg.pretrained(path)
    assert inference and sorted(target.state_dict()) == sorted(shipped_like.state_dict()) == sorted(inference)
    assert all(torch.equal(source.state_dict()[k], target.state_dict()[k]) for k in inference)
    assert all(torch.equal(source.state_dict()[k], shipped_like.state_dict()[k]) for k in inference)
    # A training-only module the values ask for is built and left as initialised (seeded), not loaded.
    with_decoder = build("dvds", path, values={"seed_everything": 2, **TINY_DVDS, "model.init_args.lambda_recon": 0.5})
    assert all(torch.equal(source.state_dict()[k], with_decoder.state_dict()[k]) for k in inference)
    decoder = [k for k in with_decoder.state_dict() if k.startswith("decoder.")]
    assert decoder and any(not torch.equal(source.state_dict()[k], with_decoder.state_dict()[k]) for k in decoder)


@pytest.mark.parametrize(
    ("name", "weights", "settings"),
    [
        ("pointnetlk", "pointnetlk-modelnet40", {"jacobian": "analytic", "eval_iterations": 40}),
        ("fmr", "fmr-modelnet40", {"jacobian": "analytic", "eval_iterations": 20}),
        ("dvds", "dvds-modelnet40", {"eval_iterations": 40}),
    ],
)
def test_build_runs_shipped_weights_with_their_own_solve_as_lcreg_test_does(
    name: str, weights: str, settings: dict[str, object]
) -> None:
    """Session 64: build() took the config's solve for a shipped file (PointNetLK: finite differences, 20 steps)."""
    configured = build(name)
    assert any(configured.hparams[k] != v for k, v in settings.items())  # the config alone differs
    model = build(name, weights)
    assert {k: model.hparams[k] for k in settings} == settings
    points = torch.rand(2, 64, 3, generator=torch.Generator().manual_seed(0)) - 0.5
    moved = points @ torch.linalg.matrix_exp(torch.tensor([[0.0, -0.2, 0.1], [0.2, 0.0, -0.1], [-0.1, 0.1, 0.0]])).T
    expected = lcreg.pretrained(weights).register(points, moved).transform_ref_src  # as `lcreg test --weights`
    assert torch.allclose(model.register(points, moved).transform_ref_src, expected, atol=1e-6)
    given = build(name, weights, values=cli_args("model", {"eval_iterations": 3}))  # values given win
    assert given.hparams["eval_iterations"] == 3


def test_build_takes_a_checkpoints_own_model_arguments(tmp_path: Path) -> None:
    """A .ckpt of a run trained with a value the config does not have is built with that value, as --weights does."""
    run = fit_overrides(max_steps=1, val_every=1, run_dir=tmp_path, name="tiny", seed=0)
    trained = {**TINY_DVDS, "model.init_args.eval_iterations": 6}
    result = fit("dvds", {**run, **trained, **synthetic_overrides(pairs=2, num_points=32)})
    model = build("dvds", result.best_checkpoint, values=TINY_DVDS)
    assert model.hparams["eval_iterations"] == 6
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), result.model.state_dict().values()))
    assert (
        build("dvds", result.best_checkpoint, values=trained | {"model.init_args.eval_iterations": 2}).hparams[
            "eval_iterations"
        ]
        == 2
    )


def test_fit_returns_the_best_checkpoint_and_it_loads_weights_only(tmp_path: Path) -> None:
    run = fit_overrides(max_steps=2, val_every=1, run_dir=tmp_path, name="tiny", seed=0)
    result = fit("dvds", {**run, **TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32)})
    assert result.best_checkpoint.is_file() and "rre" in result.best_checkpoint.name
    assert result.best_checkpoint.is_relative_to(tmp_path / "tiny") and result.trainer.global_step == 2
    content = torch.load(result.best_checkpoint, map_location="cpu", weights_only=True)  # hparams are plain values
    assert "hyper_parameters" in content
    fresh = build("dvds", result.best_checkpoint, values=TINY_DVDS)  # a .ckpt: every tensor, training-only too
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), result.model.state_dict().values()))


def test_fit_refuses_a_config_that_does_not_select_on_validation_rre(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="val/rre_mean_deg"):
        fit("icp", fit_overrides(1, 1, tmp_path))


def test_converge_stops_after_patience_validations_without_improvement(tmp_path: Path) -> None:
    # min_delta 1000: no later validation counts as an improvement, so the run stops after 1 + patience checks.
    run = converge_overrides(max_steps=20, val_every=1, patience=2, run_dir=tmp_path, name="c", min_delta=1000.0)
    result = fit("dvds", {**run, **TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32)}, monitor=CONVERGE_METRIC)
    assert result.trainer.global_step == 3
    stop = [c for c in result.trainer.callbacks if isinstance(c, EarlyStopping)]
    best = [c for c in result.trainer.callbacks if isinstance(c, ModelCheckpoint)]
    assert len(stop) == 1 and stop[0].patience == 2 and stop[0].monitor == CONVERGE_METRIC
    assert stop[0].min_delta == -1000.0  # Lightning stores it signed by the mode ("min")
    assert len(best) == 1 and best[0].monitor == CONVERGE_METRIC and result.trainer.checkpoint_callback is best[0]
    assert "val_rre_clip5_deg" in result.best_checkpoint.name and result.best_checkpoint.is_file()
    with pytest.raises(ValueError, match="patience"):
        converge_overrides(10, 1, 0, tmp_path)
    with pytest.raises(ValueError, match=CONVERGE_METRIC):  # a plain run's checkpoint selects on the mean RRE
        fit(
            "dvds",
            {**fit_overrides(1, 1, tmp_path), **TINY_DVDS, **synthetic_overrides(2, 32)},
            monitor=CONVERGE_METRIC,
        )


def test_a_run_that_never_beats_its_starting_weights_selects_them(tmp_path: Path) -> None:
    # lr 0: every validation repeats the step-0 score, so no trained checkpoint beats the starting weights (a
    # pretrained encoder that training only spoils). They are selected, and patience counts from them.
    run = converge_overrides(max_steps=20, val_every=1, patience=2, run_dir=tmp_path, name="c")
    frozen = {"model.init_args.optimizer.init_args.lr": 0.0}
    values = {**run, **TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), **frozen}
    result = fit("dvds", values, validate_first=True, monitor=CONVERGE_METRIC)
    assert result.best_checkpoint.name.startswith("step000000-") and result.best_checkpoint.is_file()
    assert torch.load(result.best_checkpoint, map_location="cpu", weights_only=False)["global_step"] == 0
    assert result.trainer.global_step == 2  # two validations without a gain over step 0, not over step 1
    curve = read_metrics(Path(result.trainer.log_dir or "") / "metrics.csv")[CONVERGE_METRIC]
    assert len(set(curve.values)) == 1  # the frozen weights really score the same at every validation
    fresh = build("dvds", result.best_checkpoint, values={**TINY_DVDS, **frozen})
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), result.model.state_dict().values()))


def test_a_run_that_beats_its_starting_weights_drops_the_step0_checkpoint(tmp_path: Path) -> None:
    run = converge_overrides(max_steps=4, val_every=2, patience=50, run_dir=tmp_path, name="c")
    result = fit(
        "dvds", {**run, **TINY_DVDS, **synthetic_overrides(2, 32)}, validate_first=True, monitor=CONVERGE_METRIC
    )
    callback = result.trainer.checkpoint_callback
    assert isinstance(callback, ModelCheckpoint) and len(callback.best_k_models) == 1
    kept = sorted(p.name for p in result.best_checkpoint.parent.glob("step*.ckpt"))
    assert kept == [result.best_checkpoint.name]  # top-1: the step-0 file went when a better one came, or stayed
    curve = read_metrics(Path(result.trainer.log_dir or "") / "metrics.csv")[CONVERGE_METRIC]
    assert float(callback.best_model_score or 0) == pytest.approx(min(curve.values), rel=1e-5)


def test_converge_run_resumes_from_last_checkpoint_and_keeps_its_curve(tmp_path: Path) -> None:
    data = {**TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), "trainer.logger.init_args.version": "seed0"}

    def converge(steps: int) -> FitResult:
        run = converge_overrides(max_steps=steps, val_every=2, patience=50, run_dir=tmp_path, name="r")
        return fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)

    first = converge(2)
    log_dir = Path(first.trainer.log_dir or "")
    assert first.trainer.global_step == 2 and last_checkpoint(log_dir) is not None
    last = torch.load(log_dir / "checkpoints" / "last.ckpt", weights_only=False)
    first_clock = last["callbacks"]["TrainingClock"]["seconds"]
    second = converge(4)  # the same run, continued: steps 3 and 4 only
    assert second.trainer.global_step == 4 and Path(second.trainer.log_dir or "") == log_dir
    assert (log_dir / "metrics.segment1.csv").is_file()
    # The training clock rides in the checkpoint: the second segment's time adds to the first's.
    assert 0 < first_clock <= first.seconds
    assert second.seconds > first_clock and second.seconds - first_clock <= second.segment_seconds + 0.5
    curve = read_metrics(log_dir / "metrics.csv")["val/rre_clip5_deg"]
    # Untrained (step 0) and after 2 steps (logged at step 1) from the first segment, after 4 steps from the second.
    assert list(curve.steps) == [0, 1, 3]
    assert last_checkpoint(tmp_path / "nothing") is None


def test_a_run_resumed_at_its_cap_keeps_one_metrics_file(tmp_path: Path) -> None:
    # A finished run started again (a queue restarted after the run's last step, before its row) trains no step and
    # logs nothing: its metrics.csv stays as it was, not renamed to a segment that the next sync copies beside the
    # committed metrics.csv it duplicates.
    data = {**TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), "trainer.logger.init_args.version": "seed0"}
    run = converge_overrides(max_steps=2, val_every=2, patience=50, run_dir=tmp_path, name="r")
    first = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    log_dir = Path(first.trainer.log_dir or "")
    before = (log_dir / "metrics.csv").read_text(encoding="utf-8")
    again = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    assert again.trainer.global_step == 2
    assert sorted(p.name for p in log_dir.glob("metrics*.csv")) == ["metrics.csv"]
    assert (log_dir / "metrics.csv").read_text(encoding="utf-8") == before


def test_a_run_resumed_at_its_cap_is_tested_into_its_metrics_file(tmp_path: Path) -> None:
    # Session 56: a converge run cut off after its last step but before its row (e.g. in its test) resumed at its cap,
    # trained nothing, and its test then failed in Lightning's CSV writer ("dict contains fields not in fieldnames").
    data = {**TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), "trainer.logger.init_args.version": "seed0"}
    run = converge_overrides(max_steps=2, val_every=2, patience=50, run_dir=tmp_path, name="r")
    first = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    log_dir = Path(first.trainer.log_dir or "")
    before = read_metrics(log_dir / "metrics.csv")
    again = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    (tested,) = again.trainer.test(again.model, datamodule=again.datamodule, verbose=False)
    after = read_metrics(log_dir / "metrics.csv")
    assert sorted(p.name for p in log_dir.glob("metrics*.csv")) == ["metrics.csv"]
    old, new = before[CONVERGE_METRIC], after[CONVERGE_METRIC]
    assert (list(new.steps), list(new.values)) == (list(old.steps), list(old.values)) and len(old.steps) == 2
    assert list(after["test/rre_mean_deg"].values) == [pytest.approx(tested["test/rre_mean_deg"])]  # added


def test_a_run_started_again_sets_aside_the_curve_of_a_lost_run(tmp_path: Path) -> None:
    # A new machine restores a run's committed metrics files but not its checkpoints: the run starts from scratch,
    # and the lost run's rows must not be read as earlier segments of the new curve.
    data = {**TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), "trainer.logger.init_args.version": "seed0"}
    run = converge_overrides(max_steps=2, val_every=2, patience=50, run_dir=tmp_path, name="r")
    first = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    log_dir = Path(first.trainer.log_dir or "")
    lost = "epoch,step,val/rre_clip5_deg\n0,0,4.0\n0,9,3.0\n0,19,2.0\n"
    (log_dir / "metrics.segment1.csv").write_text(lost, encoding="utf-8")
    for path in (log_dir / "checkpoints").glob("*.ckpt"):
        path.unlink()
    again = fit("dvds", {**run, **data}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)
    assert again.trainer.global_step == 2
    assert list(read_metrics(log_dir / "metrics.csv")["val/rre_clip5_deg"].steps) == [0, 1]
    kept = log_dir / "abandoned" / "1"
    assert (kept / "metrics.segment1.csv").read_text(encoding="utf-8") == lost and (kept / "metrics.csv").is_file()


@pytest.mark.parametrize(
    ("key", "value"),
    [("model.init_args.optimizer.init_args.lr", 2.2e-4), ("data.init_args.noise_sigma", 0.01)],
)
def test_a_run_with_other_settings_starts_afresh_and_sets_the_unfinished_one_aside(
    tmp_path: Path, key: str, value: float
) -> None:
    # A sweep's run folder is named by its variant and seed, not its learning rate or crop: a run of changed settings
    # in the folder of an unfinished one silently continued that state (and was reported under the new settings).
    data = {**TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32), "trainer.logger.init_args.version": "seed0"}

    def converge(steps: int, changed: dict[str, float]) -> FitResult:
        run = converge_overrides(max_steps=steps, val_every=2, patience=50, run_dir=tmp_path, name="r")
        return fit("dvds", {**run, **data, **changed}, validate_first=True, monitor=CONVERGE_METRIC, resume=True)

    first = converge(2, {})
    log_dir = Path(first.trainer.log_dir or "")
    old_last = (log_dir / "checkpoints" / "last.ckpt").read_bytes()
    second = converge(4, {key: value})
    assert second.trainer.global_step == 4
    # From scratch: the new curve starts at its untrained step 0, in one file; the old run is kept, whole.
    assert list(read_metrics(log_dir / "metrics.csv")["val/rre_clip5_deg"].steps) == [0, 1, 3]
    assert not list(log_dir.glob("metrics.segment*.csv"))
    aside = log_dir / "superseded" / "1"
    assert (aside / "checkpoints" / "last.ckpt").read_bytes() == old_last
    assert (aside / "metrics.csv").is_file() and (aside / "config.yaml").is_file()
    third = converge(6, {key: value})  # the same settings again: it resumes (steps 5 and 6 only)
    assert third.trainer.global_step == 6 and (log_dir / "metrics.segment1.csv").is_file()


# --- timing --------------------------------------------------------------------------------------------------------
def test_timed_reads_the_clock_around_the_call() -> None:
    out, seconds = timed(lambda: "done", clock=FakeClock([10.0, 2.5]))
    assert out == "done" and seconds == 2.5


def test_time_call_drops_warmup_and_reports_the_median() -> None:
    # each call reads the clock twice: start (+1) and end (+duration)
    durations = [100.0, 3.0, 1.0, 2.0, 7.0]  # warm-up 100 is dropped
    clock = FakeClock(list(itertools.chain.from_iterable((1.0, d) for d in durations)))
    timing = time_call(lambda: None, repeats=4, warmup=1, clock=clock)
    assert timing.runs_s == (3.0, 1.0, 2.0, 7.0) and timing.median_s == 2.5
    with pytest.raises(ValueError, match="repeats"):
        time_call(lambda: None, repeats=0)


def test_time_calls_alternates_rounds() -> None:
    calls: list[str] = []
    fns: dict[str, Callable[[], object]] = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}
    clock = FakeClock([0.0, 1.0, 0.0, 5.0] * 3)
    timings = time_calls(fns, repeats=2, warmup=1, clock=clock)
    assert calls == ["a", "b"] * 3
    assert timings["a"].runs_s == (1.0, 1.0) and timings["b"].median_s == 5.0


class _Fixed(RegistrationModule):
    """Identity estimates with 4 iterations per pair."""

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        b = points_src.shape[0]
        return RegistrationResult(torch.eye(4).expand(b, 4, 4), torch.ones(b, dtype=torch.bool), torch.full((b,), 4))


def test_peak_rss_increase_sees_a_transient_allocation() -> None:
    def allocate() -> float:
        block = torch.ones(16 * 2**20 // 4)  # 16 MiB, freed on return
        return float(block.sum())

    result, mib = peak_rss_increase_mib(allocate)
    assert result == 16 * 2**20 // 4
    if mib is None:
        pytest.skip("no resettable high-water mark on this system (Linux /proc/self/clear_refs)")
    assert 15 <= mib < 200
    _, idle = peak_rss_increase_mib(lambda: None)
    assert idle is not None and idle < 15


def test_peak_memory_is_the_resident_increase_on_cpu_and_the_allocator_peak_on_cuda(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def allocate() -> float:
        block = torch.ones(16 * 2**20 // 4)  # 16 MiB, freed on return
        return float(block.sum())

    result, mib = peak_memory_mib(allocate, "cpu")
    assert result == 16 * 2**20 // 4 and (mib is None or 15 <= mib < 200)
    calls: list[str] = []  # CUDA, without a GPU: the peak is reset before the call and read after it
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda device: calls.append(f"reset {device}"))
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device: calls.append("read") or 3 * 2**20)
    result, mib = peak_memory_mib(lambda: calls.append("fn") or 7, "cuda:0")
    assert (result, mib, calls) == (7, 3.0, ["reset cuda:0", "fn", "read"])


def test_registration_speed_is_the_median_pass_per_pair() -> None:
    points = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(0))
    clock = FakeClock([0.0, 9.0, 0.0, 0.2, 0.0, 0.4, 0.0, 0.3])  # warm-up pass 9 s, then 0.2/0.4/0.3 s
    speed = registration_speed(_Fixed(), points, points, batch_size=3, repeats=3, clock=clock)
    assert speed.ms_per_pair == pytest.approx(1000 * 0.3 / 4) and speed.mean_iterations == 4.0


def test_evaluate_times_register_with_the_harness(monkeypatch: pytest.MonkeyPatch) -> None:
    batches, _ = pair_batches(None, pairs=3, num_points=16, batch_size=2)
    monkeypatch.setattr(lcreg.experiments.evaluation, "timed", lambda fn, device=None: (fn(), 0.5))
    report = evaluate(_Fixed(), batches, "fixed")
    assert report.num_pairs == 3 and report.ms_per_pair == pytest.approx(1000 * 2 * 0.5 / 3)


# --- data and training ---------------------------------------------------------------------------------------------
def test_pair_batches_keep_the_first_pairs() -> None:
    batches, source = pair_batches(None, pairs=3, num_points=16, batch_size=2)
    assert source == "embedded synthetic shapes" and [len(b) for b in batches] == [2, 1]
    assert batches[1].points_src.shape == (1, 16, 3) and batches[1].transform_ref_src.shape == (1, 4, 4)
    val, _ = pair_batches(None, "val", pairs=2, num_points=16, batch_size=4)
    assert [len(b) for b in val] == [2]


def test_pair_classes_follow_the_pairs_of_a_labelled_split() -> None:
    # Synthetic: a shape's class is the kind of its first primitive, one per pair, in pair order.
    batches, _, classes = pair_batches_and_classes(None, pairs=3, num_points=16, batch_size=2)
    assert classes is not None and len(classes) == sum(len(b) for b in batches) == 3
    assert set(classes) <= set(PRIMITIVES)


def test_modelnet40_pair_classes_are_of_object_k_mod_the_objects() -> None:
    # Pair k of the 312 validation pairs is object k mod 78 (session 21 read DVDs' failures by class).
    root = shared_data("modelnet40_mini")
    val, _, names = pair_batches_and_classes(str(root), "val", num_points=64, batch_size=16, val_pairs_per_object=4)
    assert names is not None and len(names) == sum(len(b) for b in val) == 312
    assert names[75] == names[153] == names[231] == names[309] == "bowl" and names[184] == "airplane"


def test_training_loss_includes_injected_local_consistency() -> None:
    model = build(
        "dcp_lc", values=cli_args("model", {"emb_dims": 16, "ff_dims": 16, "k": 4, "loss_terms": _lc_terms(8)})
    )
    batch = pair_batches(None, pairs=2, num_points=32, batch_size=2)[0][0]
    torch.manual_seed(0)
    losses = training_loss(model.train(), batch)
    torch.manual_seed(0)
    host_only = model._compute_loss(model.training_forward(batch), batch)  # what the pilot regression measured
    assert "lc" in losses and "lc" not in host_only
    total = host_only["loss"] + losses["lc"]
    assert float(losses["loss"].detach()) == pytest.approx(float(total.detach()), rel=1e-5)


def test_fit_overrides_set_a_step_budget() -> None:
    values = fit_overrides(max_steps=8, val_every=2, run_dir="runs/x", name="n", seed=5)
    assert values["trainer.max_steps"] == 8 and values["trainer.val_check_interval"] == 2
    assert values["trainer.check_val_every_n_epoch"] is None and values["trainer.enable_progress_bar"] is False
    assert values["seed_everything"] == 5 and values["trainer.logger.init_args.name"] == "n"


# --- writers and options -------------------------------------------------------------------------------------------
def test_markdown_table_format() -> None:
    assert markdown_table(["a", "b"], [[1, "x"], [2.5, None]]) == "| a | b |\n|---|---|\n| 1 | x |\n| 2.5 | None |"
    assert markdown_table(["a"]) == "| a |\n|---|"
    assert markdown_table(["|X1|"], [["|X1| = 64"]]).splitlines()[-1] == "| \\|X1\\| = 64 |"  # pipes in cells escaped


def test_format_mean_std() -> None:
    # Session 53: a mean of 2.00 was printed "2" (``.3g``), as if known to one digit.
    assert format_mean_std([1.0, 3.0]) == "2.00 ± 1.4"
    assert format_mean_std([0.99, 1.01, 1.0], digits=4) == "1.000 ± 0.010"
    assert format_mean_std([1234.0, 1236.0]) == "1240 ± 1.4"  # fixed point, not 1.24e+03
    assert format_mean_std([0.5], ".1f", ".1f", scale=100.0) == "50.0 ± 0.0"
    # The IDAM bf16 seeds' RMSE(R): a spread of 1.02 was printed "± 1", as if known to one digit.
    assert format_mean_std([5.259, 5.827, 3.841]) == "4.98 ± 1.0"
    assert format_mean_std([2.0]) == "2.00 ± 0"
    assert format_mean_std([2.0], ".3g") == "2 ± 0"  # an explicit format is kept


@pytest.mark.parametrize("digits", [1, 2, 3])
def test_significant_rounds_as_format_and_keeps_its_digits(digits: int) -> None:
    """Numerically `.{digits}g` rounding, in fixed point with exactly ``digits`` significant digits."""
    exponents = torch.empty(400, dtype=torch.float64).uniform_(-6, 4, generator=torch.Generator().manual_seed(0))
    values = torch.cat([10**exponents, torch.tensor([0.996, 9.96, 99.6], dtype=torch.float64)])
    for value in [*values.tolist(), *(-values).tolist()]:
        text = significant(value, digits)
        assert "e" not in text and float(text) == pytest.approx(float(f"{value:.{digits}g}"), rel=1e-12), value
        assert len(text.lstrip("-").replace(".", "").lstrip("0")) == digits or (text.endswith("0") and "." not in text)
    assert [significant(v) for v in (1.02, 0.1, 0.0039, 123.4, 0.996, 0.0, -1.02)] == [
        "1.0",
        "0.10",
        "0.0039",
        "120",
        "1.0",
        "0",
        "-1.0",
    ]


def test_result_log_resume_skips_finished_rows(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "results.jsonl"
    log = ResultLog(path, key=("key", "setting"))
    assert log.rows == [] and not log.done(key="a", setting="clean")
    log.append({"key": "a", "setting": "clean", "value": 1})
    log.append({"key": "a", "setting": "noisy", "value": 2})
    with path.open("a") as fh:
        fh.write("\n")  # a blank line (e.g. an editor's) is ignored
    again = ResultLog(path, key=("key", "setting"))
    assert again.done(key="a", setting="clean") and not again.done(key="b", setting="clean")
    assert again.find(key="a", setting="noisy") == {"key": "a", "setting": "noisy", "value": 2}
    assert len(path.read_text().splitlines()) == 3


def test_output_path_and_options(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    assert output_path("x.md", "y.md", smoke=True) == Path("x.md")
    assert output_path(None, "y.md", smoke=False) is None
    smoke = output_path(None, "y.md", smoke=True)
    assert smoke is not None and smoke.name == "y.md" and smoke.parent.is_dir() and smoke.parent.parent == tmp_path
    assert key_values(["a=1", "b=x=y"], "--ckpt") == {"a": "1", "b": "x=y"}
    with pytest.raises(SystemExit, match="--ckpt expects key=value"):
        key_values(["a"], "--ckpt")
    assert Budget.parse("200,512,16") == Budget(200, 512, 16) and str(Budget(1, 2, 3)) == "1,2,3"
    with pytest.raises(SystemExit, match="steps,points,batch"):
        Budget.parse("200,512")


def test_a_run_stopped_by_sigterm_exits_143_not_0(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Lightning ends ``fit`` on SIGTERM with a SystemExit of code None (exit status 0): a queue took a killed job for
    a finished one. ``fit`` exits with TERMINATED_EXIT_CODE instead."""
    from lightning.pytorch import LightningModule
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from lcreg.experiments.benchmarking import TERMINATED_EXIT_CODE

    def terminated(*_: object, **__: object) -> None:
        raise SIGTERMException  # what Lightning raises once its SIGTERM handler has run

    monkeypatch.setattr(LightningModule, "on_train_batch_end", terminated)
    run = fit_overrides(max_steps=4, val_every=2, run_dir=tmp_path, name="killed", seed=0)
    with pytest.raises(SystemExit) as stop:
        fit("dvds", {**run, **TINY_DVDS, **synthetic_overrides(pairs=2, num_points=32)})
    assert stop.value.code == TERMINATED_EXIT_CODE == 143
    assert isinstance(stop.value.__cause__, SIGTERMException) and stop.value.__cause__.code is None
