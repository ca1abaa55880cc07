"""Pose uncertainty (#18): the covariance against Monte Carlo, degeneracy warnings naming the free motion, the
deviation uncertainty, FDI numbers, and the interactive 3D view opened in headless Chromium."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from browser import screenshot
from conftest import run_cli, shared
from scanreg.geometry import Cloud, make_T
from scanreg.eval.metrics import EvalParams
from scanreg.eval.uncertainty import bootstrap_spread, degeneracy_warning, pose_covariance, relative_motion


def bumpy_surface(n=3000, seed=0):
    """A closed bumpy blob: points and outward unit normals (every motion is constrained)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = np.array([3.0, 2.0, 1.2])
    p = u * a
    nrm = u / a ** 2
    return p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def solve_pose(p, q, n):
    """One linearised point-to-plane step about the centroid of p: x = (w, t) minimising |J x + r|^2."""
    c = p.mean(axis=0)
    J = np.hstack([np.cross(p - c, n), n])
    r = np.einsum("ij,ij->i", p - q, n)
    return np.linalg.lstsq(J, -r, rcond=None)[0]


def test_covariance_matches_monte_carlo():
    """The analytic covariance predicts the spread of the poses fitted to re-noised residuals: a wrong
    Jacobian, pivot or residual scaling would miss by far more than the 15 % allowed."""
    p, n = bumpy_surface()
    sigma = 0.02
    rng = np.random.default_rng(1)
    xs, pcs = [], []
    for _ in range(400):
        q = p - rng.normal(0, sigma, len(p))[:, None] * n  # the source sits off the target along the normal
        xs.append(solve_pose(p, q, n))
        pcs.append(pose_covariance(p, q, n))
    emp = np.cov(np.array(xs).T)
    pc = pcs[0]
    assert pc.residual_sigma == pytest.approx(sigma, rel=0.1)
    assert np.sqrt(np.trace(emp[:3, :3])) == pytest.approx(np.radians(pc.sigma_rot_deg), rel=0.15)
    assert np.sqrt(np.trace(emp[3:, 3:])) == pytest.approx(pc.sigma_trans, rel=0.15)
    assert pc.condition > 0.05 and degeneracy_warning(pc, 1e-3) is None
    # per point: the spread of J_i x over the fits is point_sigma
    J = pc.jacobian(p[:5], n[:5])
    emp_pt = np.std(np.array(xs) @ J.T, axis=0)
    np.testing.assert_allclose(pc.point_sigma(p[:5], n[:5]), emp_pt, rtol=0.2)
    # the mean of many points moves with the pose: its sigma is that of the mean Jacobian, not sigma/sqrt(N)
    assert pc.mean_sigma(p, n) == pytest.approx(np.std(np.array(xs) @ pc.jacobian(p, n).mean(axis=0)), rel=0.2)


def test_relative_motion_and_bootstrap_spread():
    c = np.array([10.0, 0, 0])
    T = make_T(np.eye(3), np.zeros(3))
    R = np.array([[np.cos(0.01), -np.sin(0.01), 0], [np.sin(0.01), np.cos(0.01), 0], [0, 0, 1]])
    T2 = make_T(R, np.array([0.0, 0.0, 0.3]))
    ang, shift = relative_motion(T2, T, c)
    assert ang == pytest.approx(np.degrees(0.01))
    assert shift == pytest.approx(np.hypot(0.3, np.linalg.norm(R @ c - c)))
    s = bootstrap_spread([T2, T], T, c)
    assert s["pose_bootstrap_rot_deg"] == pytest.approx(np.degrees(0.01) / np.sqrt(2))


def cylinder(n=4000, seed=0, noise=0.01):
    rng = np.random.default_rng(seed)
    th, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-5, 5, n)
    nrm = np.c_[np.cos(th), np.sin(th), np.zeros(n)]
    p = 2.0 * nrm + np.c_[np.zeros(n), np.zeros(n), z]
    return p + rng.normal(0, noise, n)[:, None] * nrm, p, nrm


def test_sliding_cylinder_warns_naming_the_axis(capsys):
    """A cylinder registered to itself: sliding along and turning about its axis (z) change nothing. The pose
    covariance from the pairs the fine stage keeps at the final pose (every point paired with its noise-free
    twin on the cylinder, no rejection), as the runner computes it."""
    from scanreg.runner.steps import pose_from_pairs
    from scanreg.types import Correspondences

    moved, q, nrm = cylinder()
    pairs = Correspondences(source=moved, target=q, normals=nrm, distances=np.linalg.norm(moved - q, axis=1))
    pc = pose_from_pairs(pairs, EvalParams())
    m = pc.metrics()
    assert m["pose_condition"] < 1e-6
    line = capsys.readouterr().out.strip()
    assert line.count("\n") == 0 and line.startswith("warning: pose poorly constrained")
    assert "translation along (0.00, 0.00, 1.00)" in line and "rotation about (0.00, 0.00, 1.00)" in line
    assert len(pc.free_directions(1e-3)) == 2


