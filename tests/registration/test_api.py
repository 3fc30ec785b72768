"""``lcreg.register``: methods recover a known motion, at any unit, from any container; init; learned models."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

import lcreg
from _register_pairs import errors, motion  # type: ignore[import-not-found]
from lcreg.registration import MethodError, available_methods, register
from lcreg.registration.api import DEFAULT, DEFAULT_WITHOUT_KISS, default_pipeline
from lcreg.registration.methods import parse_method

SMALL_CLOUDS = default_pipeline().small or default_pipeline().method
"""The default's method for the 3,000-point test clouds (at most ``target_points``: objects)."""


@pytest.mark.parametrize("method", ["default", "ransac+icp", "fgr+icp"])
def test_global_pipelines_recover_a_large_motion(pair, method):
    src, ref, gt = pair
    result = register(src, ref, method)
    rre, rte = errors(result.transform, gt)
    assert rre < 1.0 and rte < 0.01, (rre, rte)
    assert result.fitness > 0.9 and result.inlier_rmse < result.voxel_size
    assert result.method == (SMALL_CLOUDS if method == "default" else method)
    assert result.coarse_transform is not None and result.num_points == (3000, 3000)


def test_icp_alone_fails_from_far_and_succeeds_from_the_initial_guess(pair):
    src, ref, gt = pair
    far = register(src, ref, "icp")
    assert errors(far.transform, gt)[0] > 10  # a local method: 60 degrees is out of reach
    near = motion(5, angle_deg=3.0, shift=0.02) @ gt
    result = register(src, ref, "icp", init=torch.from_numpy(near))
    rre, rte = errors(result.transform, gt)
    assert rre < 0.5 and rte < 0.01
    assert result.fitness > far.fitness


def test_any_unit_gives_the_same_motion(pair):
    src, ref, _gt = pair
    metres = register(src, ref)
    millimetres = register(src * 1000, ref * 1000)
    # The automatic voxel sizes are exactly 1000 apart, so the two runs are the same computation at two scales.
    assert np.isclose(millimetres.voxel_size / metres.voxel_size, 1000, rtol=1e-9)
    np.testing.assert_allclose(millimetres.transform[:3, :3], metres.transform[:3, :3], atol=1e-3)
    np.testing.assert_allclose(millimetres.transform[:3, 3], 1000 * metres.transform[:3, 3], atol=1.0)


def test_containers_and_dtypes_agree(pair):
    src, ref, _ = pair
    base = register(src, ref).transform
    np.testing.assert_allclose(register(torch.from_numpy(src), torch.from_numpy(ref)).transform, base, atol=1e-12)
    # float32 rounds the points (1e-7 relative): ICP stops at a relative change of 1e-6, within 0.06 degrees
    np.testing.assert_allclose(register(src.astype(np.float32), ref.astype(np.float32)).transform, base, atol=1e-3)


def test_result_helpers(pair):
    src, ref, _gt = pair
    result = register(src, ref)
    moved = result.apply(src)
    np.testing.assert_allclose(moved, src @ result.transform[:3, :3].T + result.transform[:3, 3])
    record = result.to_dict()
    assert np.array(record["transform_ref_src"]).shape == (4, 4) and record["method"] == SMALL_CLOUDS


def test_learned_method_with_shipped_weights(pair):
    src, _ref, _gt = pair
    small = motion(1, angle_deg=10.0, shift=0.1)
    moved_ref = src @ small[:3, :3].T + small[:3, 3]
    alone = register(src * 5, moved_ref * 5, "dvds")  # any scale: the network sees the unit sphere
    refined = register(src * 5, moved_ref * 5, "dvds+icp")
    big = small.copy()
    big[:3, 3] *= 5
    assert errors(refined.transform, big)[0] < 1.0
    assert np.allclose(alone.transform[:3, :3] @ alone.transform[:3, :3].T, np.eye(3), atol=1e-5)
    assert errors(alone.transform, big)[0] < 10.0


def test_learned_method_without_weights_is_refused(pair):
    with pytest.raises(MethodError, match=r"'dcp'.*no shipped weights.*pointnetlk-modelnet40.*weights"):
        register(pair[0], pair[1], "dcp")


def test_method_names():
    assert parse_method("RANSAC+ICP").name == "ransac+icp"
    assert parse_method("fgr", refine="icp").name == "fgr+icp"
    assert parse_method("fgr", refine="none").name == "fgr"
    assert {"icp", "ransac", "fgr", "dvds", "ransac+icp", "dvds+icp"} <= set(available_methods())
    with pytest.raises(MethodError, match=r"unknown method 'sift'.*ransac\+icp"):
        parse_method("sift")
    with pytest.raises(MethodError, match="refinement"):
        parse_method("icp+icp")


def test_bad_options_are_named(pair):
    src, ref, _ = pair
    with pytest.raises(ValueError, match="voxel_size"):
        register(src, ref, voxel_size=-1.0)
    with pytest.raises(ValueError, match="target_points"):
        register(src, ref, target_points=3)
    with pytest.raises(ValueError, match="init"):
        register(src, ref, init=np.full((4, 4), 2.0))
    with pytest.raises(ValueError, match="init"):
        register(src, ref, init=np.eye(3))


def test_top_level_export():
    assert lcreg.register is register


