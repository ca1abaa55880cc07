"""Coarse (global) registration: an initial ``T_target_source`` from any starting pose."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.config import Context, Distances, to_abs
from scanreg.errors import ConfigError, StageError
from scanreg.geometry import (Cloud, apply_T, blas_single_thread, horn_quaternion, kabsch_batch, rigid_points_normals,
                               row_norms, sparse_voxel_mask)
from scanreg.registry import COARSE, SALIENCE
from scanreg.stages.descriptor import to_o3d


@COARSE.register("none")
class NoCoarse:
    """Start fine registration from the identity (the inputs are assumed roughly aligned)."""

    uses: tuple[str, ...] = ()

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        return np.eye(4), {}


@dataclass
class Open3dFeatureParams:
    voxel: float = 3.0
    """Voxel size of the downsampled clouds (see ``distances``)."""
    normal_radius: float = 6.0
    """Normal estimation radius (see ``distances``); Open3D's recipe uses 2 voxels."""
    feature_radius: float = 15.0
    """FPFH radius (see ``distances``); Open3D's recipe uses 5 voxels."""
    feature_max_nn: int = 100
    """At most this many neighbours per FPFH histogram."""
    seed: int = 0
    """Seed of Open3D's random generator."""
    distances: Distances = Distances.spacing
    """Unit of the distances: multiples of the sampling spacing, or absolute input units."""


@COARSE.register("open3d_fpfh_ransac")
class Open3dFpfhRansac:
    """Open3D's global registration recipe, the comparator: voxel downsampling, normals, FPFH features, and
    RANSAC on nearest-feature matches with edge-length and distance checks."""

    uses: tuple[str, ...] = ()

    @dataclass
    class Params(Open3dFeatureParams):
        distance_threshold: float = 4.5
        """Largest distance of an inlier pair (see ``distances``); Open3D's recipe uses 1.5 voxels."""
        edge_length_ratio: float = 0.9
        """Edge-length checker: corresponding edges of a sample must agree to this ratio."""
        mutual_filter: bool = False
        """Keep only mutual nearest feature matches."""
        max_iterations: int = 100000
        """Maximum RANSAC iterations."""
        confidence: float = 0.999
        """RANSAC stops early when the best model holds with this probability."""

    def __init__(self, params: Params):
        self.p = params

    def _prepare(self, cloud: Cloud, ctx: Context):
        import open3d as o3d

        p, u, s = self.p, self.p.distances, ctx.spacing
        down = to_o3d(cloud.points, cloud.normals).voxel_down_sample(to_abs(p.voxel, u, s))
        if len(down.points) < 3:
            raise StageError(f"coarse=open3d_fpfh_ransac: {cloud.source}: fewer than 3 points after downsampling")
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.normal_radius, u, s), max_nn=30))
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.feature_radius, u, s), max_nn=p.feature_max_nn)
        )
        return down, feat

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        p = self.p
        o3d.utility.random.seed(p.seed)
        tgt, ft = self._prepare(target, ctx)
        src, fs = self._prepare(source, ctx)
        dist = to_abs(p.distance_threshold, p.distances, ctx.spacing)
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, p.mutual_filter, dist,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(p.edge_length_ratio),
             reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(p.max_iterations, p.confidence),
        )
        ctx.coarse_trace = _open3d_trace(tgt, src, ft, fs, p.mutual_filter, res)
        metrics = {
            "coarse_keypoints_target": len(tgt.points),
            "coarse_keypoints_source": len(src.points),
            "coarse_fitness": float(res.fitness),
            "coarse_inlier_rmse": float(res.inlier_rmse),
            "coarse_inliers": len(res.correspondence_set),
        }
        return np.asarray(res.transformation).copy(), metrics


