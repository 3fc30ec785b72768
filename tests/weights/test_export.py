"""python -m lcreg.weights.export: slim files from Lightning checkpoints, size limit, metadata, model-card skeleton."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import lcreg.weights.export as export_module
from lcreg.checkpoints import CheckpointFormatError, CheckpointMismatchError, CheckpointNotFoundError
from lcreg.models.dvds import DVDs
from lcreg.weights import MAX_FILE_BYTES, PretrainedClassError, PretrainedSizeError, pretrained, read_weights
from lcreg.weights.export import (
    CARD_BEGIN,
    CARD_END,
    CARD_HEADINGS,
    main,
    parse_metadata,
    slim_payload,
    write_card,
)

from _weights_files import exported, lightning_checkpoint, tiny_model  # type: ignore[import-not-found]


def test_payload_holds_plain_data_and_default_metadata(tmp_path: Path) -> None:
    checkpoint = lightning_checkpoint(tiny_model("dvds"), tmp_path / "run" / "epoch003.ckpt")
    payload = slim_payload(checkpoint, "tiny", {"machine": "test box", "steps": 120})
    assert set(payload) == {"format", "name", "class_path", "init_args", "state_dict", "lcreg_version", "metadata"}
    assert payload["class_path"] == "lcreg.models.dvds.DVDs" and payload["format"] == 1
    assert payload["init_args"]["lambda_recon"] == 0.0 and payload["init_args"]["lambda_normal"] == 0.0
    assert "_class_path" not in payload["init_args"] and "optimizer" not in payload["init_args"]
    meta = payload["metadata"]
    assert meta["source_checkpoint"] == "epoch003.ckpt" and meta["global_step"] == 120 and meta["epoch"] == 3
    assert meta["data"] == "ModelNet40DataModule(root=modelnet40_mini, num_points=512)"  # no absolute paths
    assert meta["machine"] == "test box" and type(meta["torch_version"]) is str
    assert all(v.is_contiguous() and v.device.type == "cpu" for v in payload["state_dict"].values())


def test_exported_file_is_small_and_reads_back_weights_only(tmp_path: Path) -> None:
    path = exported(tiny_model("dvds"), tmp_path)
    content = torch.load(path, weights_only=True)  # plain data only
    assert set(content["state_dict"]) == {k for k in tiny_model("dvds").state_dict() if k.startswith("encoder.")}
    assert path.stat().st_size < 20_000


def test_full_size_dvds_and_pointnetlk_files_are_under_the_limit(tmp_path: Path) -> None:
    """The paper's encoder (64-64-64-128-1024); DVDs' decoder and normal head (~0.4 M parameters) are dropped."""
    from lcreg.baselines.pointnetlk import PointNetLK

    sizes = {}
    for model in (DVDs(batch_norm=False), PointNetLK()):
        path = exported(model, tmp_path, name=type(model).__name__.lower())
        sizes[path.name] = path.stat().st_size
        assert path.stat().st_size < MAX_FILE_BYTES
    assert 500_000 < sizes["dvds.pt"] < 700_000 and 500_000 < sizes["pointnetlk.pt"] < 700_000, sizes


def test_files_over_the_limit_are_refused_and_not_written(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(export_module, "MAX_FILE_BYTES", 4_000)
    with pytest.raises(
        PretrainedSizeError, match=r"exceeds the 0\.004 MB limit \(largest: encoder\.linears\.1\.weight"
    ):
        exported(tiny_model("dvds"), tmp_path)
    assert not list(tmp_path.glob("*.pt*"))


def test_checkpoint_errors_name_the_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(CheckpointNotFoundError):
        slim_payload(tmp_path / "absent.ckpt", "tiny")
    model = tiny_model("pointnetlk")
    bare = tmp_path / "bare.ckpt"
    torch.save({"state_dict": model.state_dict()}, bare)
    with pytest.raises(CheckpointFormatError, match=r"bare\.ckpt.*no 'hyper_parameters'"):
        slim_payload(bare, "tiny")
    nameless = lightning_checkpoint(model, tmp_path / "nameless.ckpt", hyper_parameters=dict(model.hparams))
    with pytest.raises(CheckpointFormatError, match="pass --class-path"):
        slim_payload(nameless, "tiny")
    assert slim_payload(nameless, "tiny", class_path="lcreg.baselines.pointnetlk.PointNetLK")["name"] == "tiny"
    other = lightning_checkpoint(model, tmp_path / "other.ckpt", state_dict=tiny_model("dvds").state_dict())
    with pytest.raises(CheckpointMismatchError, match=r"other\.ckpt.*does not fit PointNetLK: .*unexpected"):
        slim_payload(other, "tiny")
    with pytest.raises(PretrainedClassError, match="not a class of lcreg"):
        slim_payload(nameless, "tiny", class_path="collections.OrderedDict")
    with pytest.raises(ValueError, match="must match"):
        slim_payload(nameless, "../escape")


def test_existing_files_are_kept_unless_overwrite(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk", seed=1), tmp_path)
    with pytest.raises(FileExistsError, match="--overwrite"):
        exported(tiny_model("pointnetlk", seed=2), tmp_path)
    exported(tiny_model("pointnetlk", seed=2), tmp_path, overwrite=True)
    assert torch.equal(
        pretrained(path).encoder.linears[0].weight, tiny_model("pointnetlk", seed=2).encoder.linears[0].weight
    )


def test_parse_metadata_keeps_numbers_as_numbers() -> None:
    assert parse_metadata(["steps=300", "lr=1e-4", "machine=A100 x1", "command=lcreg fit --a=b"]) == {
        "steps": 300,
        "lr": 1e-4,
        "machine": "A100 x1",
        "command": "lcreg fit --a=b",
    }
    with pytest.raises(ValueError, match="key=value"):
        parse_metadata(["no-equals"])


# --- model card ----------------------------------------------------------------------------------------------------
def test_card_only_when_asked_then_refreshed_keeping_the_hand_written_text(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk", seed=1), tmp_path, name="pointnetlk-modelnet40")
    card = path.with_suffix(".md")
    assert not card.exists()  # not asked
    exported(tiny_model("pointnetlk", seed=1), tmp_path, name="pointnetlk-modelnet40", overwrite=True, card=True,
             metadata={"command": "lcreg fit --config x.yaml", "machine": "box"})  # fmt: skip
    text = card.read_text()
    assert [line[3:] for line in text.splitlines() if line.startswith("## ")] == list(CARD_HEADINGS)
    assert "| exact command | lcreg fit --config x.yaml |" in text and "| machine | box |" in text
    assert "| wall time | TODO |" in text and "| steps / epochs | 120 steps (epoch index 3) |" in text
    assert hashlib.sha256(path.read_bytes()).hexdigest() in text
    card.write_text(text.replace("| wall time | TODO |", "| wall time | 3 h |") + "\nHand-written note.\n")
    exported(tiny_model("pointnetlk", seed=2), tmp_path, name="pointnetlk-modelnet40", overwrite=True, card=True)
    refreshed = card.read_text()
    assert "| wall time | 3 h |" in refreshed and refreshed.endswith("Hand-written note.\n")
    assert hashlib.sha256(path.read_bytes()).hexdigest() in refreshed and refreshed.count(CARD_BEGIN) == 1
    assert refreshed.count(CARD_END) == 1


def test_a_card_without_the_export_block_is_never_overwritten(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk"), tmp_path)
    path.with_suffix(".md").write_text("# tiny\n\nWritten by hand.\n")
    with pytest.raises(ValueError, match="no export block"):
        write_card(path, torch.load(path, weights_only=True))
    assert path.with_suffix(".md").read_text() == "# tiny\n\nWritten by hand.\n"


# --- command line --------------------------------------------------------------------------------------------------
def test_main_writes_the_file_and_reports_errors_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    checkpoint = lightning_checkpoint(tiny_model("pointnetlk"), tmp_path / "last.ckpt")
    path = main([str(checkpoint), "--name", "tiny", "--out", str(tmp_path / "out"), "--metadata", "steps=5", "a=b"])
    assert "wrote" in capsys.readouterr().out and read_weights(path).metadata["steps"] == 5
    with pytest.raises(SystemExit) as info:
        main([str(checkpoint), "--name", "tiny", "--out", str(tmp_path / "out")])
    assert str(info.value).startswith("lcreg.weights.export: error: ") and "exists" in str(info.value)
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "absent.ckpt"), "--name", "tiny", "--out", str(tmp_path)])
    assert "absent.ckpt" in str(info.value) and "\n" not in str(info.value)


def test_module_runs_as_a_script() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "lcreg.weights.export", "--help"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and "--metadata" in proc.stdout and "--card" in proc.stdout


# --- re-export and inference settings ------------------------------------------------------------------------------
def test_init_args_replace_inference_settings_of_a_checkpoint(tmp_path: Path) -> None:
    checkpoint = lightning_checkpoint(tiny_model("pointnetlk"), tmp_path / "last.ckpt")
    path = export_module.export_weights(checkpoint, "tiny", tmp_path, init_args={"eval_iterations": 9})
    assert read_weights(path).init_args["eval_iterations"] == 9 and pretrained(path).eval_iterations == 9


def test_a_weights_file_is_re_exported_with_its_tensors_metadata_and_new_settings(tmp_path: Path) -> None:
    source = exported(tiny_model("dvds", seed=3), tmp_path / "first", metadata={"command": "lcreg fit x"})
    path = main([str(source), "--name", "again", "--out", str(tmp_path / "out"), "--init-args", "eval_iterations=20"])
    before, after = read_weights(source), read_weights(path)
    assert after.name == "again" and after.class_path == before.class_path
    assert after.init_args == {**before.init_args, "eval_iterations": 20}
    assert after.state_dict.keys() == before.state_dict.keys()
    assert all(torch.equal(after.state_dict[k], before.state_dict[k]) for k in before.state_dict)
    meta = after.metadata
    assert meta["command"] == "lcreg fit x" and meta["source_checkpoint"] == "tiny.ckpt"
    assert meta["source_weights"] == "tiny.pt" and meta["exported_utc"] >= before.metadata["exported_utc"]
    assert pretrained(path).eval_iterations == 20


def test_bad_init_args_and_other_classes_are_refused_in_one_line(tmp_path: Path) -> None:
    source = exported(tiny_model("pointnetlk"), tmp_path)
    for argv, message in [
        (["--init-args", "no_such_argument=1"], "refuses the hyper-parameters"),
        (["--init-args", "encoder_channels=[8, 8]"], "does not fit lcreg.baselines.pointnetlk.PointNetLK"),
        (["--init-args", "eval_iterations"], "key=value"),
        (["--init-args", "eval_iterations=[1"], "not a YAML value"),
        (["--class-path", "lcreg.models.dvds.DVDs"], "holds lcreg.baselines.pointnetlk.PointNetLK"),
    ]:
        with pytest.raises(SystemExit) as info:
            main([str(source), "--name", "again", "--out", str(tmp_path / "out"), *argv])
        assert message in str(info.value) and "\n" not in str(info.value), (argv, str(info.value))
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").glob("*.pt"))
