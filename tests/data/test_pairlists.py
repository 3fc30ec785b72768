from __future__ import annotations

import json
import re
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lcreg.checks import DatasetLayoutError
from lcreg.data.kitti.layout import scan_path
from lcreg.data.pairlists import ListedPair, read_gt_info, read_pair_list
from lcreg.data.threedmatch import fragment_path, read_gt_log

from _shared_data import shared_data  # type: ignore[import-not-found]


def _rigid(seed: int) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    matrix[:3, 3] = np.random.default_rng(seed).normal(size=3)
    return matrix


def _info(seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(6, 6))
    matrix = a @ a.T
    matrix[0, 0] = 5000.0
    return matrix


def _numbers(matrix: np.ndarray, sep: str = " ") -> str:
    return sep.join(repr(float(v)) for v in matrix.ravel())


def _touch(*paths: Path) -> None:
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("ply\n")  # only existence is checked when listing pairs


def _at_line(path: Path, line: int) -> str:
    return re.escape(f"{str(path)!r}, line {line}:")


# ----------------------------------------------------------------------------------------------------- CSV


@pytest.fixture
def clouds(tmp_path: Path) -> Path:
    _touch(*(tmp_path / "clouds" / f"{name}.ply" for name in ("a", "b", "c")))
    return tmp_path


def _csv(folder: Path, text: str, name: str = "pairs.csv") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_csv_two_columns_header_comments_and_relative_paths(clouds: Path) -> None:
    absolute = clouds / "clouds" / "c.ply"
    path = _csv(clouds, f"# my pairs\n\nsrc, ref\nclouds/a.ply,clouds/b.ply\n  # note\n{absolute} , clouds/a.ply\n")
    pairs = read_pair_list(path)
    assert [(p.path_src, p.path_ref) for p in pairs] == [
        (clouds / "clouds" / "a.ply", clouds / "clouds" / "b.ply"),
        (absolute, clouds / "clouds" / "a.ply"),
    ]
    assert [p.name for p in pairs] == ["a-b", "c-a"]
    assert all(p.transform_ref_src is None and p.info is None and not p.scored and p.group == "" for p in pairs)


@pytest.mark.parametrize("layout", ["third_column", "sixteen_columns"])
def test_csv_ground_truth_in_either_layout(clouds: Path, layout: str) -> None:
    gt0, gt1 = _rigid(0), _rigid(1)
    sep = "," if layout == "sixteen_columns" else " "
    text = f"clouds/a.ply,clouds/b.ply,{_numbers(gt0, sep)}\nclouds/b.ply,clouds/c.ply,{_numbers(gt1, sep)}\n"
    pairs = read_pair_list(_csv(clouds, text, "pairs.txt"))
    assert [p.scored for p in pairs] == [True, True]
    for pair, gt in zip(pairs, (gt0, gt1)):
        assert pair.transform_ref_src is not None and pair.transform_ref_src.dtype == np.float64
        np.testing.assert_array_equal(pair.transform_ref_src, gt)


def test_csv_rows_with_and_without_ground_truth_and_repeated_names(clouds: Path) -> None:
    text = f"clouds/a.ply,clouds/b.ply\nclouds/a.ply,clouds/b.ply,{_numbers(np.eye(4))}\nclouds/a.ply,clouds/b.ply\n"
    pairs = read_pair_list(_csv(clouds, text))
    assert [p.name for p in pairs] == ["a-b", "a-b-2", "a-b-3"]
    assert [p.scored for p in pairs] == [False, True, False]


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("clouds/a.ply", "expected 2 columns .* got 1"),
        ("clouds/a.ply,clouds/b.ply,1 0 0,4", "got 4"),
        ("clouds/a.ply,clouds/b.ply," + " ".join(["1"] * 15), "16 numbers .* got 15"),
        ("clouds/a.ply,clouds/b.ply," + " ".join(["x"] * 16), "must hold numbers"),
        ("clouds/a.ply,clouds/b.ply," + _numbers(np.diag([1.0, 1.0, 1.0, float("nan")])), "non-finite"),
        ("clouds/a.ply,clouds/b.ply," + _numbers(np.diag([2.0, 2.0, 2.0, 1.0])), "not a rigid motion"),
        ("clouds/a.ply,clouds/b.ply," + _numbers(np.diag([1.0, 1.0, -1.0, 1.0])), "not a rigid motion"),
        (" ,clouds/b.ply", "source path is empty"),
    ],
)
def test_csv_malformed_rows_name_file_and_line(clouds: Path, row: str, message: str) -> None:
    path = _csv(clouds, f"src,ref,gt\nclouds/a.ply,clouds/b.ply\n# comment\n{row}\n")
    with pytest.raises(DatasetLayoutError, match=_at_line(path, 4) + ".*" + message):
        read_pair_list(path)