def test_flat_patch_warns_in_plane():
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-5, 5, (3000, 2)), rng.normal(0, 0.01, 3000)]
    n = np.tile([0.0, 0, 1], (3000, 1))
    pc = pose_covariance(p, p * [1, 1, 0], n)
    msg = degeneracy_warning(pc, 1e-3)
    assert pc.condition < 1e-6 and msg is not None
    free = pc.free_directions(1e-3)
    assert len(free) == 3 and "rotation about (0.00, 0.00, 1.00)" in msg
    assert sum(f.startswith("translation along") for f in free) == 2
    assert all(f.endswith(", 0.00)") or f.endswith(", -0.00)") for f in free if f.startswith("translation"))


def test_universal_to_fdi():
    from scanreg.stages.data.dental import universal_to_fdi

    assert [universal_to_fdi(n) for n in (1, 8, 9, 16, 17, 24, 25, 32)] == [18, 11, 21, 28, 38, 31, 41, 48]
    assert len({universal_to_fdi(n) for n in range(1, 33)}) == 32


def test_tolerance_shares_need_confidence():
    from scanreg.eval.deviation import tolerance_shares

    p = EvalParams(deviation_tolerance=0.05, deviation_confidence=0.95)
    dev = np.array([0.04, 0.06, 0.2, -0.2])
    sig = np.array([0.01, 0.01, 0.01, 0.1])
    s = tolerance_shares(dev, sig, p)
    assert s["dev_over_50um_share"] == 0.75
    assert s["dev_over_50um_sure_share"] == 0.25  # 0.06 - 1.645*0.01 < 0.05; -0.2 with sigma 0.1 not sure


def arch_view(tmp_path: Path) -> Path:
    """A horseshoe of 14 numbered 'teeth' 50 um outside a target, through evaluate_deviation and write_view."""
    from scanreg.geometry import ClosestPoints
    from scanreg.eval.deviation import evaluate_deviation
    from scanreg.eval.view3d import write_view

    rng = np.random.default_rng(0)
    th = rng.uniform(0.1 * np.pi, 0.9 * np.pi, 20000)
    h = rng.uniform(0, 5, 20000)
    tgt = np.c_[25 * np.cos(th), 20 * np.sin(th), h]
    nrm = np.c_[np.cos(th), np.sin(th), np.zeros_like(th)]
    src = tgt + 0.05 * nrm * np.sign(np.cos(th))[:, None]
    target = Cloud(tgt, nrm)
    labels = np.array([31, 32, 33, 34, 35, 36, 37, 41, 42, 43, 44, 45, 46, 47])
    part = labels[np.minimum((th - 0.1 * np.pi) / (0.8 * np.pi) * 14, 13).astype(int)]

    class CP(ClosestPoints):
        def query(self, q, max_distance=None):
            closest, d, n, _ = super().query(q, max_distance)
            return closest, d, n, self._ids  # the "face" (here: labelled point) of each closest point

    cp = CP(target)
    cp._ids = np.arange(len(tgt))  # the source point i lies over target point i
    # a fixed colour range of ±100 µm: the 50 µm deviations in light red and blue (the range from the data, ±50 µm,
    # would draw them in the map's darkest colours)
    p = EvalParams(deviation_map=True, deviation_max_angle_deg=None, deviation_range=0.1)
    pc = pose_covariance(src, tgt, nrm)
    m, paths, view = evaluate_deviation(tmp_path, Cloud(src, nrm), Cloud(src, nrm), cp, part, p, "tooth", pose=pc)
    assert (tmp_path / "deviation_teeth.csv").exists() and "dev_pose_sigma_median_um" in m
    return write_view(tmp_path / "view3d.html", target, Cloud(src + [40.0, 0, 0], nrm), np.eye(4), src, None, view, p)


def coloured_share(img: np.ndarray) -> tuple[float, float]:
    """Shares of clearly red and clearly blue pixels (the deviation colours) in the 3D scene: the upper left
    part of the page, without the colour bar (right) and the table (below)."""
    h, w = img.shape[:2]
    img = img[: int(0.7 * h), : int(0.8 * w)]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    red = (r > 150) & (r - b > 60) & (r - g > 40)
    blue = (b > 120) & (b - r > 60)
    return float(red.mean()), float(blue.mean())


def test_view_is_self_contained_and_renders_offline(tmp_path):
    html = arch_view(tmp_path)
    text = html.read_text()
    assert "<script src=\"http" not in text and "cdn.plot.ly" not in text.split("</script>")[-1]
    assert 2e6 < html.stat().st_size < 6e6  # plotly.js packed: 2.0 MB (it was 4.8 MB, the page 6 MB)
    assert "tooth numbers (FDI)" in text and "signed deviation [\\u00b5m]" in text
    img = screenshot(html, tmp_path / "shot.png")
    red, blue = coloured_share(img)
    assert red > 0.001 and blue > 0.001, (red, blue)  # both sides of the arch drawn in deviation colours


