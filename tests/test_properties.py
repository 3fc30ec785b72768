"""Property-based tests (hypothesis): point-cloud file reading, SO(3)/SE(3)/Euler geometry, input checks, metrics.

Deterministic: every test runs under a registered profile with ``derandomize=True`` (the same examples on every run,
no example database). ``LCREG_HYPOTHESIS_PROFILE=lcreg-thorough`` runs ten times as many examples.

The file-reading properties write random valid clouds as ``.npy``, PLY (binary little/big endian, ASCII; optional
extra properties and faces) and PCD (ascii, binary, binary_compressed), damage the bytes (truncation, appended
garbage, flipped header bytes, flipped payload bytes) and check that :func:`lcreg.data.io.read_points` either returns
exactly what the file still says or raises :class:`~lcreg.checks.PointCloudFileError` naming the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from lcreg.checks import NonFiniteError, PointCloudFileError, ShapeError, TooFewPointsError, check_points
from lcreg.data.io import read_points
from lcreg.geometry import euler, se3, so3
from lcreg.metrics import functional
from lcreg.metrics.registration import registration_metrics

from _pointfiles import npy_bytes, pcd_bytes, ply_bytes  # type: ignore[import-not-found]

settings.register_profile(
    "lcreg-ci",
    derandomize=True,
    deadline=None,
    database=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("lcreg-thorough", settings.get_profile("lcreg-ci"), max_examples=400)
PROFILE = settings.get_profile(os.environ.get("LCREG_HYPOTHESIS_PROFILE", "lcreg-ci"))
FILE_PROFILE = settings(PROFILE, max_examples=PROFILE.max_examples // 2)  # parametrised over formats and damages

# --------------------------------------------------------------------------------------------------- file reading

FLOAT32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
FORMATS = ("npy", "ply-le", "ply-be", "ply-ascii", "pcd-ascii", "pcd-binary", "pcd-lzf")
BINARY = {"npy", "ply-le", "ply-be", "pcd-binary", "pcd-lzf"}


@dataclass(frozen=True)
class CloudFile:
    """A valid file: its format, bytes and points, and how payload bytes map to rows.

    Attributes:
        fmt: One of :data:`FORMATS`.
        data: The file's bytes.
        points: The ``(N, 3)`` float32 points it holds.
        header: Bytes before the payload.
        record: Bytes of one row of a fixed-size binary payload (0: text rows or compressed).
    """

    fmt: str
    data: bytes
    points: np.ndarray
    header: int
    record: int

    @property
    def suffix(self) -> str:
        return "." + self.fmt.split("-")[0]

    def row_of(self, position: int) -> int | None:
        """The row whose bytes include ``position`` (None in the header, faces or a compressed payload)."""
        if position < self.header or self.fmt == "pcd-lzf":
            return None
        if self.record:
            row = (position - self.header) // self.record
        else:
            row = self.data.count(b"\n", self.header, position)
        return row if row < len(self.points) else None


@st.composite
def clouds(draw: st.DrawFn, max_points: int = 20) -> np.ndarray:
    n = draw(st.integers(1, max_points))
    return draw(hnp.arrays(np.float32, (n, 3), elements=FLOAT32))


def _header_size(data: bytes, last: bytes) -> int:
    """Bytes up to and including the first line that starts with ``last``."""
    start = data.index(b"\n" + last) + 1
    return data.index(b"\n", start) + 1


@st.composite
def cloud_files(draw: st.DrawFn, fmt: str) -> CloudFile:
    """A random valid file of format ``fmt`` (one of :data:`FORMATS`) with random extra columns, and its layout."""
    points = draw(clouds())
    n = len(points)
    extra_columns = draw(st.booleans())
    if fmt == "npy":
        width = draw(st.sampled_from([3, 4, 6])) if extra_columns else 3
        dtype = draw(st.sampled_from([np.float32, np.float64]))
        table = np.concatenate([points, np.ones((n, width - 3), np.float32)], axis=1).astype(dtype)
        data = npy_bytes(table)
        return CloudFile(fmt, data, points, data.index(b"\n") + 1, width * table.itemsize)
    if fmt.startswith("ply"):
        ply_fmt = {"ply-le": "binary_little_endian", "ply-be": "binary_big_endian", "ply-ascii": "ascii"}[fmt]
        extra = {"nx": np.arange(n, dtype=np.float64) / 7, "red": np.full(n, 200, np.uint8)} if extra_columns else {}
        faces = draw(hnp.arrays(np.int32, (draw(st.integers(0, 4)), 3), elements=st.integers(0, n - 1)))
        data = ply_bytes(points, ply_fmt, extra, faces if len(faces) else None)
        record = 0 if fmt == "ply-ascii" else 12 + 9 * extra_columns
        return CloudFile(fmt, data, points, _header_size(data, b"end_header"), record)
    kind = fmt.split("-")[1].replace("lzf", "binary_compressed")
    intensity = np.linspace(0, 1, n) if extra_columns else None
    data = pcd_bytes(points, kind, intensity)
    record = 12 + 4 * extra_columns if kind == "binary" else 0
    return CloudFile(fmt, data, points, _header_size(data, b"DATA"), record)


@st.composite
def damages(draw: st.DrawFn, file: CloudFile, kind: str) -> tuple[bytes, list[int]]:
    """``(damaged bytes, flipped positions)`` of one ``kind`` of damage; the damaged bytes differ from the file's."""
    data = file.data
    if kind == "truncate":
        return data[: draw(st.integers(0, len(data) - 1))], []
    if kind == "append":
        return data + draw(st.binary(min_size=1, max_size=16)), []
    low, high = (0, file.header - 1) if kind == "header" else (file.header, len(data) - 1)
    positions = draw(st.lists(st.integers(low, high), min_size=1, max_size=3, unique=True))
    damaged = bytearray(data)
    for position in positions:
        damaged[position] ^= draw(st.integers(1, 255))
    return bytes(damaged), positions


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("properties")


