"""Voxel grids and space-filling orders: Morton order, voxel cells and groups, one representative per voxel,
isolated-point detection."""

from __future__ import annotations

import numpy as np

from scanreg.geometry.arrays import col_max, col_min


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """Insert two zero bits after each of the low 21 bits of ``x`` (uint64), for 3-D Morton codes."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation that sorts points along a Morton (Z-order) curve of a 2^bits grid over their bounding box
    (bits <= 21): queries issued in this order, and a k-d tree built on points stored in this order, touch memory
    in order."""
    lo = col_min(points)
    q = ((points - lo) / ((col_max(points) - lo).max() + 1e-300) * (2**bits - 1)).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


LOCALITY_SPAN = 1024
""":func:`locality_ordered` renumbers a mesh whose faces' vertex indices lie further apart than this many
vertices (the median over the faces of the largest difference between a face's vertex indices)."""


def locality_ordered(vertices: np.ndarray, faces: np.ndarray,
                     span: int = LOCALITY_SPAN) -> tuple[np.ndarray, np.ndarray]:
    """The mesh renumbered for memory locality when its vertex order is scattered: the vertices in Morton order
    (:func:`morton_order`), the faces by their smallest new vertex index (stable); unchanged (the same arrays)
    when the faces' vertices are already near one another in the order (a median span of at most ``span``
    vertices, see :data:`LOCALITY_SPAN`: a range scan's rows, a mesh written face by face). The same surface
    either way, renumbered only.

    For a library that builds a linked mesh from the arrays in their order (MeshFix allocates its vertices,
    edges and triangles one by one), this puts neighbours near one another in memory; meshes already in scan
    or export order are left alone (``experiments/benchmarks/repair_speed.md`` measures both)."""
    f = np.asarray(faces, dtype=np.int64)  # (differences of unsigned indices would wrap around)
    if not len(f):
        return vertices, faces
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    spread = np.maximum(np.maximum(np.abs(a - b), np.abs(b - c)), np.abs(c - a))
    if np.median(spread) <= span:
        return vertices, faces
    order = morton_order(vertices)
    new = np.empty_like(order)
    new[order] = np.arange(len(order))
    g = new[f]
    return vertices[order], g[np.argsort(g.min(axis=1), kind="stable")]


def voxel_cells(points: np.ndarray, voxel: float, margin: int = 0) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """The cell of each point on a grid of edge ``voxel`` (input units) anchored at the points' minimum corner,
    with ``margin`` empty cells on every side: ``(flat, keys, span)``, ``keys`` the (N, 3) integer cells,
    ``span`` the grid's size in cells, and ``flat`` one int64 per cell ordered as the (x, y, z) rows are
    lexicographically (the same groups in the same order as ``np.unique(keys, axis=0)``, without its row sort on a
    million points), or None when the grid has too many cells for a 62-bit index."""
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.ones(3, np.int64)
    keys = np.floor((points - col_min(points)) / voxel).astype(np.int64) + margin
    span = col_max(keys) + 1 + margin
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:
        return None, keys, span
    return (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2], keys, span


def _marked(flat: np.ndarray, span: np.ndarray) -> np.ndarray | None:
    """Which cells of a grid of ``span`` cells the cell numbers ``flat`` occupy, one flag per cell, when the
    grid has at most 4 cells per point (marking them is then quicker than sorting the points); else None."""
    n_cells = int(np.prod(span))
    if n_cells > 4 * len(flat):
        return None
    occupied = np.zeros(n_cells, bool)
    occupied[flat] = True
    return occupied


