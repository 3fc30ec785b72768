from __future__ import annotations

import re
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from lcreg.checks import NonFiniteError, PointCloudFileError, ShapeError
from lcreg.data.io import read_points, voxel_downsample

from _pointfiles import ply_bytes  # type: ignore[import-not-found]
from _shared_data import shared_data  # type: ignore[import-not-found]

POINTS = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)


def _write_open3d(path: Path, points: np.ndarray) -> None:
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points.astype(np.float64))
    assert o3d.io.write_point_cloud(str(path), cloud)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_open3d_formats_round_trip(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cloud{suffix}"
    _write_open3d(path, POINTS)
    got = read_points(path)
    assert got.dtype == np.float32 and got.shape == (50, 3)
    np.testing.assert_allclose(got, POINTS, atol=1e-5)


def test_npy_and_kitti_bin_round_trip(tmp_path: Path) -> None:
    np.save(tmp_path / "a.npy", POINTS.astype(np.float64))
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), POINTS)
    with_intensity = np.concatenate([POINTS, np.ones((50, 1), np.float32)], axis=1)
    np.save(tmp_path / "b.npy", with_intensity)
    np.testing.assert_array_equal(read_points(tmp_path / "b.npy"), POINTS)
    with_intensity.astype("<f4").tofile(tmp_path / "000000.bin")
    np.testing.assert_array_equal(read_points(tmp_path / "000000.bin"), POINTS)


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.ply"):
        read_points(tmp_path / "nope.ply")
    with pytest.raises(FileNotFoundError, match="does not exist or is not a file"):
        read_points(tmp_path)


@pytest.mark.parametrize("name", ["empty.ply", "empty.pcd", "empty.xyz", "empty.bin", "empty.npy"])
def test_empty_files_are_clear_errors(tmp_path: Path, name: str) -> None:
    pytest.importorskip("open3d")
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(PointCloudFileError, match=re.escape(name) + r".*empty file \(0 bytes\)") as info:
        read_points(path)  # a 0-byte PLY was "does not start with 'ply'"
    assert info.value.path == str(path)


@pytest.mark.parametrize("name", ["corrupt.ply", "corrupt.pcd", "corrupt.npy"])
def test_corrupt_files_are_clear_errors(tmp_path: Path, name: str) -> None:
    pytest.importorskip("open3d")
    path = tmp_path / name
    path.write_bytes(b"\x00\x01garbage that is not a point cloud\xff" * 3)
    with pytest.raises(PointCloudFileError, match=re.escape(name)):
        read_points(path)


def test_bad_contents_are_clear_errors(tmp_path: Path) -> None:
    (tmp_path / "odd.bin").write_bytes(b"\x00" * 20)
    with pytest.raises(PointCloudFileError, match="16 bytes"):
        read_points(tmp_path / "odd.bin")
    np.save(tmp_path / "flat.npy", np.zeros(9, np.float32))
    with pytest.raises(PointCloudFileError, match=r"\(N, 3\)"):
        read_points(tmp_path / "flat.npy")
    nan = POINTS.copy()
    nan[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    with pytest.raises(PointCloudFileError, match="1 point"):
        read_points(tmp_path / "nan.npy")
    (tmp_path / "cloud.las").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"unsupported extension '\.las'"):
        read_points(tmp_path / "cloud.las")


@pytest.mark.data
def test_reads_real_3dmatch_and_kitti_files() -> None:
    root = shared_data("3dmatch")
    ply = read_points(root / "fragments" / "7-scenes-redkitchen" / "cloud_bin_0.ply")
    assert ply.ndim == 2 and ply.shape[1] == 3 and len(ply) > 1000
    scan = shared_data("kitti") / "sequences" / "00" / "velodyne" / "000000.bin"
    kitti = read_points(scan)
    assert len(kitti) == scan.stat().st_size // 16 and len(kitti) > 100_000
    assert np.linalg.norm(kitti, axis=1).max() < 200  # metres around the sensor


# ------------------------------------------------------------------------------------- validation of damaged files
# Before the validating readers (Open3D for PLY/PCD/xyz/pts, np.load for .npy) each of these returned invented points
# or raised an untyped error; see the comment of each test.