def _read(workdir: Path, suffix: str, data: bytes) -> np.ndarray | None:
    """Points of ``data`` written as a file, or None when it is refused (a PointCloudFileError naming the file)."""
    path = workdir / f"cloud{suffix}"
    path.write_bytes(data)
    try:
        got = read_points(path)
    except PointCloudFileError as err:
        assert err.path == str(path) and str(path) in str(err)
        return None
    assert got.dtype == np.float32 and got.ndim == 2 and got.shape[1] == 3 and len(got) >= 1
    assert got.flags.c_contiguous and np.isfinite(got).all()
    return got


@FILE_PROFILE
@given(data=st.data())
@pytest.mark.parametrize("fmt", FORMATS)
def test_valid_files_round_trip_exactly(workdir: Path, fmt: str, data: st.DataObject) -> None:
    file = data.draw(cloud_files(fmt))
    got = _read(workdir, file.suffix, file.data)
    assert got is not None
    np.testing.assert_array_equal(got, file.points)


@FILE_PROFILE
@given(data=st.data())
@pytest.mark.parametrize("kind", ["truncate", "append", "header", "payload"])
@pytest.mark.parametrize("fmt", FORMATS)
def test_damaged_files_give_the_file_points_or_a_typed_error(
    workdir: Path, fmt: str, kind: str, data: st.DataObject
) -> None:
    file = data.draw(cloud_files(fmt))
    damaged, positions = data.draw(damages(file, kind))
    got = _read(workdir, file.suffix, damaged)
    event("refused" if got is None else "read")
    if got is None:
        return
    # a file cut short, or a binary file with trailing bytes, never reads
    assert kind != "truncate" and not (kind == "append" and fmt in BINARY)
    if kind == "append" or (kind == "header" and fmt.startswith("ply")):
        np.testing.assert_array_equal(got, file.points)  # trailing blank lines; comment/whitespace flips
    elif kind == "header" and fmt.startswith("pcd"):
        assert got.shape == file.points.shape  # TYPE F -> I keeps the size but not the values
    elif kind == "payload":
        assert got.shape == file.points.shape
        touched = {file.row_of(p) for p in positions}
        same = [i for i in range(len(got)) if i not in touched and fmt != "pcd-lzf"]
        np.testing.assert_array_equal(got[same], file.points[same])
    # npy header flips ('<f4' -> '<i4', '(6, 3)' -> '(3, 6)') can make another valid array: the contract holds


@PROFILE
@given(
    points=clouds(),
    dtype=st.sampled_from([np.float64, np.float32, np.int32, np.int16, np.uint8]),
    width=st.integers(3, 6),
    fortran=st.booleans(),
)
def test_npy_of_any_real_dtype_reads_as_float32(
    workdir: Path, points: np.ndarray, dtype: type, width: int, fortran: bool
) -> None:
    table = np.concatenate([points, points[:, :1].repeat(width - 3, axis=1)], axis=1)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        table = np.clip(table, max(info.min, -(2**24)), min(info.max, 2**24))  # exact in float32
    table = table.astype(dtype)
    got = _read(workdir, ".npy", npy_bytes(np.asfortranarray(table) if fortran else table))
    expected = table[:, :3].astype(np.float32)
    if not np.isfinite(expected).all():
        assert got is None
    else:
        assert got is not None
        np.testing.assert_array_equal(got, expected)


