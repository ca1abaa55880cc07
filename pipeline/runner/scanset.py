"""Many scans of one object into one model, on the steps of a pair run:

1. every scan prepared once (:func:`~scanreg.runner.steps.prepare_scan`: repair, sampling, spacing) and
   described by the coarse stage (its keypoints and descriptors) once per spacing its pairs take
   (:func:`spacing_levels`: once, for scans alike);
2. candidate pairs (every pair of a small set; neighbours in the given order, or by a cheap global shape
   descriptor, in a large one), each registered from any pose by the coarse and the fine stage and verified:
   the share of points that overlap, their RMS distance in spacings, and whether their normals agree;
3. the poses from the verified edges (``graph``: a robust pose graph), then every scan refined against the
   others at once (:func:`~scanreg.geometry.multiview.refine_jointly`);
4. the scans merged into one cloud, and a surface made from it (``surface``) and repaired (``repair``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Optional

import numpy as np

from scanreg.errors import InputError, ScanregError, note, warn
from scanreg.eval.uncertainty import pairs_covariance
from scanreg.geometry import (ClosestPoints, Cloud, Mesh, apply_T, bbox_diagonal, invert_T, submesh,
                              transform_geometry, voxel_representatives)
from scanreg.geometry.multiview import refine_jointly, spread_subset
from scanreg.geometry.posegraph import Edge, components
from scanreg.mesh.census import OPEN_BORDER_RATIO
from scanreg.mesh.jumps import depth_jump_faces
from scanreg.mesh.topology import open_scan_borders
from scanreg.runner.steps import prepare_scan
from scanreg.runner.settings import MultiviewParams
from scanreg.types import PreparedScan, RunContext, ScanSet, ViewEdge

if TYPE_CHECKING:
    from scanreg.runner.build import Stages
    from scanreg.stages.protocols import Described  # the coarse stages' description of a scan (the contract's type)


@dataclass
class SetRegistration:
    """What a scan set's registration produced."""

    names: list[str]
    poses: list[Optional[np.ndarray]]
    """``T_world_scan`` of every scan of the main group (the world: its first scan's frame); None elsewhere."""
    groups: list[list[int]]
    """The scans connected by accepted edges, the main group first."""
    group_poses: list[dict[int, np.ndarray]]
    """For every further group, its scans' poses in its own first scan's frame."""
    edges: list[ViewEdge]
    scans: list[PreparedScan]
    spacing: float
    """The model's sampling spacing (the merge, the surface): the finest of the main group's scans'."""
    levels: list[float]
    """Each scan's spacing in the set (:func:`spacing_levels`): a pair is registered at the larger of its two."""
    merged: Optional[Cloud] = None
    """The main group's points in the world frame, voxel-merged, with normals and ``extra['scan']``."""
    surface: Optional[Mesh] = None
    metrics: dict[str, float] = field(default_factory=dict)

    def unplaced(self) -> dict[str, str]:
        """The scans outside the main group, each with why."""
        out = {}
        for k, name in enumerate(self.names):
            if self.poses[k] is None:
                mine = [e for e in self.edges if k in (e.i, e.j)]
                other = next((g for g in self.groups[1:] if k in g), None)
                if other is not None and len(other) > 1:
                    out[name] = f"in another group of {len(other)} scans, with no verified pair to the main one"
                elif not any(e.accepted for e in mine):
                    best = max(mine, key=lambda e: e.fitness) if mine else None  # the closest it came
                    out[name] = "overlaps no other scan (no verified pair: " + (best.reason if best else
                                                                                   "no pair registered") + ")"
                else:
                    out[name] = "not connected to the main group"
        return out


