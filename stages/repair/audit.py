"""The audited repair shared by every backend: :class:`GuardParams` (each backend's ``Params`` extend it) and
:class:`AuditedRepair`, whose :meth:`~AuditedRepair.repair` runs the backend, audits the mesh before and after
and applies the guard.

Before the backend runs, the repair decides two things from the input alone (the border plan,
:func:`border_plan`):
- which parts are kept: the connected components whose area is at least ``min_component_share`` of the largest
  part's; the others (specks, scanner debris) are removed on purpose and reported as ``removed_components``;
- what becomes of an open scan's outer border (``open_border``; ``auto`` tells a one-sided scan from a closed
  model with holes by :func:`~scanreg.mesh.topology.open_scan_borders`).

The audit then compares the input and the output:
- topology and size before and after (:func:`audit_mesh`);
- the distances from the kept input parts to the output (large where surface was removed or moved) and the
  other way (large where holes were filled);
- the share of the kept input surface that is no longer there.

The guard measures damage to what was to be kept: the run fails with one clear line when the repair removed
more than ``max_removed_area`` of the kept parts' surface, or when the ``displacement_quantile`` quantile of
the distance from the kept input surface to the output exceeds ``max_displacement_edges`` median edge lengths
(the scan's own resolution: a sliver trimmed at a ragged border moves the surface by about one edge). Parts
removed on purpose are not damage. The line says which parameter to change.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from scanreg.errors import ScanregError, StageError, note, warn
from scanreg.geometry import Mesh, bbox_diagonal, row_norms, submesh
from scanreg.mesh.census import MIN_COMPONENT_SHARE, OPEN_BORDER_RATIO, mesh_census
from scanreg.mesh.distances import area_samples_on_faces, distances_near, exact_distances, shared_faces
from scanreg.mesh.intersect import Intersections, intersections_among
from scanreg.mesh.shell import close_as_shell
from scanreg.mesh.slivers import collapse_folds, collapse_slivers
from scanreg.mesh.topology import (SLIVER_ANGLE_DEG, audit_mesh, border_loops, component_areas, forget,
                                   intersections, known, mesh_stats, non_manifold_vertices, open_scan_borders,
                                   remember, remember_later, self_intersecting_count)
from scanreg.process import cores, forking, start_isolated
from scanreg.types import Repaired, RunContext


@dataclass
class GuardParams:
    remove_slivers: bool = True
    """After the backend, remove slivers (faces whose smallest angle is below ``sliver_angle_deg``: caps and
    needles, which neither MeshFix nor MeshLab's cleaning touch) by edge collapse, as the paper does, unless the
    collapse would add self-intersecting faces or non-manifold edges or vertices (then the backend's mesh
    is kept); the guard checks that the
    surface did not move. The audit counts them as ``sliver_faces`` before and after."""
    sliver_angle_deg: float = SLIVER_ANGLE_DEG
    """The smallest angle, in degrees, below which a face is a sliver (for ``remove_slivers``)."""
    apply_to: str = "both"
    """Which input meshes are repaired: ``source``, ``target`` or ``both`` (a CT surface made of separate
    teeth must not lose all but its largest component, so the dental case repairs the source only)."""
    scope: str = "defects"
    """What the backend works on. ``defects``: the input's self-intersection test is decided on the pairs the
    defect census's broad phase leaves; a mesh in which the census and that test find no defect the backend
    repairs passes untouched (``untouched`` 1, with the audit of a repair); otherwise MeshFix repairs the
    regions around the defects only, stitched back into the rest (the whole mesh when they cannot be cut out;
    docs/repair.md, "Repair where the defects are"). ``whole``: the backend always runs on the whole mesh and
    the input gets the full exact test, as the paper's procedure does."""
    check_only: bool = False
    """Audit what the repair would do (the before/after table and the guard) but go on with the unrepaired
    mesh; a guard violation is then reported, not fatal."""
    min_component_share: float = MIN_COMPONENT_SHARE
    """Parts (connected components) whose area is below this share of the largest part's area are removed on
    purpose, as specks and scanner debris, and reported (``removed_components``); every other part is repaired
    and kept (a head with separate eyes, a chair's legs). Dimensionless, relative to the largest part, never
    to the bounding box. 1: the largest part only; 0: every part."""
    max_removed_area: float = 0.10
    """Fail when more than this share of the kept parts' input surface (area share, 0-1) is gone after the
    repair (see ``removed_tolerance``). Parts removed on purpose (``min_component_share``) do not count."""
    max_displacement_edges: float = 2.0
    """Fail when the ``displacement_quantile`` quantile of the distance from the kept input surface to the
    repaired surface exceeds this many median edge lengths of the input (the scan's own resolution). Slivers
    trimmed at a ragged scan border move a little surface by about one edge; a capped border eaten by
    intersection removal moves a lot of it by tens of edges."""
    displacement_quantile: float = 0.99
    """The quantile (0-1) of the input -> output distances that ``max_displacement_edges`` limits."""
    max_hausdorff: float = 0.05
    """Fail when any point of the kept input surface lies farther than this share of the kept parts'
    bounding-box diagonal from the repaired surface (one-sided Hausdorff distance, input -> output): a
    backstop for a region cut away whole (see ``max_hausdorff_edges``)."""
    max_hausdorff_edges: float = 2.0
    """The Hausdorff limit is at least this many median edge lengths of the input: on a coarse mesh one
    triangle can span more than ``max_hausdorff`` of the diagonal (0: the diagonal share alone)."""
    removed_tolerance: float = 0.002
    """A kept input surface point counts as removed when it lies farther than this share of the kept parts'
    bounding-box diagonal from the repaired surface (a part counts as removed when most of its vertices
    do)."""
    audit_samples: int = 20000
    """Points sampled on each surface to measure the distances and the removed share (count). What the guard
    needs of n points: the removed share is a binomial estimate, standard error sqrt(p (1 - p) / n), 0.0021 at
    the ``max_removed_area`` limit 0.10 with 20000 (0.003 with 10000); the ``displacement_quantile`` 0.99 is
    read between the true 0.9886 and 0.9914 quantiles (+-2 standard errors of the 1 % tail's count) with 20000;
    the sampled Hausdorff maximum misses a displaced region of area share a with probability (1 - a)^n, 5 % for
    a = 1.5e-4 of the kept surface with 20000. Distances themselves are exact point-to-triangle distances in
    double precision both ways (libigl's, :func:`~scanreg.mesh.distances.distances_to`), 0 for the points on
    faces the repair left as they were."""
    open_border: str = "auto"
    """What becomes of an open scan's outer border. ``auto``: a mesh with an outer border (a boundary loop at
    least ``open_border_ratio`` times as long as the square root of its part's area,
    :func:`~scanreg.mesh.topology.open_scan_borders`) is a one-sided scan and keeps that border open, as ``open``;
    a closed model with holes is capped, as ``cap``. The choice is reported (``open_border_open`` 0/1).
    ``cap``: every hole filled, the outer border too (MeshFix's way; right for closed models with holes, but
    on an open scan the cap cuts through the surface and the guard fails the run). ``open``: the outer border
    (the detected loops, or with none detected every loop over half the longest one's edges) is left open
    and the smaller holes are filled. ``shell``: as ``open``, then the scan is closed as a thin shell, its
    surface plus an offset copy ``shell_thickness`` behind it, joined along the border: watertight without
    changing any scanned surface; samplers and the evaluation use the scanned side only (3-5x the time of
    ``open``)."""
    open_border_ratio: float = OPEN_BORDER_RATIO
    """``open_border=auto``: a boundary loop at least this many times as long as the square root of its
    part's area is an outer border (dimensionless; a disc's rim 3.5, a hemisphere's 2.5, a tooth crown cut off
    at 40 % of its height 1.7, a sphere with 80 % of it kept 1.6, a hole of half the radius in a sphere 0.9;
    raw Stanford scans 8.5-10.9, the holes of closed models under 0.5)."""
    shell_thickness: float = 0.001
    """``open_border=shell``: distance of the back side behind the surface, as a share of the bounding-box
    diagonal (less where the space behind the surface is narrower, see :func:`close_as_shell`)."""

    cache: str = "auto"
    """Keep the repaired mesh and its audit in a cache keyed by content (the input mesh's arrays, the
    backend and these parameters, the seed, the versions of scanreg and the backends) and reuse it: ``auto``
    in Hydra multirun sweeps (``-m``), so that a sweep over registration parameters repairs each scan once;
    ``on`` always; ``off`` never. A hit logs ``repair_cache_hit`` 1 (see :mod:`scanreg.stages.repair.cache`)."""
    cache_dir: str | None = None
    """The cache's directory (null: ``outputs/cache/repair`` under the working directory); entries are a few
    MB per scan and may be deleted at any time."""

    def check(self):
        if self.cache not in ("auto", "on", "off"):
            raise ValueError(f"cache must be auto, on or off, got '{self.cache}'")
        if self.apply_to not in ("source", "target", "both"):
            raise ValueError(f"apply_to must be source, target or both, got '{self.apply_to}'")
        if self.scope not in ("defects", "whole"):
            raise ValueError(f"scope must be defects or whole, got '{self.scope}'")
        if self.open_border not in ("auto", "cap", "open", "shell"):
            raise ValueError(f"open_border must be auto, cap, open or shell, got '{self.open_border}'")
        if not self.shell_thickness > 0:
            raise ValueError(f"shell_thickness must be > 0, got {self.shell_thickness}")
        if not 0 <= self.min_component_share <= 1:
            raise ValueError(f"min_component_share must be in [0, 1], got {self.min_component_share}")
        if not 0 < self.displacement_quantile <= 1:
            raise ValueError(f"displacement_quantile must be in (0, 1], got {self.displacement_quantile}")


VERTICES_PER_PART = 2000
"""The audit tells a part that is gone (most of its vertices farther than ``removed_tolerance`` from the
output) on at most this many of its vertices."""


def _median_edge(mesh: Mesh) -> float:
    v, f = mesh.vertices, mesh.faces
    return float(np.median(row_norms(v[f[:, [1, 2, 0]]] - v[f]))) if len(f) else 0.0


def border_plan(p: GuardParams, mesh: Mesh, fills: bool) -> tuple[str, int | None]:
    """The border mode to apply (``cap``, ``open`` or ``shell``) and the hole size limit (edges) that keeps
    the outer border open (None: the backend's own ``max_hole_edges``); ``fills``: the backend fills holes."""
    mode = p.open_border
    loops = border_loops(mesh)
    edges = loops[0]
    outer = open_scan_borders(mesh, p.open_border_ratio, loops) if len(edges) else np.zeros(0, bool)
    if mode == "auto":
        mode = "open" if outer.any() else "cap"
    if mode == "cap" or not fills or not len(edges) or p.max_hole_edges:
        return mode, None
    if outer.any():
        # every hole filled, the outer borders not: the limit is half the shortest outer border (the border
        # changes while intersections near it are cut out and refilled), more if a hole is larger
        shortest = int(edges[outer].min())
        holes = edges[~outer]
        return mode, max(shortest // 2, int(holes.max()) if len(holes) and holes.max() < shortest else 0, 1)
    return mode, max(int(edges.max()) // 2, 1)  # keep loops over half the longest open


def apply_plan(p: GuardParams, mode: str, max_hole: int | None) -> GuardParams:
    """``p`` with the border plan (:func:`border_plan`) applied."""
    if max_hole is None and mode == p.open_border:
        return p
    return replace(p, open_border=mode, **({} if max_hole is None else {"max_hole_edges": max_hole}))


def _first_line(e: BaseException) -> str:
    """The first line of an exception's message, at most 200 characters (for a one-line error)."""
    return (str(e).strip().splitlines() or [""])[0][:200]


def _input_test(mesh: Mesh, p: GuardParams) -> Intersections:
    """The input's self-intersection test: with ``scope: defects`` decided on the census's pairs
    (:func:`census_intersections`), else the full test (:func:`scanreg.mesh.topology.intersections`, remembered on
    the mesh)."""
    return intersections(mesh) if p.scope == "whole" else census_intersections(mesh, p)


def _input_test_arrays(mesh: Mesh, p: GuardParams) -> tuple:
    """:func:`_input_test` as the arrays that make it, for a child process: its intersecting pairs and its face
    keys (the mesh's own arrays stay with the caller)."""
    found = _input_test(mesh, p)
    return found.pairs, found.keys


def _run_backend(stage, mesh: Mesh, p: GuardParams, ctx: RunContext) -> Mesh:
    """The backend's ``run`` with the planned parameters ``p``; any failure, and an empty result, as one line
    naming the backend and file."""
    where = f"repair={stage.name}: {mesh.source or 'mesh'}"
    try:
        out = stage.run(mesh, p, ctx)
    except ScanregError:
        raise
    except Exception as e:  # a library's exception (PyMeshLabException, ...) becomes one line
        first = _first_line(e)
        raise StageError(f"{where}: the backend failed ({type(e).__name__}: {first}); try the other backend "
                         "(repair=meshfix / repair=meshlab) or repair=none") from e
    if not len(out.faces):
        raise StageError(f"{where}: the repair left no face; try the other backend (repair=meshfix / "
                         "repair=meshlab) or repair=none")
    return out


def _input_side(p: GuardParams, mesh: Mesh, seed: int) -> dict:
    """What the audit's distances need of the input alone (measured before the backend runs): the parts, which of
    them are to be kept, the kept parts' diagonal and median edge, the vertices that probe each part, and the
    samples on the kept surface."""
    lab, ca = component_areas(mesh)
    large = ca >= p.min_component_share * ca.max()  # as large_components
    kept_in = mesh if large.all() else submesh(mesh, large[lab])
    # a part is gone when most of its vertices are farther than the tolerance from the output; "most" is
    # judged on up to VERTICES_PER_PART of each part's vertices (every k-th, in index order)
    vcomp = np.full(len(mesh.vertices), -1, np.int64)
    vcomp[mesh.faces.ravel()] = np.repeat(lab, 3)
    used = np.flatnonzero(vcomp >= 0)
    per = np.bincount(vcomp[used], minlength=len(ca))
    order = used[np.argsort(vcomp[used], kind="stable")]  # grouped by part, index order within
    rank = np.arange(len(order)) - np.repeat(np.cumsum(per) - per, per)
    stride = np.maximum(1, -(-per // VERTICES_PER_PART))
    probe = order[rank % stride[vcomp[order]] == 0]
    samples, face = area_samples_on_faces(kept_in, p.audit_samples, seed)
    kept_faces = np.flatnonzero(large[lab]) if kept_in is not mesh else None  # (submesh keeps the faces' order)
    return {"areas": ca, "large": large, "diag": bbox_diagonal(kept_in.vertices), "edge": _median_edge(kept_in),
            "probe": probe, "probe_part": vcomp[probe], "samples": samples,
            "sample_face": face if kept_faces is None else kept_faces[face]}


NEAR_EDGES = 4.0
"""The audit measures a distance on the output's (or the input's) faces near the point first: those within the
larger of ``removed_tolerance`` and this many median edges (:func:`~scanreg.mesh.distances.distances_near`; the
values are the same, only a point farther than that is measured again on a wider neighbourhood)."""


def _audit_distances(p: GuardParams, mesh: Mesh, out: Mesh, ins: dict, seed: int) -> dict[str, float]:
    """The input's parts sorted into removed on purpose, kept, and lost; the distances between the kept input
    surface and the output (see the module docstring); ``ins``: :func:`_input_side`. The other way, from
    ``audit_samples`` samples on the output (seeded by ``seed``) to the input, large where holes were filled.

    Where the repair left the surface as it was, a point is on both surfaces: the samples on the faces that
    the input and the output share (:func:`~scanreg.mesh.distances.shared_faces`), and the input's vertices on
    such faces, are at distance 0; the others are measured, on the surface near them (:data:`NEAR_EDGES`), so
    that the audit of a repair that changed little costs little."""
    ca, large, diag, edge = ins["areas"], ins["large"], ins["diag"], ins["edge"]
    tol = p.removed_tolerance * diag
    reach = max(tol, NEAR_EDGES * edge)
    in_shared, out_shared = shared_faces(mesh, out)
    on_out = np.zeros(len(mesh.vertices), bool)
    on_out[mesh.faces[in_shared].ravel()] = True
    probe, part = ins["probe"], ins["probe_part"]
    # input -> output in one query: the parts' probe vertices, then the kept surface's samples
    points = np.concatenate([mesh.vertices[probe], ins["samples"]])
    moved = ~np.concatenate([on_out[probe], in_shared[ins["sample_face"]]])
    d = np.zeros(len(points))
    d[moved] = distances_near(out, points[moved], reach, exact_distances)
    far = np.bincount(part, d[:len(probe)] > tol, minlength=len(ca)) / np.bincount(part, minlength=len(ca))
    # output -> input
    samples_out, face_out = area_samples_on_faces(out, p.audit_samples, seed)
    d_out = np.zeros(len(samples_out))
    new = ~out_shared[face_out]
    d_out[new] = distances_near(mesh, samples_out[new], reach, exact_distances)
    return _distance_report(p, ca, large, diag, edge, far > 0.5, d[len(probe):], d_out)


def _distance_report(p: GuardParams, ca, large, diag: float, edge: float, gone: np.ndarray, d_in: np.ndarray,
                     d_out: np.ndarray) -> dict[str, float]:
    """The audit's distance metrics from the parts' areas ``ca``, which are to be kept (``large``) and which are
    gone, the kept parts' diagonal and median edge, and the distances input -> output (``d_in``, from the kept
    input surface's samples) and output -> input (``d_out``)."""
    tol = p.removed_tolerance * diag
    limit = max(p.max_hausdorff * diag, p.max_hausdorff_edges * edge)
    return {
        "components_kept": float((~gone).sum()),
        "removed_components": float((gone & ~large).sum()),
        "removed_components_area_share": float(ca[gone & ~large].sum() / ca.sum()),
        "removed_kept_components": float((gone & large).sum()),
        "median_edge": edge,
        "hausdorff_max": float(d_in.max()),
        "hausdorff_mean": float(d_in.mean()),
        "hausdorff_max_rel": float(d_in.max() / diag),
        "hausdorff_mean_rel": float(d_in.mean() / diag),
        "hausdorff_max_edges": float(d_in.max() / edge),
        "hausdorff_limit_rel": float(limit / diag),
        "displacement_q_edges": float(np.quantile(d_in, p.displacement_quantile) / edge),
        "hausdorff_added_max": float(d_out.max()),
        "hausdorff_added_max_rel": float(d_out.max() / diag),
        "removed_area_share": float((d_in > tol).mean()),
    }


def repair_with_audit(stage, mesh: Mesh, ctx: RunContext) -> Repaired:
    """Run the backend ``stage`` on ``mesh`` with the border plan, audit the input and the output, apply the
    guard. Returns the mesh to go on with and the audit's metrics (unprefixed names)."""
    p: GuardParams = stage.p
    where = f"repair={stage.name}: {mesh.source or 'mesh'}"
    if not len(mesh.faces):
        raise StageError(f"{where}: the mesh has no faces to repair (a point cloud? use repair=none)")
    try:
        import igl  # noqa: F401
    except ImportError as e:
        raise StageError(f"{where}: the repair's audit needs libigl ({_first_line(e)}): pip install libigl") from e
    t0 = time.perf_counter()
    planned = _planned(stage, mesh, where)
    # the input's exact self-intersection test (the audit's costliest part; with scope=defects decided on the
    # census's pairs) runs beside the backend, in a child process, when a core is free for it; the first test
    # that starts from it (the output's, or a backend's own loop) waits for it, as does the check that a mesh
    # has nothing to repair. (Otherwise it is made first, here: with every core busy, e.g. both scans of a pair
    # repaired at once on two, a test beside only competes for them and measures the census a second time.)
    beside = None
    if known(mesh, "intersections") is None:
        if forking() and (ctx.cores or cores()) >= 2:
            beside = start_isolated(_input_test_arrays, mesh, planned)
            remember_later(mesh, "intersections", lambda: Intersections(mesh.vertices, mesh.faces, *beside.result()))
        else:
            remember(mesh, "intersections", _input_test(mesh, planned))
    try:
        if _nothing_to_repair(stage, planned, mesh):
            note(f"{where}: no defect the repair would change (census and exact self-intersection test): left "
                 "untouched")
            return _untouched(planned, mesh, t0, where)
        before = audit_mesh(mesh, self_intersections=beside is None)
        input_side = _input_side(p, mesh, ctx.seed)
        t1 = time.perf_counter()
        out = _run_backend(stage, mesh, planned, ctx)
    except BaseException:
        if beside is not None:
            beside.cancel()
            forget(mesh, "intersections")
        raise
    tb = time.perf_counter()
    if beside is not None:
        before["self_intersecting_faces"] = self_intersecting_count(mesh)
    t_wait = time.perf_counter() - tb
    out, t_folds = _without_slivers(p, out)
    t_folds += t_wait
    mode = planned.open_border
    if mode == "shell":
        out = close_as_shell(out, p.shell_thickness * bbox_diagonal(out.vertices))
    t2 = time.perf_counter()
    after = mesh_stats(out)
    after["non_manifold_vertices"] = non_manifold_vertices(out)
    after["self_intersecting_faces"] = self_intersecting_count(out, previous=mesh)
    m = {f"before_{k}": v for k, v in before.items()}
    m.update({f"after_{k}": v for k, v in after.items()})
    m["open_border_open"] = float(mode in ("open", "shell"))
    m.update(_audit_distances(p, mesh, out, input_side, ctx.seed + 1))
    m["backend_time_s"] = t2 - t1 - t_folds  # the repair itself (slivers collapsed, the shell)
    m["audit_time_s"] = (t1 - t0) + t_folds + (time.perf_counter() - t2)  # audit and guard
    problems = guard_problems(p, m, mode, mesh, where, backend=stage.name)
    m["guard_ok"] = float(not problems)
    if problems:
        if not p.check_only:
            raise StageError(problems, metrics=m)
        warn(problems)
    m["untouched"] = 0.0
    return Repaired(mesh if p.check_only else out, m)


def census_intersections(mesh: Mesh, p: GuardParams) -> Intersections:
    """``scope: defects``: the input's self-intersection test decided on the pairs the defect census's broad
    phase cannot prove apart (:meth:`~scanreg.mesh.census.Census.pairs_to_test`), each pair by the exact test:
    the whole mesh's answer at a fraction of its cost (``experiments/benchmarks/census.md``), resting on the
    broad phase's one assumption (:func:`~scanreg.mesh.broad_phase.intersection_candidates`). The repair's output
    is tested exactly where it differs from the input (:func:`~scanreg.mesh.intersect.self_intersections`
    from this outcome), so no self-intersection the repair makes goes unreported."""
    c = mesh_census(mesh, sliver_angle_deg=p.sliver_angle_deg, min_component_share=p.min_component_share,
                    open_border_ratio=p.open_border_ratio)
    return intersections_among(mesh.vertices, mesh.faces, c.pairs_to_test(mesh.faces))


def _nothing_to_repair(stage, p: GuardParams, mesh: Mesh) -> bool:
    """Whether the backend would change nothing (``p``: its planned parameters): ``scope: defects``, a
    backend that says so of the mesh's defect census (:meth:`AuditedRepair.changes`), and no self-intersecting
    face by the exact test (the audit's own, remembered for it)."""
    if p.scope == "whole" or p.check_only or p.open_border == "shell":
        return False
    return not stage.changes(mesh, p) and self_intersecting_count(mesh) == 0


def _untouched(p: GuardParams, mesh: Mesh, t0: float, where: str) -> Repaired:
    """The input as the repair's result, with the audit a repair reports: the counts before and after (the
    same), every part kept and no distance between the input and itself, the guard's verdict; ``untouched``
    1."""
    before = audit_mesh(mesh)
    m = {f"before_{k}": v for k, v in before.items()}
    m.update({f"after_{k}": v for k, v in before.items()})
    m["open_border_open"] = float(p.open_border == "open")
    ca = component_areas(mesh)[1]  # every part kept (none below min_component_share), none moved
    zero = np.zeros(1)
    m.update(_distance_report(p, ca, np.ones(len(ca), bool), bbox_diagonal(mesh.vertices), _median_edge(mesh),
                              np.zeros(len(ca), bool), zero, zero))
    m["backend_time_s"] = 0.0
    m["audit_time_s"] = time.perf_counter() - t0
    problems = guard_problems(p, m, p.open_border, mesh, where)
    m["guard_ok"] = float(not problems)
    if problems:  # the input measured against itself: no guard can fail, unless the audit is broken
        raise StageError(problems, metrics=m)
    m["untouched"] = 1.0
    return Repaired(mesh, m)


def _planned(stage, mesh: Mesh, where: str) -> GuardParams:
    """The stage's parameters with the border plan applied (a note says what ``open_border=auto`` chose)."""
    p: GuardParams = stage.p
    try:
        mode, max_hole = border_plan(p, mesh, stage.fills_holes(p))
    except Exception as e:  # not the backend's failure: named as the plan's
        raise StageError(f"{where}: the repair's border plan failed ({type(e).__name__}: {_first_line(e)})") from e
    if p.open_border == "auto" and (mode == "open" or len(border_loops(mesh)[0])):  # (a closed mesh: nothing to say)
        note(f"{where}: " + ("an open scan (its outer border is long for its area): the border is kept "
                             "open" if mode == "open" else "no outer border: every hole is capped")
             + " (repair.open_border=auto; set cap, open or shell to choose)")
    return apply_plan(p, mode, max_hole)


def _without_slivers(p: GuardParams, out: Mesh) -> tuple[Mesh, float]:
    """``out`` with its slivers collapsed (``remove_slivers``), kept only where the collapse folds nothing (a
    raw scan's ragged border can: the vertices near such a fold are frozen and the collapse tried again,
    :data:`FOLD_RETRIES` times, before the backend's mesh is kept as it was); and the seconds the fold checks
    took (counted as the audit's)."""
    if not p.remove_slivers:
        return out, 0.0
    collapsed = collapse_slivers(out, p.sliver_angle_deg)
    if collapsed is out:
        return out, 0.0
    tf = time.perf_counter()
    # the neighbourhood of the collapse only
    folds_out, folds_collapsed, sites = collapse_folds(out, collapsed, sites=True)
    frozen = None
    for _ in range(FOLD_RETRIES):
        if (folds_collapsed <= folds_out).all():
            break
        # a kind of fold added: the vertices near it stay where they are, and the slivers elsewhere go
        frozen = _near_vertices(out, sites, frozen)
        collapsed = collapse_slivers(out, p.sliver_angle_deg, frozen=frozen)
        if collapsed is out:
            break
        folds_out, folds_collapsed, sites = collapse_folds(out, collapsed, sites=True)
    t_folds = time.perf_counter() - tf
    if collapsed is out or not (folds_collapsed <= folds_out).all():  # the backend's mesh stays
        return out, t_folds
    si = known(out, "self_intersecting_faces")
    if si is not None:  # the collapse's own change to it, measured where it happened
        remember(collapsed, "self_intersecting_faces", si + int(folds_collapsed[0] - folds_out[0]))
    return collapsed, t_folds


FOLD_RETRIES = 4
"""How often the sliver collapse is tried again, with the vertices near the folds it made frozen, before the
backend's mesh is kept as it was."""
FOLD_RINGS = 1
"""The vertices within this many rings of edges of a fold the collapse made are frozen in the next try."""


def _near_vertices(mesh: Mesh, sites: np.ndarray, frozen: np.ndarray | None) -> np.ndarray:
    """``frozen`` (a vertex mask of ``mesh``, None: none) and the vertices of ``mesh`` within
    :data:`FOLD_RINGS` rings of the one nearest each of ``sites`` (points)."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(mesh.vertices), bool) if frozen is None else frozen.copy()
    if len(sites):
        out[cKDTree(mesh.vertices).query(sites)[1]] = True
        for _ in range(FOLD_RINGS):
            out[mesh.faces[out[mesh.faces].any(axis=1)].ravel()] = True
    return out


def guard_problems(p: GuardParams, m: dict[str, float], mode: str, mesh: Mesh, where: str,
                   backend: str | None = None) -> str | None:
    """The guard's verdict on an audit ``m``: None, or the one-line message that names what the repair
    destroyed and the parameter to change (``backend``: the repair's name, whose alternative the line names)."""
    problems, hints = [], []
    removed, lost = m["removed_area_share"], m["removed_kept_components"]
    if removed > p.max_removed_area:
        problems.append(f"removed {removed:.1%} of the surface it was to keep (limit "
                        f"repair.max_removed_area={p.max_removed_area:g})")
    if lost:
        hints.append(f"{int(lost)} part(s) above repair.min_component_share={p.min_component_share:g} of the "
                     "largest part's area are gone: raise it to drop such parts on purpose, or try the other "
                     "backend")
    q_edges, q_limit = m["displacement_q_edges"], p.max_displacement_edges
    if q_edges > q_limit:
        problems.append(f"moved {1 - p.displacement_quantile:.0%} of it by {q_edges:.1f} median edges or more "
                        f"(limit repair.max_displacement_edges={q_limit:g})")
    if m["hausdorff_max_rel"] > m["hausdorff_limit_rel"]:
        problems.append(f"moved it by up to {m['hausdorff_max_rel']:.2%} of the diagonal (limit "
                        f"{m['hausdorff_limit_rel']:.2%}: repair.max_hausdorff={p.max_hausdorff:g}, or "
                        f"repair.max_hausdorff_edges={p.max_hausdorff_edges:g} median edges if more)")
    if not problems:
        return None
    if mode == "cap" and len(border_loops(mesh)[0]):
        hints.append("if this is an open scan whose outer border was capped, keep it open with "
                     "repair.open_border=open (or close it as a thin shell with repair.open_border=shell)")
    other = {"meshfix": "meshlab", "meshlab": "meshfix"}.get(backend)
    alternative = f"try the other backend (repair={other}), " if other else ""
    hints.append(f"inspect with repair.check_only=true, {alternative}or skip the repair with repair=none")
    return f"{where}: the repair {' and '.join(problems)}; it would destroy part of the model. " + "; ".join(hints)


class AuditedRepair:
    """Base of the repair backends: ``run(mesh, p, ctx)`` is the backend itself (``p``: its parameters with the
    border plan applied), :meth:`repair` the audited run (through the cache when it is on)."""

    p: GuardParams

    def __init__(self, params):
        self.p = params

    def applies_to(self, role: str) -> bool:
        return self.p.apply_to in (role, "both")

    def fills_holes(self, p: GuardParams) -> bool:
        """Whether the backend fills holes with these parameters (the border plan keeps borders open only then)."""
        return False

    def changes(self, mesh: Mesh, p: GuardParams) -> bool:
        """Whether the backend, with the planned parameters ``p``, may change ``mesh`` other than by removing
        self-intersections (which the audit's exact test looks for): a mesh it would not change at all passes
        untouched (``scope: defects``). By default it may: the backend always runs."""
        return True

    def repair(self, mesh: Mesh, ctx: RunContext) -> Repaired:
        """The backend on ``mesh`` with the audit and the guard (:func:`repair_with_audit`), through the cache
        when ``cache`` is ``on``, or ``auto`` in a sweep."""
        from scanreg.stages.repair.cache import DEFAULT_DIR, RepairCache, cache_enabled, cached_repair

        cache = RepairCache(self.p.cache_dir or DEFAULT_DIR) if cache_enabled(self.p.cache, ctx.in_sweep) else None
        return cached_repair(self, mesh, ctx, cache)
