import pytest
import torch

from lcreg.experiments.benchmarking import report_table
from lcreg.experiments.evaluation import choose_start_angle, evaluate
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.metrics.functional import registration_recall
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch, RegistrationResult


class _Oracle(RegistrationModule):
    """Returns a fixed set of transforms (for exact metric checks)."""

    def __init__(self, transforms: torch.Tensor) -> None:
        super().__init__()
        self.transforms = transforms
        self.calls = 0

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        b = points_src.shape[0]
        out = self.transforms[self.calls : self.calls + b]
        self.calls += b
        return RegistrationResult(out, torch.ones(b, dtype=torch.bool), torch.full((b,), 3))


def _batches(gt: torch.Tensor, size: int) -> list[RegistrationBatch]:
    pts = torch.rand(gt.shape[0], 16, 3, generator=torch.Generator().manual_seed(0))
    return [RegistrationBatch(pts[i : i + size], pts[i : i + size], gt[i : i + size]) for i in range(0, len(gt), size)]


def test_evaluate_perfect_and_failed_estimates() -> None:
    gt, _ = random_euler_transform(6, generator=torch.Generator().manual_seed(1))
    pred = gt.clone()
    pred[5] = float("nan")  # one failed registration: counted, never dropped
    report = evaluate(_Oracle(pred), _batches(gt, 4), "oracle")
    assert report.num_pairs == 6 and report.extra["mean_iterations"] == 3
    assert report.metrics["recall_r2_t0p01"] == pytest.approx(5 / 6)
    assert report.metrics["rre_median_deg"] == pytest.approx(0.0, abs=1e-3)
    assert torch.isnan(report.rotation_error_deg[5]) and report.rotation_error_deg[:5].abs().max() < 1e-3
    table = report_table([report])
    assert "| oracle |" in table and "83.3 %" in table and table.count("\n") == 2


def test_evaluate_one_pair_keeps_per_pair_shapes() -> None:
    """One pair gives (1,) per-pair errors, not 0-d tensors (torchmetrics squeezes one-element results), so the
    recall of ``eval_scenes --data.init_args.num_test 1`` is computed, not a ShapeError."""
    gt, _ = random_euler_transform(1, generator=torch.Generator().manual_seed(2))
    report = evaluate(_Oracle(gt.clone()), _batches(gt, 1), "oracle")
    assert report.rotation_error_deg.shape == (1,) and report.translation_error.shape == (1,)
    assert float(registration_recall(report.rotation_error_deg, report.translation_error, 2.0, 0.01)) == 1.0


def test_evaluate_needs_ground_truth() -> None:
    batch = RegistrationBatch(torch.rand(1, 8, 3), torch.rand(1, 8, 3))
    with pytest.raises(ValueError, match="ground-truth"):
        evaluate(_Oracle(torch.eye(4)[None]), [batch], "x")


def test_mean_std_row_over_seeds() -> None:
    from lcreg.experiments.benchmarking import mean_std_row

    gt, _ = random_euler_transform(4, generator=torch.Generator().manual_seed(2))
    bad = gt.clone()
    bad[:2] = float("nan")
    reports = [evaluate(_Oracle(gt), _batches(gt, 4), "a"), evaluate(_Oracle(bad), _batches(gt, 4), "b")]
    row = mean_std_row(reports, "two seeds")
    # recall 100 % and 50 %: mean 75 %, sample std 35.4 %
    assert row.startswith("| two seeds |") and "75.0 ± 35 %" in row and row.endswith("| 4 |")


def test_choose_start_angle_takes_the_lowest_mean_rre_and_breaks_ties_towards_fewer_starts() -> None:
    # FMR-Net seed 0's 312 validation pairs (docs/results/converge/fmr_1024/test/seed0_goal_c.md): +-45 deg wins
    assert choose_start_angle({None: 1.587, 30.0: 0.504, 45.0: 0.474, 60.0: 1.352, 90.0: 2.088}) == 45.0
    assert choose_start_angle({60.0: 0.5, None: 0.5, 30.0: 0.5}) is None  # a tie keeps the single start
    assert choose_start_angle({90.0: 0.5, 30.0: 0.5, 45.0: 0.7}) == 30.0  # then the smaller angle
    assert choose_start_angle({None: 0.9, 30.0: 0.8}) == 30.0
    with pytest.raises(ValueError, match="empty"):
        choose_start_angle({})
    with pytest.raises(ValueError, match="finite"):
        choose_start_angle({None: 1.0, 30.0: float("nan")})
