"""Validating parsers of point-cloud file formats, private to :mod:`lcreg.data.io`.

Every parser checks that the file is exactly what its header claims before it builds an array: the byte size of a
binary payload, the line count of a text payload, the size fields of a compressed payload. Nothing is allocated from
a header's claims alone, so a lying or truncated file costs no more memory than its own size. A parser returns the
``x, y, z`` columns in their stored dtype (the caller casts and checks finiteness) and raises :class:`FileFormatError`
(the caller adds the file name).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

__all__ = ["FileFormatError", "read_kitti_bin", "read_npy", "read_pcd", "read_ply", "read_text"]

HEADER_LIMIT = 1 << 20  # bytes searched for the end of a PLY/PCD header
LZF_MAX_RATIO = 88  # LZF expands at most 88-fold: a 3-byte back-reference copies at most 264 bytes


class FileFormatError(ValueError):
    """The bytes of a file do not follow its format (the caller names the file)."""


# ------------------------------------------------------------------------------------------------------------ shared


def _header_lines(data: bytes, is_last: Callable[[str], bool], last: str) -> tuple[list[str], int]:
    """ASCII lines of a header up to and including the ``last`` line (where ``is_last`` holds), and the header size."""
    lines: list[str] = []
    offset = 0
    while True:
        end = data.find(b"\n", offset, HEADER_LIMIT)
        if end < 0:
            raise FileFormatError(f"the header does not end: no complete {last} line in the first {HEADER_LIMIT} bytes")
        try:
            line = data[offset:end].decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            raise FileFormatError(f"header line {len(lines) + 1} is not ASCII text") from None
        lines.append(line)
        offset = end + 1
        if is_last(line):
            return lines, offset


def _count(word: str, what: str) -> int:
    """A non-negative decimal integer of a header."""
    if not (word.isascii() and word.isdigit()) or len(word) > 19:  # 19 digits: beyond any real file's count
        raise FileFormatError(f"{what} must be a non-negative integer of at most 19 digits, got {word[:40]!r}")
    return int(word)


def _text_rows(body: bytes, what: str) -> list[str]:
    """The non-blank lines of an ASCII payload."""
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as err:
        raise FileFormatError(f"the {what} is not ASCII text (byte {err.start})") from None
    return [line for line in text.split("\n") if line.strip()]


def _parse_rows(rows: Sequence[str], columns: int | None, what: str) -> np.ndarray:
    """Parse text rows of numbers into a float64 ``(len(rows), columns)`` array (``columns=None``: any, >= 3)."""
    try:
        values = np.loadtxt(rows, dtype=np.float64, ndmin=2, comments=None)
    except ValueError as err:
        raise FileFormatError(f"the {what} are not rows of numbers ({err})") from None
    width = values.shape[1]
    if (columns is None and width < 3) or (columns is not None and width != columns):
        expected = ">= 3" if columns is None else str(columns)
        raise FileFormatError(f"the {what} have {width} value(s) per line, expected {expected}")
    return values


def _needs_final_newline(body: bytes) -> None:
    if body and not body.endswith(b"\n"):
        raise FileFormatError("the last line is cut short (no final newline)")


# --------------------------------------------------------------------------------------------------------------- PLY

PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
PLY_TYPES = {
    **dict.fromkeys(("char", "int8"), "i1"),
    **dict.fromkeys(("uchar", "uint8"), "u1"),
    **dict.fromkeys(("short", "int16"), "i2"),
    **dict.fromkeys(("ushort", "uint16"), "u2"),
    **dict.fromkeys(("int", "int32"), "i4"),
    **dict.fromkeys(("uint", "uint32"), "u4"),
    **dict.fromkeys(("float", "float32"), "f4"),
    **dict.fromkeys(("double", "float64"), "f8"),
}
STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}


@dataclass(frozen=True)
class _PlyProperty:
    name: str
    dtype: str  # numpy code without byte order ("f4"); the item type of a list
    count_dtype: str | None = None  # integer code of a list's length; None for a scalar


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[_PlyProperty] = field(default_factory=list)

    def fixed_size(self) -> int | None:
        """Bytes of one record, or None when the element has list properties."""
        if any(p.count_dtype is not None for p in self.properties):
            return None
        return sum(np.dtype(p.dtype).itemsize for p in self.properties)


def _ply_type(word: str, integer: bool = False) -> str:
    code = PLY_TYPES.get(word)
    if code is None or (integer and code not in STRUCT_CODES):
        raise FileFormatError(f"unknown PLY {'list length ' if integer else ''}type {word!r}")
    return code


def _ply_property(words: list[str]) -> _PlyProperty:
    if len(words) == 3:
        return _PlyProperty(words[2], _ply_type(words[1]))
    if len(words) == 5 and words[1] == "list":
        return _PlyProperty(words[4], _ply_type(words[3]), _ply_type(words[2], integer=True))
    raise FileFormatError(f"malformed PLY property line {' '.join(words)!r}")


def _ply_header(data: bytes) -> tuple[str, list[_PlyElement], int]:
    """Byte order (``""`` for ASCII), elements and header size of a PLY file."""
    if not data.startswith(b"ply"):
        raise FileFormatError("not a PLY file (it does not start with 'ply')")
    lines, size = _header_lines(data, lambda line: line.strip() == "end_header", "'end_header'")
    if lines[0].strip() != "ply":
        raise FileFormatError("not a PLY file (its first line is not 'ply')")
    order: str | None = None
    elements: list[_PlyElement] = []
    for line in lines[1:-1]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and order is None and not elements:
            if len(words) != 3 or words[1] not in PLY_FORMATS or words[2] != "1.0":
                raise FileFormatError(f"unsupported PLY format line {line!r}")
            order = PLY_FORMATS[words[1]]
        elif words[0] == "element" and len(words) == 3:
            if any(e.name == words[1] for e in elements):
                raise FileFormatError(f"PLY element {words[1]!r} is declared twice")
            elements.append(_PlyElement(words[1], _count(words[2], f"the count of PLY element {words[1]!r}")))
        elif words[0] == "property" and elements:
            prop = _ply_property(words)
            if any(p.name == prop.name for p in elements[-1].properties):
                raise FileFormatError(f"PLY property {prop.name!r} of {elements[-1].name!r} is declared twice")
            elements[-1].properties.append(prop)
        else:
            raise FileFormatError(f"unexpected PLY header line {line!r}")
    if order is None:
        raise FileFormatError("the PLY header has no format line")
    return order, elements, size


def _vertex_element(elements: list[_PlyElement]) -> int:
    """Index of the vertex element, checked to hold scalar ``x, y, z`` and at least one point."""
    index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if index is None:
        raise FileFormatError("the PLY header declares no vertex element")
    vertex = elements[index]
    names = [p.name for p in vertex.properties]
    if vertex.fixed_size() is None:
        raise FileFormatError("list properties in the PLY vertex element are not supported")
    if not {"x", "y", "z"} <= set(names):
        raise FileFormatError(f"the PLY vertex element has no x, y, z properties (it has {names})")
    if vertex.count == 0:
        raise FileFormatError("the PLY header declares 0 vertices")
    return index


def _record_dtype(props: Sequence[tuple[str, str, int]], itemsize: int, order: str) -> np.dtype:
    """Structured dtype picking the named fields ``(name, code, byte offset)`` of a record of ``itemsize`` bytes."""
    return np.dtype(
        {
            "names": [name for name, _, _ in props],
            "formats": [order + code for _, code, _ in props],
            "offsets": [offset for _, _, offset in props],
            "itemsize": itemsize,
        }
    )


def _xyz_columns(record: np.ndarray) -> np.ndarray:
    return np.stack([record["x"], record["y"], record["z"]], axis=1)


def _first_record(element: _PlyElement, data: bytes, offset: int, order: str) -> tuple[int, list[tuple[int, str, int]]]:
    """Size of the record at ``offset`` and its list lengths ``(position in the record, length code, length)``."""
    position = 0
    lengths = []
    for prop in element.properties:
        if prop.count_dtype is None:
            position += np.dtype(prop.dtype).itemsize
            continue
        length = _list_length(data, offset + position, prop.count_dtype, order)
        lengths.append((position, prop.count_dtype, length))
        position += np.dtype(prop.count_dtype).itemsize + length * np.dtype(prop.dtype).itemsize
    return position, lengths


def _min_record_size(element: _PlyElement) -> int:
    """Bytes of a record of ``element`` whose lists are all empty."""
    return sum(np.dtype(p.dtype if p.count_dtype is None else p.count_dtype).itemsize for p in element.properties)


def _list_length(data: bytes, offset: int, code: str, order: str) -> int:
    fmt = order + STRUCT_CODES[code]
    if offset + struct.calcsize(fmt) > len(data):
        raise FileFormatError("the file ends inside a PLY list")
    (length,) = struct.unpack_from(fmt, data, offset)
    if length < 0:
        raise FileFormatError(f"a PLY list has a negative length {length}")
    return int(length)


def _uniform_list_size(element: _PlyElement, data: bytes, offset: int, order: str) -> int | None:
    """Bytes of a list element whose records all have the first record's list lengths (a triangle mesh), else None."""
    record, lengths = _first_record(element, data, offset, order)
    total = element.count * record
    if offset + total > len(data):
        return None
    block = np.frombuffer(data, np.uint8, count=total, offset=offset).reshape(element.count, record)
    for position, code, length in lengths:
        size = np.dtype(code).itemsize
        stored = np.ascontiguousarray(block[:, position : position + size]).view(order + code)
        if (stored != length).any():
            return None
    return total


