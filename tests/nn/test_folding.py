from __future__ import annotations

import pytest
import torch

from lcreg.nn.folding import FoldingDecoder
from lcreg.reference import reference_mode


def test_output_shape_grid_and_dtype(dtype: torch.dtype) -> None:
    torch.manual_seed(0)
    decoder = FoldingDecoder(feature_dim=16, grid_size=5, hidden=(32,), grid_extent=0.5).to(dtype)
    assert decoder.num_points == 25
    assert decoder.grid.shape == (25, 2)
    assert decoder.grid.min() == pytest.approx(-0.5) and decoder.grid.max() == pytest.approx(0.5)
    assert len(torch.unique(decoder.grid[:, 0])) == 5 and len(torch.unique(decoder.grid[:, 1])) == 5
    assert "grid" not in decoder.state_dict()  # rebuilt from the arguments, not checkpointed
    out = decoder(torch.randn(3, 16, dtype=dtype))
    assert out.shape == (3, 25, 3) and out.dtype == dtype and torch.isfinite(out).all()


def test_two_folds_conditioned_on_the_code() -> None:
    torch.manual_seed(0)
    decoder = FoldingDecoder(feature_dim=8, grid_size=4, hidden=(16, 16))
    code = torch.randn(2, 8)
    grid = decoder.grid.expand(2, -1, -1)
    expected = decoder.fold2(decoder.fold1(grid, code), code)
    torch.testing.assert_close(decoder(code), expected)
    # Different codewords decode to different clouds; the same code gives the same cloud.
    out = decoder(torch.stack([code[0], code[1], code[0]]))
    assert not torch.allclose(out[0], out[1])
    torch.testing.assert_close(out[0], out[2])


def test_gradients_flow_to_code_and_parameters() -> None:
    torch.manual_seed(0)
    decoder = FoldingDecoder(feature_dim=8, grid_size=3, hidden=(16,))
    code = torch.randn(2, 8, requires_grad=True)
    decoder(code).square().sum().backward()
    assert code.grad is not None and code.grad.abs().sum() > 0
    for name, param in decoder.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
        assert param.grad.abs().sum() > 0, name


def test_shared_grid_forward_matches_the_reference(dtype: torch.dtype) -> None:
    """The grid term computed once for all codewords: same points and gradients as the per-codeword grid copies."""
    torch.manual_seed(0)
    decoder = FoldingDecoder(feature_dim=8, grid_size=4, hidden=(16, 16)).to(dtype)
    code0 = torch.randn(3, 8, dtype=dtype)
    outputs = []
    for reference in (True, False):
        decoder.zero_grad()
        code = code0.clone().requires_grad_(True)
        if reference:
            with reference_mode():
                out = decoder(code)
        else:
            out = decoder(code)
        (out * torch.linspace(-1, 1, out.numel(), dtype=dtype).reshape(out.shape)).sum().backward()
        outputs.append([out.detach(), code.grad, *(p.grad for p in decoder.parameters())])
    for ref, fast in zip(*outputs, strict=True):
        torch.testing.assert_close(fast, ref)


def test_invalid_grid_size() -> None:
    with pytest.raises(ValueError, match="grid_size"):
        FoldingDecoder(feature_dim=8, grid_size=1)
