"""``benchmarks/lc_gradient_share.py --adam-steps``: the trajectory comparison measures LC, not noise."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from test_smoke import load  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_the_adam_probe_repeats_exactly_and_only_lc_or_the_order_moves_the_trajectory() -> None:
    probe = load("lc_gradient_share")
    plain, with_lc, batches = probe._host_and_lc("dcp", None, 0)  # embedded shapes, the smoke budget
    start = probe._encoder_vector(plain)
    assert torch.equal(start, probe._encoder_vector(with_lc))  # the same initial encoder
    twin, reordered = copy.deepcopy(plain), copy.deepcopy(plain)
    moved = probe._train(plain, batches[:2], 0)
    assert not torch.equal(moved, start)
    assert torch.equal(probe._train(twin, batches[:2], 0), moved)  # same batches, same draws: the same weights
    assert not torch.equal(probe._train(with_lc, batches[:2], 0), moved)  # LC changes the steps
    assert not torch.equal(probe._train(reordered, batches[1::-1], 0), moved)  # so does the order (the control)
    led = probe.lc_led_share(probe._host_and_lc("dcp", None, 0)[1], batches[0], 0)
    assert 0.0 < led < 1.0


def test_shares_can_be_measured_with_a_checkpoints_weights(tmp_path: Path) -> None:
    """``--ckpt dcp=PATH``: the shares with the checkpoint's weights; the initial weights saved as a checkpoint give
    the initial shares exactly, other weights give other gradient norms."""
    from _weights_files import lightning_checkpoint  # type: ignore[import-not-found]

    probe = load("lc_gradient_share")
    initial = probe.batch_shares("dcp", None, 2, 0)
    model = probe.build("dcp_lc", None, values=probe._values("dcp", None, 0))
    same = lightning_checkpoint(model, tmp_path / "same.ckpt")
    assert probe.batch_shares("dcp", None, 2, 0, checkpoint=str(same)) == initial
    with torch.no_grad():
        for parameter in probe._encoder_params(model):
            parameter.mul_(1.5)
    moved = lightning_checkpoint(model, tmp_path / "moved.ckpt")
    other = probe.batch_shares("dcp", None, 2, 0, checkpoint=str(moved))
    assert [s.own_grad for s in other] != [s.own_grad for s in initial]
    args = probe.parse(["--smoke", "--ckpt", f"dcp={moved}"])
    assert args.checkpoints == [("dcp", str(moved))]
    with pytest.raises(SystemExit):
        probe.parse(["--smoke", "--ckpt", "nohost=x.ckpt"])