def _walk_list_element(element: _PlyElement, data: bytes, offset: int, order: str) -> int:
    """Bytes of a list element, record by record (every record has a length field, so at most ``len(data)`` steps)."""
    start = offset
    for _ in range(element.count):
        for prop in element.properties:
            if prop.count_dtype is not None:
                length = _list_length(data, offset, prop.count_dtype, order)
                offset += np.dtype(prop.count_dtype).itemsize + length * np.dtype(prop.dtype).itemsize
            else:
                offset += np.dtype(prop.dtype).itemsize
        if offset > len(data):
            raise FileFormatError(f"the file ends inside PLY element {element.name!r}")
    return offset - start


def _binary_element_offsets(elements: list[_PlyElement], data: bytes, start: int, order: str) -> list[int]:
    """Byte offset of every element of a binary PLY file, checked to end exactly at the end of the file."""
    offsets = []
    offset = start
    for element in elements:
        offsets.append(offset)
        size = element.count * _min_record_size(element)  # exact without lists, else a lower bound (empty lists)
        if element.fixed_size() is None and size and offset + size <= len(data):
            uniform = _uniform_list_size(element, data, offset, order)
            size = _walk_list_element(element, data, offset, order) if uniform is None else uniform
        offset += size
        if offset > len(data):
            raise FileFormatError(
                f"the file is cut short: {len(data)} bytes, PLY element {element.name!r} ({element.count} records) "
                f"needs at least {offset}"
            )
    if offset != len(data):
        raise FileFormatError(f"{len(data) - offset} unexpected byte(s) after the last PLY element")
    return offsets


