import pytest
import torch

from lcreg.nn.decoders import MLPDecoder


def test_decoder_shapes_range_and_layers() -> None:
    torch.manual_seed(0)
    decoder = MLPDecoder(32, (64, 16), num_points=50)
    out = decoder(torch.randn(4, 32) * 10)
    assert out.shape == (4, 50, 3)
    assert (out.abs() < 1).all()  # tanh
    linears = [m for m in decoder.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(32, 64), (64, 16), (16, 150)]
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in decoder.modules()) == 2


def test_decoder_is_per_item_in_eval_mode() -> None:
    torch.manual_seed(0)
    decoder = MLPDecoder(8, (16,), num_points=5).eval()
    code = torch.randn(3, 8)
    torch.testing.assert_close(decoder(code), torch.cat([decoder(c[None]) for c in code]))


def test_decoder_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="num_points"):
        MLPDecoder(8, (16,), num_points=0)
