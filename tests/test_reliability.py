"""Scale-out and reliability: parallel sweeps into one store, interrupts, determinism, malformed inputs."""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli, runs




def bunny_cloud(n, seed, pose_seed=None):
    from scanreg.geometry import apply_T, random_pose
    from scanreg.io import read_mesh, resolve_path
    from scanreg.geometry import barycentric_sample

    mesh = read_mesh(resolve_path("pkg:pymeshlab/tests/sample_meshes/bunny.obj"))
    pts, _, _ = barycentric_sample(mesh, n, np.random.default_rng(seed))
    if pose_seed is not None:
        pts = apply_T(random_pose(np.random.default_rng(pose_seed), 180.0, 0.05), pts)
    return pts


@pytest.mark.slow
def test_parallel_sweep_8_jobs_2_failures_one_store(tmp_path, mlflow_uri):
    """8 jobs on 2 joblib workers into one SQLite store; one bad input, one stage failure."""
    names = []
    for i in range(6):
        np.save(tmp_path / f"s{i}.npy", bunny_cloud(3000, 10 + i, pose_seed=i))
        names.append(f"s{i}.npy")
    (tmp_path / "corrupt.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    np.save(tmp_path / "sparse.npy", np.random.default_rng(0).uniform(-1, 1, size=(12, 3)) * 0.05)
    names[2:2] = ["corrupt.ply"]
    names[5:5] = ["sparse.npy"]
    np.save(tmp_path / "target.npy", bunny_cloud(4000, 1))
    sweep = tmp_path / "sweep"
    r = run_cli(["-m", "data.target=target.npy", f"data.source={','.join(names)}", "hydra/launcher=joblib",
                 "hydra.launcher.n_jobs=2", "tracking.experiment=par8", f"hydra.sweep.dir={sweep}"],
                tmp_path, mlflow_uri, timeout=900)
    assert r.returncode == 1, r.stderr
    assert "2 failed" in r.stdout
    df = runs(mlflow_uri, "par8")
    parent = df[df["tags.scanreg.sweep"] == "parent"]
    assert len(parent) == 1 and parent.iloc[0]["status"] == "FAILED"
    assert "2 of 8 runs failed" in parent.iloc[0]["tags.error"]
    children = df[df["tags.mlflow.parentRunId"] == parent.iloc[0]["run_id"]]
    assert len(children) == 8 and len(df) == 9
    ok = children[children["status"] == "FINISHED"]
    bad = children[children["status"] == "FAILED"]
    assert len(ok) == 6 and len(bad) == 2
    for c in ("metrics.rms", "metrics.fitness", "metrics.time_total_s", "metrics.icp_iterations"):
        assert ok[c].notna().all(), c
    errors = dict(zip(bad["params.data.source"], bad["tags.error"]))
    assert "corrupt.ply" in errors["corrupt.ply"]
    assert "coarse=lo_ransac" in errors["sparse.npy"]  # raised inside the coarse stage
    import mlflow

    assert mlflow.get_experiment_by_name("Default") is None or runs(mlflow_uri, "Default").empty


@pytest.mark.slow
def test_determinism_across_repeats_and_n_jobs(tmp_path):
    """The default pipeline gives bit-identical T_target_source for the same config and seed, whether run
    alone, or in a sweep on 1 or 2 workers."""
    base = ["data=synthetic", "data.n_points=4000", "sampler.n_points=3000", "tracking=none"]
    outs = {}
    for nj in (1, 2):
        sweep = tmp_path / f"nj{nj}"
        r = run_cli(["-m", *base, "seed=0,1", "hydra/launcher=joblib", f"hydra.launcher.n_jobs={nj}",
                     f"hydra.sweep.dir={sweep}"], tmp_path, timeout=600)
        assert r.returncode == 0, r.stderr
        outs[nj] = [(sweep / str(j) / "T_target_source.txt").read_bytes() for j in (0, 1)]
    single = tmp_path / "single"
    r = run_cli([*base, "seed=1", f"hydra.run.dir={single}"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert outs[1] == outs[2]
    assert outs[1][1] == (single / "T_target_source.txt").read_bytes()
    assert outs[1][0] != outs[1][1]


@pytest.mark.slow
def test_sigint_leaves_no_run_running(tmp_path, mlflow_uri):
    """Ctrl-C in the middle of a parallel sweep: finished runs stay FINISHED with their metrics, unfinished
    ones end KILLED or FAILED with their reason, the parent ends KILLED; nothing is left RUNNING (a job's run is
    logged once, when it ends; the parent run is open while the sweep works)."""
    env = dict(os.environ, MLFLOW_TRACKING_URI=mlflow_uri)
    env.pop("SCANREG_SWEEP", None)
    sweep = tmp_path / "sweep"
    p = subprocess.Popen([sys.executable, "-m", "scanreg.app", "-m", "data=synthetic", "seed=0,1,2,3,4,5,6,7",
                          "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "tracking.experiment=sigint",
                          f"hydra.sweep.dir={sweep}"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True,
                         # a shell's background job (CI started with '&') ignores SIGINT, and children inherit
                         # that; a terminal's Ctrl-C reaches a process with the default disposition
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    progress = sweep / ".progress"
    t0 = time.time()
    while time.time() - t0 < 300 and not (progress.exists() and progress.read_text().strip()):
        time.sleep(0.5)
    assert progress.exists(), "no job finished in time"
    os.killpg(p.pid, signal.SIGINT)  # what Ctrl-C does: the whole foreground process group
    out, err = p.communicate(timeout=300)
    assert p.returncode != 0
    assert "interrupted" in err
    df = runs(mlflow_uri, "sigint")
    assert "RUNNING" not in set(df["status"]), df[["status", "tags.error"]]
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    assert parent["status"] == "KILLED"
    children = df[df["tags.mlflow.parentRunId"] == parent["run_id"]]
    done = children[children["status"] == "FINISHED"]
    assert len(done) >= 1 and done["metrics.rotation_error_deg"].notna().all()
    assert set(children["status"]) <= {"FINISHED", "KILLED", "FAILED"}
    ended = children[children["status"] != "FINISHED"]
    assert ended["tags.error"].notna().all() and (ended["tags.error"] != "").all(), ended  # with their reason
    assert "interrupted" in parent["tags.error"]
    assert len(children) < 8  # it did stop
    assert not list(sweep.glob("*/mlflow_pending.json"))  # every finished job logged, by itself or after it


def test_a_finished_job_cut_short_while_being_logged_is_logged_from_its_folder(tmp_path, monkeypatch):
    """Ctrl-C while a parallel sweep's job was logging its finished run: the launcher ends its workers at once, and
    the run was lost (a researcher's trial: the job's result.json there, MLflow holding only a RUNNING run with
    part of its parameters). The job keeps what it logs in its folder until logged; the launching process logs
    it after the interrupt, in place of the cut run."""
    import mlflow

    from scanreg.app.tracking import (PENDING_RECORD, SWEEP_ENV, MlflowTracking, RunRecord, _sweep_outcome,
                                      end_interrupted_sweep)

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tr = MlflowTracking(MlflowTracking.Params(uri=uri, experiment="cut"))
    client, eid = tr.prepare()
    parent = client.create_run(eid, tags={"scanreg.sweep": "parent"})
    sweep = tmp_path / "sweep"
    job = sweep / "0"
    job.mkdir(parents=True)
    info = {"uri": tr.uri, "experiment": "cut", "experiment_id": eid, "parent_run_id": parent.info.run_id,
            "sweep_dir": str(sweep)}
    monkeypatch.setenv(SWEEP_ENV, json.dumps(info))
    params = {f"p{k}": str(k) for k in range(150)}
    record = RunRecord("seed=0", params, {"scanreg.run_dir": str(job)}).ended("FINISHED", None, {"rms": 0.5})
    (job / PENDING_RECORD).write_text(json.dumps(tr.request(record)))
    cut = client.create_run(eid, tags={"mlflow.parentRunId": parent.info.run_id, "scanreg.run_dir": str(job)})
    client.log_param(cut.info.run_id, "p0", "0")  # (the interrupt stopped it here)
    end_interrupted_sweep()
    assert _sweep_outcome["recovered"] == 1 and not (job / PENDING_RECORD).exists()
    kids = mlflow.MlflowClient(uri).search_runs([eid], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'")
    assert [r.info.status for r in kids] == ["FINISHED"] and kids[0].data.metrics["rms"] == 0.5
    assert len(kids[0].data.params) == 150  # the whole config, once


# ------------------------------------------------------------------------------------------ bad input
PLY_ASCII = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
             b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")


def _binary_ply():
    import struct

    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    return head + struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack("<B3i", 3, 0, 1, 2)


def _binary_stl():
    import struct

    return b"\0" * 80 + struct.pack("<I", 1) + struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0)


STL_ASCII = b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n"
OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"

MALFORMED = {
    "ply_ascii_truncated.ply": PLY_ASCII[:-12],
    "ply_binary_truncated.ply": _binary_ply()[:-9],
    "stl_binary_truncated.stl": _binary_stl()[:-20],
    "stl_ascii_truncated.stl": STL_ASCII[:60],
    "obj_truncated.obj": OBJ[:-4] + b"\nf 1 2",
    "ply_wrong_count.ply": PLY_ASCII.replace(b"element vertex 3", b"element vertex 5"),
    "ply_index_out_of_range.ply": PLY_ASCII.replace(b"3 0 1 2", b"3 0 1 9"),
    "obj_index_out_of_range.obj": OBJ.replace(b"f 1 2 3", b"f 1 2 8"),
    "ply_nan.ply": PLY_ASCII.replace(b"1 0 0\n", b"nan 0 0\n"),
    "ply_inf.ply": PLY_ASCII.replace(b"1 0 0\n", b"inf 0 0\n"),
    "obj_nan.obj": OBJ.replace(b"v 1 0 0", b"v nan 0 0"),
    "empty.ply": b"",
    "empty.stl": b"",
    "empty.obj": b"",
    "zero_faces.off": b"OFF\n0 0 0\n",
    "garbage.ply": b"\x00\xff" * 50,
    "header_only.ply": b"ply\nformat ascii 1.0\nend_header\n",
    "stl_huge_count.stl": b"\0" * 80 + (10 ** 9).to_bytes(4, "little"),
    "xyz_text.xyz": b"a b c\n",
    "npy_wrong_shape.npy": None,
}


def write_case(folder: Path, name: str) -> Path:
    p = folder / name
    if name == "npy_wrong_shape.npy":
        np.save(p, np.zeros((4, 2)))
    else:
        p.write_bytes(MALFORMED[name])
    return p


@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_files_give_a_clear_error(tmp_path, name):
    from scanreg.errors import InputError
    from scanreg.io import read_geometry

    p = write_case(tmp_path, name)
    with pytest.raises(InputError) as e:
        read_geometry(p, "source")
    msg = str(e.value)
    assert name in msg and "\n" not in msg and len(msg) < 300


def test_other_bad_paths(tmp_path):
    from scanreg.errors import InputError
    from scanreg.io import read_geometry

    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(InputError, match="is a directory|not a file"):
        read_geometry(tmp_path / "dir.ply", "source")
    with pytest.raises(InputError, match="no such file"):
        read_geometry(tmp_path / "none.ply", "source")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["one_degenerate_triangle", "two_identical_clouds", "two_points"])
def test_degenerate_cases_through_the_cli(tmp_path, case):
    if case == "one_degenerate_triangle":
        (tmp_path / "s.ply").write_bytes(PLY_ASCII.replace(b"0 1 0\n", b"2 0 0\n"))
        args, expect = ["data.source=s.ply", "data.target=pkg:pymeshlab/tests/sample_meshes/bunny.obj"], "is collinear"
    elif case == "two_identical_clouds":
        np.save(tmp_path / "a.npy", bunny_cloud(3000, 0))
        args, expect = ["data.source=a.npy", "data.target=a.npy"], None
    else:
        np.save(tmp_path / "two.npy", np.eye(3)[:2])
        args, expect = ["data.source=two.npy", "data.target=pkg:pymeshlab/tests/sample_meshes/bunny.obj"], "2 point(s)"
    out = tmp_path / "out"
    r = run_cli([*args, "tracking=none", f"hydra.run.dir={out}"], tmp_path, timeout=300)
    if expect is None:  # identical clouds register to the identity
        assert r.returncode == 0, r.stderr
        T = np.loadtxt(out / "T_target_source.txt")
        assert np.abs(T - np.eye(4)).max() < 1e-6
    else:
        assert r.returncode != 0
        lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("error:")]
        assert len(lines) == 1 and expect in lines[0] and "Traceback" not in r.stderr, r.stderr


def test_readers_never_crash_or_hang_on_mutated_files(tmp_path):
    """Property-based: random byte mutations and truncations of valid files in every format end with a valid
    result or an InputError, never another exception or a hang."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from scanreg.errors import InputError
    from scanreg.geometry import Cloud, Mesh
    from scanreg.io import read_geometry

    seeds = {"a.ply": PLY_ASCII, "b.ply": _binary_ply(), "c.stl": _binary_stl(), "d.stl": STL_ASCII, "e.obj": OBJ,
             "f.off": b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "g.xyz": b"0 0 0\n1 0 0\n0 1 0\n",
             "h.off": b"COFF 3 1 0\n0 0 0 9 9 9\n1 0 0 9 9 9\n0 1 0 9 9 9\n3 0 1 2\n",
             "i.xyz": b"//X,Y,Z,R,G,B\n0,0,0,1,2,3\n1,0,0,4,5,6\n0,1,0,7,8,9\n0,0,1,0,0,0\n",
             "j.pcd": b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
                      b"0 0 0\n1 0 0\nnan 1 0\n"}

    @settings(max_examples=300, deadline=2000, suppress_health_check=list(HealthCheck), derandomize=True)
    @given(name=st.sampled_from(sorted(seeds)), cut=st.integers(0, 400),
           edits=st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=6))
    def check(name, cut, edits):
        data = bytearray(seeds[name])
        for pos, val in edits:
            if data:
                data[pos % len(data)] = val
        data = bytes(data[: max(0, len(data) - cut % (len(data) + 1))])
        p = tmp_path / name
        p.write_bytes(data)
        try:
            g = read_geometry(p, "input")
        except InputError as e:
            assert "\n" not in str(e)
            return
        pts = g.vertices if isinstance(g, Mesh) else g.points
        assert isinstance(g, (Mesh, Cloud)) and pts.ndim == 2 and pts.shape[1] == 3 and np.isfinite(pts).all()
        if isinstance(g, Mesh):
            assert g.faces.min() >= 0 and g.faces.max() < len(pts)

    check()


def test_yaml_cannot_import_code():
    """Stages resolve only through the registries: a _target_ (or any unknown key) in a stage group is a
    config error, never an import."""
    from scanreg.app.config import compose
    from scanreg.errors import ConfigError
    from scanreg.runner import build_stages

    a = compose(["+repair._target_=os.system"])
    b = compose(["repair.name=os.system"])
    with pytest.raises(ConfigError, match="unknown parameter '_target_'"):
        build_stages(a)
    with pytest.raises(ConfigError, match="unknown repair 'os.system'"):
        build_stages(b)


@pytest.mark.slow
def test_inputs_untouched_and_outputs_only_in_the_run_dir(tmp_path):
    src_dir = tmp_path / "in"
    src_dir.mkdir()
    np.save(src_dir / "s.npy", bunny_cloud(3000, 3, pose_seed=1))
    np.save(src_dir / "t.npy", bunny_cloud(3000, 4))
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in src_dir.iterdir()}
    for p in src_dir.iterdir():
        p.chmod(0o444)
    work = tmp_path / "work"
    work.mkdir()
    out = work / "run"
    r = run_cli([f"data.source={src_dir / 's.npy'}", f"data.target={src_dir / 't.npy'}", "tracking=none",
                 f"hydra.run.dir={out}"], work)
    assert r.returncode == 0, r.stderr
    after = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in src_dir.iterdir()}
    assert before == after
    assert {p.name for p in work.iterdir()} == {"run"}


# ------------------------------------------------------------------------------------------ team tracking
def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pg_bin() -> Path | None:
    import glob
    import shutil

    for cand in [shutil.which("initdb"), *sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), reverse=True)]:
        if cand:
            return Path(cand).resolve().parent
    if os.geteuid() == 0 and shutil.which("apt-get"):  # try to install it (CI on a bare machine)
        subprocess.run(["apt-get", "install", "-y", "-q", "postgresql"], capture_output=True, timeout=600)
        found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), reverse=True)
        return Path(found[0]).parent if found else None
    return None


@pytest.fixture(scope="module")
def postgres_mlflow_server(tmp_path_factory):
    """A PostgreSQL server and an MLflow tracking server on loopback, serving artifacts, for this test only."""
    pytest.importorskip("psycopg2", reason="psycopg2 not installed (pip install -e .[dev])")
    bindir = _pg_bin()
    if bindir is None:
        pytest.skip("PostgreSQL cannot be installed here (no initdb, no apt-get as root)")
    import shutil
    import tempfile

    base = Path(tempfile.mkdtemp(prefix="scanreg-pg-"))  # not under pytest's 0700 root: PostgreSQL's user reads it
    data, sock = base / "data", base / "sock"
    sock.mkdir()
    as_pg: list[str] = []
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root
        import pwd

        try:
            pw = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no 'postgres' user to run PostgreSQL as")
        os.chown(base, pw.pw_uid, pw.pw_gid)
        os.chown(sock, pw.pw_uid, pw.pw_gid)
        base.chmod(0o755)
        as_pg = ["runuser", "-u", "postgres", "--"]
    pg_port, ml_port = _free_port(), _free_port()
    r = subprocess.run([*as_pg, str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([*as_pg, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(base / "pg.log"), "-w", "-o",
                        f"-p {pg_port} -k {sock} -c listen_addresses=127.0.0.1", "start"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr + (base / "pg.log").read_text()
    server = None
    try:
        import psycopg2

        con = psycopg2.connect(host="127.0.0.1", port=pg_port, user="postgres", dbname="postgres")
        con.autocommit = True
        con.cursor().execute("CREATE DATABASE mlflow")
        con.close()
        art = base / "artifacts"
        art.mkdir()
        mlflow_bin = Path(sys.executable).parent / "mlflow"
        server = subprocess.Popen(
            [str(mlflow_bin), "server", "--backend-store-uri",
             f"postgresql+psycopg2://postgres@127.0.0.1:{pg_port}/mlflow", "--serve-artifacts",
             "--artifacts-destination", str(art), "--host", "127.0.0.1", "--port", str(ml_port), "--workers", "1"],
            stdout=open(base / "mlflow.log", "w"), stderr=subprocess.STDOUT, start_new_session=True)
        import urllib.request

        uri = f"http://127.0.0.1:{ml_port}"
        for _ in range(240):
            try:
                if urllib.request.urlopen(f"{uri}/health", timeout=2).status == 200:
                    break
            except OSError:
                time.sleep(0.5)
        else:
            pytest.fail("MLflow server did not start: " + (base / "mlflow.log").read_text()[-2000:])
        yield uri
    finally:
        if server is not None:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=60)
        subprocess.run([*as_pg, str(bindir / "pg_ctl"), "-D", str(data), "-m", "fast", "stop"], capture_output=True,
                       timeout=120)
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.slow
def test_sweep_into_a_postgres_backed_mlflow_server(tmp_path, postgres_mlflow_server):
    uri = postgres_mlflow_server
    r = run_cli(["-m", "data=synthetic", "data.n_points=3000", "sampler.n_points=2000", "seed=0,1",
                 "hydra.launcher.n_jobs=2", "tracking.experiment=team", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                tmp_path, uri, timeout=600)
    assert r.returncode == 0, r.stderr
    df = runs(uri, "team")
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    children = df[df["tags.mlflow.parentRunId"] == parent["run_id"]]
    assert parent["status"] == "FINISHED" and len(children) == 2 and set(children["status"]) == {"FINISHED"}
    assert children["metrics.rotation_error_deg"].notna().all()
    from mlflow.tracking import MlflowClient

    arts = {a.path for a in MlflowClient(uri).list_artifacts(children.iloc[0]["run_id"])}
    assert {"result.json", "T_target_source.txt"} <= arts  # served by the tracking server
    rep = run_cli(["--experiment", "team", "--uri", uri, "--out", str(tmp_path / "rep")], tmp_path,
                  module="scanreg.app.report.write")
    assert rep.returncode == 0, rep.stderr


@pytest.mark.slow
def test_ray_launcher_on_a_cluster(tmp_path, mlflow_uri):
    """The Ray launcher on an existing cluster started with 'ray start --head': its workers do not share the
    launching process's environment (the sweep's store reaches them through the sweep dir). A local Ray
    (``+hydra.launcher.ray.init.num_cpus=N``) runs the same launcher with the environment shared; it is not run
    as well: each Ray start costs 30-100 s of the suite, and its processes slow the other tests."""
    pytest.importorskip("hydra_plugins.hydra_ray_launcher", reason="pip install -e .[ray]")
    ray_bin = Path(sys.executable).parent / "ray"
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    start = subprocess.run([str(ray_bin), "start", "--head", "--num-cpus=2", "--disable-usage-stats",
                            "--include-dashboard=false"], capture_output=True, text=True, timeout=180, env=env,
                           cwd=tmp_path)
    assert start.returncode == 0, start.stderr
    try:
        r = run_cli(["-m", "data=synthetic", "data.n_points=3000", "sampler.n_points=2000", "seed=0,1",
                     "hydra/launcher=ray", "+hydra.launcher.ray.init.address=auto",
                     "+hydra.launcher.ray.init.object_store_memory=null", "tracking.experiment=ray_cluster",
                     f"hydra.sweep.dir={tmp_path / 'cluster'}"], tmp_path, mlflow_uri, timeout=600)
    finally:
        subprocess.run([str(ray_bin), "stop", "--force"], capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    df = runs(mlflow_uri, "ray_cluster")
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    children = df[df["tags.mlflow.parentRunId"] == parent["run_id"]]
    assert len(children) == 2 and set(children["status"]) == {"FINISHED"}


@pytest.mark.slow
def test_submitit_local_launcher(tmp_path, mlflow_uri):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e .[slurm]")
    r = run_cli(["-m", "data=synthetic", "data.n_points=3000", "sampler.n_points=2000", "seed=0,1",
                 "hydra/launcher=submitit_local", "tracking.experiment=submitit", f"hydra.sweep.dir={tmp_path / 's'}"],
                tmp_path, mlflow_uri, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    df = runs(mlflow_uri, "submitit")
    parent = df[df["tags.scanreg.sweep"] == "parent"].iloc[0]
    assert (df["tags.mlflow.parentRunId"] == parent["run_id"]).sum() == 2
