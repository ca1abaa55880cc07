"""A still picture of a mesh (PNG, no display needed): the reconstruction of a scan set seen from three sides."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scanreg.geometry import Mesh, principal_axes


def principal_frame(points: np.ndarray) -> np.ndarray:
    """The points centred and turned into their principal axes (:func:`scanreg.geometry.principal_axes`), the
    largest spread first: the same picture in any pose."""
    centre, axes = principal_axes(points)
    v = axes[:, ::-1].copy()
    v[:, 2] = np.cross(v[:, 0], v[:, 1])  # right-handed again after the reversal
    return (points - centre) @ v


def write_mesh_picture(path: Path, mesh: Mesh, title: str = "", max_faces: int = 150_000) -> Path:
    """``mesh`` drawn with flat shading from three sides (along each principal axis), painter's order, into
    ``path``; at most ``max_faces`` faces (an even subset of a larger mesh)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    pts = principal_frame(mesh.vertices)
    faces = mesh.faces[:: max(1, int(np.ceil(len(mesh.faces) / max_faces)))]
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.4))
    light = np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    # three right-handed views, each looking along one principal axis (the smallest spread first)
    views = {"along the 3rd axis": (0, 1, 2, 1), "along the 2nd axis": (0, 2, 1, -1), "along the 1st axis": (1, 2, 0, 1)}
    for ax, (name, (a, b, c, sign)) in zip(axes, views.items()):
        view = pts[:, [a, b, c]] * (1, 1, sign)
        tri = view[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        front = n[:, 2] > 0  # faces turned to the viewer (the mesh is closed: the rest are hidden)
        order = np.argsort(tri[front, :, 2].mean(axis=1), kind="stable")
        shade = 0.25 + 0.7 * np.clip(n[front] @ light, 0, 1)
        colours = plt.cm.bone(shade[order] * 0.9)
        # each face's edge drawn in its own colour: no seams through which hidden faces would show
        ax.add_collection(PolyCollection(tri[front][order][:, :, :2], facecolors=colours, edgecolors=colours,
                                         linewidths=0.4, antialiased=False))
        ax.set_xlim(view[:, 0].min(), view[:, 0].max())
        ax.set_ylim(view[:, 1].min(), view[:, 1].max())
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(name, fontsize=9)
    fig.suptitle(title or f"{len(mesh.faces)} faces", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
