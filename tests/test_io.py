"""Readers and writers: formats, the Stanford scanner PLY, transforms, poses, landmarks, and bad files."""

import re
import struct

import numpy as np
import pytest

from conftest import pkg_file, shared
from scanreg.errors import InputError
from scanreg.geometry import Cloud, Mesh, apply_T, invert_T
from scanreg.io import (
    read_geometry, read_landmarks, read_mesh, read_stanford_conf, read_transform, write_ply, write_transform,
)

TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def same_mesh(a: Mesh, v, f):
    """Equal up to vertex order: compare sets of triangles as coordinate triples."""
    def tris(verts, faces):
        t = verts[faces]
        return sorted(tuple(map(tuple, np.roll(tri, -int(np.lexsort(tri.T[::-1])[0]), axis=0))) for tri in t)
    return tris(a.vertices, a.faces) == tris(np.asarray(v, float), np.asarray(f))


def test_ply_binary_roundtrip(tmp_path):
    write_ply(tmp_path / "t.ply", Mesh(TET_V, TET_F))
    m = read_mesh(tmp_path / "t.ply")
    assert np.array_equal(m.vertices, TET_V) and np.array_equal(m.faces, TET_F)
    c = Cloud(TET_V, np.eye(4, 3) + [0, 0, 1e-3])
    c.normals /= np.linalg.norm(c.normals, axis=1, keepdims=True)
    write_ply(tmp_path / "c.ply", c)
    g = read_geometry(tmp_path / "c.ply")
    assert isinstance(g, Cloud) and np.array_equal(g.points, TET_V) and np.allclose(g.normals, c.normals, atol=1e-6)


