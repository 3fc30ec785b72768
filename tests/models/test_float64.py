"""float64 clouds (numpy's default) through every model, LC and the encoder (issue 14, defect 5).

Before the fix every neural model raised "mat1 and mat2 must have the same dtype" deep inside torch.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lcreg
from lcreg.nn.dtypes import module_dtype, to_module_dtype
from lcreg.types import RegistrationBatch

NEURAL = ["DVDs", "DCP", "PRNet", "IDAM", "DeepGMR", "PointNetLK", "FMRNet", "PCRNet"]


def _pair(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    src = torch.rand(2, 64, 3, generator=gen, dtype=torch.float64) - 0.5
    ref = src @ torch.tensor([[0.99, -0.14, 0.0], [0.14, 0.99, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64).T + 0.02
    return src.to(dtype), ref.to(dtype)


@pytest.mark.parametrize("name", [*NEURAL, "ICP"])
def test_float64_input_gives_float32_result_in_float64(name: str) -> None:
    torch.manual_seed(0)
    # IDAM's unit_scale would scale in each dtype first: an untrained IDAM turns that rounding into other matches.
    model = getattr(lcreg, name)(**({"unit_scale": None} if name == "IDAM" else {}))
    src64, ref64 = _pair(torch.float64)
    torch.manual_seed(1)  # PRNet samples (Gumbel) in eval mode
    out64 = model.register(src64, ref64).transform_ref_src
    torch.manual_seed(1)
    out32 = model.register(src64.float(), ref64.float()).transform_ref_src
    assert out64.dtype == torch.float64 and out32.dtype == torch.float32
    assert torch.isfinite(out64).all()
    tol = 1e-5 if name == "ICP" else 0.0  # ICP runs in the input's precision; the neural models compute in float32
    torch.testing.assert_close(out64, out32.double(), atol=tol, rtol=0.0)


@pytest.mark.parametrize("name", ["PointNetLK", "DCP"])
def test_direct_forward_accepts_float64(name: str) -> None:
    model = getattr(lcreg, name)().eval()
    src64, ref64 = _pair(torch.float64)
    with torch.no_grad():
        assert model(src64, ref64).transform_ref_src.dtype == torch.float64
        assert model(points_src=src64, points_ref=ref64).transform_ref_src.dtype == torch.float64


def test_double_model_runs_in_float64() -> None:
    model = lcreg.PointNetLK().double()
    src32, ref32 = _pair(torch.float32)
    out = model.register(src32, ref32)
    assert module_dtype(model) == torch.float64
    assert out.transform_ref_src.dtype == torch.float32  # the caller's dtype comes back
    out64 = model.register(src32.double(), ref32.double()).transform_ref_src
    torch.testing.assert_close(out.transform_ref_src.double(), out64, atol=1e-6, rtol=0.0)


def test_training_step_on_a_float64_batch() -> None:
    torch.manual_seed(0)
    model = lcreg.PointNetLK()
    src, ref = _pair(torch.float64)
    pose = torch.eye(4, dtype=torch.float64).expand(2, 4, 4).clone()
    batch = RegistrationBatch(src, ref, transform_ref_src=pose, index=torch.arange(2))
    loss = model.training_step(batch, 0)
    assert loss is not None and loss.dtype == torch.float32 and torch.isfinite(loss)
    loss.backward()


def test_numpy_float64_through_encoder_and_local_consistency() -> None:
    points = torch.from_numpy(np.random.default_rng(0).random((2, 512, 3)))  # float64
    encoder = lcreg.PointNetEncoder()
    feats = encoder(points)
    torch.testing.assert_close(feats, encoder(points.float()))
    lc = lcreg.LocalConsistency()
    value = lc(encoder, points, points + 0.01)
    assert torch.isfinite(value)
    torch.testing.assert_close(value, lc(encoder, points.float(), points.float() + 0.01))


def test_to_module_dtype_casts_floats_only() -> None:
    module = torch.nn.Linear(2, 2)
    value = {"a": torch.zeros(1, dtype=torch.float64), "b": (torch.zeros(1, dtype=torch.int64), "x")}
    cast = to_module_dtype(module, value)
    assert cast["a"].dtype == torch.float32 and cast["b"][0].dtype == torch.int64 and cast["b"][1] == "x"
    assert to_module_dtype(torch.nn.ReLU(), value)["a"].dtype == torch.float64  # no parameters: unchanged
