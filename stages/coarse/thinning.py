"""Thinning a pair of clouds for a coarse stage: isolated points (outliers) dropped, one point per voxel kept, the
voxel bounded by the counts it leaves, and the thinned pair's own spacing."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Cloud, sparse_voxel_mask, voxel_count, voxel_representatives
from scanreg.stages.pair import pair_spacing
from scanreg.types import RunContext


def without_isolated(target: Cloud, source: Cloud, spacing: float, voxel_spacings: float, ratio: float,
                     ctx: RunContext) -> tuple[Cloud, Cloud, tuple[int, int], float]:
    """Both clouds without their isolated points (:func:`scanreg.geometry.sparse_voxel_mask` on a grid of
    ``voxel_spacings`` spacings, ``ratio`` of a full cell, no neighbour within 3 spacings), the counts dropped and
    the voxel (input units) to thin with. ``spacing`` is measured on the clouds as given; when more than 5 % of a
    cloud proved isolated, it is measured again without them (the larger median nearest-neighbour distance) and,
    if smaller, the isolated points are looked for again on its finer grid, which the clouds are then thinned
    with: at 50 % outliers the first spacing is 1.5 times the surface's."""
    for attempt in range(2):
        voxel = voxel_spacings * spacing
        keep_t = sparse_voxel_mask(target.points, voxel, ratio, 3 * spacing)
        keep_s = sparse_voxel_mask(source.points, voxel, ratio, 3 * spacing)
        dropped = (int((~keep_t).sum()), int((~keep_s).sum()))
        if attempt or max(dropped[0] / target.n_points, dropped[1] / source.n_points) <= 0.05:
            break
        again = pair_spacing(target.points[keep_t], source.points[keep_s], ctx)
        if not 0 < again < spacing:
            break
        spacing = again
    return (target.subset(keep_t) if dropped[0] else target, source.subset(keep_s) if dropped[1] else source,
            dropped, voxel)


def downsampled(target: Cloud, source: Cloud, spacing: float, ctx: RunContext, voxel: float,
                max_points: int | None = None, min_points: int | None = None) -> tuple[Cloud, Cloud, float]:
    """Both clouds voxel-downsampled (edge ``voxel``, input units; one point per voxel, the one nearest its
    centroid; the voxel grown while the larger cloud has more than ``max_points`` points, or shrunk while the
    smaller has fewer than ``min_points``, by the square root of the ratio, up to 3 times) and their spacing (the
    larger median nearest-neighbour distance, as the runner measures the full clouds'; ``spacing`` when it comes
    out 0). When a cloud has fewer than ``min_points`` points, both are returned as they are, with ``spacing``, but
    for a cloud far denser than that spacing (:func:`_not_denser`)."""
    if min_points is not None and min(target.n_points, source.n_points) <= min_points:
        return _not_denser(target, spacing), _not_denser(source, spacing), spacing
    for _ in range(4):  # the voxel chosen by counts alone; the points kept at the last voxel counted
        used = voxel
        counts = voxel_count(target.points, voxel), voxel_count(source.points, voxel)
        hi, lo = max(counts), min(counts)
        if max_points is not None and hi > max_points:
            voxel *= float(np.sqrt(hi / max_points))
        elif min_points is not None and lo < min_points:
            voxel *= float(np.sqrt(lo / min_points))
        else:
            break
    tgt = target.subset(voxel_representatives(target.points, used))
    src = source.subset(voxel_representatives(source.points, used))
    thinned = pair_spacing(tgt.points, src.points, ctx)
    return tgt, src, thinned if thinned > 0 else spacing


DENSITY_GAP = 4.0
"""A sparse cloud's pair: the other cloud keeps at most the density of one point per voxel of the pair's spacing
over this (:func:`_not_denser`)."""


def _not_denser(cloud: Cloud, spacing: float) -> Cloud:
    """``cloud``, or one point per voxel of ``spacing / DENSITY_GAP`` when that keeps under a quarter of its points
    (over 4 of them to a voxel: about 8 times the sparse cloud's density in spacing, 64 in points). The pair's
    spacing is the sparser cloud's, and the coarse stage's radii are in it: 51 source points against a
    40 000-point target (22 times its spacing) made every neighbourhood in the target span most of it (81 s in
    the coarse stage); the density-robustness experiments (up to 8 times the points) are left as they were."""
    voxel = spacing / DENSITY_GAP
    if voxel_count(cloud.points, voxel) * 4 >= cloud.n_points:
        return cloud
    return cloud.subset(voxel_representatives(cloud.points, voxel))
