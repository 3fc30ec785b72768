from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lcreg.checks import DatasetLayoutError
from lcreg.data.io import read_points
from lcreg.data.threedmatch import (
    BENCHMARKS,
    SEVEN_SCENES_REDKITCHEN,
    fragment_path,
    list_scenes,
    read_gt_log,
    read_gt_overlap,
    threedmatch_pairs,
)

from _shared_data import shared_data  # type: ignore[import-not-found]


def _rigid(seed: int) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    matrix[:3, 3] = np.random.default_rng(seed).normal(size=3)
    return matrix


def _block(i: int, j: int, n: int, matrix: np.ndarray) -> str:
    """One gt.log block, formatted like the official files (tab separated, scientific notation)."""
    rows = "".join("\t".join(f"{value: .8e}" for value in row) + "\t\n" for row in matrix)
    return f"{i}\t {j}\t {n}\t\n{rows}"


def _write_scene(
    root: Path,
    scene: str,
    blocks: dict[tuple[int, int], np.ndarray],
    overlaps: dict[tuple[int, int], float] | None,
    n: int = 4,
    benchmark: str = "3DMatch",
    fragments: bool = True,
) -> Path:
    """A scene in the official layout: gt.log (blocks in the given order), optional gt_overlap.log, fragment files."""
    scene_dir = root / "benchmarks" / benchmark / scene
    scene_dir.mkdir(parents=True, exist_ok=True)
    (scene_dir / "gt.log").write_text("".join(_block(i, j, n, m) for (i, j), m in blocks.items()))
    if overlaps is not None:
        (scene_dir / "gt_overlap.log").write_text("".join(f"{i},{j},{o}\n" for (i, j), o in overlaps.items()))
    if fragments:
        (root / "fragments" / scene).mkdir(parents=True, exist_ok=True)
        for k in range(n):
            fragment_path(root, scene, k).write_text("ply\n")  # only existence is checked when listing pairs
    return scene_dir


def _matches_file_and_line(path: Path, line: int) -> str:
    return re.escape(f"{str(path)!r}, line {line}:")


# ------------------------------------------------------------------------------------------------ parsing


def test_read_gt_log_tabs_blank_lines_and_extra_whitespace(tmp_path: Path) -> None:
    m01, m23 = _rigid(0), _rigid(1)
    text = "\n" + _block(0, 1, 5, m01) + "\n\n  " + _block(2, 3, 5, m23).replace("\t", "   ") + "\n"
    (tmp_path / "gt.log").write_text(text)
    gt = read_gt_log(tmp_path / "gt.log")
    assert gt.num_fragments == 5
    assert list(gt.transforms) == [(0, 1), (2, 3)]
    assert all(m.dtype == np.float64 and m.shape == (4, 4) for m in gt.transforms.values())
    np.testing.assert_allclose(gt.transforms[(0, 1)], m01, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(gt.transforms[(2, 3)], m23, rtol=1e-8, atol=1e-9)


_GOOD_ROWS = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        ("0 1\n" + _GOOD_ROWS, 1, "block header"),
        ("0 x 3\n" + _GOOD_ROWS, 1, "integers"),
        ("0 1 3\n1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", 2, "4 numbers"),
        ("0 1 3\n1 0 0 0\n0 1 zero 0\n0 0 1 0\n0 0 0 1\n", 3, "numbers"),
        ("0 1 3\n1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n", 4, "non-finite"),
        ("0 1 3\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", 5, "0 0 0 1"),
        ("0 1 3\n" + _GOOD_ROWS + "\n1 2 3\n1 0 0 0\n0 1 0 0\n", 7, "2 matrix rows"),
        ("0 1 3\n" + _GOOD_ROWS + "1 2 4\n" + _GOOD_ROWS, 6, "n = 4"),
        ("0 3 3\n" + _GOOD_ROWS, 1, "0 <= i, j < n"),
        ("0 1 3\n" + _GOOD_ROWS + "0 1 3\n" + _GOOD_ROWS, 6, "listed twice"),
    ],
    ids=["short-header", "bad-int", "short-row", "bad-float", "nan", "bottom-row", "truncated", "n-mismatch",
         "out-of-range", "duplicate"],
)  # fmt: skip
def test_read_gt_log_errors_name_file_and_line(tmp_path: Path, text: str, line: int, message: str) -> None:
    path = tmp_path / "gt.log"
    path.write_text(text)
    with pytest.raises(DatasetLayoutError, match=_matches_file_and_line(path, line)) as info:
        read_gt_log(path)
    assert message in str(info.value)


