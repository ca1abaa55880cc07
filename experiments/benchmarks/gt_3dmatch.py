"""Check (issue #13): how well does the shared 3DMatch pair's ``gt.npy`` agree with its own data?

    ./run python experiments/benchmarks/gt_3dmatch.py        # writes experiments/benchmarks/gt_3dmatch.md

Issue #13 asks for a translation error under 5 cm on this pair. Every fine stage tried settles 8-11 cm (at the
camera origin) from ``gt.npy``. This script asks whether that is the fine stage's fault or the ground truth's:

1. every ICP variant (scanreg's point_to_plane (default), horn, gicp; Open3D point-to-plane with a Tukey kernel)
   started *at* ``gt.npy``, in both directions (source onto target and target onto source, inverted): if the two
   directions agree with each other to ~1 cm but not with ``gt.npy``, the data define a pose that is not gt.npy's;
2. the data's fit (Open3D ``evaluate_registration`` at 3 and 5 cm: fitness and inlier RMSE) along the straight
   path from ``gt.npy`` (a = 0) to the default fine stage's pose (a = 1), extended either side;
3. the analytic point-to-plane sigma of the translation at that pose, per principal direction, and the
   gt-vs-ICP shift at the overlap's centroid resolved on those directions.

Every scanreg ICP runs with its Params dataclass's defaults, which since #32 are the CLI's: point_to_plane
iterates on a quarter of the points first (``initial_share`` 0.25; the gt_3dmatch.md measured before #32 had it
at 1, and is reproduced bit for bit with 1).

Skips with a message when ../shared/data/3dmatch_pair is absent.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data" / "3dmatch_pair"


def errors(T: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres at the target frame's origin) of T against G."""
    from scanreg.geometry import transform_errors

    return transform_errors(T, G)


