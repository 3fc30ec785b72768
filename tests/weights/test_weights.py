"""lcreg.weights: pretrained weights by name or path, strict loading, typed one-line errors, the shipped files."""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import lcreg
import lcreg.weights as weights_module
from lcreg.baselines.pointnetlk import PointNetLK
from lcreg.checkpoints import (
    CheckpointError,
    CheckpointFormatError,
    CheckpointMismatchError,
    CheckpointNotFoundError,
    CheckpointReadError,
)
from lcreg.experiments.benchmarking import pair_batches
from lcreg.metrics.functional import registration_recall, rotation_error_deg, translation_error
from lcreg.models.base import RegistrationModule
from lcreg.models.dvds import DVDs
from lcreg.weights import (
    MAX_FILE_BYTES,
    REGISTRY,
    PretrainedBuildError,
    PretrainedClassError,
    PretrainedError,
    PretrainedFormatError,
    PretrainedMismatchError,
    PretrainedNotFoundError,
    PretrainedReadError,
    UnknownPretrainedError,
    load_into,
    pretrained,
    pretrained_names,
    read_weights,
    registered_names,
    resolve_class,
    shipped_names,
    training_only,
    weights_dir,
)
from lcreg.weights.export import CARD_BEGIN, CARD_END, CARD_HEADINGS

from _shared_data import shared_data  # type: ignore[import-not-found]
from _weights_files import exported, lightning_checkpoint, rewrite, tiny_model  # type: ignore[import-not-found]

REPO_ROOT = Path(__file__).resolve().parents[2]