def test_a_million_points_are_downsampled_first(pair):
    src, ref, gt = pair
    rng = np.random.default_rng(0)
    dense = (src[None] + rng.normal(scale=2e-3, size=(334, *src.shape))).reshape(-1, 3)  # ~1M points
    result = register(dense, ref)
    assert result.num_points[0] == len(dense) > 1_000_000 - 10_000
    assert result.used_points[0] <= 5000
    assert errors(result.transform, gt)[0] < 1.5


@pytest.mark.parametrize("kind", ["pointnetlk", "fmr"])
def test_learned_weights_from_a_checkpoint_or_an_export(pair, tmp_path, kind):
    from _weights_files import exported, lightning_checkpoint, tiny_model  # type: ignore[import-not-found]

    src, ref, _ = pair
    model = tiny_model(kind)
    checkpoint = lightning_checkpoint(model, tmp_path / "run.ckpt")
    export = exported(model, tmp_path / "export")
    by_ckpt = register(src, ref, kind, weights=str(checkpoint))
    by_export = register(src, ref, kind, weights=str(export))
    np.testing.assert_allclose(by_ckpt.transform, by_export.transform, atol=1e-5)  # the same network either way
    with pytest.raises(MethodError, match="dvds"):
        register(src, ref, "dvds", weights=str(checkpoint))  # weights of another method


def test_a_low_fitness_result_runs_the_fallback_and_keeps_the_better(pair):
    src, ref, gt = pair
    result = register(src, ref, "icp", fallback="ransac+icp", min_fitness=0.9)  # ICP alone cannot reach 60 degrees
    assert result.method == "ransac+icp" and errors(result.transform, gt)[0] < 1.0
    record = result.extra["fallback"]
    assert record["first"] == "icp" and record["first_fitness"] < 0.9 <= record["ran_fitness"]
    assert record["kept"] == "ransac+icp" and result.to_dict()["fallback"] == record
    good = register(src, ref, "ransac+icp", fallback="fgr", min_fitness=0.5)  # above: no second run
    assert "fallback" not in good.extra
    with pytest.raises(ValueError, match="min_fitness"):
        register(src, ref, "icp", min_fitness=1.5)
    with pytest.raises(MethodError, match="unknown method 'nope'"):
        register(src, ref, "icp", fallback="nope")


def test_threads_change_the_speed_not_the_result(pair):
    import open3d as o3d

    src, ref, _ = pair
    before = (o3d.utility.get_max_threads(), torch.get_num_threads())
    one = register(src, ref, "ransac+icp", threads=1)
    assert (o3d.utility.get_max_threads(), torch.get_num_threads()) == before  # restored
    np.testing.assert_allclose(register(src, ref, "ransac+icp", threads=2).transform, one.transform, atol=1e-9)
    with pytest.raises(ValueError, match="threads"):
        register(src, ref, threads=0)


def test_the_default_is_kiss_with_a_ransac_fallback_and_plain_ransac_without_kiss(pair, monkeypatch):
    src, ref, gt = pair
    pytest.importorskip("kiss_matcher")
    assert default_pipeline() == DEFAULT and DEFAULT.method == "kiss+icp" and DEFAULT.fallback == "ransac+icp"
    assert register(src, ref).method == DEFAULT.small == "ransac+icp"  # 3,000 points: an object
    scan = register(src, ref, target_points=1000)  # more points than the target: a scan
    assert scan.method == "kiss+icp" and errors(scan.transform, gt)[0] < 1.0  # the fallback: test_kiss.py
    monkeypatch.setitem(sys.modules, "kiss_matcher", None)  # a platform without the wheel
    assert default_pipeline() == DEFAULT_WITHOUT_KISS
    result = register(src, ref, target_points=1000)
    assert result.method == "ransac+icp" and errors(result.transform, gt)[0] < 1.0


def test_ransac_iterations_reach_every_ransac_step_and_the_default_fallback_has_its_own(pair, monkeypatch):
    """The default's fallback runs RANSAC with 25,000 iterations (chosen on validation), others 100,000; the option
    sets all of them; RANSAC is called with the limit asked for."""
    from lcreg.baselines.classical import RANSAC
    from lcreg.registration import methods
    from lcreg.registration.api import resolve_methods

    pytest.importorskip("kiss_matcher")
    first, fallback, _, small = resolve_methods("default", None, None, None)
    assert (first.ransac_iterations, fallback and fallback.ransac_iterations) == (None, 25_000)
    assert small is not None and small.ransac_iterations is None and methods.RANSAC_ITERATIONS == 100_000
    first, fallback, _, small = resolve_methods("default", None, None, None, ransac_iterations=500)
    assert {first.ransac_iterations, fallback and fallback.ransac_iterations, small and small.ransac_iterations} == {
        500
    }
    _, mine, _, _ = resolve_methods("default", None, "ransac+icp", 0.2)
    assert mine is not None and mine.ransac_iterations is None  # a fallback the user names runs as named
    limits: list[int] = []

    class Stop(Exception):
        pass

    def record(self: RANSAC, *args: object) -> None:
        limits.append(self.max_iterations)
        raise Stop

    monkeypatch.setattr(RANSAC, "match", record)
    src, ref, _ = pair
    for given, expected in ((None, 100_000), (321, 321)):
        with pytest.raises(Stop):
            register(src, ref, "ransac", ransac_iterations=given)
        assert limits[-1] == expected
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="ransac_iterations"):
            register(src, ref, ransac_iterations=bad)  # type: ignore[arg-type]
