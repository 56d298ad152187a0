"""PLY files: the header, the vertex and triangle elements, and the writer every tool uses.

No open3d (its import alone costs about a second). Covers the layouts the project reads and
writes: ASCII and binary PLY whose vertex element has scalar properties, binary triangle
meshes. The readers check the body against the header by name: a body shorter than declared is
refused (a reader that stops early fills the rest with zeros, which look like points at the
origin), and rows beyond the declared count are reported (``strict``: refused).

Coordinates are read as float64 whatever the file stores (float or double): a georeferenced
scan stored as doubles far from the origin keeps its precision until the caller centres it
(:func:`dss.pointcloud.load_ply`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .io_utils import atomic_path

log = logging.getLogger(__name__)

__all__ = [
    "PointCloudError",
    "PlyElement",
    "PlyHeader",
    "PlyArrays",
    "read_ply_header",
    "read_ply_vertices",
    "read_ply_arrays",
    "read_ply_triangles",
    "write_ply",
]


class PointCloudError(ValueError):
    """Bad point-cloud input; the message names the file (when there is one) and the problem."""


PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_TYPE_NAMES = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int"}


@dataclass
class PlyElement:
    """One ``element`` of a PLY header: its name, count and properties ``(name, type)``; a list
    property's type is ``("list", count type, item type)``."""

    name: str
    count: int
    properties: list


