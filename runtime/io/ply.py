"""PLY point clouds and triangle meshes: binary little-endian writer (float32 x, y, z + optional float32 nx, ny,
nz normals + optional uchar red, green, blue, + optional triangles ``face`` ``list uchar int vertex_indices``)
and a reader for ``ascii``, ``binary_little_endian`` and ``binary_big_endian`` vertex data (MeshLab,
CloudCompare, Open3D); :func:`read_ply_normals` reads the normals, :func:`read_ply_faces` the triangles.

:func:`read_ply` and :func:`read_ply_vertex` ignore other elements (e.g. ``face``) after ``vertex``; fixed-size
elements before it are skipped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["PlyFormatError", "write_ply", "read_ply", "read_ply_normals", "read_ply_vertex", "read_ply_faces"]

# PLY scalar types -> numpy (both the classic and the sized names)
_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
#: numpy type codes -> PLY types of the extra scalars the writer takes
_SCALAR_TYPES = {"u1": "uchar", "u2": "ushort", "i4": "int", "f4": "float"}
_RGB_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


class PlyFormatError(ValueError):
    """A PLY file is malformed or unsupported; the message names the file."""


def write_ply(
    path: str | Path,
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    scalars: dict[str, np.ndarray] | None = None,
    faces: np.ndarray | None = None,
) -> Path:
    """Write a point cloud (or, with ``faces``, a triangle mesh) as binary little-endian PLY.

    Args:
        path: output file (parent folders are created).
        xyz: (N, 3) points [m] (any frame; stored as float32), all finite.
        rgb: optional (N, 3) uint8 colours.
        normals: optional (N, 3) normals (``nx ny nz``, float32), all finite (zero = none).
        scalars: optional further per-vertex properties, name -> (N,) array of uint8, uint16, int32 or float32
            (written after the colours; :func:`read_ply_vertex` reads them).
        faces: optional (F, 3) vertex indices of triangles (``element face``, ``list uchar int``), each in
            ``[0, N)``; :func:`read_ply_faces` reads them.

    Returns:
        The path written.

    Raises:
        ValueError: bad shape, non-finite points, colours that are not uint8, or face indices out of range.
    """
    path = Path(path)
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    if not np.issubdtype(xyz.dtype, np.number):
        raise ValueError(f"xyz must be numeric, got dtype {xyz.dtype}")
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        raise ValueError(f"xyz has {int((~finite).sum())} non-finite points (first at index {np.argmin(finite)})")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != xyz.shape:
            raise ValueError(f"normals must have shape {xyz.shape} like xyz, got {normals.shape}")
        if not np.isfinite(normals).all():
            raise ValueError(f"normals has {int((~np.isfinite(normals).all(axis=1)).sum())} non-finite rows")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != xyz.shape:
            raise ValueError(f"rgb must have shape {xyz.shape} like xyz, got {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8, got dtype {rgb.dtype}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    scalars = {k: np.asarray(v) for k, v in (scalars or {}).items()}
    for k, v in scalars.items():
        if v.shape != (len(xyz),) or v.dtype.str.lstrip("<|") not in _SCALAR_TYPES:
            raise ValueError(f"scalar {k!r} must be ({len(xyz)},) of {sorted(_SCALAR_TYPES)}, got {v.dtype} {v.shape}")
        fields.append((k, "<" + v.dtype.str.lstrip("<|")))
    arr = np.empty(len(xyz), dtype=fields)
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if normals is not None:
        arr["nx"], arr["ny"], arr["nz"] = normals[:, 0], normals[:, 1], normals[:, 2]
    if rgb is not None:
        arr["red"], arr["green"], arr["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for k, v in scalars.items():
        arr[k] = v
    header = ["ply", "format binary_little_endian 1.0", "comment written by dit-slam runtime.io.ply"]
    header += [f"element vertex {len(xyz)}", "property float x", "property float y", "property float z"]
    if normals is not None:
        header += ["property float nx", "property float ny", "property float nz"]
    if rgb is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"property {_SCALAR_TYPES[v.dtype.str.lstrip('<|')]} {k}" for k, v in scalars.items()]
    tri = None if faces is None else _face_records(faces, len(xyz))
    if tri is not None:
        header += [f"element face {len(tri)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(arr.tobytes())
        if tri is not None:
            f.write(tri.tobytes())
    return path


def _face_records(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Checked triangles (F, 3) as PLY ``list uchar int`` records (count 3, then the indices)."""
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be (F, 3) integers, got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise ValueError(f"faces index vertices {f.min()}..{f.max()}, but there are {n_vertices}")
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f
    return rec