def register_scanset(problem: ScanSet, stages: Stages, params: MultiviewParams, ctx: RunContext,
                     timings: dict[str, float]) -> SetRegistration:
    """Prepare, pair, register, verify, solve the graph, refine, merge and make the surface (the module's steps);
    ``timings`` gets each step's seconds."""
    t0 = time.perf_counter_ns()
    warn_whole_objects(problem.scans, problem.names)
    scans = [prepare_scan(g, stages, ctx, name, salt=1, role="scan", repair=params.repair_scans)
             for g, name in zip(problem.scans, problem.names)]
    if not max(s.spacing for s in scans) > 0:
        raise InputError("scan set: all points coincide; cannot estimate a sampling spacing")
    levels = spacing_levels([s.spacing for s in scans], params.spacing_ratio)
    _note_levels(problem.names, levels)
    diagonal = max(bbox_diagonal(s.cloud.points) for s in scans)
    t1 = time.perf_counter_ns()
    described = describe_levels(stages, scans, levels, ctx)
    search = [ClosestPoints(s.cloud) for s in scans]
    edges = register_pairs(candidate_pairs(scans, problem.order, params), scans, described, search, stages, levels,
                           params, ctx)
    distrust_lone_loose_pairs(edges, len(scans), params)
    t2 = time.perf_counter_ns()
    groups = [g for g in components(len(scans), [Edge(e.i, e.j, e.T_i_j, e.information) for e in edges if e.accepted])]
    anchor = groups[0][0]
    # the main group's spacings: its coarsest for the graph (as one spacing for all), its finest for the model
    spacing = min(levels[k] for k in groups[0])
    if len(groups[0]) < 2:  # no verified pair: nothing to solve, merge or reconstruct (the caller says why)
        timings.update({"prepare": (t1 - t0) / 1e9, "pairs": (t2 - t1) / 1e9})
        return SetRegistration(problem.names, [None] * len(scans), groups, [], edges, scans, spacing, levels)
    poses, graph_metrics = stages.graph.solve(len(scans), edges, max(levels[k] for k in groups[0]), diagonal, anchor,
                                              ctx)
    res = SetRegistration(problem.names, poses, _groups(poses, edges, len(scans)), [], edges, scans, spacing, levels)
    res.group_poses = [_group_poses(g, edges) for g in res.groups[1:]]
    t3 = time.perf_counter_ns()
    links = [(e.i, e.j) for e in edges if e.accepted and poses[e.i] is not None and poses[e.j] is not None]
    refine_metrics = {}
    bare = [s.name for s in scans if s.cloud.normals is None]
    if links and params.refine_distances and bare:
        # point-to-plane pairs a scan's points on another's normals; estimated ones (20 neighbours) did not make
        # the poses better (rendered bunny views 0.138 -> 0.148 deg, 6 Stanford scans as .xyz 0.263 -> 0.259 deg)
        # for 0.1-0.2 s a scan: the pairs onto clouds without normals are left out, and the user is told
        note(f"scan set: {len(bare)} of the {len(scans)} scans are point clouds without normals ({', '.join(bare[:3])}"
             f"{', ...' if len(bare) > 3 else ''}): "
             + ("the joint refinement (point-to-plane) is skipped" if len(bare) == len(scans) else
                "the joint refinement (point-to-plane) pairs no points on them")
             + "; give normals (a PLY with nx ny nz, six columns in a text file) to refine with them")
        refine_metrics = {"multiview_rms": float("nan"), "multiview_pairs": 0.0}
    if links and params.refine_distances and len(bare) < len(scans):
        placed = [k for k, T in enumerate(poses) if T is not None]
        refined, refine_metrics = refine_jointly(
            [s.cloud for s in scans], [T if T is not None else np.eye(4) for T in poses], links,
            [d * spacing for d in params.refine_distances], spacing, anchor, params.refine_samples,
            params.refine_iterations, link_scales=[max(levels[i], levels[j]) / spacing for i, j in links])
        res.poses = [refined[k] if k in placed else None for k in range(len(scans))]
    t4 = time.perf_counter_ns()
    res.merged = merge(model_scans(scans, res.poses, stages, ctx, params.max_edge_ratio), res.poses,
                       params.merge_voxel * spacing)
    from_meshes = all(isinstance(g, Mesh) for g in problem.scans)
    res.surface = stages.surface.reconstruct(res.merged, from_meshes, spacing, ctx)
    if res.surface is None and not from_meshes and getattr(stages.surface.p, "when", None) == "meshes":
        clouds = sum(not isinstance(g, Mesh) for g in problem.scans)
        what = "the scans are point clouds" if clouds == len(problem.scans) else \
            f"{clouds} of the {len(problem.scans)} scans are point clouds"
        note(f"no surface reconstructed: {what} (surface.when=meshes); set surface.when=always to reconstruct one "
             "from the merged points")
    if res.surface is not None:
        res.surface = stages.repair.repair(res.surface, ctx).mesh
    t5 = time.perf_counter_ns()
    timings.update({"prepare": (t1 - t0) / 1e9, "pairs": (t2 - t1) / 1e9, "graph": (t3 - t2) / 1e9,
                    "refine": (t4 - t3) / 1e9, "surface": (t5 - t4) / 1e9})
    res.metrics = {**graph_metrics, **refine_metrics, "spacing": spacing}
    return res