@pytest.mark.parametrize(
    ("row", "role", "missing"),
    [("nope.ply,clouds/b.ply", "source", "nope.ply"), ("clouds/a.ply,x/y.ply", "reference", "x/y.ply")],
)
def test_csv_missing_point_file_names_line_and_file(clouds: Path, row: str, role: str, missing: str) -> None:
    path = _csv(clouds, f"clouds/a.ply,clouds/b.ply\n{row}\n")
    expected = _at_line(path, 2) + f" {role} file " + re.escape(repr(str(clouds / missing)))
    with pytest.raises(FileNotFoundError, match=expected):
        read_pair_list(path)


@pytest.mark.parametrize("text", ["", "# only a comment\n\n", "src,ref\n"])
def test_csv_without_pairs(clouds: Path, text: str) -> None:
    with pytest.raises(DatasetLayoutError, match="holds no pair"):
        read_pair_list(_csv(clouds, text))


def test_csv_header_only_on_the_first_row(clouds: Path) -> None:
    path = _csv(clouds, "clouds/a.ply,clouds/b.ply\nsrc,ref\n")
    with pytest.raises(FileNotFoundError, match=_at_line(path, 2) + " source file"):
        read_pair_list(path)


def test_csv_binary_content(clouds: Path) -> None:
    path = clouds / "pairs.csv"
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(DatasetLayoutError, match="not a text file"):
        read_pair_list(path)


# ----------------------------------------------------------------------------------------------------- kinds


def test_unknown_kinds_list_the_accepted_ones(tmp_path: Path) -> None:
    (tmp_path / "cloud.ply").write_text("ply\n")
    (tmp_path / "empty").mkdir()
    for path in (tmp_path / "cloud.ply", tmp_path / "empty"):
        with pytest.raises(
            DatasetLayoutError, match=re.escape(repr(str(path))) + " is not a pair list.*CSV.*gt.log.*KITTI"
        ):
            read_pair_list(path)
    with pytest.raises(FileNotFoundError, match="does not exist; expected a CSV pair list"):
        read_pair_list(tmp_path / "missing.csv")


def test_listed_pair_validation_and_scene_pair() -> None:
    with pytest.raises(ValueError, match="scored but has no ground truth"):
        ListedPair(Path("a"), Path("b"), scored=True)
    with pytest.raises(ValueError, match=r"transform_ref_src must be \(4, 4\)"):
        ListedPair(Path("a"), Path("b"), np.eye(3))
    with pytest.raises(ValueError, match=r"info must be \(6, 6\)"):
        ListedPair(Path("a"), Path("b"), np.eye(4), info=np.eye(4))
    with pytest.raises(ValueError, match="no ground truth"):
        ListedPair(Path("a"), Path("b"), name="x").to_scene_pair()
    scene_pair = ListedPair(Path("a"), Path("b"), np.eye(4), name="x", overlap=0.5).to_scene_pair()
    assert (scene_pair.path_src, scene_pair.name, scene_pair.overlap) == (Path("a"), "x", 0.5)


# ----------------------------------------------------------------------------------------------------- 3DMatch


def _gt_block(i: int, j: int, n: int, matrix: np.ndarray) -> str:
    rows = "".join("\t".join(f"{v: .8e}" for v in row) + "\t\n" for row in matrix)
    return f"{i}\t {j}\t {n}\t\n{rows}"


def _write_scene(root: Path, scene: str, keys: list[tuple[int, int]], n: int = 5, info: bool = True) -> Path:
    scene_dir = root / "benchmarks" / "3DMatch" / scene
    scene_dir.mkdir(parents=True)
    (scene_dir / "gt.log").write_text("".join(_gt_block(i, j, n, _rigid(10 * i + j)) for i, j in keys))
    if info:
        (scene_dir / "gt.info").write_text("".join(_gt_block(i, j, n, _info(10 * i + j)) for i, j in keys))
    _touch(*(fragment_path(root, scene, k) for k in range(n)))
    return scene_dir


def test_read_gt_info_blocks(tmp_path: Path) -> None:
    path = tmp_path / "gt.info"
    path.write_text("\n" + _gt_block(0, 1, 4, _info(1)) + "\n" + _gt_block(1, 3, 4, _info(13)).replace("\t", "  "))
    infos = read_gt_info(path)
    assert list(infos) == [(0, 1), (1, 3)]
    np.testing.assert_allclose(infos[(1, 3)], _info(13), rtol=1e-8)
    assert infos[(0, 1)].dtype == np.float64 and infos[(0, 1)].shape == (6, 6)


