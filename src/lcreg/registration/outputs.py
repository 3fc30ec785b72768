"""Files ``lcreg register`` writes and reads: the transform (``.txt``, ``.json``, ``.npy``), the moved source (.ply).

Every file is written to a temporary name in the target folder and renamed into place, so an error or a kill never
leaves a half-written file, and nothing is written when the registration fails.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = ["TRANSFORM_SUFFIXES", "TransformFileError", "read_transform", "write_ply", "write_transform"]

TRANSFORM_SUFFIXES = (".txt", ".json", ".npy")


class TransformFileError(ValueError):
    """A transform file that cannot be read or written (the message names it)."""


def _atomic(path: Path, write: Callable[[IO[bytes]], object]) -> Path:
    """Write through ``write(handle)`` to a temporary file beside ``path``, then rename it to ``path``."""
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write {str(path)!r}: folder {str(path.parent)!r} does not exist")
    handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as fh:
            write(fh)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600: give the file the mode open() would
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _umask() -> int:
    """The process's umask (read by setting it, then restored)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_suffix(path: str | Path, allowed: tuple[str, ...], option: str) -> Path:
    """``path`` as a Path whose suffix is one of ``allowed`` (``ValueError`` naming ``option`` otherwise)."""
    out = Path(path).expanduser()
    if out.suffix.lower() not in allowed:
        raise ValueError(f"{option} {str(out)!r}: the extension must be one of {', '.join(allowed)}")
    return out


def write_transform(path: str | Path, transform: np.ndarray, details: dict[str, Any] | None = None) -> Path:
    """Write a ``(4, 4)`` transform: ``.txt`` (4 rows of 4 numbers), ``.npy`` (float64) or ``.json``.

    Args:
        path: Target file; its extension picks the format.
        transform: ``(4, 4)`` float64.
        details: ``.json`` only: the whole record (:meth:`Registration.to_dict`), which holds the transform under
            ``transform_ref_src``; other formats store the matrix alone.

    Returns:
        The path written.
    """
    out = check_suffix(path, TRANSFORM_SUFFIXES, "--out")
    matrix = np.asarray(transform, dtype=np.float64).reshape(4, 4)
    suffix = out.suffix.lower()
    if suffix == ".txt":
        return _atomic(out, lambda fh: np.savetxt(fh, matrix, fmt="%.10g"))
    if suffix == ".npy":
        return _atomic(out, lambda fh: np.save(fh, matrix))
    record = dict(details or {}) | {"transform_ref_src": matrix.tolist()}
    return _atomic(out, lambda fh: fh.write((json.dumps(record, indent=2) + "\n").encode()))


def read_transform(path: str | Path) -> np.ndarray:
    """Read a transform written by :func:`write_transform` (or any 4x4 text/npy, or JSON with ``transform_ref_src``).

    Raises:
        FileNotFoundError: No such file.
        TransformFileError: Not a ``(4, 4)`` finite matrix in one of the formats.
    """
    src = check_suffix(path, TRANSFORM_SUFFIXES, "transform file")
    if not src.is_file():
        raise FileNotFoundError(f"transform file {str(src)!r} does not exist")
    try:
        if src.suffix.lower() == ".npy":
            value = np.load(src, allow_pickle=False)
        elif src.suffix.lower() == ".json":
            value = np.asarray(json.loads(src.read_text())["transform_ref_src"], dtype=np.float64)
        else:
            value = np.loadtxt(src, dtype=np.float64, ndmin=2)
        matrix = np.asarray(value, dtype=np.float64)
    except (ValueError, KeyError, TypeError, OSError) as err:
        raise TransformFileError(f"transform file {str(src)!r} could not be read: {err}") from err
    if matrix.size != 16 or not np.isfinite(matrix).all():
        raise TransformFileError(f"transform file {str(src)!r} must hold 16 finite numbers (a 4x4), got {matrix.shape}")
    return matrix.reshape(4, 4)


def write_ply(path: str | Path, points: np.ndarray) -> Path:
    """Write ``(N, 3)`` points as a binary little-endian PLY of float32 ``x y z`` (readable by any PLY reader).

    Returns:
        The path written.
    """
    out = check_suffix(path, (".ply",), "--save-aligned")
    array = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by lcreg register\n"
        f"element vertex {len(array)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )

    def write(fh: IO[bytes]) -> None:
        fh.write(header.encode("ascii"))
        fh.write(array.tobytes())

    return _atomic(out, write)
