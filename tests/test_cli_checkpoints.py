"""`--ckpt_path` is checked before Lightning reads it: weights-only, one typed error naming the file, right class."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import torch

from lcreg.checkpoints import CheckpointError, CheckpointMismatchError
from lcreg.cli import main

from _cli_runs import TINY_DVDS, cli_isolation, config_args  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")

DVDS = config_args("models/dvds.yaml", "data/embedded.yaml")
PLAIN = [*TINY_DVDS, "--trainer.max_steps=1"]
DATA_ONLY = [arg for arg in PLAIN if not arg.startswith("--model.")]
SUBCOMMANDS = ("fit", "validate", "test", "predict")


@dataclass(frozen=True)
class Trained:
    dvds: Path  # a DVDs checkpoint without loss terms (the model of models/dvds.yaml)
    dvds_lc: Path  # a DVDs + LC (+ self-motion) checkpoint (configs/dvds.yaml); its frozen LC metric is not saved
    pointnetlk: Path


def _fit(root: Path, name: str, args: list[str]) -> Path:
    out = [f"--trainer.logger.init_args.save_dir={root}", f"--trainer.logger.init_args.name={name}"]
    main(["fit", *args, f"--trainer.default_root_dir={root}", *out])
    return root / name / "version_0" / "checkpoints" / "last.ckpt"


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Trained:
    """One-step fits of DVDs, DVDs + LC and a small PointNetLK on the embedded shapes."""
    root = tmp_path_factory.mktemp("fits")
    with cli_isolation(root):
        pointnetlk = config_args("models/pointnetlk.yaml", "data/embedded.yaml")
        return Trained(
            dvds=_fit(root, "dvds", [*DVDS, *PLAIN]),
            dvds_lc=_fit(root, "dvds_lc", [*config_args("dvds.yaml"), *PLAIN]),
            pointnetlk=_fit(root, "plk", [*pointnetlk, *DATA_ONLY, "--model.init_args.encoder_channels=[16,32]"]),
        )


@pytest.mark.parametrize("subcommand", SUBCOMMANDS)
def test_a_checkpoint_of_another_model_class_is_refused(trained: Trained, subcommand: str) -> None:
    """Before: `lcreg test` with the DVDs config and a PointNetLK checkpoint built and tested PointNetLK (exit 0)."""
    with pytest.raises(CheckpointMismatchError) as err:
        main([subcommand, *DVDS, *PLAIN, "--ckpt_path", str(trained.pointnetlk)])
    message = str(err.value)
    assert str(trained.pointnetlk) in message and "\n" not in message
    assert "lcreg.baselines.pointnetlk.PointNetLK" in message and "lcreg.models.dvds.DVDs" in message


def test_a_checkpoint_with_other_state_dict_keys_is_refused_naming_them(trained: Trained, tmp_path: Path) -> None:
    """Before: Lightning's strict load failed with a 40-line traceback ending in `Unexpected key(s) in state_dict`."""
    content = torch.load(trained.dvds, map_location="cpu", weights_only=True)
    content["state_dict"]["loss_terms.0.other.weight"] = torch.zeros(2, 2)  # a term the configured model lacks
    content["state_dict"]["loss_terms.0.other.bias"] = torch.zeros(2)
    torch.save(content, other := tmp_path / "other.ckpt")
    with pytest.raises(CheckpointMismatchError, match=r"has unexpected 2 keys \(loss_terms\.0\.other\.") as err:
        main(["test", *DVDS, *PLAIN, "--ckpt_path", str(other)])
    assert str(other) in str(err.value)


def test_an_lc_checkpoint_leaves_out_its_frozen_metric_and_older_ones_holding_it_still_load(
    trained: Trained, tmp_path: Path
) -> None:
    """The frozen LC metric is rebuilt from its seed, so checkpoints leave it out (8.4 MB of DVDs' 19.8 MB). A
    checkpoint written before holds it: Before the check learnt that, it was refused as having unexpected keys."""
    from lcreg.nn.local_consistency import LocalConsistency

    content = torch.load(trained.dvds_lc, map_location="cpu", weights_only=True)
    assert not any(".local_consistency.metric." in key for key in content["state_dict"])
    metric = LocalConsistency(feature_dim=32).metric  # TINY_DVDS's encoder width; configs/lc.yaml is term 0
    assert metric is not None
    for name, tensor in metric.state_dict().items():  # as a checkpoint of the earlier format holds it
        content["state_dict"][f"loss_terms.0.local_consistency.metric.{name}"] = tensor
    torch.save(content, older := tmp_path / "older.ckpt")
    out = f"--trainer.logger.init_args.save_dir={tmp_path}"
    main(["test", *config_args("dvds.yaml"), *PLAIN, "--ckpt_path", str(older), out])
    assert (tmp_path / "lcreg" / "version_0" / "test_per_pair.csv").is_file()


class _Payload:
    """Unpickling runs ``exec(code)``: a checkpoint that would run code."""

    def __init__(self, code: str) -> None:
        self.code = code

    def __reduce__(self) -> tuple[Any, ...]:
        return (exec, (self.code,))