def distrust_lone_loose_pairs(edges: list[ViewEdge], n: int, p: MultiviewParams) -> None:
    """In a set of 3 or more scans, an accepted pair that is the only one of a scan and fits loosely (inlier RMS
    above ``predict_max_inlier_rms`` spacings) is rejected: nothing else checks the place it gives that scan (a
    new user's mirrored scan was placed 106 deg off by its one pair, at 1.59 spacings, with a phantom head in the
    model; right pairs fit at 0.7-1.5)."""
    if n < 3:
        return
    degree = np.bincount([k for e in edges if e.accepted for k in (e.i, e.j)], minlength=n)
    for e in edges:
        lone = min(degree[e.i], degree[e.j]) == 1 and max(degree[e.i], degree[e.j]) > 1  # (a pair apart: a group)
        if e.accepted and lone and e.inlier_rms > p.predict_max_inlier_rms:
            e.accepted = False
            e.reason = (f"the one pair that would place a scan, at an inlier RMS of {e.inlier_rms:.2f} spacings "
                        f"(above multiview.predict_max_inlier_rms {p.predict_max_inlier_rms:g}): too loose to "
                        "place it alone")


def warn_whole_objects(geometries: list, names: list[str]) -> None:
    """One warning when most scans of a set (3 or more) are closed surfaces, whole objects rather than views of one
    (no boundary loop is a scan's outer border, :func:`~scanreg.mesh.topology.open_scan_borders`): a set is
    registered as views of one object, and whole objects of a similar shape fuse (a new user's 11 CT teeth: 8
    fused into one blob, pairs overlapping 40-80 % at 1.5-1.6 spacings, without a word)."""
    meshes = [(g, n) for g, n in zip(geometries, names) if isinstance(g, Mesh) and len(g.faces)]
    whole = [n for g, n in meshes if not open_scan_borders(g, OPEN_BORDER_RATIO).any()]
    if len(names) >= 3 and 2 * len(whole) > len(names):
        warn(f"scan set: {len(whole)} of the {len(names)} scans are closed surfaces ({', '.join(whole[:3])}"
             f"{', ...' if len(whole) > 3 else ''}), whole objects rather than views of one: a set registers views "
             "of one object, and separate objects of a similar shape (teeth) can be fused into one model; register "
             "two whole objects as a pair: scanreg A B")


def model_scans(scans: list[PreparedScan], poses: list[Optional[np.ndarray]], stages: Stages, ctx: RunContext,
                ratio: Optional[float]) -> list[PreparedScan]:
    """The scans as the model takes them: a placed mesh (``poses`` not None) with faces that bridge a depth jump
    (:func:`~scanreg.mesh.jumps.depth_jump_faces` at ``ratio``; None: none) sampled again without them (the
    registration sampled every face, as a pair run does); a note says how many faces were left out."""
    if ratio is None:
        return scans
    out, dropped = [], {}
    for s, T in zip(scans, poses):
        jump = depth_jump_faces(s.mesh, ratio) if s.mesh is not None and T is not None else None
        if jump is not None and jump.any() and not jump.all():
            dropped[s.name] = int(jump.sum())
            s = replace(s, cloud=stages.sampler.sample(submesh(s.mesh, ~jump), ctx))
        out.append(s)
    if dropped:
        note(f"scan set: the model leaves out {sum(dropped.values())} faces that bridge depth jumps in "
             f"{len(dropped)} of the {sum(T is not None for T in poses)} placed scans (long thin faces of a range "
             "grid across a silhouette; multiview.max_edge_ratio=null keeps them)")
    return out


