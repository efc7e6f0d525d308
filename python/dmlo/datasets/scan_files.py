"""Single scan files: KITTI ``.bin`` and ``.label``, PLY and PCD, parsed with numpy.

The PLY and PCD parsers are dmlo's own rather than plyfile's and pypcd4's (docs/measurements.md, "PLY and
PCD readers", compares them on real scans): plyfile reads binary PLY no faster and ASCII PLY slower; pypcd4
reads PCD no faster, refuses headers without ``COUNT`` or ``POINTS`` (optional in older files) or with more
than ten lines, and reads a truncated file as fewer points instead of refusing it. Only the LZF decoding of
``binary_compressed`` PCD is borrowed: liblzf's C decoder from the ``io`` extra (``python-neo-lzf``, the one
pypcd4 uses), far faster than decoding in Python.

Every reader returns an ``(N, 4)`` float32 array ``x, y, z, reflectance`` and raises
:class:`~dmlo.datasets.base.DatasetError` naming the file and the problem for anything truncated or
malformed.

Reflectance is normalised to [0, 1]: a ``uint8`` field is divided by 255; any other field is kept when all
its values lie in [0, 1] and otherwise read as 8-bit intensity (divided by 255, clipped to [0, 1]). The field
is the first of ``intensity``, ``reflectance``, ``remission``, ``scalar_intensity``, ``i`` (any case); a
file without one gets zero reflectance. PLY and PCD points with a non-finite coordinate (organised PCD
clouds mark missing returns with NaN) are dropped.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dmlo.datasets.base import DatasetError

__all__ = [
    "SCAN_SUFFIXES",
    "LzfUnavailable",
    "in_scan_order",
    "lzf_decompress",
    "read_bin",
    "read_labels",
    "read_pcd",
    "read_ply",
    "read_scan",
    "write_bin",
    "write_labels",
]

SCAN_SUFFIXES = (".bin", ".ply", ".pcd")
REFLECTANCE_FIELDS = ("intensity", "reflectance", "remission", "scalar_intensity", "i")

PathLike = str | os.PathLike[str]


_NUMBER = re.compile(r"\d+(\.\d+)?")


def in_scan_order(paths: Iterable[Path]) -> list[Path]:
    """``paths`` in recording order: by the numeric value of their stems when every stem is a number
    (``1.bin, 2.bin, 10.bin``, or timestamps such as ``1623456789.123456.pcd``), so unpadded frame
    numbers do not run 1, 10, 2; otherwise by file name. Ties (``7.bin`` and ``07.bin``) go by name."""
    paths = list(paths)
    if paths and all(_NUMBER.fullmatch(path.stem) for path in paths):
        # Decimal, not float: nanosecond timestamps have more digits than a float holds.
        return sorted(paths, key=lambda path: (Decimal(path.stem), path.name))
    return sorted(paths)


def _read_bytes(path: Path) -> bytes:
    if not path.is_file():
        raise DatasetError(f"{path}: scan file not found")
    return path.read_bytes()


# ----------------------------------------------------------------------------------------------------
# KITTI .bin / .label


def read_bin(path: PathLike) -> NDArray[np.float32]:
    """A KITTI Velodyne scan: little-endian float32 ``x y z reflectance`` records of 16 bytes."""
    path = Path(path)
    data = _read_bytes(path)
    if len(data) % 16:
        raise DatasetError(
            f"{path}: size {len(data)} bytes is not a multiple of 16 (4 float32 per point): truncated?"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4).astype(np.float32)
    return points


def read_labels(path: PathLike, expected: int | None = None) -> NDArray[np.uint32]:
    """SemanticKITTI labels: one little-endian uint32 a point (lower 16 bits class, upper instance)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: label file not found")
    data = path.read_bytes()
    if len(data) % 4:
        raise DatasetError(f"{path}: size {len(data)} bytes is not a multiple of 4 (uint32 per point)")
    labels = np.frombuffer(data, dtype="<u4").astype(np.uint32)
    if expected is not None and len(labels) != expected:
        raise DatasetError(f"{path}: {len(labels)} labels but the scan has {expected} points")
    return labels