def _read_binary_ply(elements: list[_PlyElement], index: int, data: bytes, start: int, order: str) -> np.ndarray:
    offset = _binary_element_offsets(elements, data, start, order)[index]
    vertex = elements[index]
    picked, position = [], 0
    for prop in vertex.properties:
        if prop.name in ("x", "y", "z"):
            picked.append((prop.name, prop.dtype, position))
        position += np.dtype(prop.dtype).itemsize
    record = np.frombuffer(data, _record_dtype(picked, position, order), count=vertex.count, offset=offset)
    return _xyz_columns(record)


def _read_ascii_ply(elements: list[_PlyElement], index: int, body: bytes) -> np.ndarray:
    _needs_final_newline(body)
    rows = _text_rows(body, "PLY data")
    declared = sum(e.count for e in elements)
    if len(rows) != declared:
        raise FileFormatError(
            f"{len(rows)} data line(s), the PLY header declares {declared} ({elements[index].count} vertices)"
        )
    vertex = elements[index]
    first = sum(e.count for e in elements[:index])
    values = _parse_rows(rows[first : first + vertex.count], len(vertex.properties), "PLY vertex lines")
    names = [p.name for p in vertex.properties]
    return values[:, [names.index("x"), names.index("y"), names.index("z")]]


def read_ply(path: Path) -> np.ndarray:
    """``x, y, z`` of the vertices of an ASCII or binary PLY file, validated against its header."""
    data = path.read_bytes()
    order, elements, start = _ply_header(data)
    index = _vertex_element(elements)
    if order:
        return _read_binary_ply(elements, index, data, start, order)
    return _read_ascii_ply(elements, index, data[start:])