def spacing_levels(spacings: list[float], ratio: float) -> list[float]:
    """Each scan's sampling spacing in the set: the scans sorted by spacing, coarsest first, fall into groups
    wherever the next is more than ``ratio`` times finer than the one before, and each group takes its largest
    spacing (a scan whose points all coincide joins the finest). Scans alike share one spacing, the largest."""
    level, top, last = [0.0] * len(spacings), 0.0, 0.0
    for k in sorted(range(len(spacings)), key=lambda k: (-spacings[k], k)):
        if top == 0.0 or 0.0 < spacings[k] * ratio < last:
            top = spacings[k]
        level[k] = top
        last = spacings[k] if spacings[k] > 0 else last
    return level


def _note_levels(names: list[str], levels: list[float]) -> None:
    """Tell the user which scans are registered at a coarser spacing than the rest."""
    if len(set(levels)) < 2:
        return
    fine = min(levels)
    coarse = [f"{n} {lv / fine:.1f}x" for n, lv in zip(names, levels) if lv > fine]
    note(f"scan set: {len(coarse)} of the {len(names)} scans are sampled more coarsely than the finest ("
         f"{', '.join(coarse[:3])}{', ...' if len(coarse) > 3 else ''}): each pair is registered at the larger of "
         "its two scans' spacings, the model at the finest placed (multiview.spacing_ratio)")


def describe_levels(stages: Stages, scans: list[PreparedScan], levels: list[float],
                    ctx: RunContext) -> dict[float, list[Optional[Described]]]:
    """The coarse stage's descriptions at every spacing a pair of scans takes (the larger of its scans'): at a
    spacing, the scans at it or finer described together (one call of ``describe_set``, as for a set of one
    spacing); None for a scan coarser than it."""
    out: dict[float, list[Optional[Described]]] = {}
    for level in sorted(set(levels), reverse=True):
        members = [k for k, lv in enumerate(levels) if lv <= level]
        if len(members) < 2:
            continue
        out[level] = [None] * len(scans)
        for k, d in zip(members, stages.coarse.describe_set([scans[k].cloud for k in members], level, ctx)):
            out[level][k] = d
    return out


def _groups(poses: list[Optional[np.ndarray]], edges: list[ViewEdge], n: int) -> list[list[int]]:
    """The main group (the placed scans), then the other connected groups of accepted edges."""
    main = [k for k in range(n) if poses[k] is not None]
    rest = components(n, [Edge(e.i, e.j, e.T_i_j, e.information) for e in edges if e.accepted and
                          poses[e.i] is None and poses[e.j] is None])
    return [main] + [g for g in rest if not set(g) & set(main)]


def _group_poses(group: list[int], edges: list[ViewEdge]) -> dict[int, np.ndarray]:
    """A further group's poses in its first scan's frame, chained along its accepted edges."""
    from scanreg.geometry.posegraph import spanning_tree_poses

    live = [e for e in edges if e.accepted and e.i in group and e.j in group]
    index = {k: m for m, k in enumerate(group)}
    sub = [Edge(index[e.i], index[e.j], e.T_i_j, e.information, e.centre) for e in live]
    poses, _ = spanning_tree_poses(len(group), sub, np.array([e.fitness for e in live]), 0)
    return {k: poses[index[k]] for k in group if poses[index[k]] is not None}