def _open3d_trace(tgt, src, ft, fs, mutual: bool, res) -> dict:
    """What Open3D's feature RANSAC compared, for the evaluation: its downsampled points as keypoints, and the
    matches it draws from (each source point's nearest target feature, mutual when ``mutual``), recomputed
    here since Open3D returns only the final inliers (``ransac_inliers``: a match among them)."""
    from scipy.spatial import cKDTree

    F0, F1 = np.asarray(ft.data).T, np.asarray(fs.data).T
    pt, ps = np.asarray(tgt.points), np.asarray(src.points)
    j = cKDTree(F0).query(F1)[1]
    i = np.arange(len(F1))
    if mutual:
        keep = cKDTree(F1).query(F0[j])[1] == i
        i, j = i[keep], j[keep]
    acc = {(int(a), int(b)) for b, a in np.asarray(res.correspondence_set)}  # rows are (source, target)
    return {"keypoints_target": pt, "keypoints_source": ps, "matches_target": pt[j], "matches_source": ps[i],
            "ransac_inliers": np.array([(int(a), int(b)) in acc for a, b in zip(j, i)], bool)}


@COARSE.register("lo_ransac")
class LoRansac:
    """The paper's feature pipeline: keypoints (``salience``), descriptors (``descriptor``), correspondences
    (``matcher``), then locally optimised RANSAC (Chum et al. 2003). It draws minimal samples of 3
    correspondences (in seeded, vectorised batches), counts inliers within ``distance_threshold``, and adapts
    the number of iterations so that the chance of missing the best model is at most ``miss_probability``. Each
    new best model is locally optimised: iterative least squares on its inliers. A final fit over the inliers
    minimises sum |R p1 + t - p0|^2 + w |R n1 - n0|^2 (points and normals)."""

    uses: tuple[str, ...] = ("salience", "descriptor", "matcher")

    @dataclass
    class Params:
        distance_threshold: float = 3.0
        """Largest distance of an inlier correspondence after the transform (see ``distances``)."""
        miss_probability: float = 0.01
        """Stop when the chance of not having drawn an all-inlier sample is below this (mu). ``sampling: uniform``
        draws N = ceil(log(mu) / log(1 - w^3)) hypotheses, w the inlier share of the best model so far, rounded
        up to a whole number of batches and at least ``min_iterations``; ``guided`` uses its own all-inlier
        probability instead of w^3 (see ``sampling``)."""
        max_iterations: int = 100000
        """Most hypotheses drawn."""
        min_iterations: int = 200
        """Fewest hypotheses drawn."""
        batch: int = 256
        """Hypotheses evaluated together (vectorised) by ``sampling: uniform``; guided sampling draws 64 seeds
        of 8 samples at a time."""
        lo_iterations: int = 10
        """Rounds of least-squares re-estimation on the inliers of each new best model."""
        sampling: str = "guided"
        """How minimal samples are drawn: ``uniform`` (3 correspondences at random, plain RANSAC) or ``guided``
        (the first at random, the second among those rigidly compatible with it, the third among those
        compatible with both: the distance between their source points equals that between their target
        points to within ``distance_threshold``). Guided samples are all-inlier far more often when inliers
        are rare; the adaptive stopping rule uses the measured probability of an all-inlier guided sample."""
        normal_weight: float = 1.0
        """Weight w of the normal term of the final fit, in squared inlier thresholds: a normal residual of
        1 (about 60 degrees) costs as much as a point residual of ``w`` times ``distance_threshold`` (0: points
        only). Scaled so, the fit does not depend on the input's units."""
        min_inliers: int = 10
        """Fewer inliers than this is reported as a failure."""
        seed: int = 0
        """Seed of the sampling; the same seed gives the same transform."""
        distances: Distances = Distances.spacing
        """Unit of ``distance_threshold``: multiples of the sampling spacing, or input units."""
        fallback_voxel: Optional[float] = 2.0
        """When the configured keypoints fail (fewer than 3, fewer than 3 descriptor matches, or a best model
        with fewer than ``min_inliers`` inliers), try again once with uniform keypoints, one per voxel of this
        edge (in sampling spacings, whatever ``distances`` says; with ``voxel`` those of the downsampled clouds):
        denser and detector-free, they still match where salient points are few or not repeatable (flat indoor
        scenes). Logged as ``coarse_fallback`` (0:
        the configured keypoints served, 1: the uniform ones). null: no fallback, fail at once."""
        voxel: Optional[float] = 4.0
        """Run the whole coarse stage (keypoints, descriptors, matching, RANSAC) on the clouds voxel-downsampled to
        this edge, in sampling spacings of the full clouds (one point per voxel, the one nearest the voxel's
        centroid); inside the stage the spacing is then the downsampled clouds' own (median nearest-neighbour
        distance), so that every radius in spacings (salience, descriptor, ``distance_threshold``,
        ``fallback_voxel``) scales with it, as Open3D's recipe scales its radii with its voxel. The fine stage
        still sees every point. null: every sampled point."""
        max_points: Optional[int] = 12000
        """With ``voxel``: when a downsampled cloud still has more points than this (dense sampling, e.g.
        ``sampler.n_points=1000000``), the voxel grows by sqrt(points / max_points) (a surface's count falls with
        the square of the voxel), up to 3 times, so that the coarse stage's cost stays bounded as Open3D's recipe
        bounds it with a voxel of 1 % of the diagonal. null: no bound. The default sampling (20 000 points) gives
        about 6 500, below it."""

        min_points: Optional[int] = 2000
        """With ``voxel``: the thinner of the two downsampled clouds keeps at least this many points; the voxel
        shrinks by sqrt(points / min_points) while it has fewer (up to 3 times), and a cloud that has fewer than
        this to begin with is not thinned at all. Sparse inputs (a few thousand points, a source 4-8x sparser
        than its target) then keep enough keypoints: with the 4-spacing voxel alone, 3 000 sampled points
        became 900 and a demo pose failed (README, findings). null: no lower bound."""

        isolated_ratio: Optional[float] = 0.25
        """With ``voxel``: before thinning, drop isolated points (outliers). On the grid of the initial voxel
        (4 spacings), a cell is sparse when it holds fewer than this share (a ratio, no unit) of a full cell's
        points (the 90th percentile of the points' cell counts); its points go when its 3 x 3 x 3 block holds
        fewer than two full cells, or when no other point lies within 3 spacings (of the full clouds) of them
        (:func:`scanreg.geometry.sparse_voxel_mask`). When over 5 % of a cloud proves isolated, the spacing is
        measured again without those points and, if smaller, they are looked for again on its grid and the
        clouds thinned with it (at 50 % outliers the run's spacing is 1.5 times the surface's). A sampled
        surface fills its cells alike, outliers scattered through the volume sit one to a cell; thinning keeps
        one point per occupied cell, so without this at 30 % outliers most of the thinned source was outliers,
        the keypoints and FPFH neighbourhoods with it, and every detector failed where on every point each
        succeeded (README, findings). A clean bunny scan loses 0.2-0.7 % of its points. Logged as ``coarse_isolated_target`` / ``_source`` (points
        dropped). null: keep every point."""

        def check(self):
            if self.min_points is not None and self.min_points < 10:
                raise ValueError(f"min_points must be >= 10 or null, got {self.min_points}")
            if self.max_points is not None and self.max_points < 10:
                raise ValueError(f"max_points must be >= 10 or null, got {self.max_points}")
            if self.isolated_ratio is not None and not 0 < self.isolated_ratio <= 1:
                raise ValueError(f"isolated_ratio must be in (0, 1] or null, got {self.isolated_ratio}")
            if self.voxel is not None and not self.voxel > 0:
                raise ValueError(f"voxel must be > 0 or null, got {self.voxel}")
            if self.fallback_voxel is not None and not self.fallback_voxel > 0:
                raise ValueError(f"fallback_voxel must be > 0 or null, got {self.fallback_voxel}")
            if not 0 < self.miss_probability < 1:
                raise ValueError(f"miss_probability must be in (0, 1), got {self.miss_probability}")
            if self.batch < 1 or self.max_iterations < 1:
                raise ValueError("batch and max_iterations must be >= 1")
            if self.sampling not in ("guided", "uniform"):
                raise ValueError(f"sampling must be guided or uniform, got '{self.sampling}'")

    def __init__(self, params: Params):
        self.p = params

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        with blas_single_thread():  # small products between OpenMP calls (Open3D, k-d trees): see its note
            if self.p.voxel is None:
                return self._run(target, source, ctx)
            voxel, dropped = self.p.voxel * ctx.spacing, (0, 0)
            if self.p.isolated_ratio is not None and (self.p.min_points is None or
                                                      min(target.n_points, source.n_points) > self.p.min_points):
                target, source, dropped, voxel = self._without_isolated(target, source, ctx)
            target, source, cctx = downsampled(target, source, ctx, voxel, self.p.max_points, self.p.min_points)
            try:
                T, metrics = self._run(target, source, cctx)
            finally:
                ctx.coarse_trace = cctx.coarse_trace  # what the evaluation needs, in the thinned clouds' spacing
            metrics.update({"coarse_points_target": target.n_points, "coarse_points_source": source.n_points,
                            "coarse_spacing": cctx.spacing, "coarse_isolated_target": dropped[0],
                            "coarse_isolated_source": dropped[1]})
            return T, metrics

    def _without_isolated(self, target: Cloud, source: Cloud, ctx: Context):
        """Both clouds without their isolated points (``isolated_ratio``), the counts dropped and the voxel to
        thin with. The run's spacing is measured on the clouds as given; when more than 5 % of a cloud proved
        isolated, it is measured again without them (as the runner does: the larger median nearest-neighbour
        distance) and, if smaller, the isolated points are looked for again on its finer grid and the clouds
        thinned with it: at 50 % outliers the first spacing is 1.5 times the surface's."""
        spacing = ctx.spacing
        for attempt in range(2):
            voxel = self.p.voxel * spacing
            keep_t = sparse_voxel_mask(target.points, voxel, self.p.isolated_ratio, 3 * spacing)
            keep_s = sparse_voxel_mask(source.points, voxel, self.p.isolated_ratio, 3 * spacing)
            dropped = (int((~keep_t).sum()), int((~keep_s).sum()))
            if attempt or max(dropped[0] / target.n_points, dropped[1] / source.n_points) <= 0.05:
                break
            again = pair_spacing(target.points[keep_t], source.points[keep_s], ctx)
            if not 0 < again < spacing:
                break
            spacing = again
        return (target.subset(keep_t) if dropped[0] else target, source.subset(keep_s) if dropped[1] else source,
                dropped, voxel)

    def _run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        try:
            T, metrics = self._attempt(target, source, ctx, ctx.stages["salience"])
            metrics["coarse_fallback"] = 0
            return T, metrics
        except StageError as first:
            if self.p.fallback_voxel is None or getattr(ctx.stages["salience"], "name", "") == "uniform":
                raise
            uniform = SALIENCE.build({"name": "uniform", "voxel": self.p.fallback_voxel, "distances": "spacing"})
            if ctx.verbose:
                print(f"coarse=lo_ransac: {first}; trying uniform keypoints every {self.p.fallback_voxel:g} spacings")
            try:
                T, metrics = self._attempt(target, source, ctx, uniform)
            except StageError as second:
                raise StageError(f"{first}; the fallback to uniform keypoints failed too: "
                                 f"{str(second).removeprefix('coarse=lo_ransac: ')}") from None
            metrics["coarse_fallback"] = 1
            return T, metrics

    def _attempt(self, target: Cloud, source: Cloud, ctx: Context, salience) -> tuple[np.ndarray, dict]:
        """Keypoints by ``salience``, descriptors, matches and RANSAC; a :class:`StageError` when any is too few."""
        st = ctx.stages
        kt, ks = salience.keypoints(target, ctx), salience.keypoints(source, ctx)
        if len(kt) < 3 or len(ks) < 3:
            raise StageError(f"coarse=lo_ransac: too few keypoints (target {len(kt)}, source {len(ks)}); "
                             "lower the salience radii or use more points")
        dt, ds = st["descriptor"].compute(target, kt, ctx), st["descriptor"].compute(source, ks, ctx)
        pairs = st["matcher"].match(dt, ds, ctx)
        metrics = {"coarse_keypoints_target": len(kt), "coarse_keypoints_source": len(ks),
                   "coarse_correspondences": len(pairs)}
        if len(pairs) < 3:
            raise StageError(f"coarse=lo_ransac: only {len(pairs)} descriptor matches; need at least 3")
        P0, P1 = target.points[kt[pairs[:, 0]]], source.points[ks[pairs[:, 1]]]
        N0 = None if target.normals is None else target.normals[kt[pairs[:, 0]]]
        N1 = None if source.normals is None else source.normals[ks[pairs[:, 1]]]
        T, inl, iters = self.estimate(P0, P1, N0, N1, to_abs(self.p.distance_threshold, self.p.distances, ctx.spacing))
        ctx.coarse_trace = {"keypoints_target": target.points[kt], "keypoints_source": source.points[ks],
                            "matches_target": P0, "matches_source": P1, "ransac_inliers": inl,
                            "spacing": ctx.spacing}  # for the evaluation: positions and the detector's spacing
        metrics.update({"coarse_ransac_iterations": iters, "coarse_inliers": int(inl.sum()),
                        "coarse_inlier_ratio": float(inl.mean())})
        if inl.sum() < self.p.min_inliers:
            raise StageError(f"coarse=lo_ransac: best model has {int(inl.sum())} inliers of {len(pairs)} matches "
                             f"(min_inliers {self.p.min_inliers}); the scans may not overlap or the descriptors not match")
        return T, metrics

    def estimate(self, P0, P1, N0, N1, thr):
        """RANSAC over correspondences P1 -> P0: ``(T_target_source, inlier mask, hypotheses drawn)``."""
        p = self.p
        rng = np.random.default_rng([p.seed, 404])
        M = len(P0)
        best_T, best_inl, best_n = np.eye(4), np.zeros(M, bool), -1
        needed, drawn = p.max_iterations, 0

        def inliers(T):
            return np.linalg.norm(apply_T(T, P1) - P0, axis=1) < thr

        def local_opt(inl):
            T = np.eye(4)
            for _ in range(p.lo_iterations):
                if inl.sum() < 3:
                    break
                T = horn_quaternion(P0[inl], P1[inl])
                new = inliers(T)
                if np.array_equal(new, inl):
                    break
                inl = new
            return T, inl

        def accept(T_cand, count):
            """Local optimisation of a candidate that beats the best; it becomes the best model."""
            nonlocal best_T, best_inl, best_n
            T_lo, inl_lo = local_opt(inliers(T_cand))
            if inl_lo.sum() < count:
                T_lo, inl_lo = T_cand, inliers(T_cand)
            best_T, best_inl, best_n = T_lo, inl_lo, int(inl_lo.sum())

        def needed_for(q):
            return p.max_iterations if q <= 0 else int(np.ceil(np.log(p.miss_probability) / np.log(max(1e-12, 1 - q))))

        def valid(a, b):
            """Samples (B, 3, 3) whose side lengths agree (rigidity) and that are not near-collinear."""
            e1 = np.linalg.norm(a - np.roll(a, 1, axis=1), axis=2)
            e0 = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2)
            area = np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
            return (np.abs(e1 - e0) < thr).all(axis=1) & (area > thr * thr * 0.5)

        if p.sampling == "guided":
            # Each seed correspondence i defines the set C_i of correspondences rigidly compatible with it
            # (|d1(i, c) - d0(i, c)| < 2 thr: every inlier of a model that has i as an inlier is in it).
            # T samples (i, j, k) are drawn with j, k in C_i and compatible with each other, and each
            # hypothesis is scored on C_i only (its inliers are there). A seed yields an all-inlier sample
            # with probability q = w (1 - (1 - r^2)^T), w the inlier share, r the inlier share of C_i.
            per_seed, S = 8, 64
            from scipy.spatial.distance import cdist

            D1 = lambda a, b: cdist(P1[a], P1[b])
            D0 = lambda a, b: cdist(P0[a], P0[b])
            r_est = 0.0
            while drawn < max(needed, p.min_iterations) and drawn < p.max_iterations:
                # one batch of S seeds, vectorised over the seeds (ragged sets padded, masks mark the members)
                seeds = rng.integers(0, M, size=S)
                S_, rows = len(seeds), np.arange(len(seeds))
                drawn += S_ * per_seed
                diff = np.abs(D1(seeds, np.arange(M)) - D0(seeds, np.arange(M)))
                # j, k among the correspondences whose distance to the seed agrees within thr
                close = diff < thr
                close[rows, seeds] = False
                close_idx, member, n_close = _padded_members(close)
                if n_close.max() < 2:
                    continue
                L = close_idx.shape[1]
                jpos = np.minimum((rng.random((S_, per_seed)) * n_close[:, None]).astype(np.int64), L - 1)
                js = np.take_along_axis(close_idx, jpos, axis=1)  # (S, per_seed)
                # k compatible with j as well (and not j)
                e1 = row_norms(P1[js][:, :, None, :] - P1[close_idx][:, None, :, :])
                e0 = row_norms(P0[js][:, :, None, :] - P0[close_idx][:, None, :, :])
                ck = (np.abs(e1 - e0) < thr) & member[:, None, :] & (close_idx[:, None, :] != js[:, :, None])
                r = np.where(ck, rng.random(ck.shape), -1.0)
                kpos = np.argmax(r, axis=2)
                ok = (np.take_along_axis(r, kpos[..., None], axis=2)[..., 0] >= 0) & (n_close >= 2)[:, None]
                if not ok.any():
                    continue
                ks = np.take_along_axis(close_idx, kpos, axis=1)
                idx = np.stack([np.broadcast_to(seeds[:, None], js.shape), js, ks], axis=2)[ok]
                sid = np.broadcast_to(rows[:, None], js.shape)[ok]
                a, b = P1[idx], P0[idx]
                good = valid(a, b)
                if not good.any():
                    continue
                Ts, sid = kabsch_batch(b[good], a[good]), sid[good]
                # score each hypothesis on its seed's compatible set (every inlier of a model with the seed as
                # an inlier is there)
                pool_idx, in_pool, _ = _padded_members(diff < 2 * thr)
                counts = np.empty(len(Ts), np.int64)
                for c0 in range(0, len(Ts), 64):  # bounded memory
                    sl = slice(c0, c0 + 64)
                    pi = pool_idx[sid[sl]]
                    res = P1[pi] @ Ts[sl, :3, :3].transpose(0, 2, 1) + (Ts[sl, None, :3, 3] - P0[pi])
                    res *= res
                    sq = res[..., 0] + res[..., 1] + res[..., 2]
                    counts[sl] = ((sq < thr * thr) & in_pool[sid[sl]]).sum(axis=1)
                k = int(np.argmax(counts))
                if counts[k] > best_n:
                    accept(Ts[k], counts[k])
                    I = np.flatnonzero(best_inl)
                    if len(I) >= 3:  # r: inlier share of the compatible sets of the best model's inliers
                        sub = I[rng.permutation(len(I))[:32]]
                        Cs = np.abs(D1(sub, np.arange(M)) - D0(sub, np.arange(M))) < 2 * thr
                        r_est = float((Cs[:, I].sum(axis=1) / np.maximum(Cs.sum(axis=1), 1)).mean())
                    q = best_n / M * (1 - (1 - r_est ** 2) ** per_seed)
                    needed = needed_for(q) * per_seed
        else:
            while drawn < max(needed, p.min_iterations) and drawn < p.max_iterations:
                B = min(p.batch, p.max_iterations - drawn)
                idx = np.stack([rng.choice(M, 3, replace=False) for _ in range(B)]) if M < 8 else \
                    rng.integers(0, M, size=(B, 3))
                drawn += B
                ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])
                idx = idx[ok]
                if not len(idx):
                    continue
                a, b = P1[idx], P0[idx]
                good = valid(a, b)
                if not good.any():
                    continue
                Ts = kabsch_batch(b[good], a[good])
                moved = np.einsum("bij,mj->bmi", Ts[:, :3, :3], P1) + Ts[:, None, :3, 3]
                counts = (np.linalg.norm(moved - P0[None], axis=2) < thr).sum(axis=1)
                k = int(np.argmax(counts))
                if counts[k] > best_n:
                    accept(Ts[k], counts[k])
                    needed = needed_for((best_n / M) ** 3)
        if best_inl.sum() >= 3:
            T = best_T
            for _ in range(3):  # final fit with points and normals (normals sign-aligned to the current fit)
                inl = inliers(T)
                if inl.sum() < 3:
                    break
                n0 = n1 = None
                if N0 is not None and N1 is not None and p.normal_weight > 0:
                    n0, n1 = N0[inl], N1[inl]
                    flip = np.einsum("ij,ij->i", n1 @ T[:3, :3].T, n0) < 0
                    n1 = np.where(flip[:, None], -n1, n1)
                T = rigid_points_normals(P0[inl], P1[inl], n0, n1, p.normal_weight * thr * thr)
            if inliers(T).sum() >= best_inl.sum():  # the final fit may not lose the model's support
                best_T, best_inl = T, inliers(T)
        return best_T, best_inl, drawn


