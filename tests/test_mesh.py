"""PLY files: binary round trip, ASCII files written by hand, other writers (trimesh), polygons, malformed
and lying files."""
import sys
import tracemalloc

import numpy as np
import pytest
import trimesh

from scope3d.errors import InputError
from scope3d.io.ply import read_ply, write_ply
from scope3d.scene.mesh import Mesh, PointCloud


def _cloud(n=50, seed=0):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    return PointCloud(rng.uniform(-10, 10, (n, 3)), rng.integers(0, 256, (n, 3)),
                      normals / np.linalg.norm(normals, axis=1, keepdims=True))


def _tetrahedron():
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return Mesh(v, f, vertex_colors=[[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]],
                vertex_normals=v - v.mean(axis=0))


def test_point_cloud_round_trip(tmp_path):
    cloud = _cloud()
    write_ply(tmp_path / "c.ply", cloud)
    back = read_ply(tmp_path / "c.ply")
    assert isinstance(back, PointCloud)
    np.testing.assert_array_equal(back.points, cloud.points)  # stored as double: exact
    np.testing.assert_array_equal(back.colors, cloud.colors)
    np.testing.assert_allclose(back.normals, cloud.normals, atol=1e-7)  # stored as float32


def test_bare_point_cloud_round_trip(tmp_path):
    write_ply(tmp_path / "c.ply", PointCloud(np.arange(12.0).reshape(4, 3)))
    back = read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(back.points, np.arange(12.0).reshape(4, 3))
    assert back.colors is None and back.normals is None


def test_mesh_round_trip(tmp_path):
    mesh = _tetrahedron()
    write_ply(tmp_path / "m.ply", mesh)
    back = read_ply(tmp_path / "m.ply")
    assert isinstance(back, Mesh)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.vertex_colors, mesh.vertex_colors)
    np.testing.assert_allclose(back.vertex_normals, mesh.vertex_normals, atol=1e-6)


def test_empty_mesh_stays_a_mesh(tmp_path):
    write_ply(tmp_path / "e.ply", Mesh(np.zeros((0, 3)), np.zeros((0, 3), int)))
    back = read_ply(tmp_path / "e.ply")
    assert isinstance(back, Mesh) and back.vertices.shape == (0, 3) and back.faces.shape == (0, 3)


def test_trimesh_reads_our_binary_ply(tmp_path):
    mesh = _tetrahedron()
    write_ply(tmp_path / "m.ply", mesh)
    loaded = trimesh.load(tmp_path / "m.ply", process=False)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    np.testing.assert_array_equal(loaded.visual.vertex_colors[:, :3], mesh.vertex_colors)
    assert loaded.volume == pytest.approx(1000.0 / 6.0)  # outward-facing triangles, in mm^3
    cloud = _cloud()
    write_ply(tmp_path / "c.ply", cloud)
    np.testing.assert_allclose(trimesh.load(tmp_path / "c.ply").vertices, cloud.points)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_we_read_trimesh_ply(tmp_path, encoding):
    mesh = _tetrahedron()
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=mesh.vertex_colors, process=False)
    tm.export(tmp_path / "t.ply", encoding=encoding)  # adds alpha; vertices as float32
    back = read_ply(tmp_path / "t.ply")
    np.testing.assert_allclose(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.vertex_colors, mesh.vertex_colors)


ASCII_MESH = """ply
format ascii 1.0
comment written by hand: a unit square as one quad and a triangle fan
element vertex 5
property float x
property float y
property float z
property float nx
property float ny
property float nz
property uchar red
property uchar green
property uchar blue
element face 2
property list uchar int vertex_indices
end_header
0 0 0 0 0 1 255 0 0
1 0 0 0 0 1 0 255 0
1 1 0 0 0 1 0 0 255
0 1 0 0 0 1 10 20 30
0.5 0.5 1 0 0 1 1 2 3
4 0 1 2 3
3 0 1 4
"""


