"""Textured meshes as Wavefront OBJ + MTL + PNG: the format MeshLab, Blender, Open3D and trimesh open with
their texture. ``NAME.obj`` (``v`` in mm, ``vt``, faces ``f v/vt``, counter-clockwise seen from the side the
normals point to), ``NAME.mtl`` (one material, its ``map_Kd``) and ``NAME.png`` (the atlas), side by side."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from scope3d.io.images import write_image
from scope3d.utils.atomic import atomic_files


def write_textured_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                       face_uv: np.ndarray, image: np.ndarray) -> list[Path]:
    """Write ``path`` (.obj) with its .mtl and .png beside it, all three renamed into place together.
    vertices : (V, 3) mm; faces : (F, 3) vertex indices; uv : (T, 2) in [0, 1], v up; face_uv : (F, 3)
    indices into uv; image : (H, W, 3) uint8 RGB, row 0 at the top. Returns the three paths."""
    obj = Path(path)
    mtl, png = obj.with_suffix(".mtl"), obj.with_suffix(".png")
    buffer = io.StringIO()
    buffer.write(f"# scope3d textured mesh, lengths in mm\nmtllib {mtl.name}\n")
    np.savetxt(buffer, np.asarray(vertices, float), fmt="v %.6f %.6f %.6f")
    np.savetxt(buffer, np.asarray(uv, float), fmt="vt %.7f %.7f")
    buffer.write("usemtl wall\n")
    corners = np.stack([np.asarray(faces, np.int64) + 1, np.asarray(face_uv, np.int64) + 1], axis=2).reshape(-1, 6)
    np.savetxt(buffer, corners, fmt="f %d/%d %d/%d %d/%d")
    with atomic_files([obj, mtl, png]) as (tmp_obj, tmp_mtl, tmp_png):
        tmp_obj.write_text(buffer.getvalue(), encoding="utf-8")
        tmp_mtl.write_text(f"newmtl wall\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {png.name}\n", encoding="utf-8")
        write_image(tmp_png, image)
    return [obj, mtl, png]


def read_textured_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a triangle OBJ with texture coordinates: (vertices (V, 3), faces (F, 3), uv (T, 2), face_uv (F, 3),
    the RGB image its .mtl's ``map_Kd`` names, or None). Faces must be triangles ``f v/vt[/vn]`` (what
    :func:`write_textured_obj` writes); anything else is an InputError naming the file and line."""
    from scope3d.errors import InputError
    from scope3d.io.images import read_image

    path = Path(path)
    vertices, uv, faces, face_uv, library = [], [], [], [], None
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                vertices.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                uv.append([float(x) for x in parts[1:3]])
            elif parts[0] == "f":
                if len(parts) != 4:
                    raise ValueError("only triangles are read")
                corners = [c.split("/") for c in parts[1:]]
                faces.append([int(c[0]) - 1 for c in corners])
                face_uv.append([int(c[1]) - 1 for c in corners])
            elif parts[0] == "mtllib":
                library = path.parent / " ".join(parts[1:])
        except (ValueError, IndexError) as exc:
            raise InputError(f"{path}: line {number}: {exc}") from None
    v, f, t, ft = (np.array(vertices, float).reshape(-1, 3), np.array(faces, np.int64).reshape(-1, 3),
                   np.array(uv, float).reshape(-1, 2), np.array(face_uv, np.int64).reshape(-1, 3))
    if f.size and (f.min() < 0 or f.max() >= len(v) or ft.min() < 0 or ft.max() >= len(t)):
        raise InputError(f"{path}: a face refers to a vertex or texture coordinate that does not exist")
    image = None
    if library is not None and library.is_file():
        for line in library.read_text(encoding="utf-8").splitlines():
            if line.startswith("map_Kd"):
                image = read_image(library.parent / line.split(None, 1)[1].strip())
                break
    return v, f, t, ft, image
