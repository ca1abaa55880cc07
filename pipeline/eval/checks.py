"""Checks of a registration problem right after loading, before any expensive stage: enough points, and
geometry that determines a rigid transform (not all in one point, on a line or in a plane)."""

from __future__ import annotations

import numpy as np

from scanreg.errors import InputError
from scanreg.geometry import Mesh, points_of

UNIT_FACTORS = {1000.0: "mm vs m", 10.0: "mm vs cm", 100.0: "cm vs m", 25.4: "mm vs inches",
                39.37: "inches vs m", 304.8: "mm vs feet", 12.0: "inches vs feet"}
"""Common ratios between length units, to name the likely cause of a size mismatch."""


def likely_units(f: float) -> tuple[str, float]:
    """The likely cause of two sizes ``f`` times apart (> 1): a common unit ratio within 30 % (its name and exact
    factor), else ``different units or a different object`` and ``f`` to 3 digits."""
    unit, factor = min(((u, k) for k, u in UNIT_FACTORS.items()), key=lambda uk: abs(np.log(f / uk[1])))
    if abs(np.log(f / factor)) > np.log(1.3):  # no common unit ratio: suggest the measured one
        return "different units or a different object", float(f"{f:.3g}")
    return unit, factor


FLAT_TOLERANCE = 1e-3
"""An input whose spread off its best-fit line (plane) is below this share of its spread along its main axis is
collinear (planar): a rigid transform is not determined by it (it may slide and turn in the plane)."""

COINCIDE_SHARE = 1e-12
"""Points spread by less than this share of their largest coordinate coincide: what is left is the rounding of
their mean (100 copies of one point spread by 1e-14 of it, and were called collinear)."""

MAX_CHECKED_POINTS = 200_000
"""Larger inputs are checked on an evenly strided subset of this many points (deterministic)."""


def principal_spreads(pts: np.ndarray) -> np.ndarray:
    """Standard deviations of ``pts`` along its principal axes, largest first."""
    if len(pts) > MAX_CHECKED_POINTS:
        pts = pts[:: -(-len(pts) // MAX_CHECKED_POINTS)]
    centred = pts - pts.mean(axis=0)
    scale = np.abs(centred).max()
    if not scale > 0:
        return np.zeros(3)
    # singular values of the scaled, centred points: no squaring of the coordinates (no loss of small spreads)
    s = np.linalg.svd(centred / scale, compute_uv=False) * scale / np.sqrt(len(pts))
    return np.pad(s, (0, 3 - len(s)))


def check_geometry(g, label: str, min_points: int, n_invalid: int = 0) -> None:
    """Raise :class:`InputError` with one line when ``g`` (a mesh or cloud) cannot take part in a rigid
    registration: too few points (a cloud), all points coincide, collinear or planar."""
    pts = points_of(g)
    if not isinstance(g, Mesh) and len(pts) < min_points:
        dropped = f" ({n_invalid} invalid point(s) dropped)" if n_invalid else ""
        raise InputError(f"{label}: {len(pts)} point(s){dropped}; at least {min_points} are needed")
    s = principal_spreads(pts)
    if not s[0] > COINCIDE_SHARE * float(np.abs(pts).max(initial=0.0)):  # (equal points: rounding in their mean)
        raise InputError(f"{label}: all points coincide: rigid registration is not determined")
    for k, what in ((1, "collinear"), (2, "planar")):
        if s[k] < FLAT_TOLERANCE * s[0]:
            off = "line" if k == 1 else "plane"
            raise InputError(
                f"{label}: is {what}: rigid registration is not determined (its spread off the best-fit {off} is "
                f"{100 * s[k] / s[0]:.2g} % of its spread along its main axis; at least {100 * FLAT_TOLERANCE:g} % "
                "is needed)"
            )


def check_inputs(inputs, min_points: int) -> None:
    """:func:`check_geometry` on the source and the target of a loaded problem (:class:`scanreg.types.Problem`)."""
    info = inputs.info
    for role in ("source", "target"):
        g = getattr(inputs, role)
        check_geometry(g, g.source or role, min_points, int(info.get(f"n_{role}_invalid_points", 0)))
