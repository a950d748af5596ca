"""Point clouds and triangle meshes in millimetres, and their PLY files.

PLY files are written binary little-endian (compact, read by MeshLab, CloudCompare, Open3D, trimesh);
both ASCII and binary files are read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.scene.mesh import Mesh, PointCloud
from scope3d.utils.atomic import atomic_file

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(path: str | Path, geometry: PointCloud | Mesh) -> None:
    """Write a point cloud or mesh as binary PLY (atomically)."""
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
    """Read a PLY point cloud or triangle mesh (ASCII, binary little- or big-endian).

    Returns a :class:`Mesh` when the file has a ``face`` element (triangles only; ASCII polygons with
    more corners are split into fans), else a :class:`PointCloud`. Vertex colours ``red green blue``
    come back as uint8 (float colours in [0, 1] are scaled by 255); normals ``nx ny nz`` as float.
    Lengths are returned as stored: scope3d writes mm. A malformed file is an InputError naming it.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    newline = data.find(b"\n", end)
    header_end = newline + 1 if newline >= 0 else len(data)
    try:
        fmt, elements = _parse_ply_header(data[:header_end].decode("ascii", "replace"))
        body = data[header_end:]
        if fmt == "ascii":
            arrays = _read_ply_ascii_body(body, elements)
        elif fmt in ("binary_little_endian", "binary_big_endian"):
            arrays = _read_ply_binary_body(body, elements, "<" if fmt == "binary_little_endian" else ">")
        else:
            raise ValueError(f"PLY format {fmt!r} is not supported")
        vertex = arrays.get("vertex")
        if vertex is None or not all(k in vertex for k in "xyz"):
            raise ValueError("PLY file has no vertex element with x, y, z")
        pts = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(float)
        colors = None
        if all(k in vertex for k in ("red", "green", "blue")):
            colors = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1)
            if colors.dtype.kind == "f":
                scale = 255.0 if colors.size and colors.max() <= 1.0 else 1.0
                colors = np.clip(np.rint(colors * scale), 0, 255)
            colors = colors.astype(np.uint8)
        normals = None
        if all(k in vertex for k in ("nx", "ny", "nz")):
            normals = np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=1).astype(float)
        if "face" in arrays:
            return Mesh(pts, arrays["face"]["indices"], colors, normals)
        return PointCloud(pts, colors, normals)
    except (ValueError, KeyError, IndexError) as exc:
        if isinstance(exc, InputError):
            raise
        detail = f"unknown property type {exc}" if isinstance(exc, KeyError) else str(exc) or "malformed header"
        raise InputError(f"{path}: {detail}") from None


def _parse_ply_header(text: str) -> tuple[str, list[tuple[str, int, list[list[str]]]]]:
    fmt, elements = None, []
    for line in text.splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            count = int(parts[2])
            if count < 0:
                raise ValueError(f"element {parts[1]} has a negative count")
            elements.append((parts[1], count, []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError("property before any element in the header")
            prop = parts[1:]
            types = prop[1:3] if prop[0] == "list" else prop[:1]
            for t in types:
                _PLY_TYPES[t]  # KeyError -> "unknown property type"
            elements[-1][2].append(prop)
    return fmt, elements


def _element_result(name: str, props: list[list[str]], columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Name the face index list ``indices`` whatever the file calls it (vertex_indices, vertex_index)."""
    out = dict(columns)
    lists = [p[3] for p in props if p[0] == "list"]
    if name == "face" and lists:
        out["indices"] = out[lists[0]]
    return out


def _read_ply_ascii_body(body: bytes, elements) -> dict[str, dict[str, np.ndarray]]:
    tokens = body.split()
    pos = 0
    arrays = {}
    for name, count, props in elements:
        if not any(p[0] == "list" for p in props):
            n = len(props)
            if pos + n * count > len(tokens):
                raise ValueError(f"file ends inside element {name}")
            block = np.array(tokens[pos : pos + n * count], dtype=float).reshape(count, n)
            pos += n * count
            arrays[name] = _element_result(name, props, {p[1]: block[:, i] for i, p in enumerate(props)})
            continue
        columns: dict[str, list] = {p[-1]: [] for p in props}
        for _ in range(count):
            for p in props:
                if pos >= len(tokens):
                    raise ValueError(f"file ends inside element {name}")
                if p[0] == "list":
                    k = int(tokens[pos])
                    values = [int(t) for t in tokens[pos + 1 : pos + 1 + k]]
                    if len(values) != k:
                        raise ValueError(f"file ends inside element {name}")
                    pos += 1 + k
                    if name == "face":
                        if k < 3:
                            raise ValueError(f"a face has {k} corners")
                        # A polygon becomes a fan of triangles around its first corner.
                        columns[p[-1]].extend([values[0], values[i], values[i + 1]] for i in range(1, k - 1))
                    else:
                        columns[p[-1]].append(values)
                else:
                    columns[p[-1]].append(float(tokens[pos]))
                    pos += 1
        result = {}
        for p in props:
            if p[0] == "list" and name == "face":
                result[p[-1]] = np.array(columns[p[-1]], dtype=np.int64).reshape(-1, 3)
            elif p[0] != "list":
                result[p[-1]] = np.array(columns[p[-1]], dtype=float)
        arrays[name] = _element_result(name, props, result)
    return arrays


def _read_ply_binary_body(body: bytes, elements, order: str) -> dict[str, dict[str, np.ndarray]]:
    offset = 0
    arrays = {}
    for name, count, props in elements:
        # Lists are read as fixed-length triples (scope3d, trimesh, MeshLab and Open3D write triangles);
        # the per-row counts are then checked, since a wrong guess would misalign everything after.
        fields = []
        for p in props:
            if p[0] == "list":
                fields += [(p[3] + "__n", order + _PLY_TYPES[p[1]]), (p[3], order + _PLY_TYPES[p[2]], (3,))]
            else:
                fields.append((p[1], order + _PLY_TYPES[p[0]]))
        dt = np.dtype(fields)
        if offset + dt.itemsize * count > len(body):
            raise ValueError(f"file ends inside element {name} (truncated?)")
        block = np.frombuffer(body, dtype=dt, count=count, offset=offset)
        offset += dt.itemsize * count
        columns = {}
        for p in props:
            if p[0] == "list":
                if count and np.any(block[p[3] + "__n"] != 3):
                    raise ValueError(f"only triangles are supported in binary PLY ({name}.{p[3]})")
                columns[p[3]] = block[p[3]].astype(np.int64)
            else:
                columns[p[1]] = block[p[1]].astype(block[p[1]].dtype.newbyteorder("="))
        arrays[name] = _element_result(name, props, columns)
    return arrays