@pytest.mark.slow
def test_dental_pose_sigmas_agree_with_the_bootstrap(tmp_path):
    """The dental case: analytic sigmas within a factor 2 of a bootstrap (source points resampled, the fine
    stage rerun), the HTML view written and rendered."""
    shared("open_full_jaw_p26/mandible/tooth_18.ply")
    out = tmp_path / "run"
    r = run_cli(["experiment=dental", "tracking=none", "evaluate.pose_bootstrap=8", f"hydra.run.dir={out}"],
                tmp_path, timeout=900)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    for a, b in (("pose_sigma_rot_deg", "pose_bootstrap_rot_deg"), ("pose_sigma_trans", "pose_bootstrap_trans")):
        assert 0.5 < res[a] / res[b] < 2.0, (a, res[a], b, res[b])
    assert res["pose_condition"] > 1e-3 and "poorly constrained" not in r.stdout
    assert res["dev_mean_sigma_um"] > 0 and "dev_over_50um_sure_share" in res
    import pandas as pd

    t = pd.read_csv(out / "deviation_teeth.csv")
    assert {"tooth", "side", "mean_um", "mean_sigma_um"} <= set(t.columns)
    assert set(t["tooth"]) <= set(range(31, 39)) | set(range(41, 49))  # FDI, mandible
    html = out / "view3d.html"
    assert html.exists() and html.stat().st_size < 15e6
    if shutil.which("chromium") or shutil.which("chromium-browser"):
        red, blue = coloured_share(screenshot(html, tmp_path / "dental.png"))
        assert red + blue > 0.002, (red, blue)


def test_pipeline_on_a_cylinder_logs_the_free_axis(tmp_path):
    """The whole pipeline on a cylinder registered to itself (no repair, no coarse stage; point-to-point ICP, as
    point-to-plane refuses the exactly singular system): a poor
    pose_condition in result.json and one warning line naming the cylinder's axis (z)."""
    from scanreg.geometry import Mesh
    from scanreg.io import write_ply

    th, z = np.meshgrid(np.linspace(0, 2 * np.pi, 90, endpoint=False), np.linspace(-5, 5, 40))
    v = np.c_[2 * np.cos(th.ravel()), 2 * np.sin(th.ravel()), z.ravel()]
    i, j = np.meshgrid(np.arange(89 + 1), np.arange(39))
    a = (j * 90 + i).ravel()
    b = (j * 90 + (i + 1) % 90).ravel()
    f = np.r_[np.c_[a, b, a + 90], np.c_[b, b + 90, a + 90]]
    write_ply(tmp_path / "cyl.ply", Mesh(v, f))
    out = tmp_path / "run"
    r = run_cli([f"data.source={tmp_path / 'cyl.ply'}", f"data.target={tmp_path / 'cyl.ply'}", "repair=none",
                 "coarse=none", "icp=horn", "tracking=none", "evaluate.view_html=false", f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    assert res["pose_condition"] < 1e-3, res["pose_condition"]
    lines = [x for x in r.stdout.splitlines() if "poorly constrained" in x]
    assert len(lines) == 1 and "(0.00, 0.00, 1.00)" in lines[0], r.stdout


def test_labels_units_and_options():
    from scanreg.eval.deviation import display_unit, fdi_side, plural
    from scanreg.errors import ConfigError
    from scanreg.stages.registry import make_params

    assert [fdi_side(n) for n in (11, 18, 21, 28, 31, 38, 41, 48)] == ["right"] * 2 + ["left"] * 4 + ["right"] * 2
    assert plural("tooth") == "teeth" and plural("part") == "parts" and display_unit("um") == "µm"
    with pytest.raises(ConfigError, match="deviation_confidence must be in"):
        make_params(EvalParams, {"deviation_confidence": 1.5}, "evaluate")


def test_pairs_with_a_nan_normal_give_the_covariance_of_the_rest():
    """A degenerate face's NaN normal among the final pairs stopped the run ('Eigenvalues did not converge', an
    internal error): those pairs are left out of the covariance, which is then that of the others."""
    from types import SimpleNamespace

    from scanreg.eval.uncertainty import pairs_covariance, pose_covariance

    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3))
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    q = p + 0.01 * rng.normal(size=(200, 3))
    bad = n.copy()
    bad[[3, 50]] = np.nan
    pc = pairs_covariance(SimpleNamespace(source=p, target=q, normals=bad))
    keep = np.ones(200, bool)
    keep[[3, 50]] = False
    assert np.array_equal(pc.cov, pose_covariance(p[keep], q[keep], n[keep]).cov) and np.isfinite(pc.cov).all()
    few = bad[:8].copy()
    few[5] = np.nan  # 6 finite pairs left
    assert pairs_covariance(SimpleNamespace(source=p[:8], target=q[:8], normals=few)) is None
    assert pairs_covariance(SimpleNamespace(source=p, target=q, normals=None)) is None