RNG = np.random.default_rng(3)
CLOUD = RNG.normal(size=(64, 3)).astype(np.float32)
NORMALS = RNG.normal(size=(64, 3))
COLOURS = RNG.integers(0, 256, size=(64, 3)).astype(np.uint8)
FACES = RNG.integers(0, 64, size=(10, 3)).astype(np.int32)


def _ply(
    points: np.ndarray, fmt: str = "binary_little_endian", rich: bool = False, declared: int | None = None
) -> bytes:
    """A PLY file of ``points``, with double normals, uchar colours and a face element if ``rich``."""
    n = len(points)
    names = ("nx", "ny", "nz", "red", "green", "blue")
    extra = dict(zip(names, [*NORMALS[:n].T, *COLOURS[:n].T])) if rich else None
    return ply_bytes(points, fmt, extra, FACES if rich else None, declared)


def _pcd_header(points: int, data: str) -> bytes:
    return (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {points}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    ).encode()


def _refused(path: Path, data: bytes, match: str = "") -> PointCloudFileError:
    """Write ``data`` to ``path`` and check that reading it raises a PointCloudFileError naming the file."""
    path.write_bytes(data)
    with pytest.raises(PointCloudFileError, match=re.escape(path.name)) as info:
        read_points(path)
    assert info.value.path == str(path)
    assert re.search(match, str(info.value)), str(info.value)
    return info.value