def _triangles(faces):
    """The set of triangles, each rotated to start at its smallest index (winding kept)."""
    return {tuple(np.roll(f, -int(np.argmin(f))).tolist()) for f in np.asarray(faces)}


def test_ascii_mesh_written_by_hand(tmp_path):
    (tmp_path / "a.ply").write_text(ASCII_MESH)
    mesh = read_ply(tmp_path / "a.ply")
    assert isinstance(mesh, Mesh) and len(mesh.faces) == 3
    assert _triangles(mesh.faces) == {(0, 1, 2), (0, 2, 3), (0, 1, 4)}  # the quad split along 0-2, winding kept
    np.testing.assert_array_equal(mesh.vertex_colors[3], [10, 20, 30])
    np.testing.assert_array_equal(mesh.vertex_normals[:, 2], 1.0)
    np.testing.assert_array_equal(mesh.vertices[4], [0.5, 0.5, 1.0])


def test_ascii_point_cloud_with_float_colours(tmp_path):
    (tmp_path / "p.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\n"
        "property float red\nproperty float green\nproperty float blue\nend_header\n"
        "1 2 3 1.0 0.5 0.0\n4 5 6 0 0 0.2\n"
    )
    cloud = read_ply(tmp_path / "p.ply")
    assert isinstance(cloud, PointCloud)
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud.colors, [[255, 128, 0], [0, 0, 51]])


def _binary_polygons(faces, order="<"):
    """A binary PLY of a 2 x 3 vertex grid (double x y z, uchar colours) with the given polygons."""
    k = len(faces[0])
    header = (f"ply\nformat binary_{'little' if order == '<' else 'big'}_endian 1.0\nelement vertex 6\n"
              "property double x\nproperty double y\nproperty double z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    v = np.zeros(6, [("xyz", order + "f8", (3,)), ("rgb", "u1", (3,))])
    v["xyz"] = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]]
    v["rgb"] = np.arange(18).reshape(6, 3)
    f = np.zeros(len(faces), [("n", "u1"), ("i", order + "i4", (k,))])
    f["n"], f["i"] = k, faces
    return header.encode() + v.tobytes() + f.tobytes()


@pytest.mark.parametrize("order", ["<", ">"])
def test_binary_quad_mesh_is_triangulated(tmp_path, order):
    (tmp_path / "q.ply").write_bytes(_binary_polygons([[0, 1, 4, 3], [1, 2, 5, 4]], order))
    mesh = read_ply(tmp_path / "q.ply")
    assert isinstance(mesh, Mesh) and mesh.faces.shape == (4, 3)
    assert _triangles(mesh.faces) == {(0, 1, 4), (0, 4, 3), (1, 2, 5), (1, 5, 4)}  # the quads split, winding kept
    np.testing.assert_array_equal(mesh.vertices[5], [2, 1, 0])
    np.testing.assert_array_equal(mesh.vertex_colors, np.arange(18).reshape(6, 3))
    area = np.linalg.norm(np.cross(*(mesh.vertices[mesh.faces[:, 1:]] - mesh.vertices[mesh.faces[:, :1]]).transpose(1, 0, 2)),
                          axis=1) / 2
    assert area.sum() == pytest.approx(2.0)  # the two unit squares, covered once


def test_binary_pentagon_is_a_fan(tmp_path):
    (tmp_path / "p.ply").write_bytes(_binary_polygons([[0, 1, 2, 5, 3]]))
    assert _triangles(read_ply(tmp_path / "p.ply").faces) == {(0, 1, 2), (0, 2, 5), (0, 5, 3)}


def _refuse_lying_file(path, fmt: str, claimed: int) -> tuple[int, int]:
    """Write a 64-byte body under a header claiming ``claimed`` vertices, read it (it must be refused by the
    header check) and return (peak bytes allocated, Python lines executed) during the read."""
    path.write_bytes(
        f"ply\nformat {fmt} 1.0\nelement vertex {claimed}\nproperty double x\nproperty double y\n"
        f"property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".encode()
        + b"\0" * 64)
    lines = 0

    def count(frame, event, arg):
        nonlocal lines
        lines += event == "line"
        return count

    tracemalloc.start()
    sys.settrace(count)
    try:
        with pytest.raises(InputError, match="lie.ply: file ends inside element vertex"):
            read_ply(path)
    finally:
        sys.settrace(None)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak, lines


