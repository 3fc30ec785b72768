"""The third-party example: LocalConsistency plugs into plain-PyTorch user code without Lightning."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch
from torch import Tensor

from lcreg import LocalConsistency

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "third_party_lc.py"
HEAVY = ("lightning", "pytorch_lightning", "lightning_fabric", "open3d", "wandb")

# Runs the example as __main__ from an unrelated folder, then reports which heavy packages got imported.
SCRIPT = f"""
import json, runpy, sys
from lcreg import LocalConsistency
after_import = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
sys.argv = [{str(EXAMPLE)!r}, "--steps", "4", "--num-points", "64", "--batch-size", "2", "--log-every", "2"]
runpy.run_path(sys.argv[0], run_name="__main__")
after_run = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
print(json.dumps({{"after_import": after_import, "after_run": after_run}}))
"""


@pytest.fixture(scope="module")
def example() -> ModuleType:
    spec = importlib.util.spec_from_file_location("third_party_lc", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_script_runs_in_a_clean_environment_without_lightning(tmp_path: Path) -> None:
    env = {key: os.environ[key] for key in ("PATH", "HOME", "SYSTEMROOT") if key in os.environ}
    env["OMP_NUM_THREADS"] = "1"
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    report = json.loads(lines[-1])
    assert report == {"after_import": [], "after_run": []}
    assert [line.split()[1] for line in lines if line.startswith("step")] == ["2", "4"]
    match = re.fullmatch(r"mean rotation error on held-out batch: (\S+) deg", lines[-2])
    assert match is not None, lines
    assert 0.0 <= float(match.group(1)) <= 180.0


def test_training_reduces_the_held_out_loss_and_reports_a_positive_lc(example: ModuleType) -> None:
    with_lc = example.train(steps=60, lc_weight=1.0, seed=0, num_points=64, batch_size=4)
    without = example.train(steps=60, lc_weight=0.0, seed=0, num_points=64, batch_size=4)
    for metrics in (with_lc, without):
        assert metrics["final_loss"] < 0.8 * metrics["initial_loss"], metrics
        assert metrics["rotation_error_deg"] < metrics["initial_rotation_error_deg"], metrics
    assert with_lc["initial_loss"] == without["initial_loss"]  # same seed, same initial model and held-out batch
    assert math.isfinite(with_lc["final_lc"]) and with_lc["final_lc"] > 0
    assert with_lc["final_loss"] != without["final_loss"]  # the LC term changed the optimisation
    assert without["final_lc"] is None


def test_lc_is_called_on_the_users_encoder_only_when_weighted(
    example: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[object, tuple[int, ...]]] = []

    class CountingLC(LocalConsistency):
        def forward(
            self, encoder: Callable[[Tensor], Tensor], points_src: Tensor, points_ref: Tensor | None = None
        ) -> Tensor:
            calls.append((encoder, tuple(points_src.shape)))
            return super().forward(encoder, points_src, points_ref)

    monkeypatch.setattr(example, "LocalConsistency", CountingLC)
    example.train(steps=3, lc_weight=0.0, seed=1, num_points=64, batch_size=2)
    assert calls == []
    example.train(steps=3, lc_weight=0.5, seed=1, num_points=64, batch_size=2)
    assert len(calls) == 4  # 3 training steps + the final held-out value
    assert all(isinstance(enc, example.PointEncoder) for enc, _ in calls)
    assert [shape for _, shape in calls] == [(2, 64, 3)] * 3 + [(16, 64, 3)]


def test_lc_alone_gives_the_users_encoder_a_gradient(example: ModuleType) -> None:
    torch.manual_seed(0)
    src, ref, _, _ = example.make_pairs(4, 128, torch.Generator().manual_seed(0))
    model = example.SoftProcrustesNet()
    lc = LocalConsistency(feature_dim=64, num_local_points=32)
    value = lc(model.encoder, src, ref)
    value.backward()
    assert torch.isfinite(value) and value > 0
    for name, param in model.encoder.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
        assert param.grad.abs().sum() > 0, name
    assert all(p.grad is None for p in lc.parameters())  # LC's metric layer is frozen by default


LIGHTNING_EXAMPLE = EXAMPLE.parent / "third_party_lightning_lc.py"


@pytest.mark.parametrize("lc_weight", [0.5, 0.0])
def test_lightning_example_adds_lc_through_the_mixin(lc_weight: float, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(LIGHTNING_EXAMPLE.parent))  # it imports the plain example's pieces
    spec = importlib.util.spec_from_file_location("third_party_lightning_lc", LIGHTNING_EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    metrics = module.main(["--steps", "3", "--num-points", "64", "--lc-weight", str(lc_weight)])
    assert 0.0 <= metrics["rotation_error_deg"] <= 180.0
    lc = metrics.get("train/lc_epoch", metrics.get("train/lc"))
    if lc_weight:
        assert lc is not None and math.isfinite(lc) and lc > 0  # the mixin logged (and added) the LC term
    else:
        assert lc is None