def pair_spacing(target_points: np.ndarray, source_points: np.ndarray, ctx: Context) -> float:
    """The spacing of a pair of clouds as the runner measures the run's: the larger of the two median
    nearest-neighbour distances, each estimated with the run's seeded generators (``ctx.rng(1)``, ``ctx.rng(2)``)."""
    from scanreg.metrics import estimate_spacing

    return max(estimate_spacing(target_points, ctx.rng(1)), estimate_spacing(source_points, ctx.rng(2)))


def downsampled(target: Cloud, source: Cloud, ctx: Context, voxel: float, max_points: int | None = None,
                min_points: int | None = None) -> tuple[Cloud, Cloud, Context]:
    """Both clouds voxel-downsampled (edge ``voxel``, input units; one point per voxel, the one nearest its
    centroid; the voxel grown or shrunk as :class:`LoRansac.Params` ``max_points`` and ``min_points`` say) and a
    copy of ``ctx`` whose ``spacing`` is theirs (the larger median nearest-neighbour distance, as the runner
    measures the full clouds' spacing). Clouds with fewer than ``min_points`` points are returned as they are,
    with ``ctx`` itself."""
    from dataclasses import replace

    from scanreg.stages.salience import voxel_representatives

    if min_points is not None and min(target.n_points, source.n_points) <= min_points:
        return target, source, ctx
    for _ in range(4):
        ti, si = voxel_representatives(target.points, voxel), voxel_representatives(source.points, voxel)
        hi, lo = max(len(ti), len(si)), min(len(ti), len(si))
        if max_points is not None and hi > max_points:
            voxel *= float(np.sqrt(hi / max_points))
        elif min_points is not None and lo < min_points:
            voxel *= float(np.sqrt(lo / min_points))
        else:
            break
    tgt, src = target.subset(ti), source.subset(si)
    spacing = pair_spacing(tgt.points, src.points, ctx)
    if not spacing > 0:
        spacing = ctx.spacing
    return tgt, src, replace(ctx, spacing=spacing)