def test_read_gt_log_empty_and_missing(tmp_path: Path) -> None:
    (tmp_path / "gt.log").write_text("\n\n")
    with pytest.raises(DatasetLayoutError, match="no block"):
        read_gt_log(tmp_path / "gt.log")
    (tmp_path / "gt.log").write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(DatasetLayoutError, match="not a text file"):
        read_gt_log(tmp_path / "gt.log")
    missing = tmp_path / "scene" / "gt.log"
    with pytest.raises(FileNotFoundError, match=re.escape(repr(str(missing))) + ".*benchmarks/"):
        read_gt_log(missing)


def test_read_gt_overlap_whitespace_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "gt_overlap.log"
    path.write_text("0,1,0.8017\n\n 0 , 2 ,\t0.4621 \n1\t2\t0.25\n")
    assert read_gt_overlap(path) == {(0, 1): 0.8017, (0, 2): 0.4621, (1, 2): 0.25}
    for text, line, message in [
        ("0,1,0.5\n0,1\n", 2, "'i,j,overlap'"),
        ("0,1,abc\n", 1, "integers"),
        ("0,1,0.5\n\n0,2,1.5\n", 3, "[0, 1]"),
        ("0,1,nan\n", 1, "[0, 1]"),
        ("0,1,0.5\n0,1,0.6\n", 2, "listed twice"),
    ]:
        path.write_text(text)
        with pytest.raises(DatasetLayoutError, match=_matches_file_and_line(path, line)) as info:
            read_gt_overlap(path)
        assert message in str(info.value)
    with pytest.raises(FileNotFoundError, match=r"gt_overlap\.log"):
        read_gt_overlap(tmp_path / "none" / "gt_overlap.log")


# ------------------------------------------------------------------------------------------------ pair lists


@pytest.fixture
def layout(tmp_path: Path) -> dict[str, dict[tuple[int, int], np.ndarray]]:
    """Two scenes; gt.log blocks deliberately out of order; overlaps on both sides of 0.7 (and exactly 0.7)."""
    blocks_b = {(2, 3): _rigid(2), (0, 1): _rigid(3), (0, 2): _rigid(4), (1, 3): _rigid(5)}
    _write_scene(tmp_path, "b-scene", blocks_b, {(0, 1): 0.9, (0, 2): 0.7, (1, 3): 0.3, (2, 3): 0.71, (0, 3): 0.95})
    blocks_a = {(1, 2): _rigid(6)}
    _write_scene(tmp_path, "a-scene", blocks_a, {(2, 1): 0.8})  # listed the other way round
    (tmp_path / "benchmarks" / "3DMatch" / "no-gt-log").mkdir()
    return {"a-scene": blocks_a, "b-scene": blocks_b}


def test_pairs_selection_order_and_convention(tmp_path: Path, layout: dict) -> None:
    assert list_scenes(tmp_path) == ["a-scene", "b-scene"]
    pairs = threedmatch_pairs(tmp_path)
    assert [p.name for p in pairs] == ["a-scene/1-2", "b-scene/0-1", "b-scene/2-3"]  # 0.7 itself is not "more"
    assert [p.overlap for p in pairs] == [0.8, 0.9, 0.71]
    for pair in pairs:
        scene, ij = pair.name.split("/")
        i, j = (int(k) for k in ij.split("-"))
        assert (
            pair.path_ref == fragment_path(tmp_path, scene, i) == tmp_path / "fragments" / scene / f"cloud_bin_{i}.ply"
        )
        assert pair.path_src == fragment_path(tmp_path, scene, j)
        np.testing.assert_allclose(pair.transform_ref_src, layout[scene][(i, j)], atol=1e-8)
    assert [p.name for p in threedmatch_pairs(tmp_path, scenes=["b-scene"], min_overlap=0.0)] == [
        "b-scene/0-1", "b-scene/0-2", "b-scene/1-3", "b-scene/2-3"
    ]  # fmt: skip
    again = threedmatch_pairs(tmp_path, scenes=["b-scene", "a-scene", "b-scene"])
    assert [p.name for p in again] == [p.name for p in pairs]


