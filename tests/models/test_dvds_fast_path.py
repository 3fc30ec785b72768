"""The fast DVDs training step against its reference implementations (``lcreg.reference.reference_mode``).

One full step (``training_forward``, ``training_losses``, ``backward``) of a small DVDs model with the LC term, run
twice on the same weights and batch: the loss terms and every parameter gradient must agree. In float64 they agree
to rounding; in float32 to float32 tolerances (the two paths sum in different orders).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import torch

from lcreg.data.collate import collate_pairs
from lcreg.data.datamodule import PairDataset
from lcreg.data.pairs import PairProtocol
from lcreg.data.synthetic import synthetic_shapes
from lcreg.geometry import chamfer
from lcreg.models.dvds import DVDs
from lcreg.models.loss_terms import LocalConsistencyLoss
from lcreg.nn.folding import FoldingDecoder
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.nn.pointnet import PointNetEncoder
from lcreg.reference import reference_mode
from lcreg.types import RegistrationBatch

Grads = dict[str, torch.Tensor]


def _model(dtype: torch.dtype, batch_norm: bool = False, pairing: str = "target") -> DVDs:
    """Small DVDs + LC; the last encoder layer is wider than the hidden ones (as in the paper's 128 -> 1024)."""
    torch.manual_seed(0)
    lc = LocalConsistencyLoss(LocalConsistency(num_local_points=16, pairing=pairing))  # type: ignore[arg-type]
    model = DVDs(
        encoder_channels=(16, 32, 64),
        batch_norm=batch_norm,
        decoder_grid_size=8,
        decoder_hidden=(32, 32),
        normal_hidden=(16,),
        diagnostics_every_n_steps=0,
        loss_terms=[lc],
    )
    model.encoder.chunk_size = 48  # several chunks in the pooled arg-max search
    with torch.no_grad():
        # An untrained decoder outputs a blob ~1e-3 wide: its points then tie in float32 as nearest neighbours of the
        # input points, and the float64 k-d tree may pick another of the tied ones than the float32 distance matrix.
        # Spread it like a trained decoder's output so the float32 comparison measures rounding, not ties.
        model.decoder.fold2.rest[-1].weight.mul_(300.0)  # type: ignore[union-attr, index]
    return model.to(dtype).train()


def _batch(dtype: torch.dtype, num_points: int = 128, normals: bool = True) -> RegistrationBatch:
    points, shape_normals, _ = synthetic_shapes(4, 2 * num_points, seed=0)
    dataset = PairDataset(points, shape_normals, PairProtocol(num_points=num_points), deterministic=True, seed=0)
    batch = collate_pairs([dataset[i] for i in range(4)])
    floats = {f.name: getattr(batch, f.name) for f in dataclasses.fields(batch)}
    floats = {k: v.to(dtype) for k, v in floats.items() if isinstance(v, torch.Tensor) and v.is_floating_point()}
    batch = dataclasses.replace(batch, **{**floats, "transform_ref_src": None})
    return batch if normals else dataclasses.replace(batch, normals_src=None, normals_ref=None)


def _step(model: DVDs, batch: RegistrationBatch) -> tuple[dict[str, torch.Tensor], Grads]:
    model.zero_grad(set_to_none=True)
    losses = model.training_losses(model.training_forward(batch), batch)
    losses["loss"].backward()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return {name: value.detach() for name, value in losses.items()}, grads


def _assert_same_step(model: DVDs, batch: RegistrationBatch, rtol: float, grad_rtol: float) -> None:
    state = copy.deepcopy(model.state_dict())  # a training step updates BatchNorm's running statistics
    with reference_mode():
        loss_ref, grad_ref = _step(model, batch)
    model.load_state_dict(state)
    loss_fast, grad_fast = _step(model, batch)
    assert set(loss_fast) == set(loss_ref) == {"global", "recon", "normal", "lc", "loss"}
    for name, value in loss_ref.items():
        assert value > 0, name  # every term is exercised
        torch.testing.assert_close(loss_fast[name], value, rtol=rtol, atol=0, msg=name)
    assert set(grad_fast) == set(grad_ref)
    assert len(grad_ref) == sum(1 for p in model.parameters() if p.requires_grad)  # every trained parameter
    largest = max(float(grad.abs().max()) for grad in grad_ref.values())
    for name, grad in grad_ref.items():
        # Relative to the tensor's largest entry; a floor for gradients that vanish mathematically (the bias of a
        # linear layer followed by BatchNorm) and so are rounding noise in both paths.
        scale = max(float(grad.abs().max()), 1e-3 * largest)
        torch.testing.assert_close(grad_fast[name], grad, rtol=grad_rtol, atol=grad_rtol * scale, msg=name)


@pytest.mark.parametrize(
    ("dtype", "rtol", "grad_rtol"), [(torch.float64, 1e-10, 1e-9), (torch.float32, 1e-5, 1e-4)], ids=["f64", "f32"]
)
def test_fast_step_matches_the_reference(dtype: torch.dtype, rtol: float, grad_rtol: float) -> None:
    _assert_same_step(_model(dtype), _batch(dtype), rtol, grad_rtol)


@pytest.mark.parametrize(
    ("batch_norm", "normals", "pairing"),
    [(True, True, "target"), (False, False, "target"), (False, True, "estimate")],
    ids=["batch_norm", "estimated_normals", "lc_estimate_pairing"],
)
def test_fast_step_matches_the_reference_in_other_configurations(batch_norm: bool, normals: bool, pairing: str) -> None:
    _assert_same_step(_model(torch.float64, batch_norm, pairing), _batch(torch.float64, normals=normals), 1e-10, 1e-9)


def test_fast_step_matches_the_reference_for_clouds_of_different_sizes() -> None:
    batch = _batch(torch.float64)
    batch = dataclasses.replace(
        batch,
        points_ref=batch.points_ref[:, :100],
        normals_ref=batch.normals_ref[:, :100] if batch.normals_ref is not None else None,
    )
    _assert_same_step(_model(torch.float64), batch, 1e-10, 1e-9)


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, int]]:
    """Count the calls of every fast implementation and of its reference twin during one step."""
    counts: dict[str, int] = {}

    def spy(owner: Any, name: str) -> None:
        original: Callable[..., Any] = getattr(owner, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            counts[name] = counts.get(name, 0) + 1
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, wrapper)

    spy(PointNetEncoder, "_forward_train")
    spy(PointNetEncoder, "_forward_train_reference")
    spy(PointNetEncoder, "_twist_jacobian_reference")
    spy(FoldingDecoder, "_forward_reference")
    spy(chamfer, "_nearest_both_ways_kdtree")
    spy(chamfer, "_nearest_both_ways_dense")
    yield counts


def test_reference_mode_runs_only_the_reference_implementations(calls: dict[str, int]) -> None:
    model, batch = _model(torch.float32), _batch(torch.float32)
    with reference_mode():
        _step(model, batch)
    assert calls == {
        "_forward_train_reference": 2,  # the loss's pass and LC's pass
        "_twist_jacobian_reference": 1,
        "_forward_reference": 2,  # decoder, once per set
        "_nearest_both_ways_dense": 2,  # Chamfer, once per set
    }
    calls.clear()
    _step(model, batch)
    # LC's 16-point subsets take the dense encoder backward (below _SPARSE_MIN_POINTS).
    assert calls == {"_forward_train": 1, "_forward_train_reference": 1, "_nearest_both_ways_kdtree": 2}