def candidate_pairs(scans: list[PreparedScan], order: str, p: MultiviewParams) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, ``i < j``, to register: every pair of a set of at most ``all_pairs`` scans; else the
    next ``window`` scans in the given order (``turntable``: around), or each scan's ``neighbours`` most
    similar scans by shape (``unordered``)."""
    n = len(scans)
    if n <= p.all_pairs:
        return list(itertools.combinations(range(n), 2))
    if order in ("sequential", "turntable"):
        pairs = {(k, k + d) for k in range(n) for d in range(1, p.window + 1) if k + d < n}
        if order == "turntable":  # around, never a scan with itself (a window of n or more)
            pairs |= {tuple(sorted((k, (k + d) % n))) for k in range(n) for d in range(1, min(p.window, n - 1) + 1)}
        return sorted(pairs)
    # at most the n - 1 others (the scan itself, at distance inf, sorts last: never its own pair)
    near = np.argsort(shape_distances(scans), axis=1, kind="stable")[:, :min(p.neighbours, n - 1)]
    return sorted({(min(k, int(m)), max(k, int(m))) for k in range(n) for m in near[k]})


def shape_distances(scans: list[PreparedScan]) -> np.ndarray:
    """The L1 distances between the scans' shape histograms (:func:`shape_histogram`); inf on the diagonal."""
    hist = np.array([shape_histogram(s.cloud.points) for s in scans])
    dist = np.abs(hist[:, None, :] - hist[None, :, :]).sum(axis=2)
    np.fill_diagonal(dist, np.inf)
    return dist


def shape_histogram(points: np.ndarray, bins: int = 32, samples: int = 2000, seed: int = 0) -> np.ndarray:
    """A pose-free global descriptor: the histogram of distances between random point pairs (Osada's D2),
    the distances scaled by their median (so that a scan's extent matters less than its shape)."""
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, len(points), (2, samples))
    d = np.linalg.norm(points[a] - points[b], axis=1)
    d = d / max(float(np.median(d)), 1e-300)
    return np.histogram(d, bins=bins, range=(0.0, 3.0))[0] / samples


def register_pairs(candidates: list[tuple[int, int]], scans: list[PreparedScan],
                   described: dict[float, list[Optional[Described]]], search: list[ClosestPoints], stages: Stages,
                   levels: list[float], p: MultiviewParams, ctx: RunContext) -> list[ViewEdge]:
    """Every candidate pair registered and verified, in order. Once accepted pairs connect two scans, their
    relative pose is predicted along them (only pairs that overlap well and fit tightly predict: a false pair
    that passed the verification would hide the right pairs that outvote it): the pair is skipped when the
    prediction leaves under half ``min_fitness`` of the points in the overlap, else the fine stage starts from
    it (and the coarse stage runs only when that fails); the coarse stage runs from any pose only between scans
    not yet connected (``predict`` off: for every pair). A pair is registered at the larger of its
    scans' spacings (``levels``, :func:`spacing_levels`), from the descriptions at it (:func:`describe_levels`).
    In a set larger than ``all_pairs``, a scan the candidates leave outside the largest joined group then gets up
    to ``rescue_pairs`` pairs more (:func:`rescue_pairs`)."""
    chains = _Chains(len(scans))
    edges: list[ViewEdge] = []
    _register_in_turn(candidates, chains, edges, scans, described, search, stages, levels, p, ctx)
    if len(scans) > p.all_pairs and p.rescue_pairs > 0:
        tried = {(e.i, e.j) for e in edges}
        _register_in_turn(rescue_pairs(chains, shape_distances(scans), tried, p.rescue_pairs), chains, edges, scans,
                          described, search, stages, levels, p, ctx)
    return edges


def rescue_pairs(chains: _Chains, dist: np.ndarray, tried: set[tuple[int, int]], budget: int) -> list[tuple[int, int]]:
    """For every scan outside the largest group the accepted pairs have joined, up to ``budget`` more pairs with
    that group's scans (the most similar shapes by ``dist`` first, none already ``tried``)."""
    groups: dict[int, list[int]] = {}
    for k, r in enumerate(chains.root):
        groups.setdefault(r, []).append(k)
    main = max(groups.values(), key=len)
    out = []
    for k in range(len(chains.root)):
        if chains.root[k] == chains.root[main[0]]:
            continue
        near = sorted(main, key=lambda m: (dist[k, m], m))
        out += [p for p in (tuple(sorted((k, m))) for m in near) if p not in tried][:budget]
    return out