def test_missing_overlap_file_only_allowed_without_filter(tmp_path: Path) -> None:
    _write_scene(tmp_path, "s", {(0, 1): _rigid(0)}, overlaps=None)
    with pytest.raises(FileNotFoundError, match=r"gt_overlap\.log.*min_overlap=0\.7"):
        threedmatch_pairs(tmp_path)
    (pair,) = threedmatch_pairs(tmp_path, min_overlap=0.0)
    assert pair.name == "s/0-1" and pair.overlap is None


def test_pair_absent_from_overlap_log(tmp_path: Path) -> None:
    _write_scene(tmp_path, "s", {(0, 1): _rigid(0), (1, 2): _rigid(1)}, {(0, 1): 0.9})
    with pytest.raises(DatasetLayoutError, match=r"gt_overlap\.log.*\(1, 2\)"):
        threedmatch_pairs(tmp_path)
    assert [p.overlap for p in threedmatch_pairs(tmp_path, min_overlap=-1.0)] == [0.9, None]


def test_layout_errors(tmp_path: Path) -> None:
    scene_dir = _write_scene(tmp_path, "s", {(0, 3): _rigid(0)}, {(0, 3): 0.9}, fragments=False)
    with pytest.raises(FileNotFoundError, match=re.escape(repr(str(fragment_path(tmp_path, "s", 0))))):
        threedmatch_pairs(tmp_path)
    (tmp_path / "fragments" / "s").mkdir(parents=True)
    fragment_path(tmp_path, "s", 0).write_text("ply\n")
    with pytest.raises(FileNotFoundError, match=r"cloud_bin_3\.ply"):
        threedmatch_pairs(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"\['zz'\].*available: \['s'\]"):
        threedmatch_pairs(tmp_path, scenes=["zz"])
    with pytest.raises(FileNotFoundError, match="3DLoMatch"):
        threedmatch_pairs(tmp_path, benchmark="3DLoMatch")
    with pytest.raises(FileNotFoundError, match="not a directory"):
        list_scenes(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="benchmark"):
        threedmatch_pairs(tmp_path, benchmark="3dmatch")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="scenes"):
        threedmatch_pairs(tmp_path, scenes="s")  # type: ignore[arg-type]
    for bad in (1.0, float("nan")):
        with pytest.raises(ValueError, match="min_overlap"):
            threedmatch_pairs(tmp_path, min_overlap=bad)
    (scene_dir / "gt.log").write_text("0 3 4\n1 0 0 0\n")
    with pytest.raises(DatasetLayoutError, match=r"gt\.log', line 1"):
        threedmatch_pairs(tmp_path)


# ------------------------------------------------------------------------------------------------ real data

# Pairs with listed overlap > 0.7 per 3DMatch test scene (= the gt_overlap.log lines above 0.7, all in gt.log).
EXPECTED_COUNTS_0_7 = {
    "7-scenes-redkitchen": 52,
    "sun3d-home_at-home_at_scan1_2013_jan_1": 18,
    "sun3d-home_md-home_md_scan9_2012_sep_30": 40,
    "sun3d-hotel_uc-scan3": 21,
    "sun3d-hotel_umd-maryland_hotel1": 11,
    "sun3d-hotel_umd-maryland_hotel3": 4,
    "sun3d-mit_76_studyroom-76-1studyroom2": 36,
    "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika": 15,
}