@dataclass
class PlyHeader:
    """A parsed PLY header: ``format`` (``ascii`` | ``binary_little_endian`` |
    ``binary_big_endian``), the elements in file order, and the header's length in bytes."""

    format: str
    elements: list
    size: int

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse a PLY header; raises PointCloudError naming the file and what is wrong."""
    path = Path(path)
    with open(path, "rb") as f:
        first = f.readline()
        if first.strip() != b"ply":
            raise PointCloudError(f"{path}: not a PLY file (header does not start with 'ply')")
        fmt, elements = None, []
        while True:
            raw = f.readline()
            if not raw:
                raise PointCloudError(f"{path}: the PLY header has no 'end_header' line (truncated file?)")
            line = raw.decode("ascii", errors="replace").strip()
            words = line.split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format" and len(words) >= 2:
                fmt = words[1]
            elif words[0] == "element" and len(words) == 3 and words[2].lstrip("-").isdigit():
                if int(words[2]) < 0:
                    raise PointCloudError(f"{path}: the PLY header gives a negative count: {line!r}")
                elements.append(PlyElement(words[1], int(words[2]), []))
            elif words[0] == "property" and elements and len(words) == 3 and words[1] in PLY_TYPES:
                elements[-1].properties.append((words[2], PLY_TYPES[words[1]]))
            elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
                  and words[2] in PLY_TYPES and words[3] in PLY_TYPES):
                elements[-1].properties.append((words[4], ("list", PLY_TYPES[words[2]], PLY_TYPES[words[3]])))
            else:
                raise PointCloudError(f"{path}: unreadable PLY header line {line!r}")
        size = f.tell()
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PointCloudError(f"{path}: unknown PLY format {fmt!r}")
    return PlyHeader(fmt, elements, size)


def _fixed_dtype(element: PlyElement, endian: str) -> np.dtype | None:
    """The numpy record type of a binary element with scalar properties only, else None."""
    if any(isinstance(t, tuple) for _, t in element.properties):
        return None
    return np.dtype([(n, endian + t) for n, t in element.properties])


def _binary_offset(header: PlyHeader, element: PlyElement | None, endian: str) -> int | None:
    """Byte offset of ``element``'s body in a binary PLY file (None: the end of the last
    element), or None when an element before it has list properties (its size is then not
    known from the header)."""
    offset = header.size
    for e in header.elements:
        if e is element:
            return offset
        dt = _fixed_dtype(e, endian)
        if dt is None:
            return None
        offset += e.count * dt.itemsize
    return offset if element is None else None


def _extra_rows(path: Path, vertex: PlyElement, extra: int, unit: str, strict: bool) -> None:
    """Report rows beyond the header's counts: a header that declares fewer vertices than the
    file holds drops the rest unseen otherwise."""
    msg = (f"{path}: the file holds {extra} {unit} after the {vertex.count} vertices its header declares "
           "(a header that undercounts the points?)")
    if strict:
        raise PointCloudError(msg + "; refusing (nan_policy='raise')")
    log.warning("%s; reading the declared %d", msg, vertex.count)


def read_ply_vertices(path: str | os.PathLike, strict: bool = False) -> dict[str, np.ndarray] | None:
    """The vertex element of a PLY file as ``{property: (N,) array}``, checked against the header.

    A binary body shorter than the header's vertex count, or an ASCII body with fewer rows
    (or rows with the wrong number of values) is refused by name: readers that stop at the
    first bad row fill the rest with zeros, and those zeros look like points at the origin.
    Data after the declared elements (more rows than the header declares) is reported, and
    refused with ``strict``. ASCII tokens ``nan``, ``inf`` and ``-inf`` are read as such (the
    caller's ``nan_policy`` decides about them); ASCII values are float64. Returns None for a
    layout this reader does not cover (a list property in the vertices, or a list element before
    them in a binary file); open3d reads those.
    """
    path = Path(path)
    header = read_ply_header(path)
    vertex = header.element("vertex")
    if vertex is None:
        raise PointCloudError(f"{path}: the PLY header has no 'vertex' element")
    if any(isinstance(t, tuple) for _, t in vertex.properties):
        return None
    names = [n for n, _ in vertex.properties]
    if header.format == "ascii":
        with open(path, "rb") as f:
            f.seek(header.size)
            lines = f.read().decode("ascii", errors="replace").splitlines()
        lines = [ln for ln in lines if ln.strip()]
        skip = 0
        for e in header.elements:
            if e is vertex:
                break
            skip += e.count
        rows = lines[skip:skip + vertex.count]
        if len(rows) < vertex.count:
            raise PointCloudError(f"{path}: truncated: the header declares {vertex.count} vertices, "
                                  f"the file holds {max(0, len(rows))} rows")
        extra = len(lines) - sum(e.count for e in header.elements)
        if extra > 0:
            _extra_rows(path, vertex, extra, "more rows", strict)
        values = np.empty((vertex.count, len(names)), np.float64)
        for i, row in enumerate(rows):
            tokens = row.split()
            if len(tokens) != len(names):
                raise PointCloudError(f"{path}: vertex row {i} has {len(tokens)} values, the header "
                                      f"declares {len(names)} ({' '.join(names)})")
            try:
                values[i] = [float(t) for t in tokens]  # float() reads nan, inf, -inf too
            except ValueError:
                raise PointCloudError(f"{path}: vertex row {i} holds a value that is not a number: "
                                      f"{row.strip()[:80]!r}") from None
        return {n: values[:, j] for j, n in enumerate(names)}
    endian = "<" if header.format == "binary_little_endian" else ">"
    offset = _binary_offset(header, vertex, endian)
    if offset is None:
        return None
    dt = _fixed_dtype(vertex, endian)
    size = path.stat().st_size
    available = max(0, size - offset)
    complete = available // dt.itemsize if dt.itemsize else 0
    if complete < vertex.count:
        raise PointCloudError(f"{path}: truncated: the header declares {vertex.count} vertices, "
                              f"the file holds {complete} complete rows ({size} bytes)")
    end = _binary_offset(header, None, endian)
    # a stray byte or two (a trailing newline) is no row; a whole vertex record or more is
    if end is not None and dt.itemsize and size - end >= dt.itemsize:
        extra = size - end
        unit = (f"bytes ({extra // dt.itemsize} vertex rows)" if header.elements[-1] is vertex
                else "bytes")
        _extra_rows(path, vertex, extra, unit, strict)
    data = np.fromfile(path, dtype=dt, count=vertex.count, offset=offset)
    return {n: data[n] for n in names}


class PlyArrays(NamedTuple):
    """A point cloud's arrays from a PLY file: float64 ``points`` (N, 3), ``normals`` and
    ``colors`` (in [0, 1]) or None, and ``coordinates``: the type the file stores x, y, z in
    (``"float"`` or ``"double"``; ASCII: ``"double"``, its text is read as such)."""

    points: np.ndarray
    normals: np.ndarray | None
    colors: np.ndarray | None
    coordinates: str


def _columns(cols: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray | None:
    if not all(n in cols for n in names):
        return None
    return np.stack([np.asarray(cols[n], np.float64) for n in names], 1)


def read_ply_arrays(path: str | os.PathLike, strict: bool = False) -> PlyArrays | None:
    """Points, normals and colours of a PLY file's vertices (:func:`read_ply_vertices`), all
    float64; None when that reader does not cover the file's layout."""
    path = Path(path)
    cols = read_ply_vertices(path, strict=strict)
    if cols is None:
        return None
    points = _columns(cols, ("x", "y", "z"))
    if points is None:
        raise PointCloudError(f"{path}: the PLY vertices have no x, y, z properties")
    normals = _columns(cols, ("nx", "ny", "nz"))
    colors = None
    for names in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(n in cols for n in names):
            kind = cols[names[0]].dtype
            colors = _columns(cols, names)
            if np.issubdtype(kind, np.integer):  # 0..255 (or 0..65535) -> [0, 1]
                colors = colors / float(np.iinfo(kind).max)
            break
    stored = np.dtype(cols["x"].dtype)
    coordinates = "float" if stored.kind == "f" and stored.itemsize == 4 else "double"
    return PlyArrays(points, normals, colors, coordinates)


def read_ply_triangles(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray] | None:
    """A triangle mesh from a binary PLY file as ``(vertices (V, 3) float64, faces (F, 3) int64)``
    without open3d (whose import alone costs more than a 20K-point job's metrics).

    Covers binary files whose elements up to the faces have scalar properties only, and whose
    face element has one list property (``vertex_indices`` or ``vertex_index``) of triangles,
    other face properties scalar (colours, flags). Returns None for anything else (ASCII,
    polygons other than triangles, other list properties, a short file): :func:`dss.metrics.load_mesh`
    then uses open3d.
    """
    path = Path(path)
    header = read_ply_header(path)
    if header.format == "ascii":
        return None
    endian = "<" if header.format == "binary_little_endian" else ">"
    cols = read_ply_vertices(path)
    if cols is None or not all(n in cols for n in ("x", "y", "z")):
        return None
    face = header.element("face")
    offset = None if face is None else _binary_offset(header, face, endian)
    if offset is None:
        return None
    fields, index_name = [], None
    for name, t in face.properties:
        if isinstance(t, tuple):
            if index_name is not None or name not in ("vertex_indices", "vertex_index"):
                return None
            index_name = name
            # every face a triangle: the list is then a fixed (count, 3 indices) record
            fields += [("_count", endian + t[1]), (name, endian + t[2], (3,))]
        else:
            fields.append((name, endian + t))
    if index_name is None:
        return None
    dt = np.dtype(fields)
    available = max(0, path.stat().st_size - offset)
    if available < face.count * dt.itemsize:
        return None  # polygons with fewer corners, or a truncated file: open3d's reader decides
    data = np.fromfile(path, dtype=dt, count=face.count, offset=offset)
    if not (data["_count"] == 3).all():
        return None  # not all triangles (the records are then misaligned): open3d reads polygons
    vertices = np.stack([np.asarray(cols[n], np.float64) for n in ("x", "y", "z")], 1)
    faces = data[index_name].astype(np.int64)
    return vertices, faces


def write_ply(path: str | os.PathLike, points, normals=None, colors=None, faces=None, *,
              double: bool = False, ascii: bool = False, exclusive: bool = False) -> Path:
    """Write a PLY file atomically (:class:`dss.io_utils.atomic_path`); returns the path written.

    Args:
        points: (N, 3) coordinates, stored as float (``double``: as double, which keeps a
            cloud far from the origin exact).
        normals: (N, 3) or None, stored as float.
        colors: (N, 3) in [0, 1] or None, stored as uchar.
        faces: (F, 3) triangle vertex indices or None (binary only), stored as
            ``list uchar int vertex_indices``.
        ascii: ASCII body instead of binary little-endian.
        exclusive: never replace an existing file (the result goes beside it).
    """
    pts = np.asarray(points, np.float64 if double else np.float32)
    coord = "<f8" if double else "<f4"
    fields = [("x", coord), ("y", coord), ("z", coord)]
    cols = [pts]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        cols.append(np.asarray(normals, np.float32))
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        cols.append(np.round(np.clip(np.asarray(colors, np.float64), 0, 1) * 255).astype(np.uint8))
    if faces is not None and ascii:
        raise ValueError("write_ply: faces are written in binary files only")
    rows = np.empty(len(pts), dtype=fields)
    names = [f[0] for f in fields]
    j = 0
    for c in cols:
        for i in range(3):
            rows[names[j]] = c[:, i]
            j += 1
    header = ["ply", "format " + ("ascii" if ascii else "binary_little_endian") + " 1.0", f"element vertex {len(pts)}"]
    header += [f"property {_TYPE_NAMES[t.lstrip('<')]} {n}" for n, t in fields]
    body = b""
    if faces is not None:
        f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        f["n"] = 3
        f["i"] = np.asarray(faces, np.int32)
        header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
        body = f.tobytes()
    header.append("end_header")
    writer = atomic_path(Path(path), exclusive=exclusive)
    with writer as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        if ascii:
            # 9 significant digits round-trip a float, 17 a double
            fmt = " ".join("%d" if t == "u1" else ("%.17g" if t == "<f8" else "%.9g") for _, t in fields)
            np.savetxt(fh, np.stack([rows[n].astype(np.float64) for n in names], 1), fmt=fmt)
        else:
            fh.write(rows.tobytes())
            fh.write(body)
        fh.flush()
        os.fsync(fh.fileno())
    return writer.path
