"""``coarse=lo_ransac``: the paper's coarse registration (keypoints, descriptors, matches, LO-RANSAC)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from scanreg.errors import StageError
from scanreg.geometry import Cloud, estimate_spacing, sparse_voxel_mask, voxel_count, voxel_representatives
from scanreg.process import blas_single_thread
from scanreg.stages.coarse.base import CoarseBase, Described
from scanreg.stages.coarse.ransac import lo_ransac
from scanreg.stages.coarse.sc2 import sc2_pcr
from scanreg.stages.coarse.thinning import downsampled, without_isolated
from scanreg.stages.pair import thinned_pair
from scanreg.stages.registry import COARSE, SALIENCE
from scanreg.types import CoarseResult, CoarseTrace, Distances, RunContext, to_abs

THIN_SALT = 6100
"""Salts of the run's generators (:meth:`~scanreg.types.RunContext.rng`) that draw the points a large target
(this one) and source (the next) are thinned to (``max_input_points``)."""


@COARSE.register("lo_ransac")
class LoRansac(CoarseBase):
    """The paper's feature pipeline: keypoints (``salience``), descriptors (``descriptor``), correspondences
    (``matcher``), then locally optimised RANSAC (Chum et al. 2003; :mod:`scanreg.stages.coarse.ransac`). It
    draws minimal samples of 3 correspondences (in seeded, vectorised batches), counts inliers within
    ``distance_threshold``, and adapts the number of iterations so that the chance of missing the best model is
    at most ``miss_probability``. Each new best model is locally optimised: iterative least squares on its
    inliers. A final fit over the inliers minimises sum |R p1 + t - p0|^2 + w |R n1 - n0|^2 (points and
    normals)."""

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
        estimator: str = "ransac"
        """How the transform is found from the matches: ``ransac`` (the paper's LO-RANSAC, the sampling above) or
        ``sc2`` (second-order spatial compatibility, SC2-PCR, Chen et al. 2022: one hypothesis per seed from its
        consensus set, no random draws; :mod:`scanreg.stages.coarse.sc2`)."""
        seed_share: float = 0.2
        """``estimator: sc2``: at most this share of the matches become seeds (unitless, in (0, 1])."""
        sc2_k1: int = 30
        """``estimator: sc2``: a seed's consensus set is first the matches of highest second-order compatibility
        with it, this many."""
        sc2_k2: int = 20
        """``estimator: sc2``: then, of those, this many of highest compatibility recomputed within them; the
        hypothesis is fitted to them and the seed."""
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
        fallback_k: Optional[int] = None
        """The fallback's matching looks this far: each uniform keypoint's ``fallback_k`` nearest descriptors
        (the matcher's ``k`` in place of its own; the configured keypoints keep it). null: the matcher's own
        ``k`` (the paper's mutual 3-NN). 5 suits pairs that overlap little: uniform keypoints are many and alike,
        and where the fallback is needed at 10-20 % overlap a true match is often not among the 3 nearest (the
        bunny benchmark's 10-20 % bin 8 of 16 against 7 at its pose seed 0, 7 against 6 at seed 1; with
        ``matcher.k=5`` none of the other 35 cases of seed 0 was lost); but the fallback's matches about double
        and so does its RANSAC's work, where users start too: the 3DMatch pair always falls back, and its coarse
        stage then takes 1.7 times as long for the same final pose (``experiments/benchmarks/low_overlap.md``).
        ``second_look_fitness`` widens the matching only for the pairs that need it."""
        second_look_fitness: Optional[float] = 0.15
        """When the fallback's uniform keypoints served and the fine stage's pose keeps less than this share of
        the source on the target (``icp_fitness``: within its acceptance distance; unitless, in (0, 1]), the pair
        is registered once more, its uniform keypoints matched with ``second_look_k`` nearest descriptors, and
        of the two refined poses the one that keeps the larger share is kept (ties: the first). At 10-20 %
        overlap the true match of a uniform keypoint is often not among its 3 nearest descriptors: the bunny
        benchmark's wrong poses there keep 4-17 % of the source, its right ones 19-43 %; the 3DMatch pair,
        which always falls back, 43 %, so it is not looked at again. The share is a weak signal at such
        overlaps (on the raw scans' repaired meshes, 20 000 points, wrong poses kept 22-31 % and right ones
        15-19 %): the second look is a second chance for a pose that keeps little, at the cost of another coarse
        and fine stage (about twice the first coarse stage), not a verdict on the pose. Logged as
        ``coarse_second_look`` (1: made), ``coarse_second_look_kept`` (1: its pose kept),
        ``coarse_first_look_fitness`` and ``coarse_second_look_fitness``; a look made prints a note line.
        null: never."""
        second_look_k: int = 5
        """The second look's matching: each uniform keypoint's this many nearest descriptors (the matcher's ``k``
        in its place); no second look when the first already looked this far (``fallback_k``, else the
        matcher's ``k``) or the matcher has no ``k``."""
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
        became 900 and a demo pose failed (docs: Registration, findings). null: no lower bound."""

        max_input_points: int = 100000
        """With ``voxel``: a cloud with more points than this is first thinned to a seeded uniform random subset of
        this many (:meth:`~scanreg.geometry.Cloud.thinned`) and the pair's spacing measured again on the thinned
        clouds, before the isolated points are looked for and the clouds voxel-downsampled: those passes then cost
        what this many points cost, however large the input (the stage keeps at most ``max_points`` anyway).
        Thinning lowers the density contrast between a surface and scattered outliers that ``isolated_ratio``
        relies on. 0: every point."""

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
        succeeded (docs: Registration, findings). A clean bunny scan loses 0.2-0.7 % of its points. Logged as ``coarse_isolated_target`` / ``_source`` (points
        dropped). null: keep every point."""

        def check(self):
            if self.min_points is not None and self.min_points < 10:
                raise ValueError(f"min_points must be >= 10 or null, got {self.min_points}")
            if self.max_input_points != 0 and self.max_input_points < 1000:
                raise ValueError(f"max_input_points must be 0 (every point) or >= 1000, got {self.max_input_points}")
            if self.max_points is not None and self.max_points < 10:
                raise ValueError(f"max_points must be >= 10 or null, got {self.max_points}")
            if self.isolated_ratio is not None and not 0 < self.isolated_ratio <= 1:
                raise ValueError(f"isolated_ratio must be in (0, 1] or null, got {self.isolated_ratio}")
            if self.voxel is not None and not self.voxel > 0:
                raise ValueError(f"voxel must be > 0 or null, got {self.voxel}")
            if self.fallback_voxel is not None and not self.fallback_voxel > 0:
                raise ValueError(f"fallback_voxel must be > 0 or null, got {self.fallback_voxel}")
            if self.fallback_k is not None and self.fallback_k < 1:
                raise ValueError(f"fallback_k must be >= 1 or null, got {self.fallback_k}")
            if self.second_look_fitness is not None and not 0 < self.second_look_fitness <= 1:
                raise ValueError(f"second_look_fitness must be in (0, 1] or null, got {self.second_look_fitness}")
            if self.second_look_k < 1:
                raise ValueError(f"second_look_k must be >= 1, got {self.second_look_k}")
            if not 0 < self.miss_probability < 1:
                raise ValueError(f"miss_probability must be in (0, 1), got {self.miss_probability}")
            if self.batch < 1 or self.max_iterations < 1:
                raise ValueError("batch and max_iterations must be >= 1")
            if self.sampling not in ("guided", "uniform"):
                raise ValueError(f"sampling must be guided or uniform, got '{self.sampling}'")
            if self.estimator not in ("ransac", "sc2"):
                raise ValueError(f"estimator must be ransac or sc2, got '{self.estimator}'")
            if not 0 < self.seed_share <= 1:
                raise ValueError(f"seed_share must be in (0, 1], got {self.seed_share}")
            if not 3 <= self.sc2_k2 <= self.sc2_k1:
                raise ValueError(f"sc2_k2 must be >= 3 and <= sc2_k1, got sc2_k1 {self.sc2_k1}, sc2_k2 {self.sc2_k2}")

    def __init__(self, params: Params, salience, descriptor, matcher):
        self.p = params
        self.salience, self.descriptor, self.matcher = salience, descriptor, matcher

    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks=None) -> CoarseResult:
        return self._thinned_then(self._run, target, source, spacing, ctx)

    def second_look(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext, first: CoarseResult,
                    fitness: float | None) -> CoarseResult | None:
        """The pair again with the fallback's uniform keypoints matched wider (``second_look_fitness``,
        ``second_look_k``), when the fallback served ``first`` and its refined pose keeps less than
        ``second_look_fitness`` of the source (``fitness``); None otherwise, or when the wider matching finds
        too little. (The optional method of :class:`~scanreg.stages.protocols.CoarseStage`; pairs only, a scan
        set's pairs are not looked at again.)"""
        p, k = self.p, self.p.second_look_k
        looked = getattr(getattr(self._fallback_matcher(), "p", None), "k", None)  # how far the first look matched
        if (p.second_look_fitness is None or fitness is None or not fitness < p.second_look_fitness
                or first.metrics.get("coarse_fallback") != 1 or looked is None or looked >= k):
            return None
        if ctx.verbose:
            print(f"coarse=lo_ransac: the pose keeps {fitness:.1%} of the source (second_look_fitness "
                  f"{p.second_look_fitness:g}); matching the uniform keypoints with {k} nearest descriptors")
        wider = self._matcher_with(k)
        try:
            return self._thinned_then(lambda t, s, sp, _: self._uniform_attempt(t, s, sp, wider), target, source,
                                      spacing, ctx)
        except StageError:
            return None

    def _thinned_then(self, run, target: Cloud, source: Cloud, spacing: float, ctx: RunContext) -> CoarseResult:
        """``run(target, source, spacing, ctx)`` on the clouds thinned as ``voxel`` and its neighbours say, its
        result's metrics with the thinning's."""
        p = self.p
        with blas_single_thread():
            if p.voxel is None:
                return run(target, source, spacing, ctx)
            target, source, spacing = thinned_pair(target, source, spacing, p.max_input_points, ctx, THIN_SALT)
            inputs = {"coarse_input_points_target": target.n_points, "coarse_input_points_source": source.n_points}
            voxel, dropped = p.voxel * spacing, (0, 0)
            if p.isolated_ratio is not None and (p.min_points is None or
                                                 min(target.n_points, source.n_points) > p.min_points):
                target, source, dropped, voxel = without_isolated(target, source, spacing, p.voxel,
                                                                  p.isolated_ratio, ctx)
            target, source, thinned = downsampled(target, source, spacing, ctx, voxel, p.max_points, p.min_points)
            res = run(target, source, thinned, ctx)
            res.metrics.update({**inputs, "coarse_points_target": target.n_points,
                                "coarse_points_source": source.n_points, "coarse_spacing": thinned,
                                "coarse_isolated_target": dropped[0], "coarse_isolated_source": dropped[1]})
            return res

    def _run(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext) -> CoarseResult:
        """The configured keypoints, else (``fallback_voxel``) uniform ones."""
        try:
            res = self._attempt(target, source, spacing, self.salience, self.matcher)
            res.metrics["coarse_fallback"] = 0
            return res
        except StageError as first:
            if self.p.fallback_voxel is None or getattr(self.salience, "name", "") == "uniform":
                raise
            if ctx.verbose:
                print(f"coarse=lo_ransac: {first}; trying uniform keypoints every {self.p.fallback_voxel:g} spacings")
            try:
                return self._uniform_attempt(target, source, spacing, self._fallback_matcher())
            except StageError as second:
                raise StageError(f"{first}; the fallback to uniform keypoints failed too: "
                                 f"{str(second).removeprefix('coarse=lo_ransac: ')}") from None

    def _uniform_attempt(self, target: Cloud, source: Cloud, spacing: float, matcher) -> CoarseResult:
        """:meth:`_attempt` with the fallback's uniform keypoints and ``matcher``, logged as ``coarse_fallback``
        1."""
        res = self._attempt(target, source, spacing, self._uniform_salience(), matcher)
        res.metrics["coarse_fallback"] = 1
        return res

    def _uniform_salience(self):
        """The fallback's keypoints: uniform, one per ``fallback_voxel``."""
        return SALIENCE.build({"name": "uniform", "voxel": self.p.fallback_voxel, "distances": "spacing"})

    def _fallback_matcher(self):
        """The matcher of the fallback's uniform keypoints: the configured one with ``k`` = ``fallback_k`` (when
        it has a ``k``)."""
        return self.matcher if self.p.fallback_k is None else self._matcher_with(self.p.fallback_k)

    def _matcher_with(self, k: int):
        """The configured matcher with ``k`` nearest descriptors (itself when it has no ``k``)."""
        params = getattr(self.matcher, "p", None)
        if not hasattr(params, "k"):
            return self.matcher
        return type(self.matcher)(replace(params, k=k))

    def _attempt(self, target: Cloud, source: Cloud, spacing: float, salience, matcher) -> CoarseResult:
        """Keypoints by ``salience``, descriptors, matches by ``matcher`` and RANSAC; a :class:`StageError` when any
        is too few."""
        kt, ks = salience.keypoints(target, spacing), salience.keypoints(source, spacing)
        if len(kt) < 3 or len(ks) < 3:
            raise StageError(f"coarse=lo_ransac: too few keypoints (target {len(kt)}, source {len(ks)}); "
                             "lower the salience radii or use more points")
        dt, ds = self.descriptor.compute(target, kt, spacing), self.descriptor.compute(source, ks, spacing)
        return self._matched(Described(target, spacing, kt, dt), Described(source, spacing, ks, ds), self.p, matcher)

    def _matched(self, t: Described, s: Described, p: Params, matcher) -> CoarseResult:
        """Descriptor matches by ``matcher`` and RANSAC between two described clouds (one spacing), with the
        parameters ``p``;
        when a cloud had no normals and the descriptor says how its histograms read with the normals turned over
        (:meth:`~scanreg.stages.descriptor.FPFH.flipped`), both ways, the one with more inliers kept (ties: as
        oriented). Each cloud's estimated normals are oriented consistently on their own, so that one of the two
        ways has them on the same side of the surface in both."""
        flip = getattr(self.descriptor, "flipped", None)
        turned = flip(t.descriptors) if flip is not None and (t.cloud.normals is None or
                                                               s.cloud.normals is None) else None
        if turned is None:
            return self._matched_once(t, s, p, matcher)
        results, errors = [], []
        for k, dt in enumerate((t.descriptors, turned)):
            try:
                res = self._matched_once(Described(t.cloud, t.spacing, t.keypoints, dt), s, p, matcher)
                res.metrics["coarse_normals_turned"] = k
                results.append(res)
            except StageError as e:
                errors.append(e)
        if not results:
            raise errors[0]
        return max(results, key=lambda r: r.metrics["coarse_inliers"])  # (the first of equals: as oriented)

    def _matched_once(self, t: Described, s: Described, p: Params, matcher) -> CoarseResult:
        """:meth:`_matched` with the descriptors as they are."""
        pairs = matcher.match(t.descriptors, s.descriptors)
        metrics = {"coarse_keypoints_target": len(t.keypoints), "coarse_keypoints_source": len(s.keypoints),
                   "coarse_correspondences": len(pairs)}
        if len(pairs) < 3:
            raise StageError(f"coarse=lo_ransac: only {len(pairs)} descriptor matches; need at least 3")
        kt, ks, target, source = t.keypoints, s.keypoints, t.cloud, s.cloud
        P0, P1 = target.points[kt[pairs[:, 0]]], source.points[ks[pairs[:, 1]]]
        N0 = None if target.normals is None else target.normals[kt[pairs[:, 0]]]
        N1 = None if source.normals is None else source.normals[ks[pairs[:, 1]]]
        thr = to_abs(p.distance_threshold, p.distances, t.spacing)
        r = lo_ransac(P0, P1, N0, N1, thr, p, p.seed) if p.estimator == "ransac" else sc2_pcr(P0, P1, N0, N1, thr, p)
        inl = r.inliers
        metrics.update({"coarse_ransac_iterations": r.hypotheses, "coarse_inliers": int(inl.sum()),
                        "coarse_inlier_ratio": float(inl.mean())})
        if inl.sum() < p.min_inliers:
            raise StageError(f"coarse=lo_ransac: best model has {int(inl.sum())} inliers of {len(pairs)} matches "
                             f"(min_inliers {p.min_inliers}); the scans may not overlap or the descriptors not match")
        trace = CoarseTrace(target.points[kt], source.points[ks], P0, P1, inl, t.spacing)
        return CoarseResult(r.T_target_source, metrics, trace)

    def describe_set(self, clouds: list[Cloud], spacing: float, ctx: RunContext) -> list[Described]:
        """Every scan of a set thinned on one voxel grid (``voxel`` spacings of ``spacing``, grown or shrunk once
        for the whole set as ``max_points`` and ``min_points`` say, isolated points dropped first), then its
        keypoints and descriptors at the thinned clouds' spacing (the largest of them): each scan once, whatever
        the pairs it takes part in."""
        p = self.p
        with blas_single_thread():
            if p.voxel is None:
                thinned, ts = list(clouds), spacing
            else:
                voxel = p.voxel * spacing
                if p.isolated_ratio is not None:
                    clouds = [c.subset(sparse_voxel_mask(c.points, voxel, p.isolated_ratio, 3 * spacing))
                              for c in clouds]
                for _ in range(4):
                    counts = [voxel_count(c.points, voxel) for c in clouds]
                    if p.max_points is not None and max(counts) > p.max_points:
                        voxel *= float(np.sqrt(max(counts) / p.max_points))
                    elif p.min_points is not None and min(counts) < p.min_points:
                        voxel *= float(np.sqrt(min(counts) / p.min_points))
                    else:
                        break
                thinned = [c.subset(voxel_representatives(c.points, voxel)) for c in clouds]
                ts = max(estimate_spacing(c.points, ctx.rng(1)) for c in thinned)
            out = []
            for c in thinned:
                kp = self.salience.keypoints(c, ts)
                out.append(Described(c, ts, kp, self.descriptor.compute(c, kp, ts) if len(kp) >= 3 else None))
        return out

    def align_described(self, target: Described, source: Described, ctx: RunContext,
                        budget: int | None = None) -> CoarseResult:
        """Matches and RANSAC between two described scans of a set (at most ``budget`` hypotheses), with the
        fallback to uniform keypoints as :meth:`align` has it."""
        p = self.p if budget is None else replace(self.p, max_iterations=min(self.p.max_iterations, budget))
        with blas_single_thread():
            try:
                if target.descriptors is None or source.descriptors is None:
                    raise StageError(f"coarse=lo_ransac: too few keypoints (target {len(target.keypoints)}, source "
                                     f"{len(source.keypoints)})")
                res = self._matched(target, source, p, self.matcher)
                res.metrics["coarse_fallback"] = 0
                return res
            except StageError:
                if p.fallback_voxel is None or getattr(self.salience, "name", "") == "uniform":
                    raise
            res = self._matched(self._uniformly(target), self._uniformly(source), p, self._fallback_matcher())
            res.metrics["coarse_fallback"] = 1
            return res

    def _uniformly(self, d: Described) -> Described:
        """``d``'s cloud described with uniform keypoints (``fallback_voxel``), once."""
        if d.fallback is None:
            uniform = self._uniform_salience()
            kp = uniform.keypoints(d.cloud, d.spacing)
            d.fallback = Described(d.cloud, d.spacing, kp, self.descriptor.compute(d.cloud, kp, d.spacing))
        return d.fallback