# --------------------------------------------------------------------------------------------------------------- PCD

PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
PCD_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}


@dataclass(frozen=True)
class _PcdField:
    name: str
    code: str  # numpy code without byte order ("f4")
    count: int

    @property
    def size(self) -> int:
        return np.dtype(self.code).itemsize * self.count


def _pcd_entries(data: bytes) -> tuple[dict[str, list[str]], int]:
    """The keyword lines of a PCD header (each keyword at most once) and the header size."""
    lines, size = _header_lines(data, lambda line: line.startswith("DATA"), "'DATA'")
    entries: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if words[0] not in PCD_KEYS or words[0] in entries or len(words) < 2:
            raise FileFormatError(f"unexpected PCD header line {line!r}")
        entries[words[0]] = words[1:]
    return entries, size


def _pcd_fields(entries: dict[str, list[str]]) -> list[_PcdField]:
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT"):
        if key not in entries:
            raise FileFormatError(f"the PCD header has no {key} line")
    names, sizes, types = entries["FIELDS"], entries["SIZE"], entries["TYPE"]
    counts = entries.get("COUNT", ["1"] * len(names))
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise FileFormatError("the PCD FIELDS, SIZE, TYPE and COUNT lines have different lengths")
    if len(set(names)) != len(names):
        raise FileFormatError(f"the PCD FIELDS repeat a name: {names}")
    fields = []
    for name, size_word, kind, count_word in zip(names, sizes, types, counts):
        size = _count(size_word, f"the SIZE of PCD field {name!r}")
        if size not in PCD_SIZES.get(kind, ()):
            raise FileFormatError(f"PCD field {name!r}: unsupported TYPE {kind!r} with SIZE {size}")
        fields.append(_PcdField(name, f"{kind.lower()}{size}", _count(count_word, f"the COUNT of PCD field {name!r}")))
    if not {"x", "y", "z"} <= set(names) or any(f.count != 1 for f in fields if f.name in ("x", "y", "z")):
        raise FileFormatError(f"the PCD file has no scalar x, y, z fields (FIELDS {' '.join(names)})")
    return fields


def _pcd_number(entries: dict[str, list[str]], key: str, default: int | None = None) -> int:
    words = entries.get(key, [str(default)])
    if len(words) != 1:
        raise FileFormatError(f"the PCD {key} line must hold one number, got {' '.join(words)!r}")
    return _count(words[0], f"the PCD {key}")


def _pcd_points(entries: dict[str, list[str]]) -> int:
    """POINTS, checked against WIDTH * HEIGHT."""
    width, height = _pcd_number(entries, "WIDTH"), _pcd_number(entries, "HEIGHT")
    points = _pcd_number(entries, "POINTS", width * height)
    if points != width * height:
        raise FileFormatError(f"PCD POINTS {points} is not WIDTH {width} x HEIGHT {height}")
    if points == 0:
        raise FileFormatError("the PCD header declares 0 points")
    return points