def _padded_members(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of a boolean (S, M) mask: the column indices where it holds, in order, padded to the
    longest row (S, L); which of those are real members; and how many each row has."""
    n = mask.sum(axis=1)
    L = max(int(n.max()), 1)
    return np.argsort(~mask, axis=1, kind="stable")[:, :L], np.arange(L)[None, :] < n[:, None], n


@COARSE.register("landmarks")
class Landmarks:
    """User-picked landmark pairs (``data.landmarks``, at least 3) solved in closed form (Horn). It reports each
    landmark's residual and its leave-one-out error (the residual when the transform is fitted without it), so
    that a bad pick stands out: the paper's rough registration."""

    uses: tuple[str, ...] = ()

    @dataclass
    class Params:
        max_residual: Optional[float] = None
        """Fail when a landmark's leave-one-out error exceeds this (see ``distances``); null: only report."""
        distances: Distances = Distances.absolute
        """Unit of ``max_residual``: input units (default) or multiples of the sampling spacing."""

    def __init__(self, params: Params):
        self.p = params

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        lm = getattr(ctx, "landmarks", None)
        if lm is None:
            raise ConfigError("coarse=landmarks: no landmark pairs; give data.landmarks=FILE.csv "
                              "(rows: target x,y,z, source x,y,z)")
        T, metrics, loo = landmark_fit(lm[0], lm[1])
        ctx.step_metrics["landmark_residual"] = metrics.pop("_residuals")
        ctx.step_metrics["landmark_loo_error"] = loo.tolist()
        lim = to_abs(self.p.max_residual, self.p.distances, ctx.spacing)
        if lim is not None and loo.max() > lim:
            i = int(np.argmax(loo))
            raise StageError(f"coarse=landmarks: landmark {i + 1} has a leave-one-out error of {loo[i]:.4g} "
                             f"(limit {lim:.4g}): probably picked wrongly", metrics=metrics)
        return T, metrics


def landmark_fit(target_pts: np.ndarray, source_pts: np.ndarray) -> tuple[np.ndarray, dict, np.ndarray]:
    """Horn's fit of landmark pairs with per-landmark residuals and leave-one-out errors."""
    k = len(target_pts)
    centred = source_pts - source_pts.mean(axis=0)
    if k < 3 or np.linalg.matrix_rank(centred, tol=1e-9 * max(1.0, np.abs(centred).max())) < 2:
        raise StageError(f"coarse=landmarks: {k} landmark pair(s) that are collinear or coincide; need at "
                         "least 3 non-collinear pairs")
    T = horn_quaternion(target_pts, source_pts)
    res = np.linalg.norm(apply_T(T, source_pts) - target_pts, axis=1)
    loo = np.full(k, np.nan)
    if k >= 4:
        for i in range(k):
            keep = np.arange(k) != i
            Ti = horn_quaternion(target_pts[keep], source_pts[keep])
            loo[i] = np.linalg.norm(apply_T(Ti, source_pts[i:i + 1]) - target_pts[i:i + 1])
    metrics = {"landmark_count": k, "landmark_rms": float(np.sqrt(np.mean(res ** 2))),
               "landmark_residual_max": float(res.max()), "_residuals": res.tolist()}
    if k >= 4:
        metrics["landmark_loo_max"] = float(np.nanmax(loo))
    return T, metrics, np.nan_to_num(loo, nan=0.0)


@COARSE.register("open3d_fgr")
class Open3dFGR(Open3dFpfhRansac):
    """Open3D's Fast Global Registration (Zhou et al. 2016) on FPFH features of voxel-downsampled clouds, the
    second comparator."""

    @dataclass
    class Params(Open3dFeatureParams):
        distance_threshold: float = 1.5
        """FGR's maximum correspondence distance (see ``distances``); Open3D's recipe uses 0.5 voxels."""
        iterations: int = 64
        """FGR iterations."""

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        p = self.p
        o3d.utility.random.seed(p.seed)
        tgt, ft = self._prepare(target, ctx)
        src, fs = self._prepare(source, ctx)
        opt = reg.FastGlobalRegistrationOption(
            maximum_correspondence_distance=to_abs(p.distance_threshold, p.distances, ctx.spacing),
            iteration_number=p.iterations)
        res = reg.registration_fgr_based_on_feature_matching(src, tgt, fs, ft, opt)
        ctx.coarse_trace = {"keypoints_target": np.asarray(tgt.points), "keypoints_source": np.asarray(src.points)}
        return np.asarray(res.transformation).copy(), {
            "coarse_keypoints_target": len(tgt.points), "coarse_keypoints_source": len(src.points),
            "coarse_fitness": float(res.fitness), "coarse_inlier_rmse": float(res.inlier_rmse)}