def write_bin(path: PathLike, points: NDArray[np.floating]) -> None:
    """Write ``(N, 4)`` points as a KITTI ``.bin`` file (float32, little-endian)."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 4:
        raise ValueError(f"points must have shape (N, 4), got {array.shape}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(np.ascontiguousarray(array, dtype="<f4").tobytes())


def write_labels(path: PathLike, labels: NDArray[np.integer]) -> None:
    """Write SemanticKITTI labels (uint32, little-endian)."""
    array = np.asarray(labels)
    if array.ndim != 1:
        raise ValueError(f"labels must be one-dimensional, got shape {array.shape}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(np.ascontiguousarray(array, dtype="<u4").tobytes())


# ----------------------------------------------------------------------------------------------------
# Shared: build x y z reflectance from named fields


def _normalise_reflectance(values: NDArray[np.generic]) -> NDArray[np.float32]:
    if values.dtype == np.uint8:
        return (values.astype(np.float32) / 255.0).astype(np.float32)
    as_float = values.astype(np.float64)
    finite = as_float[np.isfinite(as_float)]
    if finite.size == 0 or (finite.min() >= 0.0 and finite.max() <= 1.0):
        return as_float.astype(np.float32)
    return np.clip(as_float / 255.0, 0.0, 1.0).astype(np.float32)


def _check_fields_read_are_unique(path: Path, names: list[str]) -> None:
    """Refuses a header declaring a field this reader takes (a coordinate or reflectance, in any case)
    twice: which of the two is meant is unknown."""
    read = {"x", "y", "z", *REFLECTANCE_FIELDS}
    seen: set[str] = set()
    for name in names:
        key = name.lower()
        if key in read and key in seen:
            raise DatasetError(f"{path}: field {name!r} is declared twice in the header")
        seen.add(key)


def _points_from_fields(path: Path, columns: dict[str, NDArray[np.generic]]) -> NDArray[np.float32]:
    lower = {name.lower(): name for name in columns}
    missing = [axis for axis in ("x", "y", "z") if axis not in lower]
    if missing:
        raise DatasetError(f"{path}: no {', '.join(missing)} field (fields: {', '.join(columns)})")
    reflectance_name = next((lower[n] for n in REFLECTANCE_FIELDS if n in lower), None)
    used = [lower[axis] for axis in ("x", "y", "z")]
    if reflectance_name is not None:
        used.append(reflectance_name)
    for name in used:
        if columns[name].ndim != 1:
            raise DatasetError(
                f"{path}: field {name!r} holds {columns[name].shape[1]} values per point (its COUNT); "
                "a coordinate or reflectance holds 1"
            )
    count = len(columns[lower["x"]])
    points = np.zeros((count, 4), dtype=np.float32)
    for axis, name in enumerate(("x", "y", "z")):
        points[:, axis] = columns[lower[name]]
    if reflectance_name is not None:
        points[:, 3] = _normalise_reflectance(columns[reflectance_name])
    keep = np.all(np.isfinite(points[:, :3]), axis=1)
    return points if keep.all() else np.ascontiguousarray(points[keep])


def _split_header(path: Path, data: bytes, terminator: bytes, what: str) -> tuple[list[str], int]:
    """Header lines up to and including the line starting with ``terminator``, and the body offset."""
    lines: list[str] = []
    offset = 0
    while True:
        end = data.find(b"\n", offset)
        if end < 0:
            raise DatasetError(f"{path}: {what} header has no '{terminator.decode()}' line")
        raw = data[offset:end]
        offset = end + 1
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise DatasetError(f"{path}: non-ASCII bytes in the {what} header") from None
        lines.append(line)
        if line.split(maxsplit=1)[:1] == [terminator.decode()]:
            return lines, offset
        if len(lines) > 10_000:
            raise DatasetError(f"{path}: {what} header too long (no '{terminator.decode()}' line)")


def _records(data: bytes, dtype: np.dtype[Any], count: int, offset: int) -> NDArray[Any]:
    """``count`` records of ``dtype`` at ``offset``; the body after a text header mostly starts at an odd
    address, where numpy reads every field through unaligned loops: copying it to an aligned buffer first is
    faster."""
    if offset % 8:
        return np.frombuffer(data[offset : offset + count * dtype.itemsize], dtype=dtype, count=count)
    return np.frombuffer(data, dtype=dtype, count=count, offset=offset)


def _number_table(rows: list[str], width: int) -> NDArray[np.float64] | None:
    """``rows`` of ASCII numbers as a ``len(rows) × width`` table, by numpy's C parser (about twice as fast as
    splitting in Python); None for anything else (no rows, another width, something that is not a number),
    which the caller then parses the slow way to say what is wrong."""
    if not rows:
        return None
    try:
        table = np.loadtxt(rows, dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        return None
    return table if table.shape == (len(rows), width) else None


# ----------------------------------------------------------------------------------------------------
# PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path: PathLike) -> NDArray[np.float32]:
    """A PLY point cloud (``ascii``, ``binary_little_endian`` or ``binary_big_endian``): its vertices.

    The ``vertex`` element needs scalar ``x``, ``y``, ``z`` properties; elements before it may only have
    scalar properties (their records are skipped).
    """
    path = Path(path)
    data = _read_bytes(path)
    if not data.startswith(b"ply"):
        raise DatasetError(f"{path}: not a PLY file (does not start with 'ply')")
    lines, body_offset = _split_header(path, data, b"end_header", "PLY")

    file_format = None
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []  # name, count, props, has_list
    for number, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            file_format = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                count = int(words[2])
            except ValueError:
                raise DatasetError(f"{path}: header line {number}: bad element count {words[2]!r}") from None
            if count < 0:
                raise DatasetError(f"{path}: header line {number}: negative element count")
            elements.append((words[1], count, [], False))
        elif words[0] == "property" and elements:
            name, count, properties, has_list = elements[-1]
            if len(words) == 5 and words[1] == "list":
                elements[-1] = (name, count, properties + [("list", words[4])], True)
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                properties.append((_PLY_TYPES[words[1]], words[2]))
            else:
                raise DatasetError(f"{path}: header line {number}: bad property {line!r}")
        else:
            raise DatasetError(f"{path}: header line {number}: unexpected {line!r}")

    if file_format not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(f"{path}: PLY format {file_format!r} is not ascii or binary")
    vertex_index = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if vertex_index is None:
        raise DatasetError(f"{path}: PLY header has no vertex element")
    _, vertex_count, vertex_properties, vertex_has_list = elements[vertex_index]
    if vertex_has_list:
        raise DatasetError(f"{path}: PLY vertex element has a list property (not a point cloud)")
    for name, _, _, has_list in elements[:vertex_index]:
        if has_list:
            raise DatasetError(f"{path}: PLY element {name!r} before the vertices has list properties")
    names = [name for _, name in vertex_properties]
    repeated = next((name for i, name in enumerate(names) if name in names[:i]), None)
    if repeated is not None:
        raise DatasetError(f"{path}: PLY vertex property {repeated!r} is declared twice")
    _check_fields_read_are_unique(path, names)

    if file_format == "ascii":
        text_lines = data[body_offset:].decode("ascii", errors="replace").splitlines()
        skip = sum(count for _, count, _, _ in elements[:vertex_index])
        rows = text_lines[skip : skip + vertex_count]
        if len(rows) < vertex_count:
            raise DatasetError(
                f"{path}: truncated: {vertex_count} vertices declared, {max(len(rows), 0)} found"
            )
        table = _number_table(rows, len(names))
        if table is None:  # the slow path, only to say what is wrong
            try:
                values = np.array(" ".join(rows).split(), dtype=np.float64)
            except ValueError:
                raise DatasetError(f"{path}: a vertex line holds something that is not a number") from None
            if values.size != vertex_count * len(names):
                raise DatasetError(
                    f"{path}: vertex lines hold {values.size} numbers, expected "
                    f"{vertex_count} × {len(names)} properties"
                )
            table = values.reshape(vertex_count, len(names))
        columns = {
            name: table[:, i].astype(kind) for i, (kind, name) in enumerate(vertex_properties)
        }
        return _points_from_fields(path, columns)

    endian = "<" if file_format == "binary_little_endian" else ">"
    skip_bytes = sum(
        count * np.dtype([(f"p{i}", endian + kind) for i, (kind, _) in enumerate(props)]).itemsize
        for _, count, props, _ in elements[:vertex_index]
    )
    dtype = np.dtype([(name, endian + kind) for kind, name in vertex_properties])
    offset = body_offset + skip_bytes
    needed = vertex_count * dtype.itemsize
    available = len(data) - offset
    if available < needed:
        raise DatasetError(
            f"{path}: truncated: {vertex_count} vertices need {needed} bytes, {max(available, 0)} present"
        )
    records = _records(data, dtype, vertex_count, offset)
    return _points_from_fields(path, {name: records[name] for name in names})


# ----------------------------------------------------------------------------------------------------
# PCD

_PCD_KINDS = {"F": "f", "U": "u", "I": "i"}
_PCD_SIZES = {"F": (2, 4, 8), "U": (1, 2, 4, 8), "I": (1, 2, 4, 8)}  # bytes numpy can read for each TYPE
# Values per point of one field: far above PCL's largest descriptors (hundreds), and low enough that the
# record layout numpy builds from the header stays within its limits.
_PCD_MAX_COUNT = 1 << 20


def read_pcd(path: PathLike) -> NDArray[np.float32]:
    """A PCL ``.pcd`` file with ``DATA ascii``, ``binary`` or ``binary_compressed`` (LZF)."""
    path = Path(path)
    data = _read_bytes(path)
    lines, body_offset = _split_header(path, data, b"DATA", "PCD")
    header: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if words and not words[0].startswith("#"):
            header[words[0].upper()] = words[1:]
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise DatasetError(f"{path}: PCD header has no {key} line")
    fields = header["FIELDS"]
    sizes, kinds = header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(kinds) == len(counts):
        raise DatasetError(f"{path}: PCD FIELDS, SIZE, TYPE and COUNT have different lengths")
    _check_fields_read_are_unique(path, fields)
    try:
        size_values = [int(s) for s in sizes]
        count_values = [int(c) for c in counts]
        if "POINTS" in header:
            points_count = int(header["POINTS"][0])
        else:
            points_count = int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    except (ValueError, KeyError, IndexError):
        raise DatasetError(f"{path}: PCD header has a bad SIZE, COUNT, WIDTH, HEIGHT or POINTS") from None
    if points_count < 0:
        raise DatasetError(f"{path}: negative point count in the PCD header")

    dtype_fields: list[tuple[Any, ...]] = []
    seen: dict[str, int] = {}
    for name, size, kind, count in zip(fields, size_values, kinds, count_values, strict=True):
        if size not in _PCD_SIZES.get(kind.upper(), ()):
            raise DatasetError(f"{path}: PCD field {name!r} has unsupported TYPE {kind} SIZE {size}")
        if not 1 <= count <= _PCD_MAX_COUNT:
            raise DatasetError(
                f"{path}: PCD field {name!r} has COUNT {count}, expected 1 to {_PCD_MAX_COUNT} values per point"
            )
        unique = name if name not in seen else f"{name}__{seen[name]}"  # padding fields repeat "_"
        seen[name] = seen.get(name, 0) + 1
        base = f"<{_PCD_KINDS[kind.upper()]}{size}"
        dtype_fields.append((unique, base) if count == 1 else (unique, base, (count,)))
    dtype = np.dtype(dtype_fields)
    encoding = (header.get("DATA") or [""])[0].lower()

    if encoding == "binary":
        needed = points_count * dtype.itemsize
        available = len(data) - body_offset
        if available < needed:
            raise DatasetError(
                f"{path}: truncated: {points_count} points need {needed} bytes, {available} present"
            )
        records = _records(data, dtype, points_count, body_offset)
        columns = {name: records[name] for name in dtype.names or ()}
    elif encoding == "ascii":
        text = data[body_offset:].decode("ascii", errors="replace")
        rows = [row for row in text.splitlines() if row.strip()]
        if len(rows) < points_count:
            raise DatasetError(f"{path}: truncated: {points_count} points declared, {len(rows)} found")
        width = sum(count_values)
        table = _number_table(rows[:points_count], width)
        if table is None:  # the slow path, only to say what is wrong
            try:
                values = np.array(" ".join(rows[:points_count]).split(), dtype=np.float64)
            except ValueError:
                raise DatasetError(f"{path}: a point line holds something that is not a number") from None
            if values.size != points_count * width:
                raise DatasetError(
                    f"{path}: point lines hold {values.size} numbers, expected {points_count} × {width}"
                )
            table = values.reshape(points_count, width)
        columns = {}
        start = 0
        for (unique, base, *_), count in zip(dtype_fields, count_values, strict=True):
            values_of_field = table[:, start : start + count].astype(base)
            columns[unique] = values_of_field[:, 0] if count == 1 else values_of_field
            start += count
    elif encoding == "binary_compressed":
        columns = _read_pcd_compressed(path, data, body_offset, dtype_fields, count_values, points_count)
    else:
        raise DatasetError(f"{path}: unknown PCD DATA encoding {encoding!r}")
    return _points_from_fields(path, columns)


def lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decompress LZF (liblzf's format, used by PCL's ``binary_compressed``) to exactly ``expected_size``
    bytes; raises ``ValueError`` for a corrupt stream or another size, and :class:`LzfUnavailable` without
    the decoder.

    The decoder is liblzf's C code (``python-neo-lzf``, the ``io`` extra, the one pypcd4 uses): the
    pure-Python decoder it replaced took 35 times as long (docs/measurements.md, "PLY and PCD readers").
    """
    try:
        import lzf
    except ImportError:
        raise LzfUnavailable(
            "binary_compressed PCD needs the LZF decoder: pip install 'dmlo[io]' (or pip install python-neo-lzf)"
        ) from None
    if expected_size == 0:  # liblzf cannot tell an empty result from a failure
        if data:
            raise ValueError(f"{len(data)} compressed bytes for an empty result")
        return b""
    # `lzf.decompress` returns None when the output would exceed its limit: allow one byte more, so a
    # stream that decodes to too much is told from one that fits.
    out = lzf.decompress(data, expected_size + 1)
    if out is None or len(out) != expected_size:
        size = f"more than {expected_size}" if out is None else str(len(out))
        raise ValueError(f"decompressed to {size} bytes, the header says {expected_size}")
    return bytes(out)


