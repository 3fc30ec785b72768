import math

import pytest
import torch

from lcreg.baselines.classical import ICP
from lcreg.data.pairs import PairProtocol, make_pair
from lcreg.data.synthetic import synthetic_shapes
from lcreg.metrics.functional import rotation_error_deg, translation_error

from _shared_data import shared_data  # type: ignore[import-not-found]

pytest.importorskip("open3d")


def _pair(points: torch.Tensor, normals: torch.Tensor | None, angle: float, seed: int = 0) -> dict[str, torch.Tensor]:
    protocol = PairProtocol(num_points=1024, max_angle_deg=angle, max_translation=0.1, independent_sampling=False)
    return make_pair(points, normals, protocol, torch.Generator().manual_seed(seed))


def _errors(model: ICP, pair: dict[str, torch.Tensor]) -> tuple[float, float]:
    result = model.register(pair["points_src"][None], pair["points_ref"][None])
    gt = pair["transform_ref_src"][None]
    return float(rotation_error_deg(result.transform_ref_src, gt)), float(
        translation_error(result.transform_ref_src, gt)
    )


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_icp_recovers_a_small_known_transform_on_a_synthetic_shape(method: str) -> None:
    points, normals, _ = synthetic_shapes(1, 2048, seed=3)
    pair = _pair(torch.from_numpy(points[0]), torch.from_numpy(normals[0]), angle=10.0)
    rot_err, trans_err = _errors(ICP(method=method, max_correspondence_distance=0.5), pair)
    assert rot_err < 0.1 and trans_err < 1e-3


@pytest.mark.data
def test_icp_recovers_a_known_transform_on_a_real_modelnet40_object() -> None:
    root = shared_data("modelnet40_mini")
    from lcreg.data.modelnet40 import load_modelnet40_h5

    points, normals, _ = load_modelnet40_h5(root, "test")
    pair = _pair(torch.from_numpy(points[0]), None if normals is None else torch.from_numpy(normals[0]), angle=15.0)
    rot_err, trans_err = _errors(ICP(max_correspondence_distance=0.5, max_iterations=100), pair)
    assert rot_err < 0.5 and trans_err < 5e-3


def test_icp_parameters_are_explicit_and_pinned() -> None:
    icp = ICP()
    assert (icp.method, icp.max_correspondence_distance, icp.max_iterations) == ("point_to_point", 0.2, 50)
    assert (icp.relative_fitness, icp.relative_rmse, icp.normal_radius, icp.normal_max_nn) == (1e-6, 1e-6, 0.1, 30)


def test_icp_result_interface() -> None:
    src = torch.rand(2, 64, 3)
    result = ICP().register(src, src + 0.01)
    assert result.transform_ref_src.shape == (2, 4, 4) and result.transform_ref_src.dtype == src.dtype
    assert result.converged.shape == (2,) and result.num_iters.shape == (2,)
    assert torch.allclose(result.transform_ref_src[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(2, 4))
    assert not math.isnan(float(result.transform_ref_src.sum()))


def test_icp_refuses_training_with_a_clear_message() -> None:
    with pytest.raises(RuntimeError, match="lcreg test"):
        ICP().configure_optimizers()


@pytest.mark.parametrize("kwargs", [{"method": "plane"}, {"max_correspondence_distance": 0.0}, {"max_iterations": 0}])
def test_icp_rejects_bad_arguments(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        ICP(**kwargs)  # type: ignore[arg-type]


def test_icp_rejects_bad_clouds() -> None:
    from lcreg.checks import NonFiniteError

    bad = torch.rand(1, 32, 3)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="points_src"):
        ICP().register(bad, torch.rand(1, 32, 3))


def test_icp_validates_and_tests_through_the_shared_step_without_a_loss() -> None:
    import lightning as L

    from lcreg.data.datamodule import SyntheticDataModule

    dm = SyntheticDataModule(num_points=128, batch_size=2, num_train=4, num_val=2, num_test=2, max_angle_deg=10.0)
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
    icp = ICP(max_correspondence_distance=0.5)
    val = trainer.validate(icp, dm, verbose=False)[0]
    test = trainer.test(icp, dm, verbose=False)[0]
    assert "val/loss" not in val and all(math.isfinite(v) for v in val.values())
    from lcreg.evaluation import evaluate

    direct = evaluate(icp, list(dm.test_dataloader()), "icp").metrics
    assert test["test/rre_mean_deg"] == pytest.approx(direct["rre_mean_deg"], rel=1e-5)
    assert test["test/rmse_t"] == pytest.approx(direct["rmse_t"], rel=1e-5)
