"""Independent writers of PLY, PCD and .npy bytes for the reader tests (tests/data/test_io.py, test_properties.py).

Text values are written with ``repr`` of the float64 value of each float32, which parses back to the same float32.
"""

from __future__ import annotations

import io
import struct

import numpy as np

PLY_NAMES = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "i2": "short"}
PLY_ORDERS = {"binary_little_endian": "<", "binary_big_endian": ">"}


def _text(value: object) -> str:
    return repr(float(value)) if isinstance(value, np.floating | float) else str(value)


def ply_bytes(
    points: np.ndarray,
    fmt: str = "binary_little_endian",
    extra: dict[str, np.ndarray] | None = None,
    faces: np.ndarray | None = None,
    declared: int | None = None,
) -> bytes:
    """A PLY file of float ``x, y, z`` plus ``extra`` vertex columns (typed by their dtype) and triangle ``faces``.

    Args:
        points: ``(N, 3)`` float32 coordinates.
        fmt: ``ascii``, ``binary_little_endian`` or ``binary_big_endian``.
        extra: More vertex properties, name -> ``(N,)`` array of a dtype in :data:`PLY_NAMES`.
        faces: ``(F, 3)`` int32 vertex indices of a ``face`` element (``property list uchar int``).
        declared: The vertex count written in the header (default: the true one).
    """
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], **(extra or {})}
    count = len(points) if declared is None else declared
    header = ["ply", f"format {fmt} 1.0", "comment lcreg test", f"element vertex {count}"]
    header += [f"property {PLY_NAMES[col.dtype.str[1:]]} {name}" for name, col in columns.items()]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head = ("\n".join([*header, "end_header"]) + "\n").encode()
    if fmt == "ascii":
        rows = [" ".join(_text(v) for v in row) for row in zip(*columns.values())]
        rows += ["3 " + " ".join(map(str, face)) for face in ([] if faces is None else faces)]
        return head + "".join(row + "\n" for row in rows).encode()
    order = PLY_ORDERS[fmt]
    vertices = np.zeros(len(points), [(name, order + col.dtype.str[1:]) for name, col in columns.items()])
    for name, col in columns.items():
        vertices[name] = col
    body = vertices.tobytes()
    if faces is not None:
        records = np.zeros(len(faces), [("n", "u1"), ("i", order + "i4", (3,))])
        records["n"], records["i"] = 3, faces
        body += records.tobytes()
    return head + body


def lzf_literals(raw: bytes) -> bytes:
    """A valid LZF stream of ``raw`` made of literal runs only (control byte ``length - 1``, then the bytes)."""
    return b"".join(bytes([len(raw[i : i + 32]) - 1]) + raw[i : i + 32] for i in range(0, len(raw), 32))


def pcd_bytes(points: np.ndarray, data: str = "binary", intensity: np.ndarray | None = None) -> bytes:
    """A PCD v0.7 file of float32 ``x, y, z`` (and a float32 ``intensity`` before them if given).

    ``binary_compressed`` stores the fields one after the other and compresses with :func:`lzf_literals`.
    """
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    if intensity is not None:
        columns = {"intensity": intensity.astype(np.float32), **columns}
    n, k = len(points), len(columns)
    header = (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(columns)}\nSIZE {' '.join('4' * k)}\nTYPE {' '.join('F' * k)}\n"
        f"COUNT {' '.join('1' * k)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode()
    table = np.stack(list(columns.values()), axis=1).astype("<f4")
    if data == "ascii":
        return header + "".join(" ".join(map(_text, row)) + "\n" for row in table).encode()
    if data == "binary":
        return header + table.tobytes()
    raw = table.T.tobytes()  # field after field
    packed = lzf_literals(raw)
    return header + struct.pack("<II", len(packed), len(raw)) + packed


def npy_bytes(array: np.ndarray) -> bytes:
    """The bytes ``np.save`` writes for ``array``."""
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()