@pytest.mark.data
def test_real_pair_counts_and_consistency() -> None:
    root = shared_data("3dmatch")
    for benchmark in BENCHMARKS:
        assert list_scenes(root, benchmark) == sorted(EXPECTED_COUNTS_0_7)
    pairs = threedmatch_pairs(root)
    counts = {scene: sum(p.name.startswith(scene + "/") for p in pairs) for scene in EXPECTED_COUNTS_0_7}
    assert counts == EXPECTED_COUNTS_0_7 and len(pairs) == 197
    assert all(p.overlap is not None and p.overlap > 0.7 for p in pairs)
    # every gt_overlap.log line above 0.7 is a gt.log pair, so the filter loses nothing
    for scene, count in EXPECTED_COUNTS_0_7.items():
        overlaps = read_gt_overlap(root / "benchmarks" / "3DMatch" / scene / "gt_overlap.log")
        assert sum(o > 0.7 for o in overlaps.values()) == count
    kitchen = threedmatch_pairs(root, scenes=[SEVEN_SCENES_REDKITCHEN], min_overlap=0.0)
    gt = read_gt_log(root / "benchmarks" / "3DMatch" / SEVEN_SCENES_REDKITCHEN / "gt.log")
    assert len(kitchen) == len(gt.transforms) == 506 and gt.num_fragments == 60
    assert len(list((root / "fragments" / SEVEN_SCENES_REDKITCHEN).glob("cloud_bin_*.ply"))) == 60
    assert len(threedmatch_pairs(root, min_overlap=0.0)) == 1623
    lo = threedmatch_pairs(root, min_overlap=0.0, benchmark="3DLoMatch")
    assert len(lo) == 1781 and all(p.overlap is not None and 0.1 <= p.overlap <= 0.3 for p in lo)
    assert threedmatch_pairs(root, benchmark="3DLoMatch") == []


@pytest.mark.data
@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_real_transforms_are_rigid(benchmark: str) -> None:
    pairs = threedmatch_pairs(shared_data("3dmatch"), min_overlap=0.0, benchmark=benchmark)  # type: ignore[arg-type]
    transforms = np.stack([p.transform_ref_src for p in pairs])
    rotations = transforms[:, :3, :3]
    gram = np.einsum("nji,njk->nik", rotations, rotations)
    # the files store 9 significant digits of matrices that are orthonormal to about 5e-4
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-3)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-3)
    np.testing.assert_array_equal(transforms[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(pairs), 4)))


def _coverage(points_ref: np.ndarray, points_src: np.ndarray, transform: np.ndarray, radius: float = 0.05) -> float:
    """Fraction of reference points with a mapped source point within ``radius`` metres."""
    mapped = points_src @ transform[:3, :3].T + transform[:3, 3]
    distances, _ = cKDTree(mapped).query(points_ref, distance_upper_bound=radius)
    return float(np.mean(distances <= radius))


@pytest.mark.data
def test_real_ground_truth_aligns_fragment_j_onto_fragment_i() -> None:
    root = shared_data("3dmatch")
    pairs = {p.name: p for p in threedmatch_pairs(root, scenes=[SEVEN_SCENES_REDKITCHEN])}
    for name in ("7-scenes-redkitchen/0-1", "7-scenes-redkitchen/16-17", "7-scenes-redkitchen/51-52"):
        pair = pairs[name]
        assert pair.overlap is not None
        ref = read_points(pair.path_ref).astype(np.float64)
        src = read_points(pair.path_src).astype(np.float64)
        covered = _coverage(ref, src, pair.transform_ref_src)
        covered_inverse = _coverage(ref, src, np.linalg.inv(pair.transform_ref_src))
        # measured on the 197 pairs > 0.7: covered - listed overlap lies in [-0.022, 0.133]
        assert abs(covered - pair.overlap) < 0.15, (name, covered, pair.overlap)
        assert covered_inverse < 0.5 * covered, (name, covered, covered_inverse)
