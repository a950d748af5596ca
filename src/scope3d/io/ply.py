"""Point clouds and triangle meshes in millimetres, and their PLY files.

PLY files are read by trimesh (ASCII, binary little- and big-endian; polygons split into triangles), with a
check of the header first so that a bad or lying file is one :class:`~scope3d.errors.InputError` naming it.
They are written binary little-endian with double vertices (compact and exact, read by MeshLab,
CloudCompare, Open3D, trimesh): trimesh's own writer stores vertices as float32, which would round the
ground-truth surfaces that accuracy figures are measured against.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.scene.mesh import Mesh, PointCloud
from scope3d.utils.atomic import atomic_file

# bytes per value of the PLY types trimesh reads (the specification's names and the common aliases)
_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "int64": 8, "uint64": 8,
    "float16": 2, "float": 4, "float32": 4, "double": 8, "float64": 8,
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def write_ply(path: str | Path, geometry: PointCloud | Mesh) -> None:
    """Write a point cloud or mesh as binary little-endian PLY (atomically): ``x y z`` double (mm),
    ``nx ny nz`` float and ``red green blue`` uchar when present, triangles as ``vertex_indices``."""
    if isinstance(geometry, Mesh):
        pts, colors, normals, faces = geometry.vertices, geometry.vertex_colors, geometry.vertex_normals, geometry.faces
    else:
        pts, colors, normals, faces = geometry.points, geometry.colors, geometry.normals, None
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(pts), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = pts.T
    if normals is not None:
        vertex["nx"], vertex["ny"], vertex["nz"] = normals.T
    if colors is not None:
        vertex["red"], vertex["green"], vertex["blue"] = colors.T
    names = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment scope3d, units mm", f"element vertex {len(pts)}"]
    header += [f"property {names[t]} {n}" for n, t in fields]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with atomic_file(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vertex.tobytes())
        if faces is not None:
            face = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            face["n"] = 3
            face["i"] = faces
            fh.write(face.tobytes())


def read_ply(path: str | Path) -> PointCloud | Mesh:
    """Read a PLY point cloud or polygon mesh (ASCII, binary little- or big-endian) with trimesh.

    Returns a :class:`Mesh` when the file has a ``face`` element (polygons are split into triangles: a
    quad ``(a, b, c, d)`` into ``(a, b, c), (c, d, a)``, larger ones into fans; in binary files every
    face must have the same number of corners), else a :class:`PointCloud`. Vertex colours
    ``red green blue`` come back as uint8 (float colours in [0, 1] are scaled by 255); normals
    ``nx ny nz`` as float. Lengths are returned as stored: scope3d writes mm. Any malformed file
    (including a header that claims more data than the file holds, refused before reading it) is one
    InputError naming the file and what is wrong.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    elements = _check_header(path, data)
    try:
        return _from_trimesh(path, data, elements)
    except InputError:
        raise
    except Exception as exc:  # trimesh's and numpy's errors about a bad file: one line, no traceback
        detail = str(exc).strip().rstrip("!") or type(exc).__name__
        if "unexpected length" in detail:
            detail = "the data does not match the header (truncated, or binary faces with different numbers of corners)"
        elif isinstance(exc, KeyError):
            detail = f"a row has fewer values than the header's properties (no {detail})"
        raise InputError(f"{path}: cannot read the data: {detail}") from None


def _from_trimesh(path: Path, data: bytes, elements: list) -> PointCloud | Mesh:
    """trimesh parses the file; scope3d's types, colours and triangles are made of what it returns."""
    import io

    from trimesh.exchange.ply import load_ply
    from trimesh.geometry import triangulate_quads

    loaded = load_ply(io.BytesIO(data), fix_texture=False, skip_materials=True)
    n_vertices = next(count for name, count, _ in elements if name == "vertex")
    pts = np.asarray(loaded.get("vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
    if len(pts) != n_vertices:
        raise InputError(f"{path}: {len(pts)} vertices read where the header declares {n_vertices}")
    colors = loaded.get("vertex_colors")
    if colors is not None:
        colors = np.asarray(colors)[:, :3]
        if colors.dtype.kind == "f":
            scale = 255.0 if colors.size and colors.max() <= 1.0 else 1.0
            colors = np.clip(np.rint(colors * scale), 0, 255)
        colors = colors.astype(np.uint8)
    normals = loaded.get("vertex_normals")
    if normals is not None:
        normals = np.asarray(normals, dtype=float)
    if not any(name == "face" for name, _, _ in elements):
        return PointCloud(pts, colors, normals)
    faces = loaded.get("faces")
    if faces is None or len(faces) == 0:
        faces = np.zeros((0, 3), np.int64)
    elif np.ndim(faces) == 2:  # one corner count (trimesh has already split mixed ASCII polygons)
        if np.shape(faces)[1] < 3:
            raise InputError(f"{path}: a face has {np.shape(faces)[1]} corners")
        faces = triangulate_quads(faces)  # triangles stay as they are
    try:
        return Mesh(pts, faces, colors, normals)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def _check_header(path: Path, data: bytes) -> list[tuple[str, int, list[list[str]]]]:
    """The header's elements ``(name, count, properties)``, after the checks trimesh leaves out or makes only
    once it has read the data: a known format and property types, counts >= 0, x y z on the vertices, and
    at least as many rows in the file as the header declares (a row takes at least one line of an ASCII
    file, or its fixed fields' bytes in a binary one), so that a lying header allocates nothing."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    newline = data.find(b"\n", end)
    body = data[newline + 1 :] if newline >= 0 else b""
    lines = data[:end].decode("ascii", "replace").splitlines()
    head = lines[1].split() if len(lines) > 1 else []
    if head[:1] != ["format"]:
        raise InputError(f"{path}: the line after 'ply' must be the format line")
    fmt, elements = (head[1] if len(head) > 1 else ""), []
    for line in lines[2:]:
        parts = line.split()
        if parts[:1] == ["element"]:
            try:
                name, count = parts[1], int(parts[2])
                if len(parts) != 3:
                    raise ValueError
            except (IndexError, ValueError):
                raise InputError(f"{path}: malformed header line {line.strip()!r}") from None
            if count < 0:
                raise InputError(f"{path}: element {name} has a negative count")
            elements.append((name, count, []))
        elif parts[:1] == ["property"]:
            if not elements:
                raise InputError(f"{path}: property before any element in the header")
            prop = parts[1:]
            types = prop[1:3] if prop[:1] == ["list"] else prop[:1]
            if len(prop) != (4 if prop[:1] == ["list"] else 2):
                raise InputError(f"{path}: malformed header line {line.strip()!r}")
            for t in types:
                if t not in _PLY_TYPE_SIZES:
                    raise InputError(f"{path}: unknown property type {t!r}")
            elements[-1][2].append(prop)
    if fmt not in _PLY_FORMATS:
        raise InputError(f"{path}: PLY format {fmt!r} is not supported")
    vertex = [props for name, _, props in elements if name == "vertex"]
    if not vertex or not {"x", "y", "z"} <= {p[-1] for p in vertex[0]}:
        raise InputError(f"{path}: PLY file has no vertex element with x, y, z")
    if fmt == "ascii":
        available = sum(1 for line in body.splitlines() if line.strip())
    else:
        available = len(body)
    needed = 0
    for name, count, props in elements:
        if fmt == "ascii":
            needed += count if props else 0
        else:  # a list takes at least its length field
            needed += count * sum(_PLY_TYPE_SIZES[p[1] if p[0] == "list" else p[0]] for p in props)
        if needed > available:
            raise InputError(f"{path}: file ends inside element {name} (truncated?)")
    return elements