def _clouds(seed: int = 1, n: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(3, n, 3, generator=g) - 0.5
    angle = torch.tensor(0.3)
    rot = torch.tensor([[angle.cos(), -angle.sin(), 0.0], [angle.sin(), angle.cos(), 0.0], [0.0, 0.0, 1.0]])
    return src, src @ rot.T + 0.05


# --- round trip ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["dvds", "pointnetlk", "fmr"])
def test_round_trip_gives_identical_outputs_and_only_inference_tensors(kind: str, tmp_path: Path) -> None:
    source = tiny_model(kind, seed=3).eval()
    path = exported(source, tmp_path)
    model = lcreg.pretrained(path)
    assert type(model) is type(source) and not model.training
    assert not any(m.training for m in model.modules())
    stored = read_weights(path).state_dict
    assert not [k for k in stored if k.startswith(("decoder", "normal_head", "loss_terms"))]
    inference = {k: v for k, v in source.state_dict().items() if k in stored}
    assert set(stored) == set(inference) and all(torch.equal(stored[k], v) for k, v in inference.items())
    src, ref = _clouds()
    expected, got = source.register(src, ref), model.register(src, ref)
    assert torch.equal(got.transform_ref_src, expected.transform_ref_src)
    assert torch.equal(got.num_iters, expected.num_iters)


def test_dvds_is_rebuilt_without_decoder_and_normal_head(tmp_path: Path) -> None:
    source = tiny_model("dvds")
    assert source.decoder is not None and source.normal_head is not None
    model = pretrained(str(exported(source, tmp_path)))
    assert isinstance(model, DVDs) and model.decoder is None and model.normal_head is None
    assert len(model.loss_terms) == 0  # components are never saved
    assert read_weights(tmp_path / "tiny.pt").init_args["lambda_recon"] == 0.0


def test_overrides_replace_init_args_and_training_only_modules_stay_initialised(tmp_path: Path) -> None:
    path = exported(tiny_model("dvds", seed=4), tmp_path)
    model = pretrained(path, eval_iterations=7, lambda_recon=0.5)
    assert model.eval_iterations == 7 and model.decoder is not None  # decoder built, left as initialised
    plain = pretrained(path)
    assert all(
        torch.equal(a, b) for a, b in zip(plain.encoder.state_dict().values(), model.encoder.state_dict().values())
    )
    with pytest.raises(PretrainedBuildError, match=r"refuses init_args \+ overrides \['no_such_arg'\]"):
        pretrained(path, no_such_arg=1)
    with pytest.raises(PretrainedMismatchError, match="shapes"):
        pretrained(path, encoder_channels=[16, 48])


def test_load_into_a_configured_model_keeps_its_training_only_modules(tmp_path: Path) -> None:
    path = exported(tiny_model("dvds", seed=5), tmp_path)
    configured = tiny_model("dvds", seed=6)  # decoder, normal head and LC term, other weights
    decoder_before = {k: v.clone() for k, v in configured.decoder.state_dict().items()}
    info = load_into(configured, path)
    assert info.path == path and info.metadata["global_step"] == 120
    assert all(
        torch.equal(v, read_weights(path).state_dict[f"encoder.{k}"])
        for k, v in configured.encoder.state_dict().items()
    )
    assert all(torch.equal(v, decoder_before[k]) for k, v in configured.decoder.state_dict().items())
    with pytest.raises(PretrainedClassError, match=r"holds lcreg\.models\.dvds\.DVDs weights, the configured model is"):
        load_into(tiny_model("pointnetlk"), path)


def test_loaded_weights_follow_the_model_to_its_device_and_dtype(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk", seed=2), tmp_path)
    model = tiny_model("pointnetlk", seed=9).double()
    load_into(model, path)
    assert all(p.dtype == torch.float64 for p in model.parameters())
    assert torch.equal(
        model.encoder.linears[0].weight.float(), read_weights(path).state_dict["encoder.linears.0.weight"]
    )


# --- strictness ----------------------------------------------------------------------------------------------------
def test_strict_loading_refuses_extra_missing_and_reshaped_tensors(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk"), tmp_path)
    state = read_weights(path).state_dict
    extra = rewrite(path, tmp_path / "extra.pt", state_dict={**state, "encoder.extra": torch.zeros(2)})
    missing = rewrite(
        path, tmp_path / "missing.pt", state_dict={k: v for k, v in state.items() if "linears.1" not in k}
    )
    reshaped = rewrite(path, tmp_path / "reshaped.pt", state_dict={**state, "encoder.linears.0.bias": torch.zeros(5)})
    cases = [
        (extra, "tensors the model lacks: encoder.extra"),
        (missing, "inference tensors missing from the file: encoder.linears.1.weight, encoder.linears.1.bias"),
        (reshaped, r"encoder\.linears\.0\.bias \(5,\) vs \(16,\)"),
    ]
    for file, message in cases:
        with pytest.raises(PretrainedMismatchError, match=message) as info:
            pretrained(file)
        assert isinstance(info.value, RuntimeError) and str(file) in str(info.value)
        assert "\n" not in str(info.value)


def test_another_architecture_is_a_mismatch_naming_the_class(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk"), tmp_path)
    other = PointNetLK(encoder_channels=[16, 16, 32])
    with pytest.raises(PretrainedMismatchError, match=r"does not fit lcreg\.baselines\.pointnetlk\.PointNetLK"):
        load_into(other, path)


def test_a_mismatch_names_the_constructor_arguments_that_differ(tmp_path: Path) -> None:
    path = exported(tiny_model("pointnetlk", batch_norm=False, jacobian="analytic"), tmp_path)
    configured = tiny_model("pointnetlk", batch_norm=True, jacobian="finite_difference")  # the config's defaults
    hint = r"built with batch_norm=False \(model: True\), jacobian='analytic' \(model: 'finite_difference'\)"
    with pytest.raises(PretrainedMismatchError, match=hint + r": configure these") as info:
        load_into(configured, path)
    assert "inference tensors missing from the file: encoder.norms" in str(info.value) and "\n" not in str(info.value)
    load_into(tiny_model("pointnetlk", batch_norm=False, jacobian="finite_difference"), path)  # tensors fit: loads


# --- errors --------------------------------------------------------------------------------------------------------
def test_unknown_name_lists_the_known_names() -> None:
    with pytest.raises(UnknownPretrainedError) as info:
        pretrained("dvds-imagenet")
    message = str(info.value)
    assert isinstance(info.value, KeyError) and isinstance(info.value, PretrainedError)
    assert message.startswith("pretrained weights 'dvds-imagenet': unknown name; known: ")
    assert all(name in message for name in REGISTRY) and "\n" not in message


def test_registered_name_without_its_file_and_missing_paths(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(weights_module, "weights_dir", lambda: tmp_path)
    with pytest.raises(PretrainedNotFoundError, match=r"'dvds-modelnet40': registered but not shipped .*none yet"):
        pretrained("dvds-modelnet40")
    for missing in (tmp_path / "absent.pt", str(tmp_path / "absent.pt"), "absent.pt"):
        with pytest.raises(PretrainedNotFoundError, match=r"absent\.pt': no such file") as info:
            pretrained(missing)
        assert isinstance(info.value, FileNotFoundError)


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_damaged_files_are_read_errors_naming_the_file(tmp_path: Path) -> None:
    good = exported(tiny_model("pointnetlk"), tmp_path)
    data = good.read_bytes()
    (tmp_path / "empty.pt").write_bytes(b"")
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "garbage.pt").write_bytes(b"\x80not a torch file" * 8)
    torch.save({"model": torch.nn.Linear(2, 2)}, tmp_path / "pickled.pt")  # needs full unpickling: refused
    for name, reason in [("empty", "empty file"), ("truncated", "not a readable"), ("garbage", "not a readable"),
                         ("pickled", "not a readable")]:  # fmt: skip
        with pytest.raises(PretrainedReadError, match=reason) as info:
            pretrained(tmp_path / f"{name}.pt")
        assert isinstance(info.value, ValueError) and f"{name}.pt" in str(info.value)
        assert "\n" not in str(info.value) and "\x1b" not in str(info.value)


def test_wrong_format_or_keys_are_format_errors(tmp_path: Path) -> None:
    good = exported(tiny_model("pointnetlk"), tmp_path)
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    torch.save({"state_dict": {}}, tmp_path / "lightning.pt")
    cases = {
        "tensor": "holds a Tensor, not a dict",
        "lightning": r"missing keys \['format', 'name', 'class_path'",
        "format2": "format 2 is not supported",
        "extra": r"unexpected keys \['optimizer_states'\]",
        "objects": "'init_args' must be a dict of plain values",
        "meta": "'metadata' must be a dict",
        "tensors": "'state_dict' must be a dict of str keys and tensors",
        "name": "'name' must be a string",
        "nan": r"tensor `encoder\.\S+` holds 1 NaN/Inf value\(s\)",
    }
    state = torch.load(good, weights_only=True)["state_dict"]
    first = next(k for k in state if k.startswith("encoder.") and state[k].is_floating_point())
    rewrite(
        good,
        tmp_path / "nan.pt",
        state_dict={
            **state,
            first: state[first].flatten().index_fill(0, torch.tensor([0]), float("nan")).view_as(state[first]),
        },
    )
    rewrite(good, tmp_path / "format2.pt", format=2)
    rewrite(good, tmp_path / "extra.pt", optimizer_states=[])
    rewrite(good, tmp_path / "objects.pt", init_args={"encoder_channels": torch.ones(2)})
    rewrite(good, tmp_path / "meta.pt", metadata={"steps": [1, 2]})
    rewrite(good, tmp_path / "tensors.pt", state_dict={"encoder.w": [1.0]})
    rewrite(good, tmp_path / "name.pt", name=3)
    for name, message in cases.items():
        with pytest.raises(PretrainedFormatError, match=message) as info:
            pretrained(tmp_path / f"{name}.pt")
        assert isinstance(info.value, ValueError) and f"{name}.pt" in str(info.value)


def test_class_path_must_be_an_lcreg_registration_module(tmp_path: Path) -> None:
    good = exported(tiny_model("pointnetlk"), tmp_path)
    cases = {
        "this.Zen": "is not a class of lcreg",  # importing `this` would print: never imported
        "lcreg.nn.pointnet.PointNetEncoder": "is not a RegistrationModule subclass",
        "lcreg.models.no_such_module.Model": "cannot be imported",
        "lcreg.models.dvds.NoSuchClass": "cannot be imported",
    }
    for index, (class_path, message) in enumerate(cases.items()):
        file = rewrite(good, tmp_path / f"class{index}.pt", class_path=class_path)
        with pytest.raises(PretrainedClassError, match=message) as info:
            pretrained(file)
        assert isinstance(info.value, TypeError) and f"class{index}.pt" in str(info.value)
    assert "this" not in sys.modules


def test_a_registered_name_must_hold_its_class_and_name(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(weights_module, "weights_dir", lambda: tmp_path)
    exported(tiny_model("pointnetlk"), tmp_path, name="dvds-modelnet40")  # a PointNetLK under the DVDs name
    with pytest.raises(PretrainedClassError, match=r"holds lcreg\.baselines\.pointnetlk\.PointNetLK, the registry"):
        pretrained("dvds-modelnet40")
    exported(tiny_model("pointnetlk"), tmp_path, name="other")
    (tmp_path / "other.pt").replace(tmp_path / "pointnetlk-modelnet40.pt")
    with pytest.raises(PretrainedFormatError, match="holds weights named 'other'"):
        pretrained("pointnetlk-modelnet40")
    assert shipped_names() == ["dvds-modelnet40", "pointnetlk-modelnet40"]


def test_a_registered_file_loads_by_name(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(weights_module, "weights_dir", lambda: tmp_path)
    source = tiny_model("pointnetlk", seed=8).eval()
    exported(source, tmp_path, name="pointnetlk-modelnet40")
    model = lcreg.pretrained("pointnetlk-modelnet40")
    src, ref = _clouds()
    assert torch.equal(model.register(src, ref).transform_ref_src, source.register(src, ref).transform_ref_src)


# --- public names and the registry ---------------------------------------------------------------------------------
def test_listing_names_stays_light() -> None:
    script = "import sys, lcreg; lcreg.pretrained_names(); print(sorted(m for m in sys.modules if 'lightning' in m))"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr


def test_lazy_exports_and_names() -> None:
    assert lcreg.pretrained is pretrained and lcreg.pretrained_names is pretrained_names
    assert registered_names() == sorted(REGISTRY) and {
        "dvds-modelnet40",
        "fmr-modelnet40",
        "pointnetlk-modelnet40",
    } <= set(REGISTRY)
    assert set(shipped_names()) <= set(REGISTRY)
    assert pretrained_names() == shipped_names()  # only what loads: a registered name without its file is left out


def test_pretrained_names_lists_only_what_loads(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(weights_module, "weights_dir", lambda: tmp_path)
    assert pretrained_names() == []
    exported(tiny_model("pointnetlk"), tmp_path, name="pointnetlk-modelnet40")
    assert pretrained_names() == ["pointnetlk-modelnet40"]
    for name in pretrained_names():
        lcreg.pretrained(name)


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_registry_classes_resolve(name: str) -> None:
    assert issubclass(resolve_class(REGISTRY[name].class_path), RegistrationModule)


def test_every_file_in_the_package_folder_is_registered() -> None:
    files = sorted(p.stem for p in weights_dir().glob("*.pt"))
    assert set(files) <= set(REGISTRY), f"unregistered weights files in {weights_dir()}: {set(files) - set(REGISTRY)}"
    cards = sorted(p.stem for p in weights_dir().glob("*.md"))
    assert cards == files, "every shipped .pt has a model card <name>.md and every card a file"


def test_the_wheel_ships_the_weights_and_cards() -> None:
    """hatchling puts every file of src/lcreg in the wheel; ``artifacts`` keeps the weights if a rule ignores them."""
    tomllib = pytest.importorskip("tomllib")
    config = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    wheel = config["tool"]["hatch"]["build"]["targets"]["wheel"]
    assert wheel["packages"] == ["src/lcreg"]
    assert {"src/lcreg/weights/*.pt", "src/lcreg/weights/*.md"} <= set(wheel["artifacts"])


def test_model_card_template_has_the_sections_of_the_export() -> None:
    text = (REPO_ROOT / "docs" / "model_card_template.md").read_text()
    assert tuple(re.findall(r"^## (.+)$", text, flags=re.M)) == CARD_HEADINGS
    assert CARD_BEGIN in text and CARD_END in text
    for field in ("exact command", "data and split", "steps / epochs", "wall time", "machine", "file size", "sha256"):
        assert f"| {field} |" in text, field


# --- the shipped files (parametrised over the registry: a name runs once its file ships) --------------------------
def _shipped(name: str) -> Path:
    if name not in shipped_names():
        pytest.skip(f"{name}: no weights shipped yet ({weights_dir() / f'{name}.pt'} absent)")
    return weights_dir() / f"{name}.pt"


@pytest.mark.parametrize("name", registered_names())
def test_shipped_file_is_slim_strict_and_matches_its_card(name: str) -> None:
    path = _shipped(name)
    data = path.read_bytes()
    assert len(data) <= MAX_FILE_BYTES
    weights = read_weights(name)
    assert weights.name == name and weights.class_path == REGISTRY[name].class_path
    model = pretrained(name)  # strict: no tensor left over, none missing
    assert {k for k in model.state_dict() if not training_only(model, k)} == set(weights.state_dict)
    card = path.with_suffix(".md").read_text()
    assert tuple(re.findall(r"^## (.+)$", card, flags=re.M)) == CARD_HEADINGS
    assert hashlib.sha256(data).hexdigest() in card and f"{len(data)} bytes" in card, "refresh the card: --card"


UNTRAINED_SEEDS = (0, 1, 2, 3, 4)


def _errors(model: RegistrationModule, batches: list) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[type-arg]
    """Rotation (degrees) and translation errors of ``model`` on every pair of ``batches``."""
    rre, rte = [], []
    for b in batches:
        transform = model.register(b.points_src, b.points_ref).transform_ref_src
        rre.append(rotation_error_deg(transform, b.transform_ref_src))
        rte.append(translation_error(transform, b.transform_ref_src))
    return torch.cat(rre), torch.cat(rte)


def _summary(rre: torch.Tensor, rte: torch.Tensor) -> dict[str, float]:
    """Mean and median RRE (degrees, lower is better) and recall at (2°, 0.01) (higher is better)."""
    recall = registration_recall(rre, rte, 2.0, 0.01)
    return {"mean RRE": float(rre.mean()), "median RRE": float(rre.median()), "recall (2°, 0.01)": float(recall)}


# Measured on this test (2-core CPU; docs/results/converge/*/test_table.md). dvds-modelnet40 (session 18: translation
# weight 100, seed 2, 40 iterations) is beyond the spread on all three: 1.61°, 0.457°, 76.2 % against 4.83 ± 3.2°,
# 0.672 ± 0.052°, 62.1 ± 8.4 % (on the mean by 0.02°; the session-7 file: 0.953°, 0.517°, 74.4 %).
# fmr-modelnet40 (session 28: fmr_1024 seed 2, analytic Jacobian, 20 iterations, one start) is on all three: 0.873°,
# 0.358°, 93.3 % against 4.60 ± 3.0°, 0.676 ± 0.059°, 62.0 ± 8.6 %.
# pointnetlk-modelnet40 (session 29: from FMR-Net's encoder, seed 2, analytic Jacobian, 40 iterations) is on all
# three: 1.434°, 0.377°, 95.7 % against 4.83 ± 3.2°, 0.672 ± 0.052°, 62.1 ± 8.4 % (the session-5 file was not on the
# mean, 1.721° against 4.595° - 2.961°, and was a strict xfail here). A file that is not beyond the spread on a metric
# goes here with that metric as the reason: strict, so that the mark must go once weights that pass ship.
NOT_YET_BEYOND_THE_SPREAD: dict[str, str] = {}


@pytest.mark.data
@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.xfail(reason=NOT_YET_BEYOND_THE_SPREAD[n], strict=True))
        if n in NOT_YET_BEYOND_THE_SPREAD
        else n
        for n in registered_names()
    ],
)
def test_shipped_weights_register_real_pairs_better_than_untrained_beyond_the_spread(name: str) -> None:
    """On all 164 real modelnet40_mini test pairs (1024 points), the shipped weights beat the same network
    untrained by more than the spread of 5 initialisations: mean and median RRE below (mean - std) of the untrained
    seeds', recall at (2°, 0.01) above (mean + std). Not the luckiest seed on a subset: the seeds' distribution."""
    _shipped(name)
    root = shared_data("modelnet40_mini")
    batches, _ = pair_batches(str(root), "test", num_points=1024, batch_size=41)
    assert sum(len(b.points_src) for b in batches) == 164
    trained = _summary(*_errors(pretrained(name), batches))
    weights = read_weights(name)
    cls = resolve_class(weights.class_path)
    seeds = []
    for seed in UNTRAINED_SEEDS:
        torch.manual_seed(seed)
        seeds.append(_summary(*_errors(cls(**weights.init_args), batches)))
    report, worse = [], []
    for stat, mine in trained.items():
        values = torch.tensor([s[stat] for s in seeds], dtype=torch.float64)
        mean, std = float(values.mean()), float(values.std())
        better = mine > mean + std if stat.startswith("recall") else mine < mean - std
        report.append(f"{stat}: {mine:.4g} trained, untrained {mean:.4g} ± {std:.4g} ({len(seeds)} seeds)")
        worse += [] if better else [stat]
    assert not worse, f"{name}: not beyond the spread on {worse}; " + "; ".join(report)


# --- one loader, one format, one error family ----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("pretrained_error", "checkpoint_error"),
    [
        (PretrainedNotFoundError, CheckpointNotFoundError),
        (PretrainedReadError, CheckpointReadError),
        (PretrainedFormatError, CheckpointFormatError),
        (PretrainedMismatchError, CheckpointMismatchError),
        (UnknownPretrainedError, CheckpointError),
        (PretrainedClassError, CheckpointError),
        (PretrainedBuildError, CheckpointError),
    ],
)
def test_weights_errors_are_one_family_rooted_at_checkpoint_error(
    pretrained_error: type[PretrainedError], checkpoint_error: type[CheckpointError]
) -> None:
    err = pretrained_error("w.pt", "reason", Path("w.pt"))
    assert isinstance(err, checkpoint_error) and isinstance(err, CheckpointError)
    assert str(err) == "pretrained weights 'w.pt': reason" and err.reason == "reason" and err.path == Path("w.pt")


def test_a_missing_exported_file_is_caught_as_a_missing_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(CheckpointNotFoundError, match=r"absent\.pt"):
        load_into(tiny_model("pointnetlk"), tmp_path / "absent.pt")


def test_one_loader_reads_a_lightning_checkpoint_like_its_export(tmp_path: Path) -> None:
    source = tiny_model("dvds", seed=3).eval()
    checkpoint = lightning_checkpoint(source, tmp_path / "run" / "best.ckpt")
    from_checkpoint = pretrained(checkpoint)
    from_export = pretrained(exported(source, tmp_path))
    assert type(from_checkpoint) is DVDs and from_checkpoint.decoder is None  # inference model, as exported
    src, ref = _clouds()
    with torch.no_grad():
        a = from_checkpoint.register(src, ref).transform_ref_src
        b = from_export.register(src, ref).transform_ref_src
    assert torch.equal(a, b)
    configured = tiny_model("dvds", seed=8)  # a .ckpt into a configured model: every tensor, the decoder's too
    load_into(configured, checkpoint)
    assert all(torch.equal(v, source.state_dict()[k]) for k, v in configured.state_dict().items())
    with pytest.raises(CheckpointMismatchError, match=r"best\.ckpt.*holds a lcreg\.models\.dvds\.DVDs model"):
        load_into(tiny_model("pointnetlk"), checkpoint)


def test_save_writes_the_exported_format_from_a_model_in_memory(tmp_path: Path) -> None:
    from lcreg.weights.export import save

    source = tiny_model("pointnetlk", seed=4).eval()
    path = save(source, tmp_path / "sub" / "mine.pt", metadata={"steps": 7})
    weights = read_weights(path)
    assert weights.name == "mine" and weights.metadata["steps"] == 7 and not list(tmp_path.glob("sub/*.partial"))
    assert set(weights.state_dict) == {k for k in source.state_dict() if not training_only(source, k)}
    src, ref = _clouds()
    with torch.no_grad():
        assert torch.equal(
            pretrained(path).register(src, ref).transform_ref_src, source.register(src, ref).transform_ref_src
        )
