"""Pose graphs: the poses of many scans from measured pairwise transforms (pure NumPy).

A graph has ``n`` nodes (scans) with poses ``T_world_k`` (4x4; the world is node ``anchor``'s frame) and edges
``(i, j, T_i_j, information)``: a measured transform mapping points of scan ``j`` into scan ``i``'s frame, with
the 6x6 information matrix of its error (the inverse of its covariance). An edge's error is the motion that
takes the measurement to the poses' prediction, ``A = inv(T_world_i) @ T_world_j @ inv(T_i_j)``, written as a
rotation vector ``w`` (radians) and the shift ``t`` of a point ``c`` of scan ``i`` (the centre of the pairs the
edge was measured from; input units): ``(w, t) = (log R_A, R_A c + t_A - c)``, the parametrisation of
:class:`scanreg.eval.uncertainty.PoseCovariance`, whose inverse is the information matrix.

:func:`optimize_pose_graph` minimises ``sum_e rho(r_e^T Omega_e r_e)`` by Gauss-Newton (iteratively reweighted
with a robust kernel ``rho``), the anchor fixed; :func:`spanning_tree_poses` gives the first poses by chaining the
most informative edges. Jacobians are first order in the errors (they vanish at the solution), which is where
Gauss-Newton converges.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.geometry.transforms import invert_T, make_T


@dataclass
class Edge:
    """A measured transform ``T_i_j`` (points of scan ``j`` into scan ``i``'s frame) and its 6x6 information
    matrix for the error ``(w, t)`` about ``centre`` (a point of scan ``i``)."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))


def hat(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[v]x`` (``hat(a) @ b == np.cross(a, b)``)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp_twist(x: np.ndarray) -> np.ndarray:
    """The transform of a small motion ``x = (w, v)``: rotation by the rotation vector ``w``, then the shift
    ``v`` (the left perturbation the optimiser applies to a pose)."""
    return make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])


def adjoint(T: np.ndarray) -> np.ndarray:
    """The 6x6 adjoint of ``T`` for motions ``(w, v)``: a left perturbation ``x`` in ``T``'s source frame is
    ``adjoint(T) @ x`` in its target frame (first order)."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = hat(t) @ R
    return A


def gauss_newton_step(H: np.ndarray, g: np.ndarray, poses: list[np.ndarray], free: list[int], col: dict,
                      tol: float) -> bool:
    """One Gauss-Newton step on the free poses (in place): the normal equations ``H x = -g`` solved with
    Jacobi scaling (least squares, so a direction the data leave free gets no step), each free pose moved by the
    twist in its columns ``col[k]:col[k] + 6`` from the left. True when the step is below ``tol`` (converged)."""
    scale = np.sqrt(np.maximum(np.diag(H), 1e-300))
    step = -np.linalg.lstsq(H / np.outer(scale, scale), g / scale, rcond=1e-12)[0] / scale
    for k in free:
        poses[k] = exp_twist(step[col[k]:col[k] + 6]) @ poses[k]
    return bool(np.abs(step).max() < tol)


def edge_error(poses: list[np.ndarray], e: Edge) -> np.ndarray:
    """The edge's error ``(w, t)`` about its centre (see the module docstring)."""
    A = invert_T(poses[e.i]) @ poses[e.j] @ invert_T(e.T_i_j)
    R = A[:3, :3]
    return np.concatenate([Rotation.from_matrix(R).as_rotvec(), R @ e.centre + A[:3, 3] - e.centre])


def _jacobian(poses: list[np.ndarray], e: Edge) -> np.ndarray:
    """d error / d x_j (first order; d / d x_i is its negative) for left perturbations ``x`` of the poses in the
    world frame: ``adjoint(inv(T_world_i))`` moves them into scan ``i``'s frame, and the shift about the origin
    becomes the shift of the centre."""
    N = np.eye(6)
    N[3:, :3] = -hat(e.centre)
    return N @ adjoint(invert_T(poses[e.i]))