def main() -> int:
    if not DATA.is_dir():
        print(f"skipped: {DATA} is absent (the shared data folder holds the 3DMatch pair)")
        return 0
    import open3d as o3d

    from scanreg.geometry import Cloud, apply_T, estimate_normals, estimate_spacing
    from scanreg.stages.registry import ICP, load_all, make_params
    from scanreg.types import RunContext

    src, ref, gt = (np.load(DATA / f) for f in ("src.npy", "ref.npy", "gt.npy"))
    load_all()
    reg = o3d.pipelines.registration

    def o3d_cloud(x):
        p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x))
        p.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
        return p

    S, R = o3d_cloud(src), o3d_cloud(ref)
    clouds = {}
    for name, x in (("src", src), ("ref", ref)):
        clouds[name] = Cloud(x, estimate_normals(x))
    ctx = RunContext(seed=0, run_dir=None)
    spacing = max(estimate_spacing(src, np.random.default_rng(1)), estimate_spacing(ref, np.random.default_rng(2)))

    def ours(variant, target, source, T0):
        cls = ICP.get(variant)
        stage = cls(make_params(cls.Params, {}, f"icp={variant}"))
        return stage.refine(target, source, T0, spacing, ctx).T_target_source

    def open3d(target, source, T0, thr=0.05):
        return np.asarray(reg.registration_icp(source, target, thr, T0, reg.TransformationEstimationPointToPlane(
            reg.TukeyLoss(k=thr)), reg.ICPConvergenceCriteria(1e-9, 1e-9, 200)).transformation)

    lines = ["# The shared 3DMatch pair: fine stages started at gt.npy", "",
             f"Produced by `experiments/benchmarks/gt_3dmatch.py` (spacing {spacing * 100:.2f} cm; gt.npy is a "
             f"{np.degrees(Rotation.from_matrix(gt[:3, :3]).magnitude()):.1f}° / {np.linalg.norm(gt[:3, 3]):.2f} m motion).", "",
             "## 1. Every ICP, started at gt.npy, both directions", "",
             "| fine stage | src→ref vs gt (°, cm) | inv(ref→src) vs gt (°, cm) | the two directions apart (°, cm) |",
             "|---|---|---|---|"]
    fits = {}
    for name in ("point_to_plane", "horn", "gicp", "open3d_tukey_5cm"):
        if name.startswith("open3d"):
            Tf, Tb = open3d(R, S, gt), np.linalg.inv(open3d(S, R, np.linalg.inv(gt)))
        else:
            Tf = ours(name, clouds["ref"], clouds["src"], gt)
            Tb = np.linalg.inv(ours(name, clouds["src"], clouds["ref"], np.linalg.inv(gt)))
        fits[name] = Tf
        (a, b), (c, d), (e, f) = errors(Tf, gt), errors(Tb, gt), errors(Tf, Tb)
        lines.append(f"| {name} | {a:.2f}°, {b * 100:.1f} cm | {c:.2f}°, {d * 100:.1f} cm | {e:.2f}°, {f * 100:.1f} cm |")
        print(lines[-1], flush=True)

    T1 = fits["point_to_plane"]
    lines += ["", "## 2. The data's fit from gt.npy (a = 0) to the default fine stage's pose (a = 1)", "",
              "| a | fitness @3 cm | inlier RMSE @3 cm [cm] | fitness @5 cm | inlier RMSE @5 cm [cm] |", "|---|---|---|---|---|"]
    dr = (Rotation.from_matrix(gt[:3, :3]).inv() * Rotation.from_matrix(T1[:3, :3])).as_rotvec()
    for a in np.linspace(-0.5, 1.5, 9):
        T = np.eye(4)
        T[:3, :3] = (Rotation.from_matrix(gt[:3, :3]) * Rotation.from_rotvec(a * dr)).as_matrix()
        T[:3, 3] = (1 - a) * gt[:3, 3] + a * T1[:3, 3]
        e3, e5 = reg.evaluate_registration(S, R, 0.03, T), reg.evaluate_registration(S, R, 0.05, T)
        lines.append(f"| {a:+.2f} | {e3.fitness:.4f} | {e3.inlier_rmse * 100:.3f} | {e5.fitness:.4f} | {e5.inlier_rmse * 100:.3f} |")

    ev = reg.evaluate_registration(S, R, 0.05, T1)
    cs = np.asarray(ev.correspondence_set)
    p, q, n = apply_T(T1, src)[cs[:, 0]], ref[cs[:, 1]], np.asarray(R.normals)[cs[:, 1]]
    c = p.mean(0)
    J = np.hstack([np.cross(p - c, n), n])
    r = np.einsum("ij,ij->i", p - q, n)
    lam, V = np.linalg.eigh((J.T @ J)[3:, 3:])
    sigma = np.sqrt(r @ r / (len(r) - 6) / lam)
    E = gt @ np.linalg.inv(T1)
    shift = E[:3, :3] @ c + E[:3, 3] - c
    lines += ["", "## 3. Translation constraint at the default fine stage's pose", "",
              f"{len(r)} pairs within 5 cm. Analytic sigma per principal direction (weakest first): "
              + ", ".join(f"{s * 100:.3f} cm" for s in sigma)
              + f". gt.npy's pose moves the overlap's centroid by {np.linalg.norm(shift) * 100:.1f} cm from the fine "
              "stage's pose; along those directions: " + ", ".join(f"{s * 100:+.1f} cm" for s in V.T @ shift) + ".",
              "", "Reading: if both directions of every ICP agree with each other to about a centimetre, and the fit "
              "improves monotonically from a = 0 to a = 1, the data define a pose that differs from gt.npy by the "
              "amounts in table 1; a translation error under 5 cm at the camera origin is then a statement about "
              "gt.npy, not about the registration. 3DMatch itself judges a registration by the RMSE of ground-truth "
              "correspondences < 0.2 m, and SOURCE.txt of this pair recommends RRE < 15°, RTE < 0.3 m."]
    out = ROOT / "experiments" / "benchmarks" / "gt_3dmatch.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines[lines.index("## 2. The data's fit from gt.npy (a = 0) to the default fine stage's pose (a = 1)"):]))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