def test_ply_ascii_with_quads_is_triangulated(tmp_path):
    p = tmp_path / "q.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                 "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    m = read_mesh(p)
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_ply_big_endian(tmp_path):
    p = tmp_path / "be.ply"
    head = ("ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
            "property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = struct.pack(">9d", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack(">B3i", 3, 0, 1, 2)
    p.write_bytes(head + body)
    m = read_mesh(p)
    assert m.vertices[1].tolist() == [1, 0, 0] and m.faces.tolist() == [[0, 1, 2]]


def test_stanford_range_grid_matches_meshlab():
    """The scanner's range_grid is triangulated exactly as MeshLab/vcglib do it (same faces, same winding)."""
    import pymeshlab

    path = shared("stanford_bunny/bun000.ply")
    m = read_mesh(path)
    assert m.vertices.shape == (40256, 3) and m.faces.shape == (79312, 3)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    ref = ms.current_mesh().face_matrix()

    def canon(F):
        k = np.argmin(F, axis=1)
        return {tuple(r) for r in np.stack([F[np.arange(len(F)), (k + i) % 3] for i in range(3)], axis=1)}

    assert canon(m.faces) == canon(ref)


def test_stl_ascii_and_binary(tmp_path):
    tris = TET_V[TET_F]
    text = "solid t\n" + "".join(
        "facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in t) + "endloop\nendfacet\n"
        for t in tris) + "endsolid t\n"
    (tmp_path / "a.stl").write_text(text)
    rec = np.zeros(len(tris), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = tris
    (tmp_path / "b.stl").write_bytes(b"\0" * 80 + struct.pack("<I", len(tris)) + rec.tobytes())
    for name in ("a.stl", "b.stl"):
        m = read_mesh(tmp_path / name)
        assert len(m.vertices) == 4 and len(m.faces) == 4  # duplicate corners merged
        assert same_mesh(m, TET_V, TET_F)


def test_obj_and_off(tmp_path):
    (tmp_path / "q.obj").write_text("# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n")
    assert read_mesh(tmp_path / "q.obj").faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    assert read_mesh(tmp_path / "n.obj").faces.tolist() == [[0, 1, 2]]
    (tmp_path / "t.off").write_text("OFF\n# comment\n4 4 0\n" + "".join(f"{x} {y} {z}\n" for x, y, z in TET_V)
                                    + "".join(f"3 {a} {b} {c}\n" for a, b, c in TET_F))
    m = read_mesh(tmp_path / "t.off")
    assert np.array_equal(m.faces, TET_F)
    assert len(read_mesh(pkg_file("pkg:pymeshlab/tests/sample_meshes/cube.obj")).faces) == 12


def test_point_cloud_formats(tmp_path):
    import open3d as o3d

    pts = np.random.default_rng(0).normal(size=(50, 3))
    np.savetxt(tmp_path / "c.xyz", pts)
    np.save(tmp_path / "c.npy", pts)
    o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    for name in ("c.xyz", "c.npy", "c.pcd"):
        g = read_geometry(tmp_path / name)
        assert isinstance(g, Cloud) and np.allclose(g.points, pts, atol=1e-6), name


def test_pkg_meshes_ship_with_packages():
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    assert m.vertices.shape == (50000, 3) and m.faces.shape == (99785, 3)


@pytest.mark.parametrize(
    "name,content,message",
    [
        ("missing.ply", None, "no such file"),
        ("empty.ply", b"", "file is empty"),
        ("nothing.ply", b"hello\n", "not a PLY file"),
        ("head.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n", "truncated PLY header"),
        ("short.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                      b"property float z\nend_header\n0 0 0\n1 1 1\n", "truncated PLY data"),
        ("nan.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n0 0 0\nnan 1 1\n2 2 inf\n", "2 point(s) with NaN or infinite"),
        ("idx.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    b"0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n", "index missing vertices"),
        ("bin.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n" + b"\0" * 20, "truncated PLY data"),
        ("bad.stl", b"garbage that is not an stl", "not an STL file"),
        ("t.stl", b"solid x\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n", "truncated ASCII STL"),
        ("none.obj", b"# nothing\n", "OBJ has no vertices"),
        ("t.off", b"OFF\n4 4 0\n0 0 0\n", "truncated OFF"),
        ("cols.xyz", b"1 2\n3 4\n", "2 column(s); a point needs at least x y z"),
        ("obj.npy", None, "not a plain numeric"),
        ("x.abc", b"1 2 3\n", "unsupported file type"),
    ],
)
def test_bad_files_give_one_clear_error(tmp_path, name, content, message):
    p = tmp_path / name
    if name == "obj.npy":
        np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif content is not None:
        p.write_bytes(content)
    with pytest.raises(InputError, match=re.escape(message)) as e:
        read_geometry(p, "source")
    assert "\n" not in str(e.value) and str(e.value).startswith(f"source {p}")


def test_directory_is_not_a_file(tmp_path):
    with pytest.raises(InputError, match="is a directory"):
        read_geometry(tmp_path)


def test_transform_io(tmp_path):
    from scanreg.geometry import random_pose

    T = random_pose(np.random.default_rng(3), 180, 5)
    write_transform(tmp_path / "T.txt", T)
    np.save(tmp_path / "T.npy", T)
    assert np.array_equal(read_transform(tmp_path / "T.txt"), T)
    assert np.array_equal(read_transform(tmp_path / "T.npy"), T)
    (tmp_path / "bad.txt").write_text("1 2 3")
    with pytest.raises(InputError, match="expected 16 numbers"):
        read_transform(tmp_path / "bad.txt")
    (tmp_path / "scale.txt").write_text(" ".join(map(str, np.diag([2, 2, 2, 1.0]).ravel())))
    with pytest.raises(InputError, match="not a rotation"):
        read_transform(tmp_path / "scale.txt")


def test_stanford_conf_convention():
    """bun045 placed by the .conf poses lies on bun000: the README's R.T convention."""
    from scipy.spatial import cKDTree

    folder = shared("stanford_bunny")
    poses = read_stanford_conf(folder / "bun.conf")
    a, b = read_mesh(folder / "bun000.ply"), read_mesh(folder / "bun045.ply")
    T = invert_T(poses["bun000.ply"]) @ poses["bun045.ply"]
    d, _ = cKDTree(a.vertices).query(apply_T(T, b.vertices))
    assert np.median(d) < 0.5e-3  # metres: well under a millimetre at the true pose


def test_landmarks(tmp_path):
    (tmp_path / "l.csv").write_text("source_x,source_y,source_z,target_x,target_y,target_z\n"
                                    "1,2,3,4,5,6\n1,1,1,2,2,2\n0,0,0,9,9,9\n")
    t, s = read_landmarks(tmp_path / "l.csv")
    assert t[0].tolist() == [4, 5, 6] and s[0].tolist() == [1, 2, 3]
    (tmp_path / "two.csv").write_text("1,2,3,4,5,6\n1,1,1,2,2,2\n")
    with pytest.raises(InputError, match="at least 3"):
        read_landmarks(tmp_path / "two.csv")


def _l_hexagon_area_check(mesh):
    from scanreg.geometry import triangle_areas_normals

    areas, normals = triangle_areas_normals(mesh)
    assert len(mesh.faces) == 4
    assert np.isclose(areas.sum(), 3.0, rtol=1e-12)  # the L covers 3 unit squares; a fan from the reflex corner: 4 - 1
    assert np.allclose(normals, [0, 0, 1])            # every triangle wound like the polygon: none flipped
    # no triangle lies outside the L: every centroid inside it (the missing square is [1,2] x [1,2])
    c = mesh.vertices[mesh.faces].mean(axis=1)
    assert not ((c[:, 0] > 1) & (c[:, 1] > 1)).any()


@pytest.mark.parametrize("start", [0, 1, 3, 4])
def test_non_convex_polygon_is_ear_clipped_in_ply_and_obj(tmp_path, start):
    """An L-shaped hexagon (a reflex corner at (1, 1)) triangulates into triangles that cover exactly its area
    of 3, in PLY and OBJ; a fan from (2, 0) or (1, 2) would cover part of the missing square."""
    ring = [(0, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0), (1, 2, 0), (0, 2, 0)]
    ring = ring[start:] + ring[:start]  # start 1, 4: a fan from there would leave the L (0, 3: it would not)
    ply = tmp_path / "l.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                   + "".join(f"{x} {y} {z}\n" for x, y, z in ring) + "6 0 1 2 3 4 5\n")
    obj = tmp_path / "l.obj"
    obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in ring) + "f 1 2 3 4 5 6\n")
    for path in (ply, obj):
        _l_hexagon_area_check(read_mesh(path))


def test_convex_polygons_keep_the_fan():
    """Convex quads and pentagons stay fans (same triangles as before), mixed sizes in one list."""
    from scanreg.io.faces import _triangulate

    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 1.5, 0]], float)
    tris = _triangulate([np.array([0, 1, 2, 4, 3]), np.array([0, 1, 2])], pts, "t")
    assert {tuple(t) for t in tris} == {(0, 1, 2), (0, 1, 2), (0, 2, 4), (0, 4, 3)} and len(tris) == 4


