"""Repair where the defects are (issue #34): regions cut out around the defects with a margin
(scanreg.mesh.regions.defect_regions), repaired by MeshFix and stitched back (stitch) only when their cut came back
unchanged; the default repair (scope=defects) on them; both scans of a pair repaired at once."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import scanreg
from conftest import shared
from scanreg.errors import StageError
from scanreg.geometry import Mesh, submesh
from scanreg.mesh.census import mesh_census
from scanreg.mesh.regions import defect_regions, stitch
from scanreg.mesh.topology import boundary_edges, dilate_faces, loop_labels, mesh_stats
from scanreg.types import Repaired, RunContext


def sphere(resolution: int = 24) -> Mesh:
    import open3d as o3d

    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    return Mesh(np.asarray(s.vertices, dtype=np.float64), np.asarray(s.triangles, dtype=np.int64), "sphere")


def punched(mesh: Mesh, centres: list[int], rings: int = 1) -> Mesh:
    """``mesh`` with the faces within ``rings`` rings of each vertex in ``centres`` removed (holes)."""
    hot = np.zeros(len(mesh.vertices), bool)
    hot[centres] = True
    gone = dilate_faces(mesh.faces, hot[mesh.faces].any(axis=1), rings - 1)
    return submesh(mesh, ~gone)


def face_set(mesh: Mesh) -> set:
    """The faces as sets of corner coordinates (independent of indices and corner order)."""
    return {frozenset(map(tuple, mesh.vertices[f])) for f in mesh.faces}


def regions_of(mesh: Mesh):
    c = mesh_census(mesh, broad_phase=False)
    holes = np.ones(len(c.loop_edges), bool)
    seeds = np.zeros(len(mesh.faces), bool)
    seeds[c.boundary_faces] = True
    return defect_regions(mesh, seeds, holes), c


def test_each_hole_gets_a_region_whose_cut_is_longer_than_the_hole():
    mesh = punched(sphere(), [530, 554, 254], rings=2)
    regions, c = regions_of(mesh)
    assert len(regions) == 3 and sorted(r.hole_edges for r in regions) == sorted(c.loop_edges.tolist())
    for r in regions:
        border = boundary_edges(Mesh(mesh.vertices, mesh.faces[r.faces]))
        sizes = np.bincount(loop_labels(border))
        # one loop is the hole (r.hole_edges edges), the other the cut, longer than it
        assert sorted(sizes)[0] == r.hole_edges and sorted(sizes)[-1] > r.hole_edges


def test_no_region_when_every_cut_is_shorter_than_the_hole():
    """A hemisphere's rim as the hole to fill: the cut of any strip along it lies inside the rim and is shorter,
    so MeshFix would fill the cut too; no margin helps, and the caller repairs the whole mesh instead."""
    full = sphere()
    below = full.vertices[full.faces].mean(axis=1)[:, 2] < 0.1
    mesh = submesh(full, below)
    c = mesh_census(mesh, broad_phase=False)
    assert len(c.loop_edges) == 1
    seeds = np.zeros(len(mesh.faces), bool)
    seeds[c.boundary_faces] = True
    assert defect_regions(mesh, seeds, np.ones(1, bool)) is None
    # a small hole in the same hemisphere has its region
    at = int(np.argmin(np.linalg.norm(mesh.vertices - [0.6, 0.0, -0.8], axis=1)))
    small = punched(mesh, [at], rings=1)
    c = mesh_census(small, broad_phase=False)
    hole = c.loop_edges < c.loop_edges.max()
    seeds = np.zeros(len(small.faces), bool)
    seeds[c.boundary_faces[hole[c.boundary_loop]]] = True
    regions = defect_regions(small, seeds, hole)
    assert regions is not None and [r.hole_edges for r in regions] == c.loop_edges[hole].tolist()


def test_stitch_takes_back_an_unchanged_region_and_refuses_a_changed_cut():
    mesh = punched(sphere(), [530, 254], rings=2)
    regions, _ = regions_of(mesh)
    parts = [submesh(mesh, r.faces) for r in regions]
    same = stitch(mesh, regions, [(q.vertices, q.faces) for q in parts])
    assert same is not None and face_set(same) == face_set(mesh) and len(same.faces) == len(mesh.faces)
    # the faces keep their order when nothing changed
    assert np.array_equal(same.vertices[same.faces], mesh.vertices[mesh.faces])
    # a cut vertex moved: refused
    q = parts[0]
    on_cut = np.flatnonzero(np.isin(np.arange(len(q.vertices)), np.unique(boundary_edges(q))))
    moved = q.vertices.copy()
    moved[on_cut[-1]] += 1e-9
    assert stitch(mesh, regions[:1], [(moved, q.faces)]) is None
    # a face on the cut dropped (the cut no longer closes): refused
    border_faces = np.flatnonzero(np.isin(q.faces, on_cut).any(axis=1))
    keep = np.ones(len(q.faces), bool)
    keep[border_faces[-1]] = False
    assert stitch(mesh, regions[:1], [(q.vertices, q.faces[keep])]) is None
    # a cut edge turned the other way round: refused
    flipped = q.faces.copy()
    flipped[border_faces[-1]] = flipped[border_faces[-1], ::-1]
    assert stitch(mesh, regions[:1], [(q.vertices, flipped)]) is None


def test_the_default_repair_fills_holes_in_their_regions_only():
    """A closed sphere with three holes: the default (scope=defects) fills them in their regions, leaves every
    other face as it was, and reports the same counts as MeshFix on the whole mesh (scope=whole)."""
    mesh = punched(sphere(32), [2 + 64 * 15, 2 + 64 * 15 + 32, 2 + 64 * 7 + 16], rings=2)
    ctx = RunContext(seed=0)
    region = scanreg.build_stage("repair", "meshfix").repair(Mesh(mesh.vertices, mesh.faces, "s"), ctx)
    whole = scanreg.build_stage("repair", "meshfix", scope="whole").repair(Mesh(mesh.vertices, mesh.faces, "s"), ctx)
    for r in (region, whole):
        assert r.metrics["after_boundary_loops"] == 0 and r.metrics["after_watertight"] == 1
        assert r.metrics["after_self_intersecting_faces"] == 0 and r.metrics["untouched"] == 0
    keys = [k for k in region.metrics if k.startswith(("before_", "after_")) and not k.endswith(("area", "volume"))]
    assert {k: region.metrics[k] for k in keys} == {k: whole.metrics[k] for k in keys}
    regions, _ = regions_of(mesh)
    outside = np.ones(len(mesh.faces), bool)
    for r in regions:
        outside[r.faces] = False
    assert face_set(submesh(mesh, outside)) <= face_set(region.mesh)
    assert len(face_set(mesh) - face_set(region.mesh)) < (~outside).sum()


def test_a_raw_scan_is_repaired_in_regions_with_its_slivers_collapsed():
    """A raw Stanford scan: regional MeshFix (its holes filled, its non-manifold vertices split), the slivers
    collapsed where that folds nothing (the collapse tried again with the vertices near a fold frozen, so that
    one fold does not keep every sliver), no self-intersection."""
    from scanreg.io import read_mesh

    from scanreg.mesh.intersect import self_intersecting_faces

    mesh = read_mesh(str(shared("stanford_bunny/bun045.ply")))
    res = scanreg.build_stage("repair", "meshfix").repair(mesh, RunContext(seed=0))
    m, out = res.metrics, res.mesh
    # the input's test decided on the census's pairs, the output's from it: the full exact tests' counts
    assert m["before_self_intersecting_faces"] == self_intersecting_faces(mesh.vertices, mesh.faces).sum()
    assert m["after_self_intersecting_faces"] == self_intersecting_faces(out.vertices, out.faces).sum()
    assert m["untouched"] == 0 and m["guard_ok"] == 1
    assert m["after_boundary_loops"] == 1 and m["after_non_manifold_vertices"] == 0  # the outer border only
    assert m["after_self_intersecting_faces"] == 0
    assert m["after_sliver_faces"] <= 12 < m["before_sliver_faces"]


class _Repair:
    """A stand-in repair stage: the mesh back with its faces reversed, or a guard failure for ``fail``."""

    def __init__(self, fail: str | None = None):
        self.fail = fail

    def applies_to(self, role: str) -> bool:
        return True

    def repair(self, mesh: Mesh, ctx) -> Repaired:
        if mesh.source == self.fail:
            raise StageError(f"{mesh.source}: the guard failed", metrics={"guard_ok": 0.0})
        return Repaired(Mesh(mesh.vertices, mesh.faces[:, ::-1].copy(), mesh.source), {"after_faces": len(mesh.faces)})


def test_both_scans_are_repaired_at_once_with_the_results_of_one_after_the_other():
    from scanreg.runner.steps import repair_scans

    a, b = punched(sphere(), [530]), punched(sphere(16), [2 + 32 * 7])
    geometries = {"source": Mesh(a.vertices, a.faces, "source"), "target": Mesh(b.vertices, b.faces, "target"),
                  "cloud": SimpleNamespace()}
    out = repair_scans(geometries, SimpleNamespace(repair=_Repair()), RunContext(seed=0))
    assert set(out) == {"source", "target"}  # a cloud is not repaired
    for role, g in geometries.items():
        if role != "cloud":
            assert np.array_equal(out[role].mesh.faces, g.faces[:, ::-1])
            assert out[role].metrics == {"after_faces": len(g.faces)}


class _Cores(_Repair):
    """A stand-in repair that reports the cores its context gives it."""

    def repair(self, mesh: Mesh, ctx) -> Repaired:
        return Repaired(mesh, {"cores": ctx.cores})


def test_scans_repaired_at_once_share_the_cores():
    """Two scans repaired at once get half the cores each (on two cores one each: no test forked beside either
    repair); one scan alone keeps the run's (None: the machine's)."""
    from scanreg.process import cores
    from scanreg.runner.steps import repair_scans

    a = punched(sphere(), [530])
    pair = {"source": Mesh(a.vertices, a.faces, "source"), "target": Mesh(a.vertices, a.faces, "target")}
    for given, each in ((4, 2), (2, 1), (1, 1), (None, max(1, cores() // 2))):
        out = repair_scans(pair, SimpleNamespace(repair=_Cores()), RunContext(seed=0, cores=given))
        assert {r: x.metrics["cores"] for r, x in out.items()} == {"source": each, "target": each}
    alone = repair_scans({"source": pair["source"]}, SimpleNamespace(repair=_Cores()), RunContext(seed=0))
    assert alone["source"].metrics["cores"] is None


@pytest.mark.parametrize("fail", ["source", "target"])
def test_a_failed_repair_says_whose_it_was(fail):
    from scanreg.runner.steps import repair_scans

    a = punched(sphere(), [530])
    geometries = {"source": Mesh(a.vertices, a.faces, "source"), "target": Mesh(a.vertices, a.faces, "target")}
    with pytest.raises(StageError) as e:
        repair_scans(geometries, SimpleNamespace(repair=_Repair(fail)), RunContext(seed=0))
    assert e.value.role == fail and e.value.metrics == {"guard_ok": 0.0} and fail in str(e.value)
    other = {"source": "target", "target": "source"}[fail]  # the other repair finished, its audit kept
    assert list(e.value.repaired) == [other] and e.value.repaired[other].metrics == {"after_faces": len(a.faces)}
    assert mesh_stats(a)["boundary_loops"] == 1


def test_a_part_split_in_two_keeps_its_largest_piece():
    """Two spheres touching at one vertex are one part; a backend that splits that vertex (MeshFix does, on
    load) makes two pieces, and the stitched mesh keeps the larger, as MeshFix keeps one piece of a part."""
    from scanreg.mesh.topology import _face_components

    big, small = sphere(24), sphere(8)
    top_big = int(np.argmax(big.vertices[:, 2]))
    low_small = int(np.argmin(small.vertices[:, 2]))
    shift = big.vertices[top_big] - small.vertices[low_small]
    n = len(big.vertices)
    idx = np.arange(len(small.vertices)) + n
    idx[low_small] = top_big  # the two spheres share that vertex
    keep_v = np.ones(len(small.vertices), bool)
    keep_v[low_small] = False
    renum = np.full(len(small.vertices), -1)
    renum[keep_v] = n + np.arange(keep_v.sum())
    renum[low_small] = top_big
    mesh = Mesh(np.vstack([big.vertices, small.vertices[keep_v] + shift]),
                np.vstack([big.faces, renum[small.faces]]), "two")
    assert _face_components(mesh).max() == 0  # one part
    at = np.zeros(len(mesh.vertices), bool)
    at[top_big] = True
    region_faces = np.flatnonzero(dilate_faces(mesh.faces, at[mesh.faces].any(axis=1), 2))
    from scanreg.mesh.regions import Region

    q = submesh(mesh, np.isin(np.arange(len(mesh.faces)), region_faces))
    # the backend's answer: the shared vertex split, the small sphere's faces on a copy of it
    centre = int(np.flatnonzero((q.vertices == mesh.vertices[top_big]).all(axis=1))[0])
    on_small = np.isin(region_faces, np.arange(len(big.faces), len(mesh.faces)))
    rv = np.vstack([q.vertices, q.vertices[centre]])
    rf = q.faces.copy()
    rf[on_small] = np.where(rf[on_small] == centre, len(q.vertices), rf[on_small])
    out = stitch(mesh, [Region(region_faces, 0)], [(rv, rf)])
    assert out is not None and _face_components(out).max() == 0
    assert face_set(out) == face_set(big)


def test_stitch_refuses_a_region_given_back_with_an_edge_the_rest_has():
    """A tetrahedron's two faces given back with their diagonal turned: every cut edge is still there, but the
    new diagonal is an edge of the rest too (a non-manifold, inconsistently oriented seam): refused."""
    from scanreg.mesh.regions import Region

    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    mesh = Mesh(v, f, "tet")
    region = Region(np.array([1, 2]), 0)
    assert stitch(mesh, [region], [(v, f[[1, 2]])]) is not None  # given back as it was: taken
    assert stitch(mesh, [region], [(v, np.array([[0, 1, 2], [0, 2, 3]]))]) is None


def test_a_face_turned_over_is_turned_back_in_its_region():
    """A closed sphere with one face reversed: the default repair (its region) orients it as MeshFix on the
    whole mesh does; the face given back turned is a new face, not the old one kept."""
    mesh = sphere(16)
    faces = mesh.faces.copy()
    faces[40] = faces[40, ::-1]
    ctx = RunContext(seed=0)
    for scope in ("defects", "whole"):
        m = scanreg.build_stage("repair", "meshfix", scope=scope, remove_slivers=False).repair(
            Mesh(mesh.vertices, faces, "s"), ctx).metrics
        assert m["before_inconsistent_orientation_edges"] == 3
        assert m["after_inconsistent_orientation_edges"] == 0 and m["after_boundary_loops"] == 0, scope


def test_a_note_is_one_write_so_two_repairs_do_not_interleave_their_lines(monkeypatch):
    """The two repairs of a pair print their notes at the same time; with unbuffered output (PYTHONUNBUFFERED)
    ``print`` writes a line and its newline in two calls, and the two processes' lines ran into one another."""
    from scanreg.errors import note, warn

    writes = []
    monkeypatch.setattr("sys.stdout", SimpleNamespace(write=writes.append, flush=lambda: None))
    note("the border is kept open")
    warn("a free motion")
    assert writes == ["note: the border is kept open\n", "warning: a free motion\n"]