@dataclass
class GraphSolution:
    poses: list[np.ndarray]
    """``T_world_k`` of every node (the anchor's the identity)."""
    weights: np.ndarray
    """The robust kernel's final weight of each edge (1: fully trusted, near 0: an outlier)."""
    errors: np.ndarray
    """Each edge's final error ``(w, t)`` (E, 6)."""
    iterations: int


def optimize_pose_graph(n: int, edges: list[Edge], initial: list[np.ndarray], anchor: int = 0,
                        kernel_scale: float | None = None, iterations: int = 50, tol: float = 1e-10) -> GraphSolution:
    """The poses minimising ``sum_e rho(r_e^T Omega_e r_e)`` over the edges (Gauss-Newton, the anchor fixed), with
    Cauchy's kernel ``rho(s) = k^2 log(1 + s / k^2)`` at ``kernel_scale`` k (in Mahalanobis units; None: least
    squares). Every node must be connected to the anchor (:func:`spanning_tree_poses` tells which are)."""
    poses = [np.array(T, dtype=float) for T in initial]
    free = [k for k in range(n) if k != anchor]
    col = {k: 6 * m for m, k in enumerate(free)}
    w = np.ones(len(edges))
    it = 0
    for it in range(1, iterations + 1):
        H = np.zeros((6 * len(free), 6 * len(free)))
        g = np.zeros(6 * len(free))
        for k, e in enumerate(edges):
            r = edge_error(poses, e)
            s = float(r @ e.information @ r)
            w[k] = 1.0 if kernel_scale is None else 1.0 / (1.0 + s / kernel_scale ** 2)
            Jj = _jacobian(poses, e)
            for node, J in ((e.j, Jj), (e.i, -Jj)):
                if node == anchor:
                    continue
                a = col[node]
                g[a:a + 6] += w[k] * J.T @ e.information @ r
                for other, K in ((e.j, Jj), (e.i, -Jj)):
                    if other != anchor:
                        b = col[other]
                        H[a:a + 6, b:b + 6] += w[k] * J.T @ e.information @ K
        if not free or gauss_newton_step(H, g, poses, free, col, tol):
            break
    errors = np.array([edge_error(poses, e) for e in edges]).reshape(-1, 6)
    return GraphSolution(poses, w, errors, it)


def spanning_tree_poses(n: int, edges: list[Edge], strength: np.ndarray, anchor: int = 0
                        ) -> tuple[list[np.ndarray | None], list[int]]:
    """Poses by chaining edges from the anchor along the maximum spanning tree of ``strength`` (one number per
    edge, larger: more trusted), and the edges used. A node no edge path reaches from the anchor gets None."""
    poses: list[np.ndarray | None] = [None] * n
    poses[anchor] = np.eye(4)
    used: list[int] = []
    order = np.argsort(-np.asarray(strength, dtype=float), kind="stable")
    grown = True
    while grown:  # Prim's algorithm on the edges sorted by strength
        grown = False
        for k in order:
            e = edges[k]
            if (poses[e.i] is None) == (poses[e.j] is None):
                continue
            if poses[e.j] is None:
                poses[e.j] = poses[e.i] @ e.T_i_j
            else:
                poses[e.i] = poses[e.j] @ invert_T(e.T_i_j)
            used.append(int(k))
            grown = True
            break
    return poses, used


def components(n: int, edges: list[Edge]) -> list[list[int]]:
    """The connected groups of nodes (largest first, then by their smallest node)."""
    parent = list(range(n))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for e in edges:
        a, b = find(e.i), find(e.j)
        if a != b:
            parent[max(a, b)] = min(a, b)
    groups: dict[int, list[int]] = {}
    for k in range(n):
        groups.setdefault(find(k), []).append(k)
    return sorted(groups.values(), key=lambda g: (-len(g), g[0]))


def cycle_errors(poses: list[np.ndarray], edges: list[Edge]) -> tuple[np.ndarray, np.ndarray]:
    """Each edge's disagreement with the poses: rotation (degrees) and shift of its centre (input units). For
    poses from a spanning tree these are the errors of the loops each other edge closes."""
    err = np.array([edge_error(poses, e) for e in edges]).reshape(-1, 6)
    return np.degrees(np.linalg.norm(err[:, :3], axis=1)), np.linalg.norm(err[:, 3:], axis=1)
