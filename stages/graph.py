"""Pose graphs (``graph=NAME``): the poses of many scans from their verified pairs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.geometry import invert_T
from scanreg.geometry.posegraph import Edge, components, cycle_errors, optimize_pose_graph, spanning_tree_poses
from scanreg.stages.registry import GRAPH
from scanreg.types import RunContext, ViewEdge


def _graph_edges(edges: list[ViewEdge]) -> list[Edge]:
    return [Edge(e.i, e.j, e.T_i_j, e.information, e.centre) for e in edges]


@GRAPH.register("robust")
class RobustGraph:
    """Least squares over the verified edges with Cauchy's robust kernel (Gauss-Newton on the poses, the first
    scan fixed, the kernel's scale from a plain least-squares solve), started from the maximum spanning tree of
    the edges' fitness; then the edge that disagrees most
    with the optimised poses, beyond ``max_rotation_deg`` or ``max_translation``, is rejected as inconsistent with
    the loops it closes, and the graph solved again, until every edge agrees. Scans no accepted edge connects to
    the first scan are not placed."""

    @dataclass
    class Params:
        max_rotation_deg: float = 1.0
        """An edge whose rotation disagrees with the optimised poses by more than this (degrees) is rejected."""
        max_translation: float = 0.005
        """... or whose centre they move by more than this share of the set's bounding-box diagonal."""
        kernel_scale: float = 3.0
        """Scale of Cauchy's kernel, in multiples of the median edge's Mahalanobis error (its square root) after
        a least-squares solve: an edge far beyond the typical one weighs little. The pairs' information matrices
        treat neighbouring residuals as independent, which makes every edge look more certain than it is; the
        median sets the unit."""
        iterations: int = 30
        """Most Gauss-Newton iterations per solve."""

        def check(self):
            if not self.max_rotation_deg > 0 or not self.max_translation > 0 or not self.kernel_scale > 0:
                raise ValueError("max_rotation_deg, max_translation and kernel_scale must be > 0")

    def __init__(self, params: Params):
        self.p = params

    def solve(self, n: int, edges: list[ViewEdge], spacing: float, diagonal: float, anchor: int,
              ctx: RunContext) -> tuple[list[Optional[np.ndarray]], dict[str, float]]:
        p = self.p
        pruned, metrics = 0, {}
        while True:
            live = [e for e in edges if e.accepted]
            poses, iterations = self._solve(n, live, anchor)
            placed = [e for e in live if poses[e.i] is not None and poses[e.j] is not None]
            if not placed:
                break
            rot, shift = cycle_errors(poses, _graph_edges(placed))
            metrics = {"graph_edge_rotation_max_deg": float(rot.max()),
                       "graph_edge_translation_max_rel": float(shift.max() / diagonal),
                       "graph_iterations": float(iterations)}
            bad = np.maximum(rot / p.max_rotation_deg, shift / (p.max_translation * diagonal))
            worst = int(np.argmax(bad))
            if bad[worst] <= 1.0:
                break
            e = placed[worst]
            e.accepted = False
            e.reason = (f"inconsistent with the other edges ({rot[worst]:.2f} deg, {shift[worst] / diagonal:.2%} of "
                        "the diagonal off the optimised poses)")
            pruned += 1
        metrics.update({"graph_edges": float(sum(e.accepted for e in edges)), "graph_edges_pruned": float(pruned)})
        return poses, metrics

    def _solve(self, n: int, live: list[ViewEdge], anchor: int) -> tuple[list[Optional[np.ndarray]], int]:
        """The poses of the anchor's group (None elsewhere) by the robust least squares, and its iterations."""
        group = next(g for g in components(n, _graph_edges(live)) if anchor in g)
        poses: list[Optional[np.ndarray]] = [None] * n
        poses[anchor] = np.eye(4)
        if len(group) < 2:
            return poses, 0
        index = {k: m for m, k in enumerate(group)}
        inside = [e for e in live if e.i in index and e.j in index]
        sub = [Edge(index[e.i], index[e.j], e.T_i_j, e.information, e.centre) for e in inside]
        initial, _ = spanning_tree_poses(len(group), sub, np.array([e.fitness for e in inside]), index[anchor])
        # the least-squares solution sets the kernel's scale (the typical edge's error); the robust solve starts
        # from the tree, where a scan's strongest pair places it: several weak wrong pairs that outvote it are
        # then the outliers, where from the least-squares solution (which follows the majority) the right pair was
        first = optimize_pose_graph(len(group), sub, initial, index[anchor], None, self.p.iterations)
        s = np.array([float(r @ e.information @ r) for r, e in zip(first.errors, sub)])
        k = self.p.kernel_scale * np.sqrt(max(float(np.median(s)), 1e-300))
        sol = optimize_pose_graph(len(group), sub, initial, index[anchor], k, self.p.iterations)
        for m, node in enumerate(group):
            poses[node] = sol.poses[m]
        return poses, first.iterations + sol.iterations


