"""How well a scan set was registered: with ground truth, every scan's pose error (the frames aligned at the
world scan) and the edges that were right or wrong; without it, every scan's residual to the scans it overlaps;
and the reconstructed surface's topology and its distance to a reference."""

from __future__ import annotations

from typing import Optional

import numpy as np

from scanreg.geometry import ClosestPoints, Cloud, Mesh, apply_T, invert_T, transform_errors
from scanreg.geometry.multiview import spread_subset
from scanreg.types import ViewEdge


def pose_errors(poses: list[Optional[np.ndarray]], poses_gt: list[Optional[np.ndarray]], anchor: int,
                diagonal: float, centres: Optional[list[np.ndarray]] = None) -> tuple[np.ndarray, np.ndarray]:
    """Each placed scan's rotation error (degrees) and translation error (share of ``diagonal``) against the
    truth, both frames aligned at the anchor, or at the first placed scan with a true pose when the anchor has
    none (NaN for a scan not placed or without a true pose). The translation error is the shift of the scan's
    ``centres`` (its points' centroid, in its own frame) between the two poses, where its points are; without
    them, of its frame's origin, which a random pose may have put far from them."""
    rot, trans = np.full(len(poses), np.nan), np.full(len(poses), np.nan)
    known = [k for k, (T, G) in enumerate(zip(poses, poses_gt)) if T is not None and G is not None]
    if not known:
        return rot, trans
    ref = anchor if anchor in known else known[0]
    G0 = invert_T(poses_gt[ref])
    T0 = None if ref == anchor else invert_T(poses[ref])  # the estimated poses into the reference scan's frame
    for k in known:
        if k == ref:  # the frames are aligned at it: no error by definition (not the rounding of G^-1 G)
            rot[k] = trans[k] = 0.0
            continue
        T, G = poses[k] if T0 is None else T0 @ poses[k], G0 @ poses_gt[k]
        rot[k] = transform_errors(T, G)[0]
        c = np.zeros(3) if centres is None else centres[k]
        trans[k] = float(np.linalg.norm(apply_T(T, c[None])[0] - apply_T(G, c[None])[0])) / diagonal
    return rot, trans


def edge_truth(edges: list[ViewEdge], poses_gt: list[Optional[np.ndarray]], diagonal: float, max_rotation_deg: float,
               max_translation: float, centres: Optional[list[np.ndarray]] = None) -> np.ndarray:
    """Whether each edge's transform is right (within the limits, translation as a share of ``diagonal``); NaN
    for an edge with a scan without a true pose. The translation error is measured at the centre of the scan
    the edge moves (``centres``, each in its scan's frame, as :func:`pose_errors` has them; without them at its
    frame's origin)."""
    ok = np.full(len(edges), np.nan)
    for k, e in enumerate(edges):
        if poses_gt[e.i] is not None and poses_gt[e.j] is not None:
            at = None if centres is None else centres[e.j]
            rot, t = transform_errors(e.T_i_j, invert_T(poses_gt[e.i]) @ poses_gt[e.j], at)
            ok[k] = float(rot <= max_rotation_deg and t <= max_translation * diagonal)
    return ok