def test_lying_header_is_refused_before_parsing_without_allocating(tmp_path, monkeypatch):
    """A tiny file whose header claims 10^9 vertices (24 GB of doubles) must fail at once, in both encodings.
    "At once" as properties that do not depend on the machine's speed or load (a wall-time limit here failed
    on a busy machine, issue 31): the parser never sees the data, the memory stays far below what one claimed
    row per byte would take, and the work done is the same whether the header claims 10^3 or 10^18 rows
    (counted in Python lines executed, so a loop over the claimed rows would show)."""
    import trimesh.exchange.ply

    def parser(*args, **kwargs):
        pytest.fail("the lying file reached the parser")

    monkeypatch.setattr(trimesh.exchange.ply, "load_ply", parser)
    for fmt in ("binary_little_endian", "ascii"):
        _refuse_lying_file(tmp_path / "lie.ply", fmt, 10**9)  # first calls: imports and caches, counted once
        peaks, lines = zip(*(_refuse_lying_file(tmp_path / "lie.ply", fmt, n) for n in (10**3, 10**9, 10**18)))
        assert max(peaks) < 10_000_000, (fmt, peaks)
        assert len(set(lines)) == 1, (fmt, lines)


def test_big_endian_binary(tmp_path):
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], ">f4").tobytes()
    face = b"\x03" + np.array([0, 1, 2], ">i4").tobytes()
    (tmp_path / "b.ply").write_bytes(header.encode() + verts + face)
    mesh = read_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(mesh.vertices[1], [1, 0, 0])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])


@pytest.mark.parametrize(
    "content, fragment",
    [
        (b"hello", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty double x\nproperty double y\n"
         b"property double z\nend_header\n" + b"\0" * 100, "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n1 2 3\n", "ends inside element vertex"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quaternion x\nend_header\n1\n", "unknown property type"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
         b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
         "vertices that do not exist"),
        (b"ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n", "negative count"),
        (b"ply\nformat binary_middle_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n" + b"\0" * 12, "format 'binary_middle_endian'"),
        # the second face has 4 corners where the first has 3: trimesh reads binary lists of one length only
        (_binary_polygons([[0, 1, 4], [1, 2, 5]])[:-26] + b"\x03" + np.array([0, 1, 4], "<i4").tobytes()
         + b"\x04" + np.array([1, 2, 5, 4], "<i4").tobytes(), "does not match the header"),
        (_binary_polygons([[0, 1, 4, 3]])[:-3], "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n1 2 3\n4 five 6\n", "bad.ply: "),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
         "no vertex element"),
    ],
)
def test_malformed_files_are_input_errors(tmp_path, content, fragment):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(InputError) as info:
        read_ply(tmp_path / "bad.ply")
    assert "bad.ply" in str(info.value) and fragment in str(info.value), str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nothing.ply: cannot read"):
        read_ply(tmp_path / "nothing.ply")


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    """A write that fails after the header (a full disk, say) leaves neither the file nor a temporary."""
    import builtins

    import scope3d.utils.atomic

    class FailsOnSecondWrite:
        def __init__(self, handle):
            self.handle, self.writes = handle, 0

        def write(self, data):
            self.writes += 1
            if self.writes == 2:
                raise OSError("No space left on device")
            return self.handle.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.handle.__exit__(*exc)

    monkeypatch.setattr(scope3d.utils.atomic, "open", lambda *a, **k: FailsOnSecondWrite(builtins.open(*a, **k)),
                        raising=False)
    with pytest.raises(OSError, match="No space"):
        write_ply(tmp_path / "m.ply", _tetrahedron())
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    write_ply(tmp_path / "m.ply", _tetrahedron())  # the same call succeeds without the failure
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]