def _register_in_turn(candidates, chains: _Chains, edges: list[ViewEdge], scans, described, search, stages, levels,
                      p: MultiviewParams, ctx: RunContext) -> None:
    """:func:`register_pairs`' loop: ``candidates`` registered in turn into ``edges``, joining ``chains``."""
    for i, j in candidates:
        start = chains.relative(i, j) if p.predict else None
        distance = p.inlier_distance * max(levels[i], levels[j])
        if start is not None and overlap_share(search[i], scans[j].cloud, start, distance) < p.min_fitness / 2:
            edges.append(_rejected(i, j, "predicted by the accepted pairs not to overlap", {"pair_skipped": 1.0}))
            continue
        edge = register_edge(i, j, scans, described, search, stages, levels, p, ctx, start)
        if start is not None and not edge.accepted:  # the prediction may be wrong: from any pose
            edge = register_edge(i, j, scans, described, search, stages, levels, p, ctx)
            edge.metrics["pair_retried"] = 1.0
        if edge.accepted and edge.fitness >= p.predict_min_fitness and edge.inlier_rms <= p.predict_max_inlier_rms:
            chains.join(i, j, edge.T_i_j)  # a weak or loose pair may be false: it predicts nothing
        edges.append(edge)


class _Chains:
    """Groups of scans joined by accepted pairs, each scan's pose relative to its group's first (union-find)."""

    def __init__(self, n: int):
        self.root = list(range(n))
        self.pose = [np.eye(4) for _ in range(n)]  # T_root_scan

    def relative(self, i: int, j: int) -> Optional[np.ndarray]:
        """``T_i_j`` along accepted pairs, or None when the scans are not connected."""
        if self.root[i] != self.root[j]:
            return None
        return invert_T(self.pose[i]) @ self.pose[j]

    def join(self, i: int, j: int, T_i_j: np.ndarray) -> None:
        ri, rj = self.root[i], self.root[j]
        if ri == rj:
            return
        T_ri_rj = self.pose[i] @ T_i_j @ invert_T(self.pose[j])  # root j's frame into root i's
        for k in range(len(self.root)):
            if self.root[k] == rj:
                self.root[k], self.pose[k] = ri, T_ri_rj @ self.pose[k]


def register_edge(i: int, j: int, scans: list[PreparedScan], described: dict[float, list[Optional[Described]]],
                  search: list[ClosestPoints], stages: Stages, levels: list[float], p: MultiviewParams,
                  ctx: RunContext, start: Optional[np.ndarray] = None) -> ViewEdge:
    """Scan ``j`` registered to scan ``i`` (coarse from their descriptions, or from ``start``; then fine, on the
    points: the joint refinement pairs with every scan later) and verified; ``search``: each scan's closest-point
    search; ``described`` and ``levels``: as :func:`register_pairs` has them. A coarse pose that leaves under half ``min_fitness`` of the points in the overlap is rejected before
    the fine stage."""
    target, source = scans[i], scans[j]
    spacing = max(levels[i], levels[j])
    distance = p.inlier_distance * spacing
    try:
        if start is None:
            coarse = stages.coarse.align_described(described[spacing][i], described[spacing][j], ctx,
                                                   p.coarse_budget)
            T0, coarse_metrics = coarse.T_target_source, coarse.metrics
            if overlap_share(search[i], source.cloud, T0, distance) < p.min_fitness / 2:
                return _rejected(i, j, f"the coarse pose leaves under {p.min_fitness / 2:g} of the points in the "
                                 "overlap", coarse_metrics)
        else:
            T0, coarse_metrics = start, {"pair_predicted": 1.0}
        moving = spread_subset(source.cloud, p.pair_samples) if p.pair_samples > 0 else source.cloud
        icp = stages.icp.refine(target.cloud, moving, T0, spacing, ctx, None)
    except ScanregError as e:
        return _rejected(i, j, str(e).splitlines()[0])
    T = icp.T_target_source
    fitness, rms, agree = verify_overlap(search[i], search[j], target.cloud, source.cloud, T, distance)
    pc = pairs_covariance(icp.final_pairs)
    if pc is not None:
        information, centre = np.linalg.pinv(pc.cov, rcond=1e-12, hermitian=True), pc.centre
    else:
        information, centre = np.eye(6), np.zeros(3)
    edge = ViewEdge(i, j, T, information, centre, fitness, rms / spacing, agree,
                    metrics={**coarse_metrics, "icp_iterations": icp.iterations, **icp.metrics})
    problems = []
    if fitness < p.min_fitness:
        problems.append(f"overlap {fitness:.2f} < multiview.min_fitness {p.min_fitness:g}")
    if rms / spacing > p.max_inlier_rms:
        problems.append(f"inlier RMS {rms / spacing:.2f} spacings > multiview.max_inlier_rms {p.max_inlier_rms:g}")
    own = min(search[i].normal_coherence(), search[j].normal_coherence())  # noisy normals agree less anywhere
    bar = max(MIN_NORMAL_AGREEMENT, p.min_normal_agreement * own)
    if agree < bar:
        problems.append(f"normals agree on {agree:.3f} < {bar:.3f} (multiview.min_normal_agreement "
                        f"{p.min_normal_agreement:g} of the scans' own {own:.3f}, at least {MIN_NORMAL_AGREEMENT:g})")
    edge.accepted, edge.reason = not problems, "; ".join(problems)
    return edge