def _damaged(kind: str, trained: Trained, directory: Path) -> Path:
    path = directory / f"{kind}.ckpt"
    if kind == "truncated":
        data = trained.dvds.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "random":
        noise = torch.randint(0, 256, (4096,), generator=torch.Generator().manual_seed(0))
        path.write_bytes(noise.byte().numpy().tobytes())
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "no_state_dict":
        torch.save({"epoch": 0, "global_step": 1}, path)
    elif kind == "nan_weight":  # a diverged run's state: before, `fit` went on into a raw LinAlgError
        content = torch.load(trained.dvds, map_location="cpu", weights_only=False)
        key = next(k for k, v in content["state_dict"].items() if v.is_floating_point() and v.numel() > 1)
        content["state_dict"][key].view(-1)[0] = float("inf")
        torch.save(content, path)
    return path


@pytest.mark.parametrize(
    ("kind", "reason"),
    [
        ("truncated", "not a readable weights-only torch file"),
        ("random", "not a torch.save file"),
        ("empty", "empty file"),
        ("no_state_dict", "no 'state_dict'"),
        ("nan_weight", r"tensor `\S+` holds 1 NaN/Inf value\(s\): take an earlier checkpoint"),
        ("missing", "no such file"),
    ],
)
def test_a_damaged_checkpoint_is_one_line_naming_the_file(
    trained: Trained, tmp_path: Path, kind: str, reason: str
) -> None:
    """Before: EOFError / UnpicklingError / KeyError: 'pytorch-lightning_version' tracebacks (or a silent fresh
    start for fit)."""
    path = _damaged(kind, trained, tmp_path)
    for subcommand in ("fit", "test"):
        with pytest.raises(CheckpointError, match=reason) as err:
            main([subcommand, *DVDS, *PLAIN, "--ckpt_path", str(path)])
        assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_checkpoint_that_would_run_code_is_refused_without_running_it(tmp_path: Path) -> None:
    live, marker = tmp_path / "live", tmp_path / "marker"
    torch.save(_Payload(f"open({str(live)!r}, 'w').close()"), tmp_path / "probe.ckpt")
    torch.load(tmp_path / "probe.ckpt", weights_only=False)
    assert live.is_file()  # the payload does run when fully unpickled
    evil = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "payload": _Payload(f"open({str(marker)!r}, 'w').close()")}, evil)
    for subcommand in SUBCOMMANDS:
        with pytest.raises(CheckpointError, match="not a readable weights-only torch file") as err:
            main([subcommand, *DVDS, *PLAIN, "--ckpt_path", str(evil)])
        assert str(evil) in str(err.value)
    assert not marker.exists()


def test_lightning_loads_the_checkpoint_weights_only(trained: Trained, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: Lightning's `trainer.test(ckpt_path=...)` got `weights_only=None` (a full unpickle for local files)."""
    from lightning.pytorch import Trainer

    calls: list[dict[str, Any]] = []

    @functools.wraps(Trainer.test)  # keeps the signature LightningCLI builds the `test` options from
    def record(self: Trainer, **kwargs: Any) -> None:
        calls.append(kwargs)

    monkeypatch.setattr(Trainer, "test", record)
    main(["test", *DVDS, *PLAIN, "--ckpt_path", str(trained.dvds)])
    assert calls[0]["weights_only"] is True and calls[0]["ckpt_path"] == str(trained.dvds)
    with pytest.raises(ValueError, match="weights-only"):
        main(["test", *DVDS, *PLAIN, "--ckpt_path", str(trained.dvds), "--weights_only=false"])


def test_a_matching_checkpoint_tests_end_to_end(trained: Trained, tmp_path: Path) -> None:
    """The checks pass a checkpoint of the configured model; Lightning's weights-only load reads every state."""
    main(["test", *DVDS, *PLAIN, "--ckpt_path", str(trained.dvds), f"--trainer.logger.init_args.save_dir={tmp_path}"])
    assert (tmp_path / "lcreg" / "version_0" / "test_per_pair.csv").is_file()


def test_the_recalls_asked_for_at_test_time_beat_the_checkpoints(trained: Trained, tmp_path: Path) -> None:
    """Before: a checkpoint of `lcreg fit` saves `recall_thresholds: null`, and its hyper-parameters override the
    command line's model arguments (LightningCLI's merge), so `--model.init_args.recall_thresholds` was dropped."""
    import csv

    content = torch.load(trained.dvds, map_location="cpu", weights_only=True)
    assert content["hyper_parameters"]["recall_thresholds"] is None
    del content["hyper_parameters"]["recall_thresholds"]  # a checkpoint written before the argument existed
    torch.save(content, tmp_path / "old.ckpt")
    for name, checkpoint in (("new", trained.dvds), ("old", tmp_path / "old.ckpt")):
        out = [f"--trainer.logger.init_args.save_dir={tmp_path}", f"--trainer.logger.init_args.name={name}"]
        recall = ["--model.init_args.recall_thresholds", "[[15, 0.3]]"]
        main(["test", *DVDS, *PLAIN, "--ckpt_path", str(checkpoint), *recall, *out])
        rows = list(csv.DictReader((tmp_path / name / "version_0" / "metrics.csv").open()))
        assert any(row.get("test/recall_r15_t0p3") for row in rows), name