def _parse_header(path: Path, f) -> tuple[str, list[tuple[str, int, list]]]:
    """-> (format, [(element name, count, [(prop name, dtype | ('list', count dtype, item dtype))])])."""
    if f.readline().strip() != b"ply":
        raise PlyFormatError(f"{path}: not a PLY file (first line is not 'ply')")
    fmt = None
    elements: list[tuple[str, int, list]] = []
    while True:
        raw = f.readline()
        if not raw:
            raise PlyFormatError(f"{path}: header has no 'end_header'")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if len(words) < 2 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise PlyFormatError(f"{path}: unsupported format line {raw!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyFormatError(f"{path}: malformed element line {raw!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyFormatError(f"{path}: property before any element: {raw!r}")
            if len(words) == 5 and words[1] == "list":
                if words[2] not in _TYPES or words[3] not in _TYPES:
                    raise PlyFormatError(f"{path}: unknown list property type in {raw!r}")
                elements[-1][2].append((words[4], ("list", _TYPES[words[2]], _TYPES[words[3]])))
            elif len(words) == 3 and words[1] in _TYPES:
                elements[-1][2].append((words[2], _TYPES[words[1]]))
            else:
                raise PlyFormatError(f"{path}: unsupported property line {raw!r}")
        else:
            raise PlyFormatError(f"{path}: unexpected header line {raw!r}")
    if fmt is None:
        raise PlyFormatError(f"{path}: header has no 'format' line")
    return fmt, elements


def read_ply_vertex(path: str | Path) -> dict[str, np.ndarray]:
    """Every vertex property of a PLY file: name -> (N,) array in the file's type.

    Raises:
        PlyFormatError: as :func:`read_ply`.
    """
    return _read_vertices(Path(path))[0]


def _read_vertices(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The vertex columns of a PLY file (name -> (N,) array) and their numpy type codes."""
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(f"{path}: missing file")
    with open(path, "rb") as f:
        fmt, elements = _parse_header(path, f)
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise PlyFormatError(f"{path}: no 'vertex' element")
        vi = names.index("vertex")
        _, n, props = elements[vi]
        if any(isinstance(t, tuple) for _, t in props):
            raise PlyFormatError(f"{path}: list properties in 'vertex' are not supported")
        pnames = [p for p, _ in props]
        for c in ("x", "y", "z"):
            if c not in pnames:
                raise PlyFormatError(f"{path}: vertex has no property '{c}' (has {pnames})")
        if fmt == "ascii":
            skip = 0
            for _, count, _ in elements[:vi]:  # ascii: one line per item, lists included
                skip += count
            lines = f.read().decode("ascii", errors="replace").splitlines()
            lines = [ln for ln in lines if ln.strip()][skip : skip + n]
            if len(lines) < n:
                raise PlyFormatError(f"{path}: expected {n} vertex lines, found {len(lines)}")
            try:
                table = np.loadtxt(lines, dtype=np.float64, ndmin=2, usecols=range(len(pnames)))
            except ValueError as e:
                raise PlyFormatError(f"{path}: malformed vertex data ({e})") from None
            cols = {p: table[:, j] for j, p in enumerate(pnames)}
            types = dict(props)
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            for name, count, eprops in elements[:vi]:
                if any(isinstance(t, tuple) for _, t in eprops):
                    raise PlyFormatError(
                        f"{path}: element '{name}' with list properties before 'vertex' is unsupported"
                    )
                f.seek(count * np.dtype([(p, order + t) for p, t in eprops]).itemsize, 1)
            dtype = np.dtype([(p, order + t) for p, t in props])
            buf = f.read(n * dtype.itemsize)
            if len(buf) < n * dtype.itemsize:
                raise PlyFormatError(f"{path}: truncated vertex data ({len(buf)} of {n * dtype.itemsize} bytes)")
            arr = np.frombuffer(buf, dtype=dtype, count=n)
            cols = {p: arr[p] for p in pnames}
            types = dict(props)
    return cols, types


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY file.

    Args:
        path: ``.ply`` file (ascii or binary, either endianness).

    Returns:
        xyz (N, 3) float64 [file units], rgb (N, 3) uint8 or None when the vertices have no colour.

    Raises:
        PlyFormatError: missing file, malformed header, no vertex element or x/y/z, truncated data.
    """
    cols, types = _read_vertices(Path(path))
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], -1).astype(np.float64)
    rgb = None
    for trio in _RGB_NAMES:
        if all(c in cols for c in trio):
            kind = np.dtype(types[trio[0]]).kind
            c = np.stack([cols[k] for k in trio], -1).astype(np.float64)
            if kind == "f":  # float colours are in [0, 1]
                c = c * 255.0
            rgb = np.clip(np.rint(c), 0, 255).astype(np.uint8)
            break
    return xyz, rgb


def read_ply_normals(path: str | Path) -> np.ndarray | None:
    """The vertex normals (N, 3) float64 (``nx ny nz``) of a PLY file, or None when it has none.

    Raises:
        PlyFormatError: as :func:`read_ply`.
    """
    cols, _ = _read_vertices(Path(path))
    if not all(c in cols for c in ("nx", "ny", "nz")):
        return None
    return np.stack([cols["nx"], cols["ny"], cols["nz"]], -1).astype(np.float64)


def read_ply_faces(path: str | Path) -> np.ndarray:
    """The triangles (F, 3) int64 of a PLY file's ``face`` element (``vertex_indices`` or ``vertex_index``), or
    an empty (0, 3) array when it has none.

    Raises:
        PlyFormatError: as :func:`read_ply`; a face that is not a triangle, or elements after ``vertex`` with
            list properties before ``face`` (binary).
    """
    path = Path(path)
    cols, _ = _read_vertices(path)  # checks the file and its vertex element
    n_vert = len(cols["x"])
    with open(path, "rb") as f:
        fmt, elements = _parse_header(path, f)
        names = [e[0] for e in elements]
        if "face" not in names:
            return np.zeros((0, 3), np.int64)
        fi = names.index("face")
        _, n, props = elements[fi]
        lists = [(p, t) for p, t in props if isinstance(t, tuple)]
        if len(props) != 1 or not lists or lists[0][0] not in ("vertex_indices", "vertex_index"):
            raise PlyFormatError(f"{path}: face element must hold only a vertex_indices list, has {props}")
        _, ctype, itype = lists[0][1]
        if fmt == "ascii":
            skip = sum(count for _, count, _ in elements[:fi])
            lines = [ln for ln in f.read().decode("ascii", errors="replace").splitlines() if ln.strip()]
            rows = [ln.split() for ln in lines[skip : skip + n]]
            if len(rows) < n or any(len(r) != 4 or r[0] != "3" for r in rows):
                raise PlyFormatError(f"{path}: expected {n} triangle lines ('3 i j k')")
            tri = np.array([[int(x) for x in r[1:]] for r in rows], np.int64).reshape(-1, 3)
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            for name, count, eprops in elements[:fi]:
                if any(isinstance(t, tuple) for _, t in eprops):
                    raise PlyFormatError(f"{path}: element '{name}' with list properties before 'face'")
                f.seek(count * np.dtype([(p, order + t) for p, t in eprops]).itemsize, 1)
            dtype = np.dtype([("n", order + ctype), ("i", order + itype, (3,))])
            buf = f.read(n * dtype.itemsize)
            if len(buf) < n * dtype.itemsize:
                raise PlyFormatError(f"{path}: truncated face data ({len(buf)} of {n * dtype.itemsize} bytes)")
            rec = np.frombuffer(buf, dtype=dtype, count=n)
            if (rec["n"] != 3).any():
                raise PlyFormatError(f"{path}: only triangles are supported (a face has {rec['n'].max()} vertices)")
            tri = rec["i"].astype(np.int64).reshape(-1, 3)
    if tri.size and (tri.min() < 0 or tri.max() >= n_vert):
        raise PlyFormatError(f"{path}: face indices {tri.min()}..{tri.max()} outside the {n_vert} vertices")
    return tri