@pytest.mark.parametrize(
    ("edit", "line", "message"),
    [
        (lambda rows: [*rows[:3], rows[3] + " 1", *rows[4:]], 4, "6 numbers"),
        (lambda rows: [*rows[:3], "a b c d e f", *rows[4:]], 4, "must hold numbers"),
        (lambda rows: [*rows[:3], "nan 0 0 0 0 0", *rows[4:]], 4, "non-finite"),
        (lambda rows: rows[:5], 1, "4 matrix rows, expected 6"),
        (lambda rows: ["0 1", *rows[1:]], 1, "block header"),
        (lambda rows: [*rows, "0 1 9", *rows[1:7]], 8, "n = 9"),
        (lambda rows: rows + rows, 8, r"pair \(0, 1\) is listed twice"),
    ],
)
def test_read_gt_info_malformed_names_file_and_line(
    tmp_path: Path, edit: Callable[[list[str]], list[str]], line: int, message: str
) -> None:
    rows = [" ".join(["0", "1", "4"])] + [" ".join(str(v) for v in row) for row in np.eye(6) * 5]
    path = tmp_path / "gt.info"
    path.write_text("\n".join(edit(rows)) + "\n")
    with pytest.raises(DatasetLayoutError, match=_at_line(path, line) + ".*" + message):
        read_gt_info(path)


@pytest.mark.parametrize(
    ("matrix", "message"), [(np.triu(np.ones((6, 6))), "not symmetric"), (np.zeros((6, 6)), "positive")]
)
def test_read_gt_info_rejects_unusable_matrices(tmp_path: Path, matrix: np.ndarray, message: str) -> None:
    path = tmp_path / "gt.info"
    path.write_text(_gt_block(0, 2, 4, matrix))
    with pytest.raises(DatasetLayoutError, match=_at_line(path, 1) + ".*" + message):
        read_gt_info(path)


def test_read_gt_info_missing_or_empty(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"gt\.info"):
        read_gt_info(tmp_path / "gt.info")
    (tmp_path / "gt.info").write_text("\n\n")
    with pytest.raises(DatasetLayoutError, match="holds no block"):
        read_gt_info(tmp_path / "gt.info")


def test_threedmatch_scene_folder_and_gt_log_file(tmp_path: Path) -> None:
    scene_dir = _write_scene(tmp_path, "kitchen", [(0, 1), (0, 3), (2, 4), (1, 2)])
    (scene_dir / "gt_overlap.log").write_text("0,3,0.55\n4,2,0.8\n")
    pairs = read_pair_list(scene_dir)
    assert read_pair_list(scene_dir / "gt.log") == pairs
    assert [p.name for p in pairs] == ["kitchen/0-1", "kitchen/0-3", "kitchen/2-4", "kitchen/1-2"]  # gt.log order
    assert [p.scored for p in pairs] == [False, True, True, False]
    assert [p.overlap for p in pairs] == [None, 0.55, 0.8, None]
    pair = pairs[1]
    assert (pair.path_src, pair.path_ref, pair.group) == (
        fragment_path(tmp_path, "kitchen", 3),
        fragment_path(tmp_path, "kitchen", 0),
        "kitchen",
    )
    assert pair.transform_ref_src is not None and pair.info is not None
    np.testing.assert_allclose(pair.transform_ref_src, _rigid(3), rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(pair.info, _info(3), rtol=1e-7)


def test_threedmatch_benchmark_folder_reads_every_scene_sorted(tmp_path: Path) -> None:
    _write_scene(tmp_path, "b-scene", [(0, 2)])
    _write_scene(tmp_path, "a-scene", [(1, 3), (0, 1)], info=False)
    (tmp_path / "benchmarks" / "3DMatch" / "not-a-scene").mkdir()
    pairs = read_pair_list(tmp_path / "benchmarks" / "3DMatch")
    assert [(p.group, p.name) for p in pairs] == [
        ("a-scene", "a-scene/1-3"),
        ("a-scene", "a-scene/0-1"),
        ("b-scene", "b-scene/0-2"),
    ]
    assert [p.info is None for p in pairs] == [True, True, False]


def test_threedmatch_layout_errors(tmp_path: Path) -> None:
    scene_dir = _write_scene(tmp_path, "kitchen", [(0, 2), (1, 3)])
    (scene_dir / "gt.info").write_text(_gt_block(0, 2, 5, _info(0)))
    with pytest.raises(DatasetLayoutError, match=r"gt.info'? has no block for 1 gt.log pair\(s\), e.g. \[\(1, 3\)\]"):
        read_pair_list(scene_dir)
    (scene_dir / "gt.info").unlink()
    fragment_path(tmp_path, "kitchen", 3).unlink()
    with pytest.raises(FileNotFoundError, match=r"cloud_bin_3.ply'? of gt.log pair \(1, 3\) does not exist"):
        read_pair_list(scene_dir)
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "gt.log").write_text(_gt_block(0, 1, 2, np.eye(4)))
    with pytest.raises(DatasetLayoutError, match="not a folder <root>/benchmarks/<benchmark>/<scene>"):
        read_pair_list(loose / "gt.log")