def _npy(header: str, payload: bytes = CLOUD.tobytes()) -> bytes:
    """A version 1.0 .npy file with the header dictionary text ``header`` (padded as numpy pads it)."""
    text = header + " " * (-(len(header) + 11) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1") + payload


NPY_HEADER = "{'descr': '<f4', 'fortran_order': False, 'shape': (64, 3), }"


def test_truncated_binary_ply_is_refused(tmp_path: Path) -> None:
    # Open3D: 136 of 884 bytes (one complete vertex) gave 64 rows, 63 of them invented
    _refused(tmp_path / "cut.ply", _ply(CLOUD)[:136], "cut short: 136 bytes")
    _refused(tmp_path / "cut_faces.ply", _ply(CLOUD, rich=True)[:-5], "cut short|ends inside")
    _refused(tmp_path / "cut_be.ply", _ply(CLOUD, "binary_big_endian", rich=True)[:-1], "cut short|ends inside")


def test_lying_vertex_count_is_refused_without_allocating(tmp_path: Path) -> None:
    # Open3D: a header declaring 10,000,000 vertices over 64 gave (10000000, 3), mostly zeros (+343 MB peak)
    tracemalloc.start()
    try:
        _refused(tmp_path / "liar.ply", _ply(CLOUD, declared=10_000_000), "10000000 records")
        _refused(tmp_path / "liar_ascii.ply", _ply(CLOUD, "ascii", declared=10_000_000), "declares 10000000")
        _refused(tmp_path / "liar.pcd", _pcd_header(10_000_000, "binary") + CLOUD.tobytes(), "POINTS 10000000")
        faces = _ply(CLOUD, rich=True).replace(b"face 10\n", b"face 10000000\n")  # refused before walking faces
        _refused(tmp_path / "liar_faces.ply", faces, "'face' \\(10000000 records\\) needs at least")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10e6  # the 10,000,000 declared points would need 120 MB as float32


def test_extra_or_missing_bytes_of_a_binary_ply_are_refused(tmp_path: Path) -> None:
    _refused(tmp_path / "tail.ply", _ply(CLOUD) + b"\x00", "1 unexpected byte")
    _refused(tmp_path / "tail_faces.ply", _ply(CLOUD, rich=True) + b"\x00" * 4, "4 unexpected byte")
    _refused(tmp_path / "fewer.ply", _ply(CLOUD, declared=63), "12 unexpected byte")


def test_ascii_ply_with_fewer_lines_than_declared_is_refused(tmp_path: Path) -> None:
    # Open3D: 64 vertex lines under "element vertex 100" gave 100 rows
    _refused(tmp_path / "short.ply", _ply(CLOUD, "ascii", declared=100), "64 data line")
    _refused(tmp_path / "more.ply", _ply(CLOUD, "ascii") + b"1 2 3\n", "65 data line")
    _refused(tmp_path / "cut.ply", _ply(CLOUD, "ascii")[:-3], "no final newline")
    head, body = _ply(CLOUD[:2], "ascii").split(b"end_header\n")
    ragged = head + b"end_header\n" + body.replace(b"\n", b" 7\n", 1)  # the 1st vertex line has a 4th number
    _refused(tmp_path / "ragged.ply", ragged, "not rows of numbers|value")


def test_bad_ply_headers_are_refused(tmp_path: Path) -> None:
    good = _ply(CLOUD)
    cases = {
        "no_end.ply": (_ply(CLOUD, "ascii").replace(b"end_header", b"end_heade_"), "does not end"),
        "binary_no_end.ply": (good.replace(b"end_header", b"end_heade_"), "not ASCII"),
        "format.ply": (good.replace(b"1.0", b"2.0"), "unsupported PLY format"),
        "type.ply": (good.replace(b"float x", b"flot8 x"), "unknown PLY type"),
        "no_x.ply": (good.replace(b"float x", b"float w"), "no x, y, z"),
        "twice.ply": (good.replace(b"float x", b"float y"), "declared twice"),
        "count.ply": (good.replace(b"vertex 64", b"vertex -4"), "non-negative integer"),
        "digits.ply": (good.replace(b"vertex 64", b"vertex " + b"9" * 5000), "at most 19 digits"),
        "word.ply": (good.replace(b"comment", b"commant"), "unexpected PLY header line"),
        "zero.ply": (_ply(CLOUD[:0]), "0 vertices"),
    }
    for name, (data, match) in cases.items():
        _refused(tmp_path / name, data, match)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_header_only_pcd_is_refused(tmp_path: Path, data: str) -> None:
    # Open3D: a header-only ascii PCD gave uninitialised memory (POINTS 2,000,000: 2,000,000 rows)
    _refused(tmp_path / "header_only.pcd", _pcd_header(2_000_000, data), "0 data line|0 bytes|no size fields")


def test_truncated_or_lying_pcd_is_refused(tmp_path: Path) -> None:
    _refused(tmp_path / "cut.pcd", _pcd_header(64, "binary") + CLOUD.tobytes()[:300], "300 bytes")
    _refused(tmp_path / "long.pcd", _pcd_header(64, "binary") + CLOUD.tobytes() + b"\x00", "769 bytes")
    text = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in CLOUD.tolist())
    _refused(tmp_path / "short.pcd", _pcd_header(65, "ascii") + text.encode(), "64 data line")
    wide = _pcd_header(64, "binary").replace(b"WIDTH 64", b"WIDTH 32")
    _refused(tmp_path / "wide.pcd", wide + CLOUD.tobytes(), "not WIDTH 32 x HEIGHT 1")
    # a compressed payload claiming 10,000,000 points in 145 bytes is refused before decompressing
    absurd = _pcd_header(10_000_000, "binary_compressed") + struct.pack("<II", 145, 120_000_000) + b"\x1f" * 145
    _refused(tmp_path / "absurd.pcd", absurd, "cannot expand")
    lzf = _pcd_header(2, "binary_compressed") + struct.pack("<II", 3, 24) + b"\x40\x00\x00"  # reference before start
    _refused(tmp_path / "lzf.pcd", lzf, "LZF stream is corrupt")


def test_text_formats_are_validated(tmp_path: Path) -> None:
    # Open3D: a .pts declaring 10 points over 2 gave 10 rows (uninitialised memory); an .xyz line that is not 3
    # numbers was skipped silently
    _refused(tmp_path / "liar.pts", b"10\n1 2 3\n4 5 6\n", "2 point line")
    _refused(tmp_path / "garbage.xyz", b"1 2 3\ngarbage\n4 5 6\n", "not rows of numbers")
    _refused(tmp_path / "short.xyz", b"1 2 3\n4 5\n", "not rows of numbers")
    _refused(tmp_path / "xyzn.xyzn", b"1 2 3\n4 5 6\n", "expected 6")
    _refused(tmp_path / "big.xyz", b"1e39 2 3\n", "float32 range")
    (tmp_path / "ok.pts").write_bytes(b"2\r\n1 2 3 0.5 1 2 3\r\n4 5 6 0.5 1 2 3\r\n")
    np.testing.assert_array_equal(read_points(tmp_path / "ok.pts"), [[1, 2, 3], [4, 5, 6]])