def _pcd_offsets(fields: list[_PcdField]) -> tuple[list[tuple[str, str, int]], int]:
    """``(name, code, byte offset)`` of x, y, z within a record, and the record size."""
    picked, position = [], 0
    for f in fields:
        if f.name in ("x", "y", "z"):
            picked.append((f.name, f.code, position))
        position += f.size
    return picked, position


def _read_ascii_pcd(fields: list[_PcdField], points: int, body: bytes) -> np.ndarray:
    _needs_final_newline(body)
    rows = _text_rows(body, "PCD data")
    if len(rows) != points:
        raise FileFormatError(f"{len(rows)} data line(s), the PCD header declares POINTS {points}")
    values = _parse_rows(rows, sum(f.count for f in fields), "PCD data lines")
    columns, column = {}, 0
    for f in fields:
        columns[f.name] = column
        column += f.count
    return values[:, [columns["x"], columns["y"], columns["z"]]]


def _read_binary_pcd(fields: list[_PcdField], points: int, body: bytes) -> np.ndarray:
    picked, record = _pcd_offsets(fields)
    if len(body) != points * record:
        raise FileFormatError(
            f"the binary payload has {len(body)} bytes; POINTS {points} x {record}-byte records need {points * record}"
        )
    return _xyz_columns(np.frombuffer(body, _record_dtype(picked, record, "<"), count=points))


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress an LZF stream (liblzf's format) that must expand to exactly ``size`` bytes.

    A control byte below 32 starts a run of ``ctrl + 1`` literal bytes; otherwise its top 3 bits are a length
    (7: one more length byte follows) and its low 5 bits the high bits of a back-reference distance whose low byte
    follows; a back-reference copies ``length + 2`` bytes and may overlap its own output.
    """
    out = bytearray(size)
    src, dst = 0, 0
    while src < len(data):
        ctrl = data[src]
        src += 1
        if ctrl < 32:
            length = ctrl + 1
            if src + length > len(data) or dst + length > size:
                raise FileFormatError("the LZF stream is corrupt (a literal run overflows)")
            out[dst : dst + length] = data[src : src + length]
            src += length
        else:
            length = ctrl >> 5
            if length == 7:
                length += data[src] if src < len(data) else 0
                src += 1
            if src >= len(data):
                raise FileFormatError("the LZF stream is corrupt (it ends inside a back-reference)")
            ref = dst - ((ctrl & 0x1F) << 8) - data[src] - 1
            src += 1
            length += 2
            if ref < 0 or dst + length > size:
                raise FileFormatError("the LZF stream is corrupt (a back-reference points outside the output)")
            if dst - ref >= length:
                out[dst : dst + length] = out[ref : ref + length]
            else:  # the copy overlaps its own output: repeat the period
                period = out[ref:dst]
                out[dst : dst + length] = (period * (length // len(period) + 1))[:length]
        dst += length
    if dst != size:
        raise FileFormatError(f"the LZF stream expands to {dst} bytes, its header says {size}")
    return bytes(out)


def _read_compressed_pcd(fields: list[_PcdField], points: int, body: bytes) -> np.ndarray:
    picked, record = _pcd_offsets(fields)
    if len(body) < 8:
        raise FileFormatError("the binary_compressed payload has no size fields")
    compressed, uncompressed = struct.unpack_from("<II", body)
    if uncompressed != points * record:
        raise FileFormatError(
            f"the uncompressed size {uncompressed} is not POINTS {points} x {record}-byte records ({points * record})"
        )
    if len(body) != 8 + compressed:
        raise FileFormatError(f"the compressed payload has {len(body) - 8} bytes, its size field says {compressed}")
    if uncompressed > LZF_MAX_RATIO * compressed:
        raise FileFormatError(f"{compressed} compressed bytes cannot expand to {uncompressed}")
    raw = lzf_decompress(body[8:], uncompressed)
    # binary_compressed stores fields one after the other (all x, then all y, ...): field offset x POINTS
    columns = [np.frombuffer(raw, "<" + code, count=points, offset=offset * points) for _, code, offset in picked]
    order = [name for name, _, _ in picked]
    return np.stack([columns[order.index(axis)] for axis in ("x", "y", "z")], axis=1)


def read_pcd(path: Path) -> np.ndarray:
    """``x, y, z`` of a PCD file (DATA ascii, binary or binary_compressed), validated against its header."""
    data = path.read_bytes()
    entries, start = _pcd_entries(data)
    fields, points = _pcd_fields(entries), _pcd_points(entries)
    kind = entries["DATA"]
    body = data[start:]
    if kind == ["ascii"]:
        return _read_ascii_pcd(fields, points, body)
    if kind == ["binary"]:
        return _read_binary_pcd(fields, points, body)
    if kind == ["binary_compressed"]:
        return _read_compressed_pcd(fields, points, body)
    raise FileFormatError(f"unsupported PCD DATA {' '.join(kind)!r}")


# -------------------------------------------------------------------------------------------------- text, npy, bin

TEXT_COLUMNS = {".xyz": None, ".xyzn": 6, ".xyzrgb": 6, ".pts": None}


def read_text(path: Path) -> np.ndarray:
    """``x, y, z`` of a text file of one point a line (``.pts``: after a first line holding the point count)."""
    suffix = path.suffix.lower()
    rows = _text_rows(path.read_bytes(), f"{suffix} file")
    if suffix == ".pts" and rows:
        declared = _count(rows[0].strip(), "the point count on the first line of a .pts file")
        rows = rows[1:]
        if len(rows) != declared:
            raise FileFormatError(f"{len(rows)} point line(s), the first line declares {declared}")
    if not rows:
        return np.zeros((0, 3))
    return _parse_rows(rows, TEXT_COLUMNS[suffix], "point lines")[:, :3]


def _npy_header(file: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and dtype of an open ``.npy`` file; any failure of numpy's parser is a format error."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(file)
        if version not in ((1, 0), (2, 0)):
            raise FileFormatError(f"unsupported .npy format version {version}")
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        return read(file)
    except FileFormatError:
        raise
    except Exception as err:  # a garbled header fails in the tokenizer, literal_eval, dtype parsing, ...
        raise FileFormatError(f"not a readable .npy file ({type(err).__name__}: {err})") from None


def _check_npy_dtype(dtype: np.dtype) -> None:
    if dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in "iuf":
        reason = {"c": "complex values have no single coordinate", "b": "booleans are not coordinates"}
        detail = reason.get(dtype.kind, "expected an integer or float array")
        raise FileFormatError(f"unsupported .npy dtype {dtype} ({detail})")


def read_npy(path: Path) -> np.ndarray:
    """``x, y, z`` (first 3 columns) of an ``(N, C >= 3)`` numeric ``.npy`` array, its size checked before loading."""
    with path.open("rb") as file:
        shape, fortran_order, dtype = _npy_header(file)
        if len(shape) != 2 or shape[1] < 3 or min(shape) < 0:
            raise FileFormatError(f"expected an (N, 3) or (N, C>=3) array, got shape {shape}")
        _check_npy_dtype(dtype)
        needed = math.prod(shape) * dtype.itemsize
        payload = path.stat().st_size - file.tell()
        if payload != needed:
            raise FileFormatError(f"the header declares shape {shape} of {dtype} ({needed} bytes); payload {payload}")
        array = np.fromfile(file, dtype=dtype, count=math.prod(shape))
    return array.reshape(shape, order="F" if fortran_order else "C")[:, :3]


def read_kitti_bin(path: Path) -> np.ndarray:
    """``x, y, z`` of a KITTI velodyne scan: little-endian float32 records ``(x, y, z, reflectance)``."""
    size = path.stat().st_size
    if size % 16:
        raise FileFormatError(f"a KITTI .bin holds float32 (x, y, z, r) records of 16 bytes; size {size}")
    return np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]