# ----------------------------------------------------------------------------------------------------- KITTI


def _write_kitti(root: Path, entries: list[tuple[int, int, int]], scans: list[tuple[int, int]]) -> Path:
    rows = [
        {"seq_id": s, "frame0": f0, "frame1": f1, "transform": _rigid(f0 + f1).tolist(), "pcd0": "", "pcd1": ""}
        for s, f0, f1 in entries
    ]
    path = root / "pairs" / "test.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(rows))
    for seq_id, frame in scans:
        scan_path(root, seq_id, frame).parent.mkdir(parents=True, exist_ok=True)
        scan_path(root, seq_id, frame).write_bytes(b"")
    return path


def test_kitti_json_skips_pairs_without_scans_with_a_warning(tmp_path: Path) -> None:
    path = _write_kitti(tmp_path, [(8, 12, 0), (8, 30, 12), (9, 10, 0)], [(8, 0), (8, 12)])
    with pytest.warns(UserWarning, match=r"2 of the 3 pairs .* skipped.*'" + re.escape(str(tmp_path / "sequences"))):
        pairs = read_pair_list(path)
    assert len(pairs) == 1
    pair = pairs[0]
    assert (pair.name, pair.group, pair.scored, pair.info) == ("08/12-0", "08", True, None)
    assert (pair.path_src, pair.path_ref) == (scan_path(tmp_path, 8, 0), scan_path(tmp_path, 8, 12))
    np.testing.assert_array_equal(pair.transform_ref_src, _rigid(12))


def test_kitti_json_all_scans_present_is_silent_and_root_can_be_given(tmp_path: Path) -> None:
    path = _write_kitti(tmp_path / "lists", [(0, 11, 0)], [])
    scans = tmp_path / "scans"
    for frame in (0, 11):
        _touch(scan_path(scans, 0, frame))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pairs = read_pair_list(path, kitti_root=scans)
    assert [p.path_src for p in pairs] == [scan_path(scans, 0, 0)]
    with pytest.raises(FileNotFoundError, match=r"KITTI root .* is not a directory"):
        read_pair_list(path, kitti_root=tmp_path / "nowhere")


def test_kitti_json_without_any_scan_or_malformed(tmp_path: Path) -> None:
    path = _write_kitti(tmp_path, [(8, 12, 0)], [])
    with pytest.raises(FileNotFoundError, match="lists 1 pairs in sequences"):
        read_pair_list(path)
    path.write_text('[{"seq_id": 8}]')
    with pytest.raises(DatasetLayoutError, match="is not a pair list"):
        read_pair_list(path)


# ----------------------------------------------------------------------------------------------------- real data


@pytest.mark.data
def test_real_threedmatch_benchmark() -> None:
    bench = shared_data("3dmatch") / "benchmarks" / "3DMatch"
    pairs = read_pair_list(bench)
    scenes = sorted(d.name for d in bench.iterdir() if (d / "gt.log").is_file())
    assert len(scenes) == 8 and [p.group for p in pairs] == sorted(p.group for p in pairs)
    for scene in scenes:
        blocks = read_gt_log(bench / scene / "gt.log").transforms
        scene_pairs = [p for p in pairs if p.group == scene]
        assert len(scene_pairs) == len(blocks)
        assert sum(p.scored for p in scene_pairs) == sum(j - i > 1 for i, j in blocks)
    assert (len(pairs), sum(p.scored for p in pairs)) == (1623, 1279)  # the official 3DMatch numbers
    assert all(p.info is not None and p.path_src.is_file() for p in pairs)
    kitchen = read_pair_list(bench / "7-scenes-redkitchen")
    assert (len(kitchen), sum(p.scored for p in kitchen)) == (506, 449)
    assert kitchen[0].name == "7-scenes-redkitchen/0-1" and not kitchen[0].scored


@pytest.mark.data
def test_real_kitti_train_list_keeps_the_pairs_with_scans() -> None:
    kitti = shared_data("kitti")
    with pytest.warns(UserWarning, match=r"1357 of the 1358 pairs .* skipped.*1 pair\(s\) remain"):
        pairs = read_pair_list(kitti / "pairs" / "train.json")
    assert [p.name for p in pairs] == ["00/11-0"]
    with pytest.raises(FileNotFoundError, match="no KITTI pair has both scans"):
        read_pair_list(kitti / "pairs" / "test.json")
