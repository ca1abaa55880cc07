"""Experiments, reports, the extra data providers and the dental case."""

import json
import re

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from conftest import ROOT, run_cli, shared, runs
from scanreg.app.config import compose
from scanreg.types import RunContext as Context
from scanreg.geometry import Cloud, Mesh, apply_T, invert_T, vertex_normals
from scanreg.stages.registry import DATA, conf_dir, load_all

CONF_DIR = conf_dir()


def test_experiments_are_sweeps_that_write_their_report():
    """Every experiment except the single dental run is a sweep (hydra.mode MULTIRUN) with its own MLflow
    experiment and a report, written to outputs/reports/ (never over the committed one in experiments/, which
    its header names: report.out=experiments/... only when asked)."""
    for p in sorted((CONF_DIR / "experiment").glob("*.yaml")):
        cfg = compose([f"experiment={p.stem}"], return_hydra_config=True)
        if p.stem == "dental":
            assert cfg.evaluate.deviation_map and cfg.coarse.name == "landmarks"
            continue
        if p.stem.startswith("tune_"):  # tuning: Optuna minimises the objective; its result is the sweeper's
            assert "optuna" in str(cfg.hydra.sweeper._target_).lower() and cfg.objective
            continue
        assert str(cfg.hydra.mode) == "RunMode.MULTIRUN", p.name
        assert cfg.report.enabled and cfg.report.out is None, p.name
        committed = re.search(r"add report\.out=(experiments/\S+)", p.read_text())
        assert committed and (ROOT / committed.group(1) / "report.md").exists(), p.name
        assert cfg.tracking.experiment != "scanreg", p.name
        assert cfg.hydra.sweeper.params, p.name


def test_report_block_matches_its_params():
    """The ``report`` and ``evaluate`` blocks are their Params dataclasses (``_report@report``,
    ``_evaluate@evaluate`` in config.yaml's defaults): every field, with its default."""
    from dataclasses import asdict, fields

    from scanreg.app.report.params import ReportParams
    from scanreg.eval.metrics import EvalParams

    defaults = list(OmegaConf.load(CONF_DIR / "config.yaml").defaults)
    assert "_report@report" in defaults and "_evaluate@evaluate" in defaults
    cfg = compose([])
    for block, params in (("report", ReportParams), ("evaluate", EvalParams)):
        assert set(cfg[block]) == {f.name for f in fields(params)}, block
        composed = OmegaConf.to_container(cfg[block], resolve=True)
        assert composed == asdict(params()), block


@pytest.mark.slow
def test_tiny_experiment_report_matches_result_json(tmp_path, mlflow_uri):
    """A two-run experiment run as one command: its report table holds the runs' own result.json values."""
    sweep = tmp_path / "sweep"
    r = run_cli(["-m", "data=synthetic", "data.n_points=4000", "sampler.n_points=2000,3000",
                 "tracking.experiment=tiny", "report.enabled=true", f"report.out={tmp_path / 'rep'}",
                 "report.group_by=[sampler.n_points]", "report.x=sampler.n_points",
                 "report.metrics=[icp_iterations,coarse_rotation_error_deg]", f"hydra.sweep.dir={sweep}"],
                tmp_path, mlflow_uri)
    assert r.returncode == 0, r.stderr
    assert "sweep [" in r.stdout and "2/2 jobs" in r.stdout  # the progress bar
    assert "done: success, rot " in r.stdout  # each job's outcome: whether a success (a 162-degree result was 'ok')
    table = pd.read_csv(tmp_path / "rep" / "report.csv")
    assert list(table["sampler.n_points"]) == [2000, 3000] and list(table["runs"]) == [1, 1]
    for job, (_, row) in enumerate(table.iterrows()):
        res = json.loads((sweep / str(job) / "result.json").read_text())
        assert row["rotation_error_deg_median"] == pytest.approx(res["rotation_error_deg"], rel=1e-12)
        assert row["translation_error_median"] == pytest.approx(res["translation_error"], rel=1e-12)
        assert row["time_coarse_s_median"] == pytest.approx(res["time_coarse_s"], rel=1e-12)
        assert row["success_rate"] == res["success"]
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## How this was produced" in md and "commit:" in md and "scanreg" in md
    assert (tmp_path / "rep" / "success.png").stat().st_size > 1000
    assert (tmp_path / "rep" / "error_time_vs_sampler.n_points.png").exists()
    # --compare-to puts two experiments side by side
    r2 = run_cli(["-m", "data=synthetic", "data.n_points=4000", "sampler.n_points=2000", "tracking.experiment=tiny2",
                  f"hydra.sweep.dir={tmp_path / 's2'}"], tmp_path, mlflow_uri)
    assert r2.returncode == 0, r2.stderr
    rep = run_cli(["--experiment", "tiny", "--compare-to", "tiny2", "--group-by", "sampler.n_points", "--uri",
                   mlflow_uri, "--out", str(tmp_path / "cmp")], tmp_path, module="scanreg.app.report.write")
    assert rep.returncode == 0, rep.stderr
    cmp = pd.read_csv(tmp_path / "cmp" / "compare.csv")
    assert "success_rate [tiny]" in cmp and "success_rate [tiny2]" in cmp and len(cmp) == 2


