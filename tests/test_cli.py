"""Level 3: the command line end to end (subprocesses): demo, file inputs, bad inputs, sweeps, reports."""

import json

import numpy as np
import pytest

from conftest import ROOT, run_cli, shared, runs
from scanreg.errors import ConfigError
from scanreg.geometry import Cloud, apply_T, random_pose, transform_geometry
from scanreg.io import read_mesh, write_ply, write_transform
from scanreg.geometry import barycentric_sample

RESULT_KEYS = {
    "T_target_source", "rms", "fitness", "n_source_points", "n_target_points", "icp_iterations",
    "time_load_s", "time_repair_s", "time_sample_s", "time_coarse_s", "time_icp_s", "time_total_s",
}




@pytest.mark.slow
def test_demo_recovers_random_pose_and_logs(tmp_path, mlflow_uri):
    out = tmp_path / "run"
    r = run_cli(["data=synthetic", f"hydra.run.dir={out}", "tracking.experiment=demo"], tmp_path, mlflow_uri)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    assert RESULT_KEYS | {"rotation_error_deg", "translation_error"} <= set(res)
    # measured: 0.0082 deg and 4.6e-5 of the diagonal (the coarse stage alone: 1.19 deg)
    assert res["rotation_error_deg"] < 0.025 and res["translation_error_rel"] < 1.4e-4, res
    assert res["repair_before_boundary_loops"] == 70 and res["repair_after_boundary_loops"] == 0
    T = np.loadtxt(out / "T_target_source.txt")
    assert np.array_equal(T, np.array(res["T_target_source"]))
    for f in ("aligned_source.ply", "target.ply", "config.yaml"):
        assert (out / f).exists(), f
    assert "rotation_error_deg" in r.stdout and "stage" in r.stdout
    # the run folder keeps what the console said: the table (summary.txt) and each note (main.log), shown once
    assert (out / "summary.txt").read_text().startswith("stage ") and f"results: {out}" in r.stdout
    note = "note: repair=meshfix: data.mesh pkg:pymeshfix/examples/StanfordBunny.ply: no outer border"
    assert r.stdout.count(note) == 1 and (out / "main.log").read_text().count(note) == 1
    df = runs(mlflow_uri, "demo")
    row = df.iloc[0]
    assert row["status"] == "FINISHED"
    assert row["tags.group.icp"] == "point_to_plane" and row["tags.group.coarse"] == "lo_ransac"
    assert row["params.icp.max_iterations"] == "100"
    for k in RESULT_KEYS - {"T_target_source"}:
        assert row[f"metrics.{k}"] == pytest.approx(res[k]), k
    import mlflow

    arts = {a.path for a in mlflow.MlflowClient(mlflow_uri).list_artifacts(row["run_id"])}
    assert {"config.yaml", "result.json", "T_target_source.txt", "aligned_source.ply", "view3d.html"} <= arts
    hist = mlflow.MlflowClient(mlflow_uri).get_metric_history(row["run_id"], "icp_rms_step")
    assert len(hist) == res["icp_iterations"] + 1


