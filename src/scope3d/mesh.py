"""Point clouds and triangle meshes in millimetres, and their PLY files.

PLY files are written binary little-endian (compact, read by MeshLab, CloudCompare, Open3D, trimesh);
both ASCII and binary files are read.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_file
from .errors import InputError


@dataclass(frozen=True)
class PointCloud:
    """points : (N, 3) float64 mm; colors : (N, 3) uint8 RGB or None; normals : (N, 3) float or None."""

    points: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float).reshape(-1, 3)
        object.__setattr__(self, "points", pts)
        if self.colors is not None:
            object.__setattr__(self, "colors", np.asarray(self.colors, dtype=np.uint8).reshape(len(pts), 3))
        if self.normals is not None:
            object.__setattr__(self, "normals", np.asarray(self.normals, dtype=float).reshape(len(pts), 3))

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Mesh:
    """vertices : (V, 3) float64 mm; faces : (F, 3) int64 vertex indices, counter-clockwise seen from
    the side the normals point to; vertex_colors : (V, 3) uint8 or None; vertex_normals : (V, 3) or None."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float).reshape(-1, 3)
        f = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError("mesh faces index vertices that do not exist")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        if self.vertex_colors is not None:
            object.__setattr__(self, "vertex_colors", np.asarray(self.vertex_colors, np.uint8).reshape(len(v), 3))
        if self.vertex_normals is not None:
            object.__setattr__(self, "vertex_normals", np.asarray(self.vertex_normals, float).reshape(len(v), 3))

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, vertex_colors=self.vertex_colors, process=False)


# --- PLY ---------------------------------------------------------------------------------------

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
    """Read a PLY point cloud or triangle mesh (ASCII or binary little-endian).

    Returns a :class:`Mesh` when the file has triangular faces, else a :class:`PointCloud`.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    header_end = data.index(b"\n", end) + 1
    lines = data[:header_end].decode("ascii", "replace").splitlines()
    fmt, elements = None, []
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            elements[-1][2].append(parts[1:])
    if fmt not in ("ascii", "binary_little_endian"):
        raise InputError(f"{path}: PLY format {fmt!r} is not supported")
    body = data[header_end:]
    arrays: dict[str, np.ndarray] = {}
    if fmt == "ascii":
        tokens = body.split()
        pos = 0
        for name, count, props in elements:
            if props and props[0][0] == "list":
                rows = []
                for _ in range(count):
                    k = int(tokens[pos])
                    rows.append([int(t) for t in tokens[pos + 1 : pos + 1 + k]])
                    pos += 1 + k
                arrays[name] = np.array(rows, dtype=np.int64).reshape(count, -1)
            else:
                n = len(props)
                block = np.array(tokens[pos : pos + n * count], dtype=float).reshape(count, n)
                pos += n * count
                arrays[name] = {p[1]: block[:, i] for i, p in enumerate(props)}
    else:
        offset = 0
        for name, count, props in elements:
            if props and props[0][0] == "list":
                count_t, index_t = _PLY_TYPES[props[0][1]], _PLY_TYPES[props[0][2]]
                dt = np.dtype([("n", "<" + count_t), ("i", "<" + index_t, (3,))])
                block = np.frombuffer(body, dtype=dt, count=count, offset=offset)
                if count and np.any(block["n"] != 3):
                    raise InputError(f"{path}: only triangle faces are supported")
                arrays[name] = block["i"].astype(np.int64)
                offset += dt.itemsize * count
            else:
                dt = np.dtype([(p[1], "<" + _PLY_TYPES[p[0]]) for p in props])
                block = np.frombuffer(body, dtype=dt, count=count, offset=offset)
                arrays[name] = {n: block[n] for n in dt.names}
                offset += dt.itemsize * count
    vertex = arrays.get("vertex")
    if vertex is None:
        raise InputError(f"{path}: PLY file has no vertex element")
    pts = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(float)
    colors = (
        np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.uint8)
        if "red" in vertex else None
    )
    normals = np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=1) if "nx" in vertex else None
    if "face" in arrays and len(arrays["face"]):
        return Mesh(pts, arrays["face"], colors, normals)
    return PointCloud(pts, colors, normals)
