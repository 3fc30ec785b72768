"""Every learned model under bfloat16 autocast (Lightning's ``bf16-mixed``): its networks in bfloat16, its
registration solves and metrics in float32 (:mod:`lcreg.geometry.precision`).

Before the fix every correspondence model raised "`points_ref` must be float32 or float64, got torch.bfloat16" from
its Procrustes head, and the IC-LK solves would have run their updates in bfloat16.
"""

from __future__ import annotations

import pytest
import torch

import lcreg
from lcreg.geometry import se3
from lcreg.types import RegistrationBatch

NEURAL = ["DVDs", "DCP", "PRNet", "IDAM", "DeepGMR", "PointNetLK", "FMRNet", "PCRNet"]
IC_LK = ["DVDs", "PointNetLK", "FMRNet"]  # the registration is the solve: all of it in float32


def _model(name: str) -> lcreg.RegistrationModule:
    torch.manual_seed(0)
    return getattr(lcreg, name)()


def _batch() -> RegistrationBatch:
    gen = torch.Generator().manual_seed(0)
    src = torch.rand(2, 64, 3, generator=gen) - 0.5
    angle = torch.tensor(0.14)
    rot = torch.tensor([[angle.cos(), -angle.sin(), 0.0], [angle.sin(), angle.cos(), 0.0], [0.0, 0.0, 1.0]])
    pose = se3.make_transform(rot.expand(2, 3, 3), torch.full((2, 3), 0.02))
    return RegistrationBatch(src, se3.transform_points(pose, src), transform_ref_src=pose, index=torch.arange(2))


@pytest.mark.parametrize("name", NEURAL)
def test_a_training_step_under_bfloat16_autocast_has_a_finite_float32_loss_and_gradients(name: str) -> None:
    model = _model(name).train()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = model.training_step(_batch(), 0)
    assert loss is not None and loss.dtype == torch.float32 and bool(torch.isfinite(loss))
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads)


@pytest.mark.parametrize("name", NEURAL)
def test_registration_under_autocast_is_a_float32_rigid_transform(name: str) -> None:
    batch = _batch()
    torch.manual_seed(1)  # PRNet samples (Gumbel) in eval mode
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = _model(name).register(batch.points_src, batch.points_ref).transform_ref_src
    assert out.dtype == torch.float32 and bool(torch.isfinite(out).all())
    rot = out[:, :3, :3]
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, torch.eye(3).expand(2, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(2), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", IC_LK)
def test_an_iclk_registration_is_the_same_with_and_without_autocast(name: str) -> None:
    batch = _batch()
    model = _model(name)
    plain = model.register(batch.points_src, batch.points_ref).transform_ref_src
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = model.register(batch.points_src, batch.points_ref).transform_ref_src
    assert torch.equal(plain, cast)


def test_validation_metrics_under_autocast_equal_the_float32_ones() -> None:
    """Lightning runs ``validation_step`` under autocast too: the errors must not be rounded to bfloat16."""
    batch = _batch()
    noisy = batch.transform_ref_src @ se3.exp(torch.tensor([[0.01, -0.02, 0.005, 0.001, 0.0, -0.002]] * 2))
    plain = lcreg.metrics.functional.rotation_error_deg(noisy, batch.transform_ref_src)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = lcreg.metrics.functional.rotation_error_deg(noisy, batch.transform_ref_src)
    assert torch.equal(plain, cast)


def test_local_consistency_under_autocast_is_computed_in_float32_from_the_descriptors() -> None:
    """The encoder pass runs in bfloat16; the metric, softmaxes and KL after it in float32."""
    batch = _batch()
    lc, encoder = lcreg.LocalConsistency(num_local_points=16), lcreg.PointNetEncoder(channels=(16, 32))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = lc(encoder, batch.points_src, batch.points_ref)
        subsets = torch.cat([*lc.subsets(batch.points_src), *lc.subsets(batch.points_ref)])  # X1, X2, W(X1), W(X2)
        feats = encoder(subsets)  # one pass, as LC's (BatchNorm sees the same batch)
    assert feats.dtype == torch.bfloat16 and cast.dtype == torch.float32
    assert torch.equal(cast, lc._symmetric_kl(feats.float()))


@pytest.mark.parametrize("half", [torch.bfloat16, torch.float16])
def test_a_half_precision_model_is_a_type_error_that_points_to_autocast(half: torch.dtype) -> None:
    """``bf16-true``/``16-true`` (or ``.half()``) would run the geometry in half precision: refused at the boundary."""
    batch = _batch()
    model = _model("DCP").to(half)
    with pytest.raises(TypeError, match="bf16-mixed"):
        model.register(batch.points_src, batch.points_ref)
    with pytest.raises(TypeError, match="bf16-mixed"):
        model.training_step(batch, 0)