def test_an_experiment_for_another_data_provider_says_so_in_one_line():
    """A provider's parameters are typed (its Params): an experiment's provider-specific value (tune_lo_ransac's
    data.pair) does not merge into another provider, and the line names the key, the provider and its
    parameters."""
    from scanreg.errors import ConfigError

    with pytest.raises(ConfigError) as e:
        compose(["experiment=tune_lo_ransac", "data=synthetic"])
    msg = str(e.value)
    assert msg.startswith("data=synthetic: unknown parameter 'pair'; valid parameters:") and "mesh" in msg
    assert "set by a config file" in msg


def test_method_presets_switch_several_stages():
    cfg = compose(["method=open3d"])
    default = compose(["method=scanreg"])
    assert cfg.coarse.name == "open3d_fpfh_ransac" and cfg.icp.name == "open3d"
    assert default.coarse.name == "lo_ransac" and default.icp.name == "point_to_plane"


def test_stanford_pairs_and_overlap():
    shared("stanford_bunny/bun.conf")
    load_all()
    cls = DATA.get("stanford")
    a = cls(cls.Params(pair="bun000:bun045", pose_seed=3)).load(Context(0, ROOT))
    b = cls(cls.Params(source="bun045.ply", target="bun000.ply", pose_seed=3)).load(Context(0, ROOT))
    assert np.array_equal(a.T_gt, b.T_gt) and 0.85 < a.info["gt_overlap"] < 0.97
    from scanreg.errors import ConfigError

    with pytest.raises(ConfigError, match="TARGET:SOURCE"):
        cls(cls.Params(pair="bun000")).load(Context(0, ROOT))
    with pytest.raises(ConfigError, match="not in bun.conf"):
        cls(cls.Params(pair="bun000:nope")).load(Context(0, ROOT))