class LzfUnavailable(ImportError):
    """The LZF decoder (the ``io`` extra) is not installed."""


def _read_pcd_compressed(
    path: Path,
    data: bytes,
    offset: int,
    dtype_fields: list[tuple[Any, ...]],
    counts: list[int],
    points_count: int,
) -> dict[str, NDArray[np.generic]]:
    """PCL ``binary_compressed``: two uint32 sizes, then LZF data holding each field for all points."""
    if len(data) < offset + 8:
        raise DatasetError(f"{path}: truncated: binary_compressed PCD without its size words")
    compressed_size, raw_size = np.frombuffer(data, dtype="<u4", count=2, offset=offset)
    body = data[offset + 8 : offset + 8 + int(compressed_size)]
    if len(body) < compressed_size:
        raise DatasetError(
            f"{path}: truncated: {compressed_size} compressed bytes declared, {len(body)} present"
        )
    try:
        raw = lzf_decompress(body, int(raw_size))
    except LzfUnavailable as err:
        raise DatasetError(f"{path}: {err}") from None
    except ValueError as err:
        raise DatasetError(f"{path}: corrupt LZF data ({err})") from None
    columns = {}
    start = 0
    for (unique, base, *_), count in zip(dtype_fields, counts, strict=True):
        item = np.dtype(base)
        nbytes = item.itemsize * count * points_count
        if start + nbytes > len(raw):
            raise DatasetError(f"{path}: decompressed data too short for field {unique!r}")
        values = np.frombuffer(raw, dtype=item, count=count * points_count, offset=start)
        columns[unique] = values if count == 1 else values.reshape(points_count, count)
        start += nbytes
    return columns


# ----------------------------------------------------------------------------------------------------


def read_scan(path: PathLike) -> NDArray[np.float32]:
    """Read a ``.bin``, ``.ply`` or ``.pcd`` scan, chosen by the file's suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return read_bin(path)
    if suffix == ".ply":
        return read_ply(path)
    if suffix == ".pcd":
        return read_pcd(path)
    raise DatasetError(f"{path}: unknown scan suffix {path.suffix!r} (expected one of {SCAN_SUFFIXES})")