def set_metrics(poses: list[Optional[np.ndarray]], edges: list[ViewEdge], anchor: int, diagonal: float,
                poses_gt: Optional[list[Optional[np.ndarray]]], tol_rotation_deg: float, tol_translation: float,
                false_rotation_deg: float, false_translation: float,
                centres: Optional[list[np.ndarray]] = None) -> tuple[dict[str, float], dict[str, list]]:
    """The set's numbers and, per scan, its errors (with ground truth; ``centres``: each scan's centroid in its
    own frame, where its translation error is measured). Scans without a true pose are not evaluated
    (``scans_evaluated`` says how many are, when not all)."""
    placed = np.array([T is not None for T in poses])
    accepted = np.array([e.accepted for e in edges], bool)
    m = {"scans": float(len(poses)), "scans_placed": float(placed.sum()), "scans_unplaced": float((~placed).sum()),
         "edges_registered": float(len(edges)), "edges_accepted": float(accepted.sum()),
         "edges_rejected": float((~accepted).sum()), "model_diagonal": diagonal,
         **{f"edges_{k}": float(sum(e.metrics.get(f"pair_{k}", 0.0) for e in edges))
            for k in ("predicted", "skipped", "retried")}}
    per_scan: dict[str, list] = {}
    if poses_gt is None:
        return m, per_scan
    rot, trans = pose_errors(poses, poses_gt, anchor, diagonal, centres)
    judged = np.array([G is not None for G in poses_gt])  # the scans with a true pose
    within = placed & (np.nan_to_num(rot, nan=np.inf) < tol_rotation_deg) & \
        (np.nan_to_num(trans, nan=np.inf) < tol_translation)
    truth = edge_truth(edges, poses_gt, diagonal, false_rotation_deg, false_translation, centres)
    right, wrong = truth == 1.0, truth == 0.0
    if not judged.all():
        m["scans_evaluated"] = float(judged.sum())
    if np.isfinite(rot).any():  # a placed scan with a true pose
        m.update({"scan_rotation_error_mean_deg": float(np.nanmean(rot)),
                  "scan_rotation_error_max_deg": float(np.nanmax(rot)),
                  "scan_translation_error_mean_rel": float(np.nanmean(trans)),
                  "scan_translation_error_max_rel": float(np.nanmax(trans))})
    m.update({"scans_within_tolerance": float(within[judged].mean()), "success": float(within[judged].all()),
              "edges_false": float((accepted & wrong).sum()), "edges_rejected_right": float((~accepted & right).sum())})
    per_scan = {"rotation_error_deg": rot.tolist(), "translation_error_rel": trans.tolist(),
                "within_tolerance": np.where(judged, within.astype(float), np.nan).tolist()}
    return m, per_scan


def scan_residuals(clouds: list[Cloud], poses: list[Optional[np.ndarray]], links: list[tuple[int, int]],
                   distance: float, samples: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """Without ground truth: each placed scan's RMS distance to the scans it is linked to (its points' closest
    points on any of them, within ``distance``) and the share of its points within ``distance`` (NaN: unplaced)."""
    rms, share = np.full(len(clouds), np.nan), np.full(len(clouds), np.nan)
    search = {k: ClosestPoints(clouds[k]) for k in {a for link in links for a in link}}
    for k, T in enumerate(poses):
        others = {b if a == k else a for a, b in links if k in (a, b)}
        if T is None or not others:
            continue
        pts = spread_subset(clouds[k], samples).points
        d = np.full(len(pts), np.inf)
        for o in others:
            d = np.minimum(d, search[o](apply_T(invert_T(poses[o]) @ T, pts), distance)[1])
        near = d <= distance
        share[k] = float(near.mean())
        rms[k] = float(np.sqrt(np.mean(d[near] ** 2))) if near.any() else np.nan
    return rms, share


def surface_metrics(mesh: Mesh, reference: Optional[Mesh] = None, samples: int = 20000,
                    seed: int = 0) -> dict[str, float]:
    """The reconstruction's topology (closed, manifold, self-intersections: exact) and, with a reference surface
    (same frame), the distances from its samples to it."""
    from scanreg.mesh.distances import area_samples, distances_to
    from scanreg.mesh.topology import audit_mesh

    stats = audit_mesh(mesh)
    keys = ("vertices", "faces", "components", "boundary_edges", "non_manifold_edges", "non_manifold_vertices",
            "self_intersecting_faces", "watertight", "area")
    m = {f"surface_{k}": float(stats[k]) for k in keys}
    m["surface_closed_manifold"] = float(stats["watertight"] == 1 and stats["non_manifold_vertices"] == 0
                                         and stats["self_intersecting_faces"] == 0 and stats["components"] == 1)
    if reference is not None and isinstance(reference, Mesh):
        d = distances_to(reference)(area_samples(mesh, samples, seed))
        m.update({"surface_reference_rms": float(np.sqrt(np.mean(d ** 2))),
                  "surface_reference_max": float(d.max())})
    return m