@PROFILE
@given(points=clouds(), pts=st.booleans())
def test_text_point_files_round_trip(workdir: Path, points: np.ndarray, pts: bool) -> None:
    lines = [" ".join(repr(float(v)) for v in row) for row in points]
    text = "\n".join([str(len(points)), *lines] if pts else lines) + "\n"
    got = _read(workdir, ".pts" if pts else ".xyz", text.encode())
    assert got is not None
    np.testing.assert_array_equal(got, points)


# -------------------------------------------------------------------------------------------------------- geometry

ANGLE_VECTORS = hnp.arrays(np.float64, 3, elements=st.floats(-10, 10))
TRANSLATIONS = hnp.arrays(np.float64, 3, elements=st.floats(-100, 100))
QUATERNIONS = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).map(
    lambda q: q if np.linalg.norm(q) > 1e-3 else q + np.array([1.0, 0, 0, 0])  # no (near-)zero quaternion
)
UNIT_VECTORS = hnp.arrays(np.float64, 3, elements=st.floats(-1, 1)).map(
    lambda v: v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-3 else np.array([0.0, 0, 1])
)


def _rotation(quat: np.ndarray) -> torch.Tensor:
    """Rotation matrix of a scalar-first quaternion, computed by scipy (scalar-last)."""
    return torch.from_numpy(Rotation.from_quat(np.roll(quat, -1)).as_matrix())


@st.composite
def transforms(draw: st.DrawFn) -> torch.Tensor:
    """A ``(1, 4, 4)`` float64 rigid transform, rotation uniform-ish over SO(3) (scipy), translation within 100."""
    rot = _rotation(draw(QUATERNIONS))
    return se3.make_transform(rot, torch.from_numpy(draw(TRANSLATIONS)))[None]


@PROFILE
@given(omega=ANGLE_VECTORS)
def test_so3_exp_is_scipy_from_rotvec(omega: np.ndarray) -> None:
    got = so3.exp(torch.from_numpy(omega))
    torch.testing.assert_close(got, torch.from_numpy(Rotation.from_rotvec(omega).as_matrix()), rtol=0, atol=1e-12)


@PROFILE
@given(quat=QUATERNIONS)
def test_so3_log_inverts_exp_and_is_scipy_as_rotvec(quat: np.ndarray) -> None:
    rot = _rotation(quat)
    omega = so3.log(rot)
    torch.testing.assert_close(so3.exp(omega), rot, rtol=0, atol=1e-9)
    angle = float(omega.norm())
    assert 0 <= angle <= np.pi + 1e-12
    if angle < np.pi - 1e-3:  # at pi, omega and -omega are both right
        expected = torch.from_numpy(Rotation.from_matrix(rot.numpy()).as_rotvec())
        torch.testing.assert_close(omega, expected, rtol=0, atol=1e-9)


@PROFILE
@given(quat=QUATERNIONS, scale=st.floats(0.2, 5.0), negate=st.booleans())
def test_quaternion_to_matrix_is_scipy_and_scale_invariant(quat: np.ndarray, scale: float, negate: bool) -> None:
    expected = _rotation(quat)
    scaled = torch.from_numpy(quat * scale * (-1 if negate else 1))
    torch.testing.assert_close(so3.quaternion_to_matrix(torch.from_numpy(quat)), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(so3.quaternion_to_matrix(scaled), expected, rtol=0, atol=1e-12)


@PROFILE
@given(
    z=st.floats(-np.pi + 1e-6, np.pi - 1e-6),
    y=st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3),
    x=st.floats(-np.pi + 1e-6, np.pi - 1e-6),
)
def test_euler_zyx_matches_scipy_and_round_trips(z: float, y: float, x: float) -> None:
    angles = torch.tensor([z, y, x], dtype=torch.float64)
    rot = euler.euler_zyx_to_matrix(angles)
    scipy_rot = Rotation.from_euler("zyx", [z, y, x])
    torch.testing.assert_close(rot, torch.from_numpy(scipy_rot.as_matrix()), rtol=0, atol=1e-12)
    back = euler.matrix_to_euler_zyx(rot)
    torch.testing.assert_close(back, angles, rtol=0, atol=1e-9)
    torch.testing.assert_close(back, torch.from_numpy(scipy_rot.as_euler("zyx")), rtol=0, atol=1e-9)


