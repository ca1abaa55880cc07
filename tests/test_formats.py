"""Issue 19: what scanners and other tools write. Format variants, header claims against the file's size
(bounded memory), invalid points dropped and counted, the meaning of text columns, crafted in each test."""

import os
import re
import struct
import subprocess
import sys

import numpy as np
import pytest

from scanreg.errors import InputError
from scanreg.geometry import Cloud, apply_T
from scanreg.io import detect_columns, read_geometry, read_input, read_mesh, write_ply

TRI_V = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]


def write(tmp_path, name, data) -> str:
    p = tmp_path / name
    p.write_bytes(data if isinstance(data, bytes) else data.encode())
    return str(p)


# ------------------------------------------------------------------------------------------ format variants
VARIANTS = {
    "coff.off": "COFF\n3 1 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n3 0 1 2\n",
    "counts_on_keyword_line.off": "OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    "noff.off": "NOFF\n3 1 0\n0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n3 0 1 2 255 0 0\n",
    "glued_counts.off": "\t  OFF3 1 0 # counts glued to the keyword, leading whitespace\n"
                        "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    "vcglib_face_colours.ply": "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                               "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                               "property list uchar float texcoord\nproperty uchar red\nproperty uchar green\n"
                               "property uchar blue\nproperty uchar alpha\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
                               "3 0 1 2 6 0.6 0.4 0.5 0.4 0.6 0.4 9 1 1 1 1 1 1 1 1 1\n",
    "continued.obj": "v 0 0 0\nv 1 0 \\\n 0\nv 0 1 0\nf 1 2 \\\n3\n",
    "texcoord_ascii.ply": "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                          "property float z\n"
                          "element face 1\nproperty list uchar int vertex_indices\nproperty list uchar float texcoord\n"
                          "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2 6 0 0 1.5 0 0 1\n",
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_mesh_variants_other_tools_write(tmp_path, name):
    m = read_mesh(write(tmp_path, name, VARIANTS[name]), "source")
    assert m.vertices.tolist() == TRI_V and m.faces.tolist() == [[0, 1, 2]]


def test_binary_ply_with_texcoord_list(tmp_path):
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            b"property list uchar float texcoord\nend_header\n")
    body = (struct.pack("<9f", *np.ravel(TRI_V)) + struct.pack("<B3i", 3, 0, 1, 2)
            + struct.pack("<B6f", 6, 0, 0, 1.5, 0, 0, 1))
    m = read_mesh(write(tmp_path, "tc.ply", head + body))
    assert m.faces.tolist() == [[0, 1, 2]]


@pytest.mark.parametrize("text,columns", [
    ("x y z r g b a\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n", "x y z r g b a"),
    ("//X,Y,Z,R,G,B\n0,0,0,255,0,0\n1,0,0,0,255,0\n0,1,0,0,0,255\n", "x y z r g b"),
    ("0 0 0 255 0 0 128\n1 0 0 0 255 0 128\n0 1 0 0 0 255 128\n", "x y z r g b a"),  # 7 columns, no header
    ("0 0 0 1 0 0\n1 0 0 0 1 0\n0 1 0 0 0 1\n", "x y z nx ny nz"),  # unit vectors are normals
    ("# exported by a scanner\n# X Y Z Intensity\n0 0 0 17\n1 0 0 18\n0 1 0 19\n", "x y z -"),  # named
    ("X;Y;Z;Nx;Ny;Nz\n0;0;0;0;0;1\n1;0;0;0;0;1\n0;1;0;0;0;1\n", "x y z nx ny nz"),
])
def test_text_cloud_variants(tmp_path, text, columns):
    c = read_geometry(write(tmp_path, "c.xyz", text))
    assert isinstance(c, Cloud) and c.points.tolist() == TRI_V and c.extra["columns"] == columns