def occupied_cells(flat: np.ndarray, span: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(flat, return_inverse=True, return_counts=True)`` for the cell numbers ``flat`` of
    :func:`voxel_cells` on a grid of ``span`` cells: the occupied cells in order, each point's position among
    them, each one's point count; a small grid's cells are marked (:func:`_marked`) instead of sorted."""
    occupied = _marked(flat, span)
    if occupied is None:
        cells, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
        return cells, inv.ravel(), counts
    cells = np.flatnonzero(occupied)
    rank = np.zeros(len(occupied), np.int64)
    rank[cells] = np.arange(len(cells))
    inv = rank[flat]
    return cells, inv, np.bincount(inv, minlength=len(cells))


def voxel_groups(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells of :func:`voxel_cells`' grid in key order: each point's cell number and each cell's
    point count, ``(inv (N,), counts (cells,))``."""
    flat, keys, span = voxel_cells(points, voxel)
    if flat is not None:
        _, inv, counts = occupied_cells(flat, span)
        return inv, counts
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return inv.ravel(), counts


def voxel_count(points: np.ndarray, voxel: float) -> int:
    """How many cells of :func:`voxel_cells`' grid hold a point: the number of points
    :func:`voxel_representatives` keeps, without choosing them."""
    flat, keys, span = voxel_cells(points, voxel)
    if flat is None:
        return len(np.unique(keys, axis=0))
    occupied = _marked(flat, span)
    return distinct_count(flat) if occupied is None else int(np.count_nonzero(occupied))


def distinct_count(values: np.ndarray) -> int:
    """How many distinct values the 1-D integer array ``values`` holds: ``len(np.unique(values))``, by a sort and
    a count of changes (NumPy's hash-based unique is slower on a million cell numbers that are mostly distinct)."""
    if len(values) == 0:
        return 0
    v = np.sort(values)
    return int(np.count_nonzero(v[1:] != v[:-1])) + 1


def voxel_occupancy(points: np.ndarray, voxel: float) -> np.ndarray:
    """For each point, how many points (itself included) fall in its cell of a grid of edge ``voxel`` (input units)
    anchored at the points' minimum corner: the grid :func:`scanreg.stages.salience.voxel_representatives` thins
    with."""
    inv, counts = voxel_groups(points, voxel)
    return counts[inv]


def sparse_voxel_mask(points: np.ndarray, voxel: float, ratio: float, near: float | None = None) -> np.ndarray:
    """Which points to keep, dropping isolated ones (outliers scattered through the volume), on a grid of edge
    ``voxel`` (input units). A full cell holds ``full`` points, the 90th percentile of the points' cell counts
    (:func:`voxel_occupancy`; counted per point, it is a surface cell's count while fewer than about 85 % of the
    points are outliers). A cell is sparse when it holds fewer than ``ratio * full`` points, and its points are
    dropped when its 3 x 3 x 3 block of cells (itself and its 26 neighbours) holds fewer than ``2 * full`` points
    too: a sampled surface fills its cells alike and a sparse cell at its border or where it grazes a cell's
    corner has full neighbours, while an outlier sits alone in an empty block. Voxel thinning would give each
    outlier a representative of its own. With ``near`` (input units), a point of a sparse cell whose block is
    full enough is dropped still when no other point lies within ``near`` of it: an outlier floating a few
    cells off the surface, where a point at the surface's border has neighbours one spacing away. A cloud
    whose full cells hold fewer than ``1 / ratio`` points (a sparse cloud) keeps every point, and so does one
    too large for a 62-bit cell index."""
    n = len(points)
    keep = np.ones(n, bool)
    if n == 0:
        return keep
    flat, _, span = voxel_cells(points, voxel, margin=1)  # a margin for the neighbours
    if flat is None:
        return keep
    cells, inv, counts = occupied_cells(flat, span)
    full = float(np.quantile(counts[inv], 0.9))  # voxel_occupancy's counts
    sparse = np.flatnonzero(counts < ratio * full)
    if not len(sparse):
        return keep
    c = cells[sparse]
    cx, rest = np.divmod(c, span[1] * span[2])
    cy, cz = np.divmod(rest, span[2])
    o = np.arange(-1, 2)
    ox, oy, oz = (a.ravel() for a in np.meshgrid(o, o, o, indexing="ij"))
    nb = ((cx[:, None] + ox) * span[1] + cy[:, None] + oy) * span[2] + cz[:, None] + oz  # (sparse, 27)
    pos = np.minimum(np.searchsorted(cells, nb), len(cells) - 1)
    occupied = cells[pos] == nb  # the neighbour cell holds points: it is cells[pos]
    block = np.where(occupied, counts[pos], 0).sum(axis=1)
    drop = np.zeros(len(cells), bool)
    drop[sparse[block < 2 * full]] = True
    keep = ~drop[inv]
    if near is not None:
        sparse_cell = np.zeros(len(cells), bool)
        sparse_cell[sparse] = True
        ask = np.flatnonzero(sparse_cell[inv] & keep)
        if len(ask):
            from scipy.spatial import cKDTree

            # every point within near of an asked one lies in its cell's 3 x 3 x 3 block when near <= voxel: the
            # tree holds those blocks' points only
            in_block = np.zeros(len(cells), bool)
            in_block[pos[occupied]] = True  # np.isin(cells, nb), from the search above
            pool = points[in_block[inv]] if near <= voxel else points
            tree = cKDTree(pool, leafsize=32, balanced_tree=False, compact_nodes=False)  # an unbalanced tree: quicker to build
            d = tree.query(points[ask], k=2, distance_upper_bound=near)[0][:, 1]  # inf beyond near
            keep[ask[d > near]] = False
    return keep


def voxel_representatives(points: np.ndarray, voxel: float) -> np.ndarray:
    """Index of one point per occupied voxel: the point nearest to the centroid of the voxel's points.
    Sorted by voxel key, so the result does not depend on the order of equal keys (deterministic)."""
    inv, counts = voxel_groups(points, voxel)
    # per-voxel sums in the points' order (as np.add.at would add them)
    sums = np.stack([np.bincount(inv, weights=points[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    centroids = sums / counts[:, None]
    d = np.linalg.norm(points - centroids[inv], axis=1)
    # per voxel the point at the least distance, the lowest index among equals: the smallest index of a voxel
    # among the points at its least distance (no sort of all the points by (voxel, distance))
    least = np.full(len(counts), np.inf)
    np.minimum.at(least, inv, d)
    at_least = np.flatnonzero(d == least[inv])
    _, first = np.unique(inv[at_least], return_index=True)
    return np.sort(at_least[first])


def in_cells_around(points: np.ndarray, seeds: np.ndarray, cell: float) -> np.ndarray | None:
    """Which of ``points`` (n, 3) lie in the cell of a seed (``seeds`` (m, 3)) or in one of its 26 neighbours, on a
    grid of cubes of side ``cell``: every point within ``cell`` of a seed along each axis is among them (the
    side is widened by a millionth for the rounding of the cells' coordinates). None when the seeds' cells
    cannot be numbered in 63 bits, or a seed is not finite (then take every point)."""
    points, seeds = np.asarray(points, np.float64), np.asarray(seeds, np.float64)
    h = cell * (1 + 1e-6)
    if not (len(seeds) and h > 0 and np.isfinite(h)):
        return None if len(seeds) else np.zeros(len(points), bool)
    if not np.isfinite(seeds).all():
        return None
    org = col_min(seeds) - 2 * h
    rel = np.floor((seeds - org) / h)
    if float(np.prod(col_max(rel) + 3)) > 2.0 ** 62:  # (checked in floats, before the cast could wrap)
        return None
    cells = rel.astype(np.int64)
    dims = col_max(cells) + 3
    off = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3)
    around = (np.unique(cells, axis=0)[:, None] + off).reshape(-1, 3)
    keys = np.unique((around[:, 0] * dims[1] + around[:, 1]) * dims[2] + around[:, 2])
    g = [np.floor((points[:, k] - org[k]) / h) for k in range(3)]
    inside = (g[0] >= 0) & (g[0] < dims[0]) & (g[1] >= 0) & (g[1] < dims[1]) & (g[2] >= 0) & (g[2] < dims[2])
    pk = np.full(len(points), -1, np.int64)
    pk[inside] = ((g[0][inside].astype(np.int64) * dims[1] + g[1][inside].astype(np.int64)) * dims[2]
                  + g[2][inside].astype(np.int64))
    at = np.minimum(np.searchsorted(keys, pk), len(keys) - 1)
    return inside & (keys[at] == pk)