@PROFILE
@given(a=transforms(), b=transforms(), points=clouds(8))
def test_se3_compose_inverse_and_application(a: torch.Tensor, b: torch.Tensor, points: np.ndarray) -> None:
    eye = se3.identity(1, dtype=torch.float64)
    torch.testing.assert_close(se3.compose(a, se3.inverse(a)), eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(se3.compose(se3.inverse(a), a), eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(se3.inverse(se3.inverse(a)), a, rtol=0, atol=1e-12)
    torch.testing.assert_close(se3.inverse(se3.compose(a, b)), se3.compose(se3.inverse(b), se3.inverse(a)))
    p = torch.from_numpy(points.astype(np.float64)).clamp(-1e3, 1e3)[None]
    step = se3.transform_points(a, se3.transform_points(b, p))
    torch.testing.assert_close(se3.transform_points(se3.compose(a, b), p), step, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(se3.transform_points(se3.inverse(a), se3.transform_points(a, p)), p, atol=1e-9, rtol=0)


@PROFILE
@given(axis=UNIT_VECTORS, angle=st.floats(0, np.pi - 1e-3), v=TRANSLATIONS)
def test_se3_log_inverts_exp(axis: np.ndarray, angle: float, v: np.ndarray) -> None:
    xi = torch.from_numpy(np.concatenate([axis * angle, v]))
    torch.testing.assert_close(se3.log(se3.exp(xi)), xi, rtol=0, atol=1e-8)
    torch.testing.assert_close(se3.exp(xi)[:3, :3], so3.exp(xi[:3]), rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------- checks

NAMES = st.from_regex(r"[a-z][a-z_0-9]{0,11}", fullmatch=True)
DEFECTS = {
    "rank": ShapeError,
    "last_dim": ShapeError,
    "empty_batch": ShapeError,
    "dtype": TypeError,
    "not_tensor": TypeError,
    "too_few": TooFewPointsError,
    "non_finite": NonFiniteError,
}


@st.composite
def bad_points(draw: st.DrawFn) -> tuple[str, object, int]:
    """``(defect, candidate, min_points)`` with exactly one defect of :data:`DEFECTS`."""
    defect = draw(st.sampled_from(sorted(DEFECTS)))
    b, n = draw(st.integers(1, 3)), draw(st.integers(1, 6))
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    x = torch.zeros(b, n, 3, dtype=dtype)
    min_points = draw(st.integers(1, n))
    if defect == "rank":
        shape = draw(st.sampled_from([(), (n,), (n, 3), (1, b, n, 3)]))
        return defect, torch.zeros(shape, dtype=dtype), min_points
    if defect == "last_dim":
        return defect, torch.zeros(b, n, draw(st.sampled_from([0, 1, 2, 4, 6])), dtype=dtype), min_points
    if defect == "empty_batch":
        return defect, torch.zeros(0, n, 3, dtype=dtype), min_points
    if defect == "dtype":
        bad = draw(st.sampled_from([torch.int32, torch.int64, torch.float16, torch.bfloat16, torch.bool]))
        return defect, x.to(bad), min_points
    if defect == "not_tensor":
        return defect, draw(st.sampled_from([x.numpy(), x.tolist(), None, 3.0])), min_points
    if defect == "too_few":
        return defect, x, n + draw(st.integers(1, 5))
    flat = x.view(-1)
    for index in draw(st.lists(st.integers(0, flat.numel() - 1), min_size=1, max_size=3)):
        flat[index] = draw(st.sampled_from([float("nan"), float("inf"), float("-inf")]))
    return defect, x, min_points


@PROFILE
@given(case=bad_points(), name=NAMES)
def test_check_points_raises_the_typed_error_naming_the_argument(case: tuple[str, object, int], name: str) -> None:
    defect, candidate, min_points = case
    with pytest.raises(ValueError if DEFECTS[defect] is not TypeError else TypeError) as info:
        check_points(candidate, name, min_points=min_points)
    assert type(info.value) is DEFECTS[defect], (defect, info.value)
    assert f"`{name}`" in str(info.value)


@PROFILE
@given(points=clouds(10), batch=st.integers(1, 3), double=st.booleans())
def test_check_points_returns_valid_input_unchanged(points: np.ndarray, batch: int, double: bool) -> None:
    x = torch.from_numpy(np.repeat(points[None], batch, axis=0)).to(torch.float64 if double else torch.float32)
    assert check_points(x, "x", min_points=len(points)) is x


# --------------------------------------------------------------------------------------------------------- metrics

PAIRS = st.tuples(transforms(), transforms())


def _swap_sign(f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], a: torch.Tensor, b: torch.Tensor) -> None:
    torch.testing.assert_close(f(a, b), -f(b, a), rtol=0, atol=0)


@PROFILE
@given(t=transforms(), single=st.booleans())
def test_metrics_of_a_perfect_estimate_are_zero(t: torch.Tensor, single: bool) -> None:
    t = t.float() if single else t
    assert float(functional.rotation_error_deg(t, t)) < (1e-3 if single else 1e-9)
    assert float(functional.translation_error(t, t)) == 0.0
    assert not functional.euler_errors_deg(t, t).any() and not functional.translation_errors(t, t).any()
    metrics = registration_metrics()
    metrics.update(transform_pred=t, transform_gt=t)
    values = {k: float(v) for k, v in metrics.compute().items()}
    assert values.pop("recall_r2_t0p01") == values.pop("recall_r5_t0p05") == 1.0
    assert all(abs(v) < 1e-3 for v in values.values()), values


@PROFILE
@given(pair=PAIRS, common=transforms())
def test_rotation_error_is_a_bi_invariant_metric_matching_scipy(
    pair: tuple[torch.Tensor, torch.Tensor], common: torch.Tensor
) -> None:
    a, b = pair
    err = functional.rotation_error_deg(a, b)
    rel = Rotation.from_matrix(a[0, :3, :3].numpy()).inv() * Rotation.from_matrix(b[0, :3, :3].numpy())
    assert abs(float(err) - np.degrees(rel.magnitude())) < 1e-6
    assert 0 <= float(err) <= 180
    torch.testing.assert_close(functional.rotation_error_deg(b, a), err, rtol=0, atol=1e-9)
    q = se3.make_transform(common[:, :3, :3], torch.zeros(1, 3, dtype=torch.float64))
    torch.testing.assert_close(functional.rotation_error_deg(q @ a, q @ b), err, rtol=0, atol=1e-6)
    torch.testing.assert_close(functional.rotation_error_deg(a @ q, b @ q), err, rtol=0, atol=1e-6)


@PROFILE
@given(a=transforms(), b=transforms(), c=transforms())
def test_rotation_error_triangle_inequality(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> None:
    ab, bc, ac = (float(functional.rotation_error_deg(p, q)) for p, q in ((a, b), (b, c), (a, c)))
    assert ac <= ab + bc + 1e-6


@PROFILE
@given(pair=PAIRS)
def test_translation_and_euler_errors_are_antisymmetric(pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    a, b = pair
    _swap_sign(functional.translation_errors, a, b)
    _swap_sign(functional.euler_errors_deg, a, b)
    assert float(functional.translation_error(a, b)) == float(functional.translation_error(b, a))
    expected = np.linalg.norm(a[0, :3, 3].numpy() - b[0, :3, 3].numpy())
    assert abs(float(functional.translation_error(a, b)) - expected) < 1e-9


@PROFILE
@given(
    errors=hnp.arrays(np.float64, st.tuples(st.integers(1, 20), st.just(2)), elements=st.floats(0, 200)),
    failed=st.lists(st.integers(0, 19), max_size=3),
    thresholds=st.lists(st.floats(0, 200), min_size=4, max_size=4),
)
def test_registration_recall_is_a_monotone_fraction(
    errors: np.ndarray, failed: list[int], thresholds: list[float]
) -> None:
    rot, trans = torch.from_numpy(errors).unbind(1)
    for index in failed:
        if index < len(rot):
            rot[index] = float("nan")  # a failed pair never counts as a success
    r1, r2 = sorted(thresholds[:2])
    t1, t2 = sorted(thresholds[2:])
    low = float(functional.registration_recall(rot, trans, r1, t1))
    high = float(functional.registration_recall(rot, trans, r2, t2))
    assert 0 <= low <= high <= 1
    expected = np.mean((errors[:, 0] < r2) & (errors[:, 1] < t2) & ~np.isnan(rot.numpy()))
    assert high == pytest.approx(expected)