MIN_NORMAL_AGREEMENT = 0.5
"""The least share of a pair's overlapping points whose normals must agree, however little a scan's own normals
agree among themselves (normals of random signs agree on about half: the check would be off)."""


def _rejected(i: int, j: int, reason: str, metrics: dict | None = None) -> ViewEdge:
    return ViewEdge(i, j, np.eye(4), np.zeros((6, 6)), np.zeros(3), 0.0, np.inf, 0.0, False, reason,
                    dict(metrics or {}))


def overlap_share(search: ClosestPoints, source: Cloud, T: np.ndarray, distance: float, k: int = 2000) -> float:
    """The share of (at most ``k``, spread) source points within ``distance`` of the target at ``T``."""
    pts = spread_subset(source, k).points
    return float((search(apply_T(T, pts), distance)[1] <= distance).mean())


def verify_overlap(search_t: ClosestPoints, search_s: ClosestPoints, target: Cloud, source: Cloud, T: np.ndarray,
                   distance: float) -> tuple[float, float, float]:
    """How well two clouds overlap at ``T`` (target <- source): the smaller share of each cloud's points within
    ``distance`` of the other, the RMS distance of the source's points that are, and the share of those whose
    normals agree with the target's (cosine above 0.5; 1 without normals)."""
    q, d, qn = search_t(apply_T(T, source.points), distance)
    near = d <= distance
    back = search_s(apply_T(invert_T(T), target.points), distance)[1] <= distance
    fitness = min(float(near.mean()), float(back.mean()))
    if not near.any():
        return fitness, float("inf"), 0.0
    rms = float(np.sqrt(np.mean(d[near] ** 2)))
    if qn is None or source.normals is None:
        return fitness, rms, 1.0
    cos = np.einsum("ij,ij->i", source.normals[near] @ T[:3, :3].T, qn[near])
    return fitness, rms, float((cos > 0.5).mean())


def merge(scans: list[PreparedScan], poses: list[Optional[np.ndarray]], voxel: float) -> Cloud:
    """The placed scans' points in the world frame, one point per voxel (``voxel`` 0: all), with normals and each
    point's scan index (``extra['scan']``)."""
    clouds = [transform_geometry(T, s.cloud) for s, T in zip(scans, poses) if T is not None]
    index = np.concatenate([np.full(s.cloud.n_points, k) for k, (s, T) in enumerate(zip(scans, poses))
                            if T is not None])
    pts = np.vstack([c.points for c in clouds])
    nrm = np.vstack([c.normals for c in clouds]) if all(c.normals is not None for c in clouds) else None
    cloud = Cloud(pts, nrm, "merged", {"scan": index})
    return cloud.subset(voxel_representatives(pts, voxel)) if voxel > 0 else cloud