def test_binary_stl_padded_or_without_a_count_is_read(tmp_path, capsys):
    """Exporters that pad a binary STL, or never fill in its triangle count: the triangles are read with a
    warning (it said 'not an STL file'); a truncated one says so with the sizes."""
    import struct

    from scanreg.io import read_mesh

    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    faces = [(0, 1, 2), (1, 3, 2)]
    body = b"".join(struct.pack("<3f", 0, 0, 1) + tri[list(f)].tobytes() + b"\0\0" for f in faces)
    exact = b"x" * 80 + struct.pack("<I", 2) + body
    (tmp_path / "pad.stl").write_bytes(exact + b"\0" * 7)
    (tmp_path / "zero.stl").write_bytes(b"x" * 80 + struct.pack("<I", 0) + body)
    (tmp_path / "cut.stl").write_bytes(exact[:-20])
    for name in ("pad.stl", "zero.stl"):
        m = read_mesh(str(tmp_path / name))
        assert len(m.faces) == 2 and len(m.vertices) == 4
    out = capsys.readouterr().out
    assert "declares 2 triangles (184 bytes) but the file has 191 bytes" in out
    assert "declares 0 triangles but holds 2 by its size" in out
    with pytest.raises(InputError, match=r"truncated or not an STL file: .* declares 2 triangles \(184 bytes\) but "
                                         r"has 164 bytes"):
        read_mesh(str(tmp_path / "cut.stl"))
