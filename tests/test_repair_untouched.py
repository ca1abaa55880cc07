"""Issue #34: a repair that costs what the defects cost. A mesh in which the census and the exact
self-intersection test find no defect MeshFix repairs passes untouched (``repair.scope=defects``, the default),
with the audit a repair reports; any one defect sends it through MeshFix as before; ``repair.scope=whole`` always
runs MeshFix."""

import numpy as np
import open3d as o3d
import pytest

import scanreg
from scanreg.errors import ConfigError
from scanreg.geometry import Mesh
from scanreg.types import RunContext

CTX = RunContext(seed=0, run_dir=None)


def sphere(radius=1.0, resolution=30, centre=(0.0, 0.0, 0.0)) -> Mesh:
    s = o3d.geometry.TriangleMesh.create_sphere(radius, resolution)
    return Mesh(np.asarray(s.vertices) + centre, np.asarray(s.triangles).astype(np.int64), "sphere")


def repaired(mesh: Mesh, **params):
    return scanreg.build_stage("repair", "meshfix", **params).repair(mesh, CTX)


def test_a_clean_closed_mesh_passes_untouched_with_the_audit_of_a_repair():
    m = sphere()
    r = repaired(m)
    assert r.mesh is m and r.metrics["untouched"] == 1.0 and r.metrics["guard_ok"] == 1.0
    before = {k[7:]: v for k, v in r.metrics.items() if k.startswith("before_")}
    after = {k[6:]: v for k, v in r.metrics.items() if k.startswith("after_")}
    assert before == after and before["faces"] == len(m.faces) and before["self_intersecting_faces"] == 0
    assert before["watertight"] == 1 and before["boundary_loops"] == 0
    assert r.metrics["hausdorff_max"] == r.metrics["removed_area_share"] == r.metrics["backend_time_s"] == 0.0
    assert r.metrics["components_kept"] == 1 and r.metrics["median_edge"] > 0
    # the same keys as a repair through MeshFix (scope=whole), which changes nothing countable here
    whole = repaired(sphere(), scope="whole")
    assert whole.metrics["untouched"] == 0.0 and whole.mesh is not m
    assert set(whole.metrics) == set(r.metrics)
    assert {k: whole.metrics[f"after_{k}"] for k in ("faces", "boundary_loops", "self_intersecting_faces")} == \
        {k: after[k] for k in ("faces", "boundary_loops", "self_intersecting_faces")}


def _with_hole(m: Mesh) -> Mesh:
    return Mesh(m.vertices, m.faces[1:], m.source)


def _with_unreferenced_vertex(m: Mesh) -> Mesh:
    return Mesh(np.vstack([m.vertices, [[5.0, 5.0, 5.0]]]), m.faces, m.source)


def _interpenetrating(m: Mesh) -> Mesh:
    other = sphere(centre=(0.8, 0.0, 0.0))  # two parts of equal area crossing each other: topology clean
    return Mesh(np.vstack([m.vertices, other.vertices]), np.vstack([m.faces, other.faces + len(m.vertices)]),
                m.source)


def _with_sliver(m: Mesh) -> Mesh:
    v = m.vertices.copy()
    a, b, c = m.faces[0]
    v[c] = v[a] + (v[b] - v[a]) * 0.5 + 1e-4 * (v[c] - v[a])  # the face's third corner almost on its edge
    return Mesh(v, m.faces, m.source)


@pytest.mark.parametrize("defect", [_with_hole, _with_unreferenced_vertex, _interpenetrating, _with_sliver])
def test_any_defect_sends_the_mesh_through_meshfix(defect):
    m = defect(sphere())
    r = repaired(m)
    assert r.metrics["untouched"] == 0.0 and r.mesh is not m
    if defect is _with_hole:
        assert r.metrics["before_boundary_loops"] == 1 and r.metrics["after_boundary_loops"] == 0
    if defect is _interpenetrating:
        assert r.metrics["before_self_intersecting_faces"] > 0


def test_scope_is_checked():
    with pytest.raises((ConfigError, ValueError), match="scope"):
        scanreg.build_stage("repair", "meshfix", scope="parts")