def test_npy_beyond_float32_range_is_refused(tmp_path: Path) -> None:
    # np.load + cast after the finiteness check: 1e39 (float64) became inf
    values = CLOUD.astype(np.float64)
    values[5, 2] = 1e39
    np.save(tmp_path / "big.npy", values)
    _refused(tmp_path / "big.npy", (tmp_path / "big.npy").read_bytes(), "1 point.*float32 range")


@pytest.mark.parametrize("dtype", [np.complex64, np.bool_, object, [("a", "f4")]])
def test_npy_without_real_coordinates_is_refused(tmp_path: Path, dtype: object) -> None:
    # a complex64 array lost its imaginary part silently
    array = np.ones((4, 3), dtype=dtype)  # type: ignore[call-overload]
    np.save(tmp_path / "odd.npy", array, allow_pickle=True)
    _refused(tmp_path / "odd.npy", (tmp_path / "odd.npy").read_bytes(), "unsupported .npy dtype")


def test_garbled_npy_header_is_refused(tmp_path: Path) -> None:
    # np.load raised tokenize.TokenError on an unclosed parenthesis
    (tmp_path / "ok.npy").write_bytes(_npy(NPY_HEADER))
    np.testing.assert_array_equal(read_points(tmp_path / "ok.npy"), CLOUD)  # the hand-made file itself is valid
    _refused(tmp_path / "paren.npy", _npy(NPY_HEADER.replace("3)", "3 ")), "TokenError")
    _refused(tmp_path / "quote.npy", _npy(NPY_HEADER.replace("'descr'", "'descr")), "not a readable .npy")
    _refused(tmp_path / "key.npy", _npy(NPY_HEADER.replace("'shape'", "'shapes'")), "not a readable .npy")
    _refused(tmp_path / "magic.npy", _npy(NPY_HEADER).replace(b"\x01\x00", b"\x09\x00", 1), "version")


def test_npy_with_a_huge_declared_shape_is_refused_without_allocating(tmp_path: Path) -> None:
    # np.load raised MemoryError ("Unable to allocate 1.09 TiB for an array with shape (300000000000,)")
    tracemalloc.start()
    try:
        _refused(tmp_path / "huge.npy", _npy(NPY_HEADER.replace("64", "100000000000")), "1200000000000 bytes")
        _refused(tmp_path / "more.npy", _npy(NPY_HEADER.replace("64", "65")), r"shape \(65, 3\).*payload 768")
        _refused(tmp_path / "cut.npy", _npy(NPY_HEADER, CLOUD.tobytes()[:-1]), "payload 767")
        _refused(tmp_path / "neg.npy", _npy(NPY_HEADER.replace("(64, 3)", "(-64, -3)")), "got shape")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1e6


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("rich", [False, True], ids=["xyz", "normals-colours-faces"])
def test_ply_round_trip_is_exact(tmp_path: Path, fmt: str, rich: bool) -> None:
    path = tmp_path / "cloud.ply"
    path.write_bytes(_ply(CLOUD, fmt, rich))
    got = read_points(path)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, CLOUD)


def test_ply_with_irregular_lists_and_elements_before_the_vertices(tmp_path: Path) -> None:
    """Faces of 3 and 4 corners (walked record by record) and a fixed-size element before the vertices."""
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement camera 2\nproperty double f\nelement vertex 64\n"
        b"property float x\nproperty float y\nproperty float z\n"
        b"element face 2\nproperty list uchar int idx\nend_header\n"
    )
    faces = struct.pack("<B3i", 3, 0, 1, 2) + struct.pack("<B4i", 4, 0, 1, 2, 3)
    path = tmp_path / "mesh.ply"
    path.write_bytes(header + np.zeros(2).tobytes() + CLOUD.tobytes() + faces)
    np.testing.assert_array_equal(read_points(path), CLOUD)
    _refused(path, header + np.zeros(2).tobytes() + CLOUD.tobytes() + faces[:-1], "ends inside|cut short")