def test_symlink_loop_and_broken_link(tmp_path):
    os.symlink(tmp_path / "b.ply", tmp_path / "a.ply")
    os.symlink(tmp_path / "a.ply", tmp_path / "b.ply")
    with pytest.raises(InputError, match="symbolic link loop"):
        read_geometry(tmp_path / "a.ply", "source")
    os.symlink(tmp_path / "nowhere.ply", tmp_path / "broken.ply")
    with pytest.raises(InputError, match="broken symbolic link"):
        read_geometry(tmp_path / "broken.ply", "source")


@pytest.mark.parametrize("name,data,message", [
    ("4d.off", "4OFF\n1 0 0\n0 0 0 0\n", "4D or n-dimensional OFF"),
    ("bad_counts.off", "OFF\n3\n", "OFF counts line"),
    ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "OBJ indices start at 1"),
    ("four.xyz", "0 0 0 7\n1 0 0 8\n0 1 0 9\n", "4 columns; expected x y z"),
    ("weird.xyz", "0 0 0 3 4 5\n1 0 0 8 9 1000\n0 1 0 1 1 1\n", "neither unit normals nor colours"),
    ("ragged.xyz", "# c\n0 0 0\n1 0 0 1\n0 1 0\n", "line 3: '1 0 0 1' is not a row of 3 numbers"),
    ("binary.pts", b"[Expe/PointSet/Binary/0.1]\n\0\1\2", "binary data, not a text point cloud"),
    ("header_only.xyz", "x y z\n", "contains no points"),
    ("no_vertices.ply", "ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nproperty list uchar int "
     "vertex_indices\nend_header\n", "contains no points (its header says 0 vertices)"),
    ("pcd_no_header.pcd", "hello\n", "not a PCD file"),
    ("image.pcd", "FIELDS rgba\nSIZE 4\nTYPE U\nCOUNT 1\nPOINTS 1\nDATA ascii\n7\n", "PCD has no x y z fields"),
    ("pcd_short.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 5\nDATA ascii\n0 0 0\n",
     "truncated PCD"),
])
def test_variant_errors_are_one_line(tmp_path, name, data, message):
    with pytest.raises(InputError, match=re.escape(message)) as e:
        read_geometry(write(tmp_path, name, data), "source")
    assert "\n" not in str(e.value) and name in str(e.value)


# ------------------------------------------------------------------------------------------ bounded memory
MEMORY_PROBE = """
import resource, sys
from scanreg.errors import InputError
from scanreg.io import read_geometry
try:
    read_geometry(sys.argv[1], "source")
    print("read")
except InputError as e:
    print(e)
try:  # this process's own peak (ru_maxrss would include the forking parent's, the test runner's)
    print(next(int(ln.split()[1]) * 1024 for ln in open("/proc/self/status") if ln.startswith("VmHWM:")))
except OSError:
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
"""


def _bomb_ply_binary():
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 200000000\nproperty list uchar int vertex_indices\nend_header\n")
    return head + struct.pack("<9f", *np.ravel(TRI_V)) + struct.pack("<B3i", 3, 0, 1, 2)