def test_3dmatch_pair_ground_truth():
    shared("3dmatch_pair/gt.npy")
    from scipy.spatial import cKDTree

    load_all()
    cls = DATA.get("pairs_3dmatch")
    inp = cls(cls.Params(pose_seed=2)).load(Context(0, ROOT))
    d, _ = cKDTree(inp.target.points).query(apply_T(inp.T_gt, inp.source.points))
    # the folder's README: 45 % of the source within 5 cm of the target at the true pose
    assert 0.40 < np.mean(d < 0.05) < 0.50
    R = inp.T_gt[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


# ------------------------------------------------------------------------------------------------- dental
@pytest.fixture(scope="module")
def dental_case():
    shared("open_full_jaw_p26/mandible/tooth_18.ply")
    load_all()
    cls = DATA.get("dental")
    p = cls.Params(noise=0.0, holes=0, flaps=0, pick_error=0.0, landmarks=5, pose_seed=4)
    return cls(p), cls(p).load(Context(0, ROOT))


def test_dental_case_geometry(dental_case):
    from scanreg.eval.deviation import signed_deviation
    from scanreg.mesh.topology import audit_mesh

    gen, inp = dental_case
    assert inp.target_labels is not None and set(np.unique(inp.target_labels)) == set(range(31, 39)) | set(range(41, 49))  # FDI (Universal 17-32)
    # the cast is one connected, oriented, open surface
    a = audit_mesh(inp.source)
    assert a["components"] == 1 and a["non_manifold_edges"] == 0 and a["inconsistent_orientation_edges"] == 0
    assert a["boundary_loops"] >= 1
    # noise-free: at the true pose, the crown tops lie on the CT surface (height-field interpolation only)
    back = Mesh(apply_T(inp.T_gt, inp.source.vertices), inp.source.faces)
    nrm = vertex_normals(back)
    axis = nrm.mean(axis=0)
    up = nrm @ (axis / np.linalg.norm(axis)) > 0.9  # facing the occlusal side
    from scanreg.geometry import ClosestPoints

    dev, _, ids = signed_deviation(back.vertices, nrm, ClosestPoints(Cloud(inp.target.vertices), inp.target))
    crown_tops = up & (np.abs(dev) < 0.5)
    assert crown_tops.mean() > 0.05
    assert np.median(np.abs(dev[crown_tops])) < 0.02  # mm
    # landmarks: exact cusp tips when the pick error is 0, consistent with the ground truth
    lt, ls = inp.landmarks
    assert len(lt) == 5
    assert np.abs(apply_T(inp.T_gt, ls) - lt).max() < 0.2  # nearest cast vertex to the tip (grid 0.15 mm)


def test_dental_pick_error_and_determinism():
    shared("open_full_jaw_p26/mandible/tooth_18.ply")
    load_all()
    cls = DATA.get("dental")
    a = cls(cls.Params(pick_error=1.0, landmarks=6, seed=2, pose_seed=1)).load(Context(0, ROOT))
    b = cls(cls.Params(pick_error=1.0, landmarks=6, seed=2, pose_seed=1)).load(Context(0, ROOT))
    assert np.array_equal(a.source.vertices, b.source.vertices) and np.array_equal(a.landmarks[1], b.landmarks[1])
    err = np.linalg.norm(apply_T(a.T_gt, a.landmarks[1]) - a.landmarks[0], axis=1)
    # two picks of 1 mm RMS each: sqrt(2) mm expected over many landmarks; this seed's 6 give 1.26 mm (without
    # the pick error: 0.07 mm, the snapping to the nearest vertex; a doubled error: about 2.5 mm)
    assert 1.0 < np.sqrt(np.mean(err ** 2)) < 1.9


def test_deviation_of_a_known_offset(tmp_path):
    """A surface moved 50 um along its normals deviates by +50 um; per-part statistics split by label."""

    from scanreg.eval.deviation import evaluate_deviation
    from scanreg.io import resolve_path, read_mesh
    from scanreg.eval.metrics import EvalParams

    mesh = read_mesh(resolve_path("pkg:pymeshlab/tests/sample_meshes/bunny.obj"))
    scale = 50.0 / np.ptp(mesh.vertices, axis=0).max()  # about 50 mm across
    mesh = Mesh(mesh.vertices * scale, mesh.faces)
    moved = Mesh(mesh.vertices + 0.05 * vertex_normals(mesh), mesh.faces)
    labels = (mesh.vertices[mesh.faces].mean(axis=1)[:, 0] > np.median(mesh.vertices[:, 0])).astype(int) + 1
    from scanreg.geometry import barycentric_sample

    pts, nrm, _ = barycentric_sample(moved, 20000, np.random.default_rng(0))
    from scanreg.geometry import ClosestPoints

    m, paths, _ = evaluate_deviation(tmp_path, Cloud(pts, nrm), moved, ClosestPoints(Cloud(mesh.vertices), mesh), labels,
                                  EvalParams(deviation_map=True), "part")
    assert m["dev_median_um"] == pytest.approx(50.0, abs=3.0)
    assert m["dev_within_100um"] > 0.95 and m["dev_p05_um"] > 30
    assert m["dev_rms_um_part_1"] == pytest.approx(50.0, abs=5.0) and m["dev_rms_um_part_2"] == pytest.approx(50, abs=5)
    names = {p.name for p in paths}
    assert {"deviation_map.ply", "deviation_histogram.png", "deviation_map.png", "deviation_parts.csv"} <= names
    from scanreg.io import read_geometry

    ply = read_geometry(tmp_path / "deviation_map.ply")
    assert len(ply.vertices) == len(moved.vertices)
    header = (tmp_path / "deviation_map.ply").read_bytes()[:400]
    assert b"property float quality" in header and b"property uchar red" in header


@pytest.mark.slow
def test_dental_experiment_end_to_end(tmp_path):
    shared("open_full_jaw_p26/mandible/tooth_18.ply")
    out = tmp_path / "run"
    r = run_cli(["experiment=dental", "tracking=none", f"hydra.run.dir={out}"], tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    # measured: 0.017 deg and 0.026 mm (the landmarks alone: 0.27 deg)
    assert res["rotation_error_deg"] < 0.052 and res["translation_error"] < 0.078, res
    assert res["coarse_rotation_error_deg"] > res["rotation_error_deg"]  # landmarks alone are worse
    assert res["repair_before_self_intersecting_faces"] > 0 and res["repair_after_self_intersecting_faces"] == 0
    assert res["repair_after_components"] == 1
    assert 10 < res["dev_rms_um"] < 200 and res["dev_compared_share"] > 0.2  # measured: 96.7 um, 50 %
    assert sum(k.startswith("dev_rms_um_tooth_") for k in res) == 14
    # every compared point lies on a tooth: the overall RMS is the teeth's, weighted by their points (the CSV)
    import pandas as pd

    teeth = pd.read_csv(out / "deviation_teeth.csv")
    assert len(teeth) == 14
    pooled = float(np.sqrt((teeth["points"] * teeth["rms_um"] ** 2).sum() / teeth["points"].sum()))
    assert res["dev_rms_um"] == pytest.approx(pooled, rel=1e-9)
    for _, row in teeth.iterrows():
        assert res[f"dev_rms_um_tooth_{int(row['tooth'])}"] == pytest.approx(row["rms_um"], rel=1e-9)
    for f in ("deviation_map.ply", "deviation_histogram.png", "deviation_map.png", "deviation_teeth.csv"):
        assert (out / f).exists(), f


def test_files_with_a_further_pose(tmp_path):
    """data=files can move the source by a seeded pose too; the ground truth and landmarks follow it."""
    from scanreg.geometry import random_pose

    rng = np.random.default_rng(0)
    tgt = rng.normal(size=(200, 3))
    T = random_pose(rng, 30.0, 0.5)
    np.save(tmp_path / "t.npy", tgt)
    np.save(tmp_path / "s.npy", apply_T(invert_T(T), tgt))
    np.savetxt(tmp_path / "T.txt", T)
    (tmp_path / "lm.csv").write_text("\n".join(",".join(map(str, [*tgt[i], *apply_T(invert_T(T), tgt[i:i + 1])[0]]))
                                               for i in range(4)))
    load_all()
    cls = DATA.get("files")
    kw = dict(source=str(tmp_path / "s.npy"), target=str(tmp_path / "t.npy"), gt=str(tmp_path / "T.txt"),
              landmarks=str(tmp_path / "lm.csv"))
    plain = cls(cls.Params(**kw)).load(Context(0, ROOT))
    assert np.array_equal(plain.T_gt, T)
    moved = cls(cls.Params(**kw, max_angle_deg=180.0, max_translation=0.5, pose_seed=5)).load(Context(0, ROOT))
    assert not np.allclose(moved.T_gt, T)
    assert np.allclose(apply_T(moved.T_gt, moved.source.points), tgt, atol=1e-9)
    assert np.allclose(apply_T(moved.T_gt, moved.landmarks[1]), moved.landmarks[0], atol=1e-9)


@pytest.mark.slow
def test_optuna_sweep_tunes_against_the_registration_error(tmp_path, mlflow_uri):
    """The tuning experiment as shipped (its Stanford pair; 3 trials on 2000 points instead of 12 on 10000): the
    synthetic case with '~data.pair' no longer composes (test_an_experiment_runs_on_another_data_provider)."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="./run installs hydra-optuna-sweeper")
    shared("stanford_bunny/bun.conf")
    sweep = tmp_path / "sweep"
    r = run_cli(["experiment=tune_lo_ransac", "sampler.n_points=2000", "hydra.sweeper.n_trials=3",
                 "tracking.experiment=optuna", f"hydra.sweep.dir={sweep}"], tmp_path, mlflow_uri, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    import yaml

    res = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert set(res["best_params"]) == {"coarse.distance_threshold", "salience.salient_radius"}
    df = runs(mlflow_uri, "optuna")
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    children = df[df["tags.mlflow.parentRunId"] == parent["run_id"]]
    assert len(children) == 3 and parent["status"] == "FINISHED"
    assert res["best_value"] == pytest.approx(children["metrics.rotation_error_deg"].min())


# ------------------------------------------------------------------------------------------- harder cases
def _plane_inputs(n: int = 4000, seed: int = 0):
    """A flat 10 x 10 square source mesh (2 triangles) and a cloud target on the same square: diagonal known."""
    from scanreg.types import Problem as Inputs

    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    mesh = Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), "square")
    rng = np.random.default_rng(seed)
    tgt = Cloud(np.c_[rng.uniform(0, 10, (n, 2)), np.zeros(n)], np.tile([0.0, 0, 1], (n, 1)), "target")
    return Inputs(mesh, tgt, np.eye(4), None, {"gt_overlap": 1.0})


def _perturb(inputs, **kw):
    from scanreg.stages.data.perturb import PerturbParams, perturb_inputs

    p = PerturbParams(**kw)
    p.check()
    return perturb_inputs(inputs, p)


def test_perturbations_off_keep_the_inputs():
    inp = _plane_inputs()
    assert _perturb(inp) is inp


def test_noise_has_the_stated_std():
    """add_noise is a share of the target's diagonal (about 10 sqrt(2)); the plane's z is pure noise."""
    out = _perturb(_plane_inputs(), add_noise=0.005, cloud_points=20000, perturb_seed=3)
    z = out.source.points[:, 2]
    assert out.source.n_points == 20000 and isinstance(out.source, Cloud)
    assert np.std(z) == pytest.approx(0.005 * 10 * np.sqrt(2), rel=0.03)
    diag = np.linalg.norm(np.ptp(out.target.points, axis=0))
    assert out.info["perturb_noise_std"] == pytest.approx(0.005 * diag, rel=1e-12)
    assert out.target.n_points == 4000 and np.all(out.target.points[:, 2] == 0)  # the target untouched
    nz = out.source.normals[:, 2]  # re-estimated from the noisy points, oriented like the face's +z
    assert np.all(nz >= 0) and np.median(nz) > 0.8 and np.mean(nz > 0.999) < 0.5


def test_outliers_are_the_stated_share_in_the_bbox():
    out = _perturb(_plane_inputs(), add_outliers=0.3, cloud_points=7000, perturb_seed=1)
    pts = out.source.points
    assert len(pts) == 10000 and out.info["perturb_source_outliers"] == 3000  # 3000 / 10000 = 30 %
    assert np.all((pts[:, :2] >= 0) & (pts[:, :2] <= 10)) and np.all(pts[:, 2] == 0)  # inside the (flat) bbox
    out_xy = pts[7000:, :2]  # the outliers come last: uniform over the 10 x 10 box (std 10 / sqrt(12) = 2.89)
    assert np.allclose(out_xy.mean(0), 5, atol=0.2) and np.allclose(out_xy.std(0), 10 / np.sqrt(12), atol=0.1)
    out = _perturb(_plane_inputs(), add_outliers=0.5, cloud_points=1000, perturb=("both"), perturb_seed=1)
    assert out.source.n_points == 2000 and out.target.n_points == 8000


def test_density_ratio_and_crop_counts():
    out = _perturb(_plane_inputs(), density_ratio=8, cloud_points=16000)
    assert out.source.n_points == 2000 and out.target.n_points == 4000  # target not perturbed: as it was
    out = _perturb(_plane_inputs(), crop=0.6, cloud_points=10000, perturb_seed=5)
    assert out.source.n_points == 6000 and out.info["perturb_source_crop_kept"] == pytest.approx(0.6)
    # by hand: the same seeded stream draws the 10000 points, then the plane's normal; the kept 6000 are the
    # ones lowest along it (one side of a plane)
    from scanreg.geometry import barycentric_sample

    rng = np.random.default_rng([5, 909, 0])
    full, _, _ = barycentric_sample(_plane_inputs().source, 10000, rng)
    d = rng.normal(size=3)
    h = full @ d
    low = np.sort(np.argsort(h, kind="stable")[:6000])
    assert np.array_equal(out.source.points, full[low]) and h[low].max() <= np.delete(h, low).min()
    # a cloud source keeps 1/ratio of its points
    from scanreg.types import Problem as Inputs

    inp = _plane_inputs()
    swapped = Inputs(inp.target, inp.source, np.eye(4), None, {})
    assert _perturb(swapped, density_ratio=8).source.n_points == 500


def test_perturbations_are_deterministic_per_seed():
    kw = dict(add_noise=0.002, add_outliers=0.2, crop=0.8, density_ratio=2, cloud_points=3000)
    a = _perturb(_plane_inputs(), perturb_seed=7, **kw)
    b = _perturb(_plane_inputs(), perturb_seed=7, **kw)
    c = _perturb(_plane_inputs(), perturb_seed=8, **kw)
    assert np.array_equal(a.source.points, b.source.points) and np.array_equal(a.source.normals, b.source.normals)
    assert not np.array_equal(a.source.points, c.source.points)


def test_stanford_perturbed_keeps_ground_truth():
    """The bunny with noise, outliers and a crop on the source: the true pose still maps the clean part of the
    source onto the target (within the noise)."""
    shared("stanford_bunny/bun.conf")
    from scipy.spatial import cKDTree

    load_all()
    cls = DATA.get("stanford")
    inp = cls(cls.Params(pair="bun000:bun045", pose_seed=1, add_noise=0.002, add_outliers=0.2, crop=0.7,
                         cloud_points=5000, perturb_seed=2)).load(Context(0, ROOT))
    assert isinstance(inp.source, Cloud) and inp.source.n_points == round(3500 / 0.8)
    d, _ = cKDTree(inp.target.vertices).query(apply_T(inp.T_gt, inp.source.points))
    diag = np.linalg.norm(np.ptp(inp.target.vertices, axis=0))
    assert np.median(d) < 3 * 0.002 * diag and inp.info["gt_overlap"] > 0.85
