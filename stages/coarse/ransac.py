"""Locally optimised RANSAC (Chum et al. 2003) over point correspondences: the estimator of ``coarse=lo_ransac``.

:func:`lo_ransac` draws minimal samples of 3 correspondences (in seeded, vectorised batches), counts inliers
within the threshold, and adapts the number of hypotheses so that the chance of missing the best model is at
most ``miss_probability``. Each new best model is locally optimised (least squares on its inliers, repeated); a
final fit over the inliers minimises ``sum |R p1 + t - p0|^2 + w |R n1 - n0|^2`` (points and normals).

Two ways of drawing samples (``sampling``): ``uniform`` draws 3 correspondences at random (plain RANSAC);
``guided`` draws the first at random and the other two among those rigidly compatible with it and with each
other, which finds an all-inlier sample far more often when inliers are rare.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from scanreg.geometry import apply_T, horn_quaternion, kabsch_batch, rigid_points_normals, row_norms


@dataclass
class RansacResult:
    T_target_source: np.ndarray
    inliers: np.ndarray
    """Mask over the correspondences: within the threshold at the final model."""
    hypotheses: int
    """Hypotheses drawn."""
    all_inlier_probability: float = 0.0
    """The probability that one hypothesis is all-inlier, as the adaptive stopping rule last estimated it from
    the best model (0 before any model)."""


PER_SEED = 8
"""Guided sampling: samples drawn per seed correspondence."""
SEEDS = 64
"""Guided sampling: seed correspondences per batch."""


def lo_ransac(P0: np.ndarray, P1: np.ndarray, N0: np.ndarray | None, N1: np.ndarray | None, thr: float,
              p, seed: int) -> RansacResult:
    """RANSAC over the correspondences ``P1[i] -> P0[i]`` (target points ``P0``, source points ``P1``, their
    normals ``N0``, ``N1`` or None), inlier threshold ``thr`` (input units), the parameters ``p`` of
    ``coarse=lo_ransac`` (:class:`scanreg.stages.coarse.lo_ransac.LoRansac.Params`), seeded by ``seed``."""
    search = _Search(P0, P1, thr, p)
    rng = np.random.default_rng([seed, 404])
    if p.sampling == "guided":
        search.guided(rng)
    else:
        search.uniform(rng)
    if search.best_inl.sum() >= 3:
        search.final_fit(N0, N1)
    return RansacResult(search.best_T, search.best_inl, search.drawn, search.q)


class _Search:
    """One RANSAC search: the correspondences, the best model so far and the hypotheses drawn."""

    def __init__(self, P0: np.ndarray, P1: np.ndarray, thr: float, p):
        self.P0, self.P1, self.thr, self.p = P0, P1, thr, p
        self.M = len(P0)
        self.best_T, self.best_inl, self.best_n = np.eye(4), np.zeros(self.M, bool), -1
        self.needed, self.drawn = p.max_iterations, 0
        self.q = 0.0  # the all-inlier probability the stopping rule last used

    def more(self) -> bool:
        """Whether to draw another batch (the adaptive count, at least ``min_iterations``, at most
        ``max_iterations``)."""
        return self.drawn < max(self.needed, self.p.min_iterations) and self.drawn < self.p.max_iterations

    def accept(self, T_cand: np.ndarray) -> None:
        """A candidate that beats the best, locally optimised (:func:`refine`), becomes the best model."""
        self.best_T, self.best_inl = refine(self.P0, self.P1, self.thr, T_cand, self.p.lo_iterations)
        self.best_n = int(self.best_inl.sum())

    def needed_for(self, q: float) -> int:
        """Hypotheses needed to draw one all-inlier sample with probability 1 - ``miss_probability`` when each
        is one with probability ``q``: ceil(log(mu) / log(1 - q))."""
        if q <= 0:
            return self.p.max_iterations
        return int(np.ceil(np.log(self.p.miss_probability) / np.log(max(1e-12, 1 - q))))

    def valid(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Samples (B, 3, 3) whose side lengths agree (rigidity) and that are not near-collinear."""
        e1 = np.linalg.norm(a - np.roll(a, 1, axis=1), axis=2)
        e0 = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2)
        area = np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
        return (np.abs(e1 - e0) < self.thr).all(axis=1) & (area > self.thr * self.thr * 0.5)

    def uniform(self, rng: np.random.Generator) -> None:
        """Plain RANSAC: 3 correspondences at random per hypothesis, ``batch`` at a time; all-inlier with
        probability w^3 (w the inlier share of the best model)."""
        P0, P1, M, thr = self.P0, self.P1, self.M, self.thr
        while self.more():
            B = min(self.p.batch, self.p.max_iterations - self.drawn)
            idx = np.stack([rng.choice(M, 3, replace=False) for _ in range(B)]) if M < 8 else \
                rng.integers(0, M, size=(B, 3))
            self.drawn += B
            a, b = P1[idx], P0[idx]
            good = self.valid(a, b)  # a sample that repeats a correspondence has no area: not valid
            if not good.any():
                continue
            Ts = kabsch_batch(b[good], a[good])
            moved = np.einsum("bij,mj->bmi", Ts[:, :3, :3], P1) + Ts[:, None, :3, 3]
            counts = (np.linalg.norm(moved - P0[None], axis=2) < thr).sum(axis=1)
            k = int(np.argmax(counts))
            if counts[k] > self.best_n:
                self.accept(Ts[k])
                self.q = (self.best_n / M) ** 3
                self.needed = self.needed_for(self.q)

    def guided(self, rng: np.random.Generator) -> None:
        """Guided sampling. Each seed correspondence i defines the set C_i of correspondences rigidly compatible
        with it (|d1(i, c) - d0(i, c)| < 2 thr: every inlier of a model that has i as an inlier is in it).
        ``PER_SEED`` samples (i, j, k) are drawn with j, k in C_i and compatible with each other, and each
        hypothesis is scored on C_i only (its inliers are there). A seed yields an all-inlier sample with
        probability q = w (1 - (1 - r^2)^T), w the inlier share, r the inlier share of C_i."""
        M, thr = self.M, self.thr
        r_est = 0.0
        while self.more():
            seeds = rng.integers(0, M, size=SEEDS)
            self.drawn += len(seeds) * PER_SEED
            diff = np.abs(self._d1(seeds) - self._d0(seeds))
            hypotheses = self._guided_batch(rng, seeds, diff)
            if hypotheses is None:
                continue
            Ts, counts = hypotheses
            k = int(np.argmax(counts))
            if counts[k] > self.best_n:
                self.accept(Ts[k])
                I = np.flatnonzero(self.best_inl)
                if len(I) >= 3:  # r: inlier share of the compatible sets of the best model's inliers
                    sub = I[rng.permutation(len(I))[:32]]
                    Cs = np.abs(self._d1(sub) - self._d0(sub)) < 2 * thr
                    r_est = float((Cs[:, I].sum(axis=1) / Cs.sum(axis=1)).mean())  # each row holds its own
                self.q = self.best_n / M * (1 - (1 - r_est ** 2) ** PER_SEED)
                self.needed = self.needed_for(self.q) * PER_SEED

    def _d1(self, rows: np.ndarray) -> np.ndarray:
        return cdist(self.P1[rows], self.P1[np.arange(self.M)])

    def _d0(self, rows: np.ndarray) -> np.ndarray:
        return cdist(self.P0[rows], self.P0[np.arange(self.M)])

    def _guided_batch(self, rng: np.random.Generator, seeds: np.ndarray,
                      diff: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """One batch of guided samples from ``seeds`` (vectorised over the seeds; ragged sets padded, masks
        mark the members): the hypotheses and their inlier counts on their seeds' compatible sets, or None when
        the batch yields no valid sample. ``diff``: |d1 - d0| from each seed to every correspondence."""
        P0, P1, thr = self.P0, self.P1, self.thr
        S, rows = len(seeds), np.arange(len(seeds))
        # j, k among the correspondences whose distance to the seed agrees within thr
        close = diff < thr
        close[rows, seeds] = False
        close_idx, member, n_close = _padded_members(close)
        if n_close.max() < 2:
            return None
        jpos = (rng.random((S, PER_SEED)) * n_close[:, None]).astype(np.int64)  # < n_close: random() < 1
        js = np.take_along_axis(close_idx, jpos, axis=1)  # (S, PER_SEED)
        # k compatible with j as well (and not j)
        e1 = row_norms(P1[js][:, :, None, :] - P1[close_idx][:, None, :, :])
        e0 = row_norms(P0[js][:, :, None, :] - P0[close_idx][:, None, :, :])
        ck = (np.abs(e1 - e0) < thr) & member[:, None, :] & (close_idx[:, None, :] != js[:, :, None])
        kpos = np.argmax(np.where(ck, rng.random(ck.shape), -np.inf), axis=2)
        ok = ck.any(axis=2)
        if not ok.any():
            return None
        ks = np.take_along_axis(close_idx, kpos, axis=1)
        idx = np.stack([np.broadcast_to(seeds[:, None], js.shape), js, ks], axis=2)[ok]
        sid = np.broadcast_to(rows[:, None], js.shape)[ok]
        a, b = P1[idx], P0[idx]
        good = self.valid(a, b)
        if not good.any():
            return None
        Ts, sid = kabsch_batch(b[good], a[good]), sid[good]
        # each hypothesis scored on its seed's compatible set (every inlier of a model with the seed as an
        # inlier is there), 64 at a time (bounded memory)
        pool_idx, in_pool, _ = _padded_members(diff < 2 * thr)
        counts = np.empty(len(Ts), np.int64)
        for c0 in range(0, len(Ts), 64):
            sl = slice(c0, c0 + 64)
            pi = pool_idx[sid[sl]]
            res = P1[pi] @ Ts[sl, :3, :3].transpose(0, 2, 1) + (Ts[sl, None, :3, 3] - P0[pi])
            res *= res
            sq = res[..., 0] + res[..., 1] + res[..., 2]
            counts[sl] = ((sq < thr * thr) & in_pool[sid[sl]]).sum(axis=1)
        return Ts, counts

    def final_fit(self, N0: np.ndarray | None, N1: np.ndarray | None) -> None:
        self.best_T, self.best_inl = final_fit(self.P0, self.P1, N0, N1, self.thr, self.p.normal_weight,
                                               self.best_T, self.best_inl)


def inliers_at(T: np.ndarray, P0: np.ndarray, P1: np.ndarray, thr: float) -> np.ndarray:
    """Mask of the correspondences within ``thr`` at ``T``."""
    return np.linalg.norm(apply_T(T, P1) - P0, axis=1) < thr


def local_opt(P0: np.ndarray, P1: np.ndarray, thr: float, T: np.ndarray, inl: np.ndarray,
              rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """Least squares on the inliers ``inl`` of the model ``T``, re-selected, until they stop changing (``rounds``
    at most): the local optimisation of LO-RANSAC. Returns the last fit and its inliers (``T`` and ``inl`` when
    never fitted: no rounds, or fewer than 3 inliers)."""
    for _ in range(rounds):
        if inl.sum() < 3:
            break
        T = horn_quaternion(P0[inl], P1[inl])
        new = inliers_at(T, P0, P1, thr)
        if np.array_equal(new, inl):
            break
        inl = new
    return T, inl


def refine(P0: np.ndarray, P1: np.ndarray, thr: float, T: np.ndarray,
           rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """The candidate model ``T`` locally optimised (:func:`local_opt`, ``rounds`` at most) and its inliers; the
    candidate and its own inliers when the optimisation ends with fewer inliers."""
    inl = inliers_at(T, P0, P1, thr)
    T_lo, inl_lo = local_opt(P0, P1, thr, T, inl, rounds)
    if inl_lo.sum() < inl.sum():
        return T, inl
    return T_lo, inl_lo


def final_fit(P0: np.ndarray, P1: np.ndarray, N0: np.ndarray | None, N1: np.ndarray | None, thr: float,
              normal_weight: float, T: np.ndarray, inl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model ``T`` (inliers ``inl``) refitted over its inliers with points and normals (normals sign-aligned
    to the current fit), three times; the refit and its inliers when it loses none of the model's support,
    else ``T`` and ``inl``."""
    T0 = T
    for _ in range(3):
        cur = inliers_at(T, P0, P1, thr)
        if cur.sum() < 3:
            break
        n0 = n1 = None
        if N0 is not None and N1 is not None:  # (rigid_points_normals leaves them out at weight 0)
            n0, n1 = N0[cur], N1[cur]
            flip = np.einsum("ij,ij->i", n1 @ T[:3, :3].T, n0) < 0
            n1 = np.where(flip[:, None], -n1, n1)
        T = rigid_points_normals(P0[cur], P1[cur], n0, n1, normal_weight * thr * thr)
    new = inliers_at(T, P0, P1, thr)
    if new.sum() >= inl.sum():
        return T, new
    return T0, inl


def _padded_members(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of a boolean (S, M) mask: the column indices where it holds, in order, padded to the
    longest row (S, L); which of those are real members; and how many each row has."""
    n = mask.sum(axis=1)
    L = int(n.max())
    return np.argsort(~mask, axis=1, kind="stable")[:, :L], np.arange(L)[None, :] < n[:, None], n
