"""Point-to-point ICP: ``icp=horn`` (Besl-McKay with Horn's quaternions, the paper's) and ``icp=anderson``
(the same fixed point, accelerated by Anderson mixing)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.geometry import apply_T, horn_quaternion, make_T, rotate_normals
from scanreg.stages.icp.base import IcpBase, IcpParams, PairLimit, _compress, _rms
from scanreg.stages.registry import ICP
from scanreg.types import IcpResult


@ICP.register("horn")
class Horn(IcpBase):
    """Besl-McKay point-to-point ICP: closest target point (or closest point on the target's triangles) for
    every source point, the rigid transform by Horn's quaternion closed form (weighted under a robust kernel),
    until the RMS error changes by less than ``tau`` at the final pair limit."""

    @dataclass
    class Params(IcpParams):
        pass

    def step(self, moved, q, qn, ok, w):
        return horn_quaternion(q, moved, w) if ok.all() else horn_quaternion(*_compress(ok, q, moved), w)


@ICP.register("anderson")
class Anderson(IcpBase):
    """Point-to-point ICP accelerated by Anderson mixing (AA-ICP; Pavlov et al. 2018, with the energy safeguard
    of Zhang et al. 2021). The fixed point is Besl-McKay/Horn's. The transform is a 6-vector (rotation vector,
    translation); each iterate mixes the last ``memory`` ICP updates. A mixed iterate whose RMS is not below the
    last accepted one is replaced by the plain ICP step, so the accepted RMS never increases at a given pair
    limit; the mixing restarts when the limit tightens (the fixed-point map changes)."""

    @dataclass
    class Params(IcpParams):
        memory: int = 5
        """Number of past iterates mixed (Anderson window)."""

        def check(self):
            super().check()
            if self.memory < 1:
                raise ValueError(f"memory must be >= 1, got {self.memory}")

    @staticmethod
    def _vec(T):
        return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])

    @staticmethod
    def _mat(x):
        return make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])

    def iterate(self, target, source, T_init, cp, tau, limit: PairLimit, update=None) -> IcpResult:
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        x = self._vec(T_init)
        G_hist: list[np.ndarray] = []
        F_hist: list[np.ndarray] = []
        history: list[float] = []
        accepted_rms, g_acc = np.inf, None
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            T = self._mat(x)
            moved = apply_T(T, src)
            mn = rotate_normals(T, sn)
            q, d, qn, ok = self.pairs(moved, mn, cp, limit.limit, it)
            rms = _rms(d, ok)
            if rms > accepted_rms and g_acc is not None:
                # the mixed iterate made things worse: take the plain ICP step from the last accepted iterate
                G_hist, F_hist = [], []
                x = g_acc
                T = self._mat(x)
                moved = apply_T(T, src)
                mn = rotate_normals(T, sn)
                q, d, qn, ok = self.pairs(moved, mn, cp, limit.limit, it)
                rms = _rms(d, ok)
            history.append(rms)
            if it > 0:
                if limit.settled and abs(history[-2] - history[-1]) < tau:
                    converged = True
                    break
                if limit.advance(history[-2], history[-1], tau):
                    ok = self.select(d, mn, qn, limit.limit, it)
                    history[-1] = rms = _rms(d, ok)
                    G_hist, F_hist = [], []
            if it == self.p.max_iterations:
                break
            w = self.weights(np.compress(ok, d), limit)
            g = self._vec(horn_quaternion(*_compress(ok, q, moved), w) @ T)  # plain ICP map G(x)
            accepted_rms, g_acc = rms, g
            G_hist.append(g)
            F_hist.append(g - x)
            if len(G_hist) > self.p.memory + 1:
                G_hist.pop(0)
                F_hist.pop(0)
            x = g
            if len(G_hist) > 1:
                dF = np.diff(np.array(F_hist), axis=0).T
                dG = np.diff(np.array(G_hist), axis=0).T
                try:
                    gamma = np.linalg.lstsq(dF, F_hist[-1], rcond=None)[0]
                    if np.all(np.isfinite(gamma)):
                        x = g - dG @ gamma
                except np.linalg.LinAlgError:  # no mixing this time: the plain step
                    pass
            iterations += 1
        if limit.limit is not None and limit.floor is not None and limit.limit > limit.floor:
            d = np.where(d <= limit.floor, d, np.inf)
        return IcpResult(self._mat(x), iterations, history, converged, final_distances=d, final_limit=limit.limit)