@pytest.mark.parametrize("name,data", [
    ("faces_binary.ply", _bomb_ply_binary()),  # the ragged-list path (count 3 then a short tail)
    ("faces_ascii.ply", _bomb_ply_binary().replace(b"binary_little_endian", b"ascii")[:230]),
    ("points.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000\nHEIGHT 1\n"
                   b"POINTS 1000000000\nDATA binary\n" + b"\0" * 24),
    ("compressed.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1000000000\n"
                       b"DATA binary_compressed\n" + struct.pack("<II", 16, 12 * 10 ** 9 % 2 ** 32) + b"\0" * 16),
    ("off_claims.off", b"OFF\n3 200000000 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"),
    ("points.npy", b"\x93NUMPY\x01\x00v\x00" + b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000, 3), }"
                   .ljust(117) + b"\n" + b"\0" * 96),
])
def test_header_claims_are_checked_before_allocating(tmp_path, name, data):
    """A tiny file whose header claims 2e8 faces (or 1e9 points) fails in one line with a peak memory far
    under 1 GB (the interpreter with NumPy and SciPy is about 100 MB)."""
    assert len(data) < 300
    p = write(tmp_path, name, data)
    r = subprocess.run([sys.executable, "-c", MEMORY_PROBE, p], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    message, peak = r.stdout.strip().splitlines()
    assert re.search("truncated|do not match", message) and name in message, message
    assert int(peak) < 1e9, f"peak memory {int(peak) / 1e6:.0f} MB"


# ------------------------------------------------------------------------------------------ invalid points
def _organised_pcd(tmp_path, nan_share=0.25, seed=0, pose=None):
    """A depth-camera-like organised cloud (HEIGHT > 1) of a wavy surface, NaN where a pixel has no depth."""
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 1.0 + 0.08 * np.sin(u / 6.0) * np.cos(v / 5.0) + 0.05 * np.sin((u + v) / 9.0)
    pts = np.stack([(u - w / 2) / 60 * z, (v - h / 2) / 60 * z, z], -1).reshape(-1, 3)
    if pose is not None:
        pts = pts @ pose[:3, :3].T + pose[:3, 3]
    pts = pts.astype(np.float32)
    pts[np.random.default_rng(seed).random(len(pts)) < nan_share] = np.nan
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\nHEIGHT {h}\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\nDATA binary\n").encode()
    return head + pts.tobytes(), int(np.isnan(pts).any(axis=1).sum())


def test_nan_pixels_are_dropped_and_counted(tmp_path, capsys):
    data, n_nan = _organised_pcd(tmp_path)
    g, dropped = read_input(write(tmp_path, "org.pcd", data), "source")
    assert dropped == n_nan > 1000 and g.n_points == 4800 - n_nan and np.isfinite(g.points).all()
    assert f"dropped {n_nan} point(s) with NaN" in capsys.readouterr().out


def test_nan_normals_drop_their_points(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(300, 3))
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    n[:15] = np.nan
    lines = "\n".join(" ".join(f"{x:.9g}" for x in row) for row in np.hstack([pts, n]))
    g, dropped = read_input(write(tmp_path, "n.xyz", lines.replace("nan", "NaN")), "target")
    assert dropped == 15 and g.n_points == 285 and np.allclose(g.normals, n[15:])


def test_zero_normals_drop_their_points_not_every_normal(tmp_path, capsys):
    """A few zero normals (a mesh's vertices that no face uses, exported with its vertex normals): those points
    go, with a warning, and the others keep their normals (every normal was dropped, silently: raw bun270 given so
    registered 94 deg off, with its normals 0.2 deg); every normal zero (an exporter's placeholder): an unoriented
    cloud, nothing dropped."""
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(300, 3))
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    n[:4] = 0.0
    np.save(tmp_path / "z.npy", np.hstack([pts, n]))
    np.save(tmp_path / "all_zero.npy", np.hstack([pts, 0 * n]))
    g, dropped = read_input(str(tmp_path / "z.npy"), "source")
    assert dropped == 4 and g.n_points == 296 and np.allclose(g.normals, n[4:])
    assert "dropped 4 point(s) with zero normals (of 300)" in capsys.readouterr().out
    g, dropped = read_input(str(tmp_path / "all_zero.npy"), "source")
    assert dropped == 0 and g.n_points == 300 and g.normals is None


