"""Repair backends and the repair audit on real defect meshes (../shared/data and meshes packages ship)."""

import numpy as np
import pytest

from conftest import shared
from pipeline.config import Context
from pipeline.errors import StageError
from pipeline.io import read_mesh
from pipeline.registry import REPAIR, make_params
from stages.repair import audit_mesh, mesh_stats, repair_with_audit

CTX = Context(seed=0, run_dir=None)


def stage(name, **kw):
    cls = REPAIR.get(name)
    return cls(make_params(cls.Params, kw, f"repair={name}"))


def load(spec):
    m = read_mesh(spec if spec.startswith("pkg:") else shared(spec))
    m.source = spec
    return m


def assert_clean(after, watertight=True):
    assert after["after_components"] == 1
    assert after["after_non_manifold_edges"] == 0 and after["after_non_manifold_vertices"] == 0
    assert after["after_inconsistent_orientation_edges"] == 0, "not coherently oriented"
    assert after["after_self_intersecting_faces"] == 0
    assert after["after_degenerate_faces"] == 0
    if watertight:
        assert after["after_boundary_edges"] == 0 and after["after_watertight"] == 1
        assert after["after_volume"] > 0, "outward orientation gives a positive volume"


def strip(m, prefix="r_"):
    return {k[len(prefix):]: v for k, v in m.items()}


@pytest.mark.parametrize("backend,mesh", [
    ("meshfix", "pkg:pymeshfix/examples/StanfordBunny.ply"),
    pytest.param("meshlab", "pkg:pymeshfix/examples/StanfordBunny.ply", marks=pytest.mark.slow),  # ~40 s
    ("meshfix", "meshlab_defects/screwdriver.ply"),
    ("meshlab", "meshlab_defects/screwdriver.ply"),
])
def test_closed_models_become_single_watertight_manifolds(backend, mesh):
    m = load(mesh)
    out, metrics = repair_with_audit(stage(backend), m, CTX, "r_")
    a = strip(metrics)
    assert_clean(a)
    assert a["guard_ok"] == 1 and a["removed_area_share"] < 0.1 and a["hausdorff_max_rel"] < 0.01
    if "StanfordBunny" in mesh:  # the defects were there, and are reported as gone
        assert a["before_boundary_loops"] == 70 and a["before_non_manifold_edges"] == 132
        assert a["before_self_intersecting_faces"] > 0


@pytest.mark.parametrize("backend", ["meshfix", "meshlab"])
@pytest.mark.parametrize("mesh", ["meshlab_defects/many_small_holes.ply", "meshlab_defects/non_manif_hole.ply"])
def test_guard_stops_repairs_that_destroy_open_scans(backend, mesh):
    """Filling every hole caps these open scans' borders; the caps cut through the scans and removing the
    intersections eats a third or more of the surface. The guard must fail such a run, with the audit."""
    m = load(mesh)
    with pytest.raises(StageError, match=r"removed \d+\.\d% of the surface") as e:
        repair_with_audit(stage(backend), m, CTX, "r_")
    assert "\n" not in str(e.value) and "max_hole_edges" in str(e.value)
    assert e.value.metrics["r_removed_area_share"] > 0.3 and e.value.metrics["r_guard_ok"] == 0
    # check_only audits the same repair but hands the unchanged mesh on
    out, metrics = repair_with_audit(stage(backend, check_only=True), m, CTX, "r_")
    assert out is m and metrics["r_guard_ok"] == 0


@pytest.mark.parametrize("backend,mesh,max_edges", [
    ("meshfix", "meshlab_defects/many_small_holes.ply", 100),
    ("meshlab", "meshlab_defects/many_small_holes.ply", 100),
    ("meshfix", "meshlab_defects/non_manif_hole.ply", 50),
    ("meshlab", "meshlab_defects/non_manif_hole.ply", 50),
    ("meshfix", "stanford_bunny/bun000.ply", 300),
])
def test_open_scans_with_the_border_kept_open(backend, mesh, max_edges):
    """Every hole but the scan's outer border closed; one manifold, oriented component, no self-intersection,
    little of the surface removed."""
    m = load(mesh)
    before = mesh_stats(m)
    _, metrics = repair_with_audit(stage(backend, max_hole_edges=max_edges, max_hausdorff=1.0), m, CTX, "r_")
    a = strip(metrics)
    assert_clean(a, watertight=False)
    assert before["boundary_loops"] > 1 and a["after_boundary_loops"] == 1
    assert a["removed_area_share"] < 0.1
    if "bun000" in mesh:
        assert a["hausdorff_max_rel"] < 0.01 and a["removed_area_share"] < 0.01


@pytest.mark.slow
def test_meshlab_on_a_stanford_scan_with_border_open():
    m = load("stanford_bunny/bun000.ply")
    _, metrics = repair_with_audit(stage("meshlab", max_hole_edges=300, max_hausdorff=1.0), m, CTX, "r_")
    a = strip(metrics)
    assert_clean(a, watertight=False)
    assert a["after_boundary_loops"] == 1 and a["removed_area_share"] < 0.01


def test_audit_counts_self_intersections_and_nonmanifold_vertices():
    from pipeline.geometry import Mesh

    # two triangles crossing each other
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, -1], [0.5, 0.5, 1], [1.5, 1.5, 0]], float)
    a = audit_mesh(Mesh(v, np.array([[0, 1, 2], [3, 4, 5]])))
    assert a["self_intersecting_faces"] == 2
    # two triangles sharing only a vertex: a non-manifold vertex
    v2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    assert audit_mesh(Mesh(v2, np.array([[0, 1, 2], [0, 3, 4]])))["non_manifold_vertices"] == 1