@pytest.mark.slow
def test_deterministic_transform(tmp_path):
    """The same config and seed give the same transform, bit for bit: a second run into the first one's folder
    (a reused hydra.run.dir), which a line says may keep old files."""
    out = tmp_path / "r0"
    r = run_cli(["data=synthetic", "tracking=none", "seed=5", f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0, r.stderr
    first = (out / "T_target_source.txt").read_bytes()
    res = json.loads((out / "result.json").read_text())
    assert res["rotation_error_deg"] < 0.04, res  # and the right transform (measured: 0.0127 deg)
    assert "holds an earlier run's results" not in r.stdout
    (out / "T_target_source.txt").unlink()  # (written again, not left over)
    r = run_cli(["data=synthetic", "tracking=none", "seed=5", f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0 and (out / "T_target_source.txt").read_bytes() == first
    assert f"warning: {out} holds an earlier run's results" in r.stdout


def make_case(tmp_path, seed=0):
    """A bunny mesh, a resampled cloud of it under a random pose, and the ground truth."""
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    rng = np.random.default_rng(seed)
    pts, n, _ = barycentric_sample(m, 15000, rng)
    T = random_pose(rng, 180, 20)
    return m, Cloud(pts, n), T


@pytest.mark.slow
def test_files_mesh_to_cloud_and_cloud_to_mesh(tmp_path, mlflow_uri):
    m, cloud, T = make_case(tmp_path)
    np.save(tmp_path / "target.npy", apply_T(T, cloud.points))
    write_transform(tmp_path / "gt.txt", T)
    write_ply(tmp_path / "mesh_moved.ply", transform_geometry(T, m))
    np.savetxt(tmp_path / "source.xyz", cloud.points)
    cases = {
        "mesh_to_cloud": ["data.source=pkg:pymeshfix/examples/StanfordBunny.ply", "data.target=target.npy"],
        "cloud_to_mesh": ["data.source=source.xyz", "data.target=mesh_moved.ply", "repair=none"],
    }
    for name, args in cases.items():
        out = tmp_path / name
        r = run_cli([*args, "data.gt=gt.txt", f"hydra.run.dir={out}", "tracking.experiment=files"], tmp_path, mlflow_uri)
        assert r.returncode == 0, r.stderr
        res = json.loads((out / "result.json").read_text())
        assert RESULT_KEYS <= set(res)
        assert res["rotation_error_deg"] < 1.0, (name, res["rotation_error_deg"])
    assert set(runs(mlflow_uri, "files")["status"]) == {"FINISHED"}


def _write(tmp_path, name, data):
    p = tmp_path / name
    if isinstance(data, bytes):
        p.write_bytes(data)
    else:
        np.save(p, data)
    return name


PLY_HEAD = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" \
           b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
BAD_CASES = {
    "missing": (["data.source=nope.ply"], "source nope.ply: no such file"),
    "corrupt": (["data.source=corrupt.ply"], "source corrupt.ply: not a PLY file"),
    "empty": (["data.source=empty.stl"], "source empty.stl: file is empty"),
    "nan": (["data.source=nan.ply"], "source nan.ply: 1 point(s) with NaN or infinite coordinates"),
    "bad_index": (["data.source=idx.ply"], "source idx.ply: 1 face(s) index missing vertices"),
    "too_few_points": (["data.source=two.npy"], "source two.npy: 2 point(s); at least 10"),
    "degenerate": (["data.source=flat.ply", "repair=none"], "source flat.ply: is collinear: rigid registration is not determined"),
    "zero_area": (["data.source=zero.ply"], "source zero.ply: no triangle has an area above 0 (every face is degenerate)"),
    "unknown_group_choice": (["icp=bogus"], "unknown icp 'bogus'; valid icp choices: anderson, gicp, horn, open3d, point_to_plane"),
    "unknown_stage_name": (["coarse.name=bogus"], "unknown coarse 'bogus'; valid coarse names: landmarks, lo_ransac, none, open3d_fgr, open3d_fpfh_ransac"),
    "wrong_type": (["icp.max_iterations=many"], "icp=point_to_plane: parameter 'max_iterations' expects int, got 'many'"),
    "unknown_param": (["sampler.n_pionts=5"], "sampler=barycentric: unknown parameter 'n_pionts'"),
    "no_source": (["data.source=null"], "data=files: data.source is not set"),
    "wrong_enum": (["icp.distances=furlongs"], "icp=point_to_plane: parameter 'distances' expects spacing | absolute, got 'furlongs'"),
    "unknown_tracking_param": (["tracking.bogus=1"], "tracking=mlflow: unknown parameter 'bogus'; valid parameters: uri, experiment"),
    "several_values": (["icp.max_iterations=10,20"], "icp.max_iterations=10,20: several values for one run; to run "
                       "each, sweep them with -m (scanreg -m icp.max_iterations=10,20); for one value with commas "
                       "quote it (icp.max_iterations=\"'10,20'\"), for a list write icp.max_iterations=[10,20]"),
    "several_choices": (["icp=horn,gicp"], "icp=horn,gicp: several values for one run; to run each, sweep them with -m "
                        "(scanreg -m icp=horn,gicp)"),
}


CONFIG_CASES = {"unknown_group_choice", "unknown_stage_name", "wrong_type", "unknown_param", "no_source", "wrong_enum",
                "unknown_tracking_param", "several_values", "several_choices"}
"""Usage and config errors: exit 2 before any MLflow run exists. The others are input errors: exit 1, and the
run ends FAILED with the reason."""



@pytest.mark.slow
@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_one_line_error_and_failed_run(tmp_path, mlflow_uri, case):
    _write(tmp_path, "corrupt.ply", b"this is not a mesh\n")
    _write(tmp_path, "empty.stl", b"")
    _write(tmp_path, "nan.ply", PLY_HEAD + b"0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n")
    _write(tmp_path, "idx.ply", PLY_HEAD + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    _write(tmp_path, "flat.ply", PLY_HEAD + b"0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n")
    _write(tmp_path, "two.npy", np.random.default_rng(0).normal(size=(2, 3)))
    _write(tmp_path, "zero.ply", PLY_HEAD.replace(b"vertex 3", b"vertex 4").replace(b"face 1", b"face 2")
           + b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 0 1\n3 2 3 3\n")  # a tetrahedron's corners, no face of any area
    args, message = BAD_CASES[case]
    base = ["data.source=pkg:pymeshfix/examples/StanfordBunny.ply", "data.target=pkg:pymeshfix/examples/StanfordBunny.ply"]
    keys = {a.split("=")[0] for a in args}
    argv = [a for a in base if a.split("=")[0] not in keys] + args
    r = run_cli([*argv, f"hydra.run.dir={tmp_path / 'out'}", f"tracking.experiment=bad_{case}"], tmp_path, mlflow_uri)
    assert r.returncode == (2 if case in CONFIG_CASES else 1), r.stderr
    assert "Traceback" not in r.stderr + r.stdout
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error: ") and message in lines[-1], r.stderr
    assert sum(ln.startswith("error:") for ln in lines) == 1
    assert "repair (" not in r.stdout  # found before any work: no scan was repaired (the target's table came first)
    import mlflow

    exp = mlflow.MlflowClient(mlflow_uri).get_experiment_by_name(f"bad_{case}")
    if case in CONFIG_CASES:  # a typo adds no run to MLflow, and leaves no run folder
        assert exp is None or mlflow.MlflowClient(mlflow_uri).search_runs([exp.experiment_id]) == []
        assert not (tmp_path / "out").exists()
        return
    df = runs(mlflow_uri, f"bad_{case}")
    assert list(df["status"]) == ["FAILED"]
    assert message in df.iloc[0]["tags.error"]
    assert lines[-1] in (tmp_path / "out" / "main.log").read_text()  # the run folder keeps the reason too


def test_a_config_error_found_in_the_job_leaves_no_folder(tmp_path):
    """A data provider's config error (data=scanset without data.scans) surfaces inside the job, after Hydra made
    outputs/runs/DATE/TIME: none of them stays (the empty DATE folder did); a folder that was there stays."""
    r = run_cli(["data=scanset", "tracking=none"], tmp_path)
    assert r.returncode == 2 and "data.scans is not set" in r.stderr
    assert not (tmp_path / "outputs").exists()
    (tmp_path / "outputs" / "runs" / "old").mkdir(parents=True)
    assert run_cli(["data=scanset", "tracking=none"], tmp_path).returncode == 2
    assert sorted(p.name for p in (tmp_path / "outputs" / "runs").iterdir()) == ["old"]
    old = tmp_path / "outputs" / "runs" / "old"  # an earlier run's folder, reused: its log stays, the error added
    (old / "config.yaml").write_text("seed: 0\n")
    (old / "main.log").write_text("earlier run\n")
    assert run_cli(["data=scanset", "tracking=none", f"hydra.run.dir={old}"], tmp_path).returncode == 2
    assert (old / "main.log").read_text().startswith("earlier run\n") and (old / "config.yaml").exists()


@pytest.mark.slow
def test_sweep_parent_children_and_report(tmp_path, mlflow_uri):
    r = run_cli(["-m", "data=synthetic", "sampler.n_points=3000,6000", "tracking.experiment=sweep",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}"], tmp_path, mlflow_uri)
    assert r.returncode == 0, r.stderr
    df = runs(mlflow_uri, "sweep")
    parent = df[df["tags.scanreg.sweep"] == "parent"]
    children = df[df["tags.mlflow.parentRunId"] == parent.iloc[0]["run_id"]]
    assert len(parent) == 1 and parent.iloc[0]["status"] == "FINISHED"
    assert sorted(children["params.sampler.n_points"]) == ["3000", "6000"]
    assert set(children["status"]) == {"FINISHED"}
    rep = run_cli(["--experiment", "sweep", "--uri", mlflow_uri, "--out", str(tmp_path / "rep")], tmp_path,
                  module="scanreg.app.report.write")
    assert rep.returncode == 0, rep.stderr
    import pandas as pd

    table = pd.read_csv(tmp_path / "rep" / "report.csv")
    assert list(table["sampler.n_points"]) == [3000, 6000] and list(table["runs"]) == [1, 1]
    for _, row in table.iterrows():
        child = children[children["params.sampler.n_points"] == str(int(row["sampler.n_points"]))].iloc[0]
        assert row["rotation_error_deg_median"] == pytest.approx(child["metrics.rotation_error_deg"])
    assert "sampler.n_points" in (tmp_path / "rep" / "report.md").read_text()
    # the store as a plain path (as the default is written: outputs/mlflow.db): the same report
    plain = mlflow_uri[len("sqlite:///"):]
    rep = run_cli(["--experiment", "sweep", "--uri", plain, "--out", str(tmp_path / "rep2")], tmp_path,
                  module="scanreg.app.report.write")
    assert rep.returncode == 0 and pd.read_csv(tmp_path / "rep2" / "report.csv").equals(table), rep.stderr
    # a store that is not there is not created empty; a folder (MLflow's file store) is no store: one line each
    for uri, code in (("nothere/mlflow.db", 1), ("mlruns", 2)):
        rep = run_cli(["--uri", uri], tmp_path, module="scanreg.app.report.write")
        assert rep.returncode == code and len(rep.stderr.strip().splitlines()) == 1, rep.stderr
        assert rep.stderr.startswith("error:") and uri.split("/")[0] in rep.stderr
    assert not (tmp_path / "nothere").exists()


def test_tracking_store_given_as_a_path():
    """tracking.uri / $MLFLOW_TRACKING_URI / --uri: a URI as it is, a SQLite file's plain path as sqlite:/// and
    its absolute path, a folder (MLflow's file store, which MLflow 3 does not write) one error line naming it."""
    from pathlib import Path

    from scanreg.app.tracking import MlflowTracking, store_uri
    from scanreg.errors import ConfigError

    assert store_uri("http://host:5000", "x") == "http://host:5000"
    assert store_uri("sqlite:///rel.db", "x") == "sqlite:///rel.db"
    assert store_uri("other/mlflow.db", "x") == f"sqlite:///{(Path.cwd() / 'other' / 'mlflow.db').resolve()}"
    with pytest.raises(ConfigError, match=r"^tracking.uri=mlruns: not a tracking store"):
        MlflowTracking(MlflowTracking.Params(uri="mlruns"))


def test_a_file_store_uri_is_one_line_before_any_run(tmp_path, monkeypatch):
    """tracking.uri=file:///...: MLflow 3 refuses its file store only when a run is logged, after the work; a
    sweep then printed MLflow's exception as a Python warning and counted every job twice (4/2 jobs, exit 1).
    Now one line before any run or job starts, unless MLflow's own opt-in MLFLOW_ALLOW_FILE_STORE is set."""
    from scanreg.app.tracking import store_uri
    from scanreg.errors import ConfigError

    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE", raising=False)
    uri = (tmp_path / "mlruns").as_uri()
    with pytest.raises(ConfigError, match=r"^MLFLOW_TRACKING_URI=file:///.*a file store .*MLFLOW_ALLOW_FILE_STORE=true"):
        store_uri(uri, "MLFLOW_TRACKING_URI")
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    assert store_uri(uri, "x") == uri
    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE")
    for args in (["data=synthetic"], ["-m", "data=synthetic", "sampler.n_points=2000,3000"]):
        r = run_cli([*args, f"tracking.uri={uri}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
                     f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "a file store" in r.stderr and "Warning" not in r.stderr and "jobs" not in r.stdout, r.stderr
    assert not (tmp_path / "mlruns").exists() and not (tmp_path / "sweep").exists() and not (tmp_path / "run").exists()


BUNNY = "pkg:pymeshfix/examples/StanfordBunny.ply"


@pytest.mark.slow
def test_sweep_goes_on_after_a_failed_job(tmp_path, mlflow_uri):
    """A job that fails when it runs (a corrupt file passes the sweep's check before the start, which reads
    no scan) fails alone: the other job runs, the parent ends FAILED."""
    _write(tmp_path, "corrupt.ply", b"this is not a mesh\n")
    r = run_cli(["-m", "data=synthetic", f"data.mesh=corrupt.ply,{BUNNY}", "sampler.n_points=3000",
                 "tracking.experiment=sweepfail", f"hydra.sweep.dir={tmp_path / 'sweep'}"], tmp_path, mlflow_uri)
    assert r.returncode == 1
    assert "data.mesh corrupt.ply: not a PLY file" in r.stderr and "1 failed" in r.stdout
    df = runs(mlflow_uri, "sweepfail")
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    children = df[df["tags.mlflow.parentRunId"] == parent["run_id"]]
    assert sorted(children["status"]) == ["FAILED", "FINISHED"]
    assert parent["status"] == "FAILED"
    assert (tmp_path / "sweep" / "1" / "result.json").exists()


@pytest.mark.slow
def test_an_untracked_sweep_exits_1_when_a_job_failed(tmp_path):
    """The exit code of a sweep counts its jobs' outcomes with tracking=none too (it was 0 with every job failed):
    one closing line with the count, exit 1; a reused sweep folder does not count the earlier sweep's jobs."""
    sweep = tmp_path / "sweep"
    _write(tmp_path, "corrupt.ply", b"this is not a mesh\n")
    args = ["-m", "data=synthetic", "tracking=none", f"hydra.sweep.dir={sweep}", "sampler.n_points=3000"]
    r = run_cli([*args, f"data.mesh=corrupt.ply,{BUNNY}"], tmp_path)
    assert r.returncode == 1, r.stderr
    assert "not a PLY file" in r.stderr
    assert f"sweep: 2 job(s), 1 failed; results in {sweep}" in r.stdout
    r = run_cli([*args, f"data.mesh={BUNNY}"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "sweep: 1 job(s), 0 failed" in r.stdout


SWEEP_TYPOS = {
    "unknown_choice": (["repair=none,foo"], 2,
                       "job #1 (repair=foo): unknown repair 'foo'; valid repair choices: meshfix, meshlab, none"),
    "bad_value": (["sampler.n_points=3000,-1"], 2,
                  "job #1 (sampler.n_points=-1): sampler=barycentric: n_points must be >= 1, got -1"),
    "missing_file": ([f"data.mesh={BUNNY},bunny.pyl"], 1, "job #1 (data.mesh=bunny.pyl): data.mesh bunny.pyl: no such file"),
    "glob_choices": (["icp=glob(ho*)", "icp.max_iterations=20,-1"], 2,
                     "job #1 (icp.max_iterations=-1): icp=horn: max_iterations must be >= 1, got -1"),
    "two_of_six": (["sampler.n_points=3000,-1,-2", "seed=0,1"], 2,
                   "job #2 (sampler.n_points=-1 seed=0): sampler=barycentric: n_points must be >= 1, got -1 (and 3 more "
                   "of the 6 jobs)"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(SWEEP_TYPOS))
def test_a_sweep_with_a_value_no_job_can_run_starts_no_job(tmp_path, mlflow_uri, case):
    """Every job of a sweep is checked as its run would first check it (config and data, files there) before
    any starts: a typo in one swept value is one error line naming the job and the value, before any job ran
    and before any MLflow run was made (exit 2 for a config error, 1 for a missing file)."""
    args, code, message = SWEEP_TYPOS[case]
    r = run_cli(["-m", "data=synthetic", *args, "tracking.experiment=sweeptypo",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}"], tmp_path, mlflow_uri)
    assert r.returncode == code, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: sweep not started: {message}"), r.stderr
    assert not (tmp_path / "sweep").exists()
    import mlflow

    mlflow.set_tracking_uri(mlflow_uri)
    exp = mlflow.get_experiment_by_name("sweeptypo")
    assert exp is None or mlflow.search_runs([exp.experiment_id]).empty


@pytest.mark.slow
@pytest.mark.parametrize("pose_seed", [0, 1])
def test_stanford_bun045_to_bun000_from_random_pose(tmp_path, pose_seed):
    shared("stanford_bunny/bun.conf")
    out = tmp_path / "run"
    r = run_cli(["data=stanford", "repair=none", "tracking=none", f"seed={pose_seed}", f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    # measured: 0.054 / 0.059 deg and 2.4e-4 / 1.6e-4 of the diagonal; the coarse stage alone ends 0.46-0.70 deg
    # off, so a fine stage that does nothing fails
    assert res["rotation_error_deg"] < 0.2 and res["translation_error_rel"] < 7.5e-4, res
    assert res["coarse_rotation_error_deg"] > 2 * res["rotation_error_deg"], res


def test_readme_starts_with_the_two_commands():
    lines = [ln.strip() for ln in (ROOT / "README.md").read_text().splitlines()]
    code = [ln for ln in lines if ln.startswith("./run ")]
    assert code[:2] == ["./run demo", "./run test"]


@pytest.mark.slow
def test_repair_guard_fails_the_run_with_its_audit(tmp_path, mlflow_uri):
    mesh = shared("meshlab_defects/many_small_holes.ply")
    r = run_cli([f"data.source={mesh}", f"data.target={mesh}", "repair=meshfix", "repair.open_border=cap",
                 "tracking.experiment=guard", f"hydra.run.dir={tmp_path / 'g'}"], tmp_path, mlflow_uri)
    assert r.returncode == 1
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("error: repair=meshfix:") and "of the surface" in last and "repair.open_border=shell" in last
    assert "removed_area_share" in r.stdout  # the before/after table is still shown
    row = runs(mlflow_uri, "guard").iloc[0]
    assert row["status"] == "FAILED" and row["metrics.repair_guard_ok"] == 0
    assert row["metrics.repair_before_boundary_loops"] == 32
    # the default (open_border=auto) sees an open scan, keeps its border open and registers the scan to itself
    r = run_cli([f"data.source={mesh}", f"data.target={mesh}", "repair=meshfix", "tracking=none",
                 f"hydra.run.dir={tmp_path / 'ok'}"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "ok" / "result.json").read_text())
    assert res["repair_after_boundary_loops"] == 1 and res["repair_after_self_intersecting_faces"] == 0
    assert res["repair_open_border_open"] == 1 and res["repair_guard_ok"] == 1


@pytest.mark.slow
def test_landmark_alignment_then_icp(tmp_path):
    """The paper's route: rough alignment from picked landmark pairs, refined by ICP."""
    m, cloud, T = make_case(tmp_path, seed=3)
    np.save(tmp_path / "target.npy", apply_T(T, cloud.points))
    write_transform(tmp_path / "gt.txt", T)
    rng = np.random.default_rng(0)
    picks = m.vertices[rng.choice(len(m.vertices), 5, replace=False)]
    rows = np.hstack([apply_T(T, picks) + rng.normal(scale=0.3, size=picks.shape), picks])
    np.savetxt(tmp_path / "lm.csv", rows, delimiter=",", header="target_x,target_y,target_z,source_x,source_y,source_z",
               comments="")
    out = tmp_path / "run"
    r = run_cli(["data.source=pkg:pymeshfix/examples/StanfordBunny.ply", "data.target=target.npy", "data.gt=gt.txt",
                 "data.landmarks=lm.csv", "coarse=landmarks", "tracking=none", f"hydra.run.dir={out}"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "result.json").read_text())
    assert res["landmark_count"] == 5 and res["landmark_rms"] < 1.0 and "landmark_loo_max" in res
    assert res["coarse_rotation_error_deg"] > res["rotation_error_deg"]  # ICP improves on the landmarks
    assert res["rotation_error_deg"] < 0.5


@pytest.mark.slow
def test_a_sweep_launches_unchecked_when_asked(tmp_path, monkeypatch):
    """SCANREG_SWEEP_CHECK=0 (a launching machine that does not see the jobs' data): the sweep starts, and the
    job whose file is missing fails alone when it runs."""
    monkeypatch.setenv("SCANREG_SWEEP_CHECK", "0")
    sweep = tmp_path / "sweep"
    r = run_cli(["-m", "data=synthetic", f"data.mesh={BUNNY},bunny.pyl", "sampler.n_points=3000", "tracking=none",
                 f"hydra.sweep.dir={sweep}"], tmp_path)
    assert r.returncode == 1, r.stderr
    assert "data.mesh bunny.pyl: no such file" in r.stderr and "sweep not started" not in r.stderr
    assert f"sweep: 2 job(s), 1 failed; results in {sweep}" in r.stdout


def test_a_plugin_data_provider_without_preflight_is_checked_by_its_require():
    """preflight is optional for a data provider (a plugin written to the protocol has require and load)."""
    from scanreg.app.sweep import _preflight

    class Plugin:
        def require(self):
            raise ConfigError("data=mine: data.path is not set")

        def load(self, ctx):
            return None

    with pytest.raises(ConfigError, match="data.path is not set"):
        _preflight(Plugin())


def test_hydras_validation_is_left_out_only_after_every_job_was_checked():
    """The basic sweeper's own composition of every job (validate_batch_is_legal) runs unless scanreg's check
    composed and checked every job of this sweep."""
    from scanreg.app.sweep import _validate_unless_checked
    from scanreg.app.tracking import _sweep_outcome

    calls = []
    validate = _validate_unless_checked(lambda self, batch: calls.append(batch))
    _sweep_outcome.clear()
    validate(None, ["a"])
    _sweep_outcome["checked"] = False
    validate(None, ["b"])
    _sweep_outcome["checked"] = True
    validate(None, ["c"])
    _sweep_outcome.clear()
    assert calls == [["a"], ["b"]]


@pytest.mark.slow
def test_the_sweep_check_resolves_each_jobs_own_values(tmp_path):
    """A swept value with an interpolation (data.mesh=m${seed}.ply) is checked with each job's own values and
    environment (hydra.job.env_set), not the sweep's base config (it was checked as m0.ply, refusing a valid
    sweep): only the job whose file is missing is named."""
    (tmp_path / "m1.ply").symlink_to(pkg_bunny_path())
    r = run_cli(["-m", "data=synthetic", "tracking=none", "seed=1,3", "data.mesh=${oc.env:MESHES,nowhere}/m${seed}.ply",
                 f"+hydra.job.env_set.MESHES={tmp_path}", f"hydra.sweep.dir={tmp_path / 'sweep'}"], tmp_path)
    assert r.returncode == 1, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(
        f"error: sweep not started: job #1 (seed=3): data.mesh {tmp_path}/m3.ply: no such file"), r.stderr


def pkg_bunny_path():
    from scanreg.io import resolve_path

    return resolve_path(BUNNY)