def test_many_missing_normals_drop_the_normals_not_the_points(tmp_path, capsys):
    """A third of the points without a normal (zero): every point kept, the cloud read as one without normals
    (a third of a scan was dropped for it); up to 5 % still drop their points."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(300, 3))
    n = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    n[:100] = 0.0
    np.save(tmp_path / "third.npy", np.hstack([pts, n]))
    g, dropped = read_input(str(tmp_path / "third.npy"), "source")
    assert dropped == 0 and g.n_points == 300 and g.normals is None
    assert "100 of 300 point(s) have zero, NaN or infinite normals: the normals are ignored" in capsys.readouterr().out
    n[15:100] = pts[15:100] / np.linalg.norm(pts[15:100], axis=1, keepdims=True)  # 15 of 300: 5 %
    np.save(tmp_path / "few.npy", np.hstack([pts, n]))
    g, dropped = read_input(str(tmp_path / "few.npy"), "source")
    assert dropped == 15 and g.normals is not None


def test_mesh_nan_vertices_drop_their_faces(tmp_path):
    text = ("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 3\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0\n1 0 0\n0 1 0\n1 1 0\nnan 5 5\n3 0 1 2\n3 1 3 2\n3 2 3 4\n")
    m, dropped = read_input(write(tmp_path, "m.ply", text), "source")
    assert dropped == 1 and len(m.vertices) == 4 and len(m.faces) == 2 and np.isfinite(m.vertices).all()


def test_too_few_valid_points_still_fail(tmp_path):
    with pytest.raises(InputError, match=r"4 point\(s\) with NaN or infinite coordinates \(of 6\); 2 valid left"):
        read_geometry(write(tmp_path, "few.xyz", "0 0 0\n1 0 0\nnan 0 0\n0 inf 0\nnan nan nan\n1 nan 1\n"), "source")


# ------------------------------------------------------------------------------------------ column meaning
def test_columns_detected_from_values():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)) * 10
    unit = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    rgb255 = rng.integers(0, 256, size=(50, 3)).astype(float)
    rgb1 = rng.random((50, 3))
    cases = {
        "x y z": xyz,
        "x y z nx ny nz": np.hstack([xyz, unit]),
        "x y z r g b": np.hstack([xyz, rgb255]),
        "x y z r g b a": np.hstack([xyz, rgb1, np.ones((50, 1))]),
        "x y z nx ny nz r g b": np.hstack([xyz, unit, rgb255]),
        "x y z r g b nx ny nz": np.hstack([xyz, rgb1, unit]),
        "x y z nx ny nz r g b a": np.hstack([xyz, unit, rgb255, np.full((50, 1), 255.0)]),
    }
    for expect, arr in cases.items():
        assert " ".join(detect_columns(arr, "t")) == expect


def test_a_transform_file_given_as_a_cloud_is_named_so(tmp_path):
    """A 4x4 rigid transform (the ground truth beside the scans) given as the source: said to be a transform, with
    where one goes (it was '4 columns; ... set data.columns', whose advice led nowhere)."""
    from scanreg.geometry import random_pose
    from scanreg.io import read_input

    np.savetxt(tmp_path / "cow_T.txt", random_pose(np.random.default_rng(0), 90.0, 1.0))
    with pytest.raises(InputError, match=r"cow_T.txt: a 4x4 matrix, a rigid transform, not a point cloud .*data.gt"):
        read_input(str(tmp_path / "cow_T.txt"), "source")


def test_columns_guessed_from_values_are_said(tmp_path, capsys):
    """Colours detected from the values (which an intensity column can mimic) come with a note naming the
    columns; all-zero columns 4-6 are neither normals nor black colours: ignored, with a note."""
    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(40, 3))
    np.savetxt(tmp_path / "i.txt", np.hstack([xyz, rng.integers(0, 256, size=(40, 4))]), fmt="%.9g")
    c = read_geometry(tmp_path / "i.txt")
    assert "columns read as x y z r g b a from their values" in capsys.readouterr().out and "colors" in c.extra
    np.savetxt(tmp_path / "z.xyz", np.hstack([xyz, np.zeros((40, 3))]), fmt="%.9g")
    c = read_geometry(tmp_path / "z.xyz")
    assert c.normals is None and "colors" not in c.extra
    assert "columns 4-6 are all zero: ignored" in capsys.readouterr().out
    np.savetxt(tmp_path / "n.xyz", np.hstack([xyz, xyz / np.linalg.norm(xyz, axis=1, keepdims=True)]), fmt="%.9g")
    assert read_geometry(tmp_path / "n.xyz").normals is not None
    assert "note" not in capsys.readouterr().out  # unit normals: not a guess worth a line


def test_leica_pts_and_decimal_commas(tmp_path):
    """Leica's PTS (a point-count line, then x y z intensity r g b) and a European CSV (semicolons between
    values, decimal commas) read as meant; a bad row is quoted as the file has it."""
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(30, 3))
    rows = np.hstack([xyz, rng.integers(-2048, 2048, size=(30, 1)), rng.integers(0, 256, size=(30, 3))])
    (tmp_path / "s.pts").write_text("30\n" + "\n".join(" ".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    c = read_geometry(tmp_path / "s.pts")
    assert np.allclose(c.points, xyz) and np.array_equal(c.extra["colors"], rows[:, 4:].astype(np.uint8))
    eu = "x;y;z\n" + "\n".join(";".join(f"{v:.6f}".replace(".", ",") for v in r) for r in xyz) + "\n"
    (tmp_path / "eu.csv").write_text(eu)
    assert np.allclose(read_geometry(tmp_path / "eu.csv").points, xyz, atol=1e-6)
    (tmp_path / "bad.csv").write_text(eu + "1,5;2,5\n")
    with pytest.raises(InputError, match=r"line 32: '1,5;2,5' is not a row of 3 numbers"):
        read_geometry(tmp_path / "bad.csv")


def test_colours_are_read_not_taken_for_normals(tmp_path):
    """A photogrammetry export x y z r g b: colours, not normals; they are carried into the written PLY."""
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(40, 3))
    rgb = rng.integers(0, 256, size=(40, 3))
    np.savetxt(tmp_path / "photo.xyz", np.hstack([xyz, rgb]), fmt="%.9g")
    c = read_geometry(tmp_path / "photo.xyz")
    assert c.normals is None and np.array_equal(c.extra["colors"], rgb)
    write_ply(tmp_path / "out.ply", c)
    back = read_geometry(tmp_path / "out.ply")
    assert np.array_equal(back.extra["colors"], rgb) and np.allclose(back.points, xyz)


def test_columns_override(tmp_path):
    rng = np.random.default_rng(3)
    arr = np.hstack([rng.normal(size=(20, 3)), rng.random((20, 1)) * 1000, rng.random((20, 3))])
    p = tmp_path / "scan.txt"
    np.savetxt(p, arr)
    with pytest.raises(InputError, match="7 columns|neither unit normals nor colours"):
        read_geometry(p)
    c = read_geometry(p, columns="x y z - r g b")
    assert np.allclose(c.points, arr[:, :3])
    assert np.array_equal(c.extra["colors"], np.round(arr[:, 4:7] * 255).astype(np.uint8))  # 0..1 -> 0..255
    c = read_geometry(p, columns="x,y,z,-,-,-,-")
    assert c.normals is None and "colors" not in c.extra
    with pytest.raises(InputError, match="names 3 column"):
        read_geometry(p, columns="x y z")
    with pytest.raises(InputError, match="unknown column 'q'"):
        read_geometry(p, columns="x y z q r g b")
    np.save(tmp_path / "scan.npy", arr[:, [0, 1, 2, 4, 5, 6]])
    assert read_geometry(tmp_path / "scan.npy").extra["columns"] == "x y z r g b"


# ------------------------------------------------------------------------------------------ degenerate geometry
@pytest.mark.parametrize("name,data,what", [
    ("polygon.off", "OFF\n5 1 0\n0 0 0\n2 0 0\n3 1 0\n1 2 0\n-1 1 0\n5 0 1 2 3 4\n", "is planar"),
    ("line.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 1 1\n2 2 2\n3 0 1 2\n",
     "is collinear"),
    ("plane.xyz", "\n".join(f"{i % 7} {i // 7} {0.5 * (i % 7) - 0.25 * (i // 7)}" for i in range(49)), "is planar"),
    ("one_point.xyz", "1 2 3\n" * 20, "all points coincide"),
    # copies of a point whose mean rounds off it (spread 1e-14 of it: was called collinear)
    ("same_point.xyz", "0.368101 -0.109047 0.238249\n" * 100, "all points coincide"),
    ("few.npy", None, "4 point(s) (3 invalid point(s) dropped); at least 10"),
])
def test_degenerate_inputs_are_input_errors(tmp_path, name, data, what):
    from scanreg.eval.checks import check_geometry

    if data is None:
        arr = np.random.default_rng(0).normal(size=(7, 3))
        arr[:3, 0] = np.nan
        np.save(tmp_path / name, arr)
        p = str(tmp_path / name)
    else:
        p = write(tmp_path, name, data)
    g, bad = read_input(p, "source")
    with pytest.raises(InputError, match=re.escape(what)) as e:
        check_geometry(g, g.source, 10, bad)
    assert str(e.value).startswith(f"source {p}: ")
    if what.startswith("is "):
        assert "rigid registration is not determined" in str(e.value)


def test_bumpy_but_thin_input_passes():
    """A wavy sheet 1 % as thick as it is wide is not flat."""
    from scanreg.eval.checks import check_geometry

    u, v = np.mgrid[0:40, 0:40] / 40.0
    pts = np.stack([u, v, 0.01 * np.sin(7 * u) * np.cos(5 * v)], -1).reshape(-1, 3)
    check_geometry(Cloud(pts), "t", 10)


def test_point_to_plane_singular_system_takes_the_least_norm_step():
    """Point-to-plane on a plane: the 6x6 system is singular (sliding in the plane, turning about its normal).
    No LinAlgError: the least-norm step moves only along what the pairs determine (the plane's normal)."""
    from scanreg.stages.icp.plane import PointToPlane

    u, v = np.mgrid[0:10, 0:10].reshape(2, -1).astype(float)
    pts = np.stack([u, v, np.zeros_like(u)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    icp = PointToPlane.__new__(PointToPlane)
    ok = np.ones(len(pts), bool)
    T = icp.step(pts + [0, 0, 0.1], pts, nrm, ok, None)
    assert np.allclose(T[:3, 3], [0, 0, -0.1], atol=1e-9) and np.allclose(T[:3, :3], np.eye(3), atol=1e-9)
    R = np.array([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]])  # a tilted plane: no zero column
    T = icp.step(pts @ R.T + 0.1 * R[:, 2], pts @ R.T, nrm @ R.T, ok, None)
    assert np.isfinite(T).all() and np.allclose(apply_T(T, pts @ R.T + 0.1 * R[:, 2]) @ R[:, 2], 0, atol=1e-6)
    sphere = np.random.default_rng(1).normal(size=(200, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)  # turning about its centre changes nothing
    T = icp.step(sphere * 1.01, sphere, sphere, np.ones(len(sphere), bool), None)
    from scanreg.geometry import rotation_angle_deg

    assert rotation_angle_deg(T[:3, :3]) < 0.1 and np.abs(T[:3, 3]).max() < 0.01  # no wild turn
    varied = np.random.default_rng(0).normal(size=pts.shape)  # normals in every direction: determined
    varied /= np.linalg.norm(varied, axis=1, keepdims=True)
    exact = np.eye(4)
    exact[2, 3] = -0.1  # moves every source point onto its pair: zero residual, the one solution here
    T = icp.step(pts + [0, 0, 0.1], pts, varied, ok, None)
    assert np.allclose(T, exact, atol=1e-9), T
    utm = pts + [665187.5, 5648349.9, 241.8]  # geo-referenced coordinates (metres, UTM) are not singular
    T = icp.step(utm + [0, 0, 0.1], utm, varied, ok, None)
    assert np.allclose(apply_T(T, utm + [0, 0, 0.1]), utm, atol=1e-6), apply_T(T, utm + [0, 0, 0.1]) - utm


@pytest.mark.slow
def test_flat_mesh_stops_before_the_coarse_stage_through_the_cli(tmp_path):
    from conftest import run_cli

    write(tmp_path, "polygon.off", VARIANTS["coff.off"])
    r = run_cli(["data.source=polygon.off", "data.target=pkg:pymeshlab/tests/sample_meshes/bunny.obj",
                 "tracking=none", f"hydra.run.dir={tmp_path / 'out'}"], tmp_path)
    assert r.returncode != 0 and "Traceback" not in r.stderr + r.stdout
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == ["error: source polygon.off: is planar: rigid registration is not determined"
                     + lines[0].split("not determined", 1)[1]], r.stderr
    assert "internal error" not in r.stderr


@pytest.mark.slow
def test_depth_camera_clouds_with_nan_pixels_register(tmp_path):
    """Two organised PCD clouds with NaN for a quarter of their pixels (different ones) register through the
    CLI, and result.json counts the dropped points."""
    import json

    from conftest import run_cli
    from scanreg.geometry import random_pose

    T = random_pose(np.random.default_rng(5), 30.0, 0.05)
    src, n_src = _organised_pcd(tmp_path, seed=1)
    tgt, n_tgt = _organised_pcd(tmp_path, seed=2, pose=T)
    write(tmp_path, "s.pcd", src)
    write(tmp_path, "t.pcd", tgt)
    np.savetxt(tmp_path / "gt.txt", T)
    out = tmp_path / "out"
    r = run_cli(["data.source=s.pcd", "data.target=t.pcd", "data.gt=gt.txt", "tracking=none",
                 f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    assert res["n_source_invalid_points"] == n_src and res["n_target_invalid_points"] == n_tgt
    assert f"dropped {n_src} point(s) with NaN" in r.stdout
    assert res["rotation_error_deg"] < 1.0 and res["translation_error_rel"] < 0.01, res


@pytest.mark.slow
def test_colours_of_a_text_cloud_colour_the_aligned_output(tmp_path):
    """x y z r g b (a photogrammetry export) registers as points with colours, and aligned_source.ply carries
    them; data.columns overrides the detection."""
    from conftest import run_cli
    from scanreg.geometry import apply_T, random_pose
    from scanreg.geometry import barycentric_sample

    mesh = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    rng = np.random.default_rng(0)
    src, _, _ = barycentric_sample(mesh, 4000, rng)
    tgt, _, _ = barycentric_sample(mesh, 4000, rng)
    T = random_pose(rng, 40.0, 0.02)
    rgb = rng.integers(0, 256, size=(len(src), 3))
    np.savetxt(tmp_path / "s.xyz", np.hstack([src, rgb]), fmt="%.9g")
    np.save(tmp_path / "t.npy", apply_T(T, tgt))
    np.savetxt(tmp_path / "gt.txt", T)
    for args in ([], ["data.source_columns='x y z r g b'"]):
        out = tmp_path / f"out{len(args)}"
        r = run_cli(["data.source=s.xyz", "data.target=t.npy", "data.gt=gt.txt", "tracking=none",
                     f"hydra.run.dir={out}", *args], tmp_path)
        assert r.returncode == 0, r.stderr
        aligned = read_geometry(out / "aligned_source.ply")
        assert np.array_equal(aligned.extra["colors"], rgb) and aligned.normals is None
        assert np.allclose(aligned.points, apply_T(T, src), atol=5e-3 * np.ptp(src, axis=0).max())


def test_text_rows_parsed_at_once_as_line_by_line(tmp_path):
    """The one-call parse of a text cloud's rows (4x faster on a million rows) gives the line-by-line parse's
    values bit for bit, and leaves to it what needs lines: comments among the rows, a bad row to name."""
    from scanreg.io.clouds import _parsed_at_once, _parsed_by_line

    rng = np.random.default_rng(6)
    rows = rng.normal(size=(500, 3)) * 10.0 ** rng.uniform(-6, 6, (500, 1))
    for sep, end in ((" ", "\n"), (",", "\r\n"), ("\t", "\n")):
        text = end.join(sep.join(f"{v:.17g}" for v in r) for r in rows) + end + end
        data = text.encode()
        fast = _parsed_at_once(data)
        assert fast is not None and np.array_equal(fast, _parsed_by_line(data.splitlines(), 0, "t"))
        assert np.array_equal(fast, rows)
    assert _parsed_at_once(b"1 2 3\n# a comment\n4 5 6\n") is None
    assert _parsed_at_once(b"1 2 3\n4 5\n") is None
    with pytest.raises(InputError, match=r"line 2: '4 5' is not a row of 3 numbers"):
        _parsed_by_line([b"1 2 3", b"4 5"], 0, "t")