@pytest.mark.parametrize("kwargs", [{"write_ascii": True}, {}, {"compressed": True}], ids=["ascii", "binary", "lzf"])
def test_pcd_written_by_open3d_round_trips_exactly(tmp_path: Path, kwargs: dict[str, bool]) -> None:
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(CLOUD.astype(np.float64)))
    cloud.normals = o3d.utility.Vector3dVector(NORMALS)
    cloud.colors = o3d.utility.Vector3dVector(COLOURS / 255.0)
    path = tmp_path / "cloud.pcd"
    assert o3d.io.write_point_cloud(str(path), cloud, **kwargs)
    np.testing.assert_array_equal(read_points(path), CLOUD)


def test_pcd_binary_compressed_with_repeats_round_trips(tmp_path: Path) -> None:
    """Repeated points compress into overlapping LZF back-references."""
    o3d = pytest.importorskip("open3d")
    points = np.repeat(CLOUD[:3], 100, axis=0)
    path = tmp_path / "repeats.pcd"
    assert o3d.io.write_point_cloud(
        str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)), compressed=True
    )
    assert path.stat().st_size < points.nbytes  # LZF did compress
    np.testing.assert_array_equal(read_points(path), points)


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32, np.uint8])
@pytest.mark.parametrize("columns", [3, 6])
def test_npy_round_trip_is_exact(tmp_path: Path, dtype: type, columns: int) -> None:
    array = (RNG.normal(size=(20, columns)) * 50).astype(dtype)
    np.save(tmp_path / "a.npy", array)
    np.save(tmp_path / "f.npy", np.asfortranarray(array))
    for name in ("a.npy", "f.npy"):
        got = read_points(tmp_path / name)
        assert got.dtype == np.float32 and got.flags.c_contiguous
        np.testing.assert_array_equal(got, array[:, :3].astype(np.float32))


# ------------------------------------------------------------------------------------------------ voxel_downsample


def _open3d_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    return np.asarray(cloud.voxel_down_sample(voxel_size).points)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_voxel_downsample_is_open3d_voxel_down_sample(dtype: type) -> None:
    points = (np.random.default_rng(1).uniform(-1, 1, (3000, 3)) + 5.0).astype(dtype)
    got = voxel_downsample(points, 0.2)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, _open3d_downsample(points, 0.2).astype(dtype))


def test_voxel_downsample_grid_starts_half_a_voxel_below_the_minimum() -> None:
    """Independent per-voxel mean on the documented grid (origin ``min - v / 2``) gives the same centroids."""
    points = np.random.default_rng(2).uniform(-1, 1, (2000, 3)) + 3.3
    voxel = 0.25
    keys = np.floor((points - (points.min(0) - voxel / 2)) / voxel).astype(int)
    groups: dict[tuple[int, ...], list[np.ndarray]] = {}
    for key, point in zip(map(tuple, keys), points):
        groups.setdefault(key, []).append(point)
    expected = np.array(sorted(np.mean(g, axis=0).tolist() for g in groups.values()))
    got = np.array(sorted(voxel_downsample(points, voxel).tolist()))
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_voxel_downsample_errors_name_the_argument() -> None:
    points = np.zeros((4, 3))
    assert voxel_downsample(np.zeros((0, 3), np.float32), 0.1).shape == (0, 3)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="voxel_size"):
            voxel_downsample(points, bad)
    with pytest.raises(ValueError, match=r"voxel_size.*too small"):
        voxel_downsample(np.array([[0.0, 0.0, 0.0], [1e9, 0.0, 0.0]]), 1e-3)
    with pytest.raises(ShapeError, match="points"):
        voxel_downsample(np.zeros((4, 2)), 0.1)
    with pytest.raises(TypeError, match="points"):
        voxel_downsample(np.zeros((4, 3), np.int64), 0.1)
    with pytest.raises(NonFiniteError, match="points"):
        voxel_downsample(np.full((4, 3), np.nan), 0.1)


@pytest.mark.data
def test_voxel_downsample_count_on_a_real_fragment() -> None:
    """7-scenes-redkitchen cloud_bin_0 at 5 cm: Open3D keeps 4,910 of 18,977 points (a grid at the origin: 5,170)."""
    points = read_points(shared_data("3dmatch") / "fragments" / "7-scenes-redkitchen" / "cloud_bin_0.ply")
    assert len(points) == 18_977
    assert len(voxel_downsample(points, 0.05)) == len(_open3d_downsample(points, 0.05)) == 4_910