@GRAPH.register("open3d")
class Open3dGraph:
    """Open3D's pose graph optimisation, as its multiway-registration tutorial uses it (the comparator):
    Levenberg-Marquardt with a line process over the pairs, the consecutive pairs (``i``, ``i + 1``) as certain
    odometry edges and every other pair whose fitness exceeds ``min_fitness`` as an uncertain loop closure, which
    the optimisation prunes (``edge_prune_threshold``)."""

    @dataclass
    class Params:
        min_fitness: float = 0.3
        """A loop closure enters the graph when its fitness (share of points within the inlier distance) exceeds
        this."""
        max_correspondence_distance: float = 1.5
        """Open3D's correspondence distance of the line process, in sampling spacings (the tutorial: 1.5 voxels)."""
        edge_prune_threshold: float = 0.25
        """Open3D's threshold under which an uncertain edge's line-process weight prunes it."""
        preference_loop_closure: float = 1.0
        """Open3D's weight of loop closures against odometry."""

    def __init__(self, params: Params):
        self.p = params

    def solve(self, n: int, edges: list[ViewEdge], spacing: float, diagonal: float, anchor: int,
              ctx: RunContext) -> tuple[list[Optional[np.ndarray]], dict[str, float]]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        for e in edges:
            if e.accepted and e.j != e.i + 1 and not e.fitness > self.p.min_fitness:
                e.accepted, e.reason = False, f"fitness {e.fitness:.2f} <= graph.min_fitness {self.p.min_fitness:g}"
        live = [e for e in edges if e.accepted]
        group = next(g for g in components(n, _graph_edges(live)) if anchor in g)
        initial, _ = spanning_tree_poses(n, _graph_edges(live), np.array([e.fitness for e in live]), anchor)
        graph = reg.PoseGraph()
        for T in initial:
            graph.nodes.append(reg.PoseGraphNode(np.eye(4) if T is None else T))
        for e in live:
            graph.edges.append(reg.PoseGraphEdge(e.j, e.i, e.T_i_j, _information_about_origin(e),
                                                 uncertain=e.j != e.i + 1))
        option = reg.GlobalOptimizationOption(max_correspondence_distance=self.p.max_correspondence_distance * spacing,
                                              edge_prune_threshold=self.p.edge_prune_threshold,
                                              preference_loop_closure=self.p.preference_loop_closure,
                                              reference_node=anchor)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                    reg.GlobalOptimizationConvergenceCriteria(), option)
        T0 = invert_T(np.asarray(graph.nodes[anchor].pose))
        poses = [T0 @ np.asarray(graph.nodes[k].pose) if k in group else None for k in range(n)]
        return poses, {"graph_edges": float(len(live))}


def _information_about_origin(e: ViewEdge) -> np.ndarray:
    """The edge's information for motions about the origin of scan ``i``'s frame (Open3D's convention) from the
    one about its centre: the centre's shift is ``t - c x w``."""
    from scanreg.geometry.posegraph import hat

    N = np.eye(6)
    N[3:, :3] = -hat(e.centre)
    return N.T @ e.information @ N
