"""The start-up measures of the ``scanreg`` command (scanreg.app.startup), each kept for the time it saves and
each checked here: the stand-in that defers Open3D's plotly viewer, the MLflow worker that logs a single run
(and only when the command may be one), the exit without the interpreter's teardown that still flushes every
output. ``--help`` without Hydra's help machinery (quick_help) is checked in tests/test_config.py."""

import json
import os
import subprocess
import sys
import textwrap
import uuid
from dataclasses import asdict
from pathlib import Path

import pytest

from conftest import children, settled
from scanreg.app import startup
from scanreg.app.tracking import RunRecord


def _run(code: str, *args: str, cwd=None, env=None, code_expected: int = 0) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, text=True,
                       timeout=300, cwd=cwd, env=env)
    assert r.returncode == code_expected, r.stdout + r.stderr
    return r


# ------------------------------------------------------------------------------- 1. Open3D's plotly viewer

def test_open3d_imported_after_the_stand_in_skips_dash_and_plotly():
    out = _run("""
        import sys
        from scanreg.app.startup import defer_open3d_viewer
        print(defer_open3d_viewer())
        import open3d as o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0, 0, 0], [1, 0, 0]]))
        print(len(pc.points), "dash" in sys.modules, "plotly" in sys.modules)
        print(defer_open3d_viewer())  # once only
    """).stdout.split("\n")
    assert out[:3] == ["True", "2 False False", "False"]


def test_no_stand_in_once_open3d_is_imported_nor_for_library_callers():
    """The stand-in is the command's (scanreg.app.cli): importing scanreg (the Python API, the geometry core)
    leaves Open3D as it is; once Open3D is imported, the stand-in is not put in place."""
    out = _run("""
        import sys
        import scanreg, scanreg.geometry
        print("open3d.visualization.draw_plotly" in sys.modules)
        import open3d
        from scanreg.app.startup import defer_open3d_viewer
        print(defer_open3d_viewer(), getattr(sys.modules["open3d.visualization.draw_plotly"], "_scanreg_stub", False))
    """).stdout.split("\n")
    assert out[:2] == ["False", "False False"]


def test_plotly_viewer_still_works_through_the_stand_in():
    # the forwarder imports the real module on first use and gives Open3D's own result
    out = _run("""
        import sys
        from scanreg.app.startup import defer_open3d_viewer
        defer_open3d_viewer()
        import open3d as o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0, 0, 0], [1, 0, 0], [0, 1, 0]]))
        fig = o3d.visualization.get_plotly_fig([pc])
        print(type(fig).__name__, len(fig.data), "dash" in sys.modules)
        # afterwards Open3D's names are its own functions again, not the module
        m = sys.modules["open3d.visualization.draw_plotly"]
        print(o3d.visualization.draw_plotly is m.draw_plotly, callable(o3d.visualization.draw_plotly))
        print(getattr(m, "_scanreg_stub", False))
    """).stdout
    assert out.splitlines() == ["Figure 1 True", "True True", "False"]


def test_without_the_stand_in_open3d_imports_dash():
    # the stand-in is what keeps dash out: without it, Open3D imports it (if this fails, drop the stand-in)
    out = _run("""
        import sys
        import open3d
        print("dash" in sys.modules)
    """).stdout
    assert out.strip() == "True"


def test_the_command_puts_the_stand_in_in_place_first():
    """``scanreg`` (scanreg.app.cli.main) defers the viewer before the application imports Open3D, and a run
    that is not tracked starts no MLflow worker."""
    r = _run("""
        import sys
        sys.argv = ["scanreg", "tracking=none"]
        import scanreg.app.main as app_main
        from scanreg.app import cli, startup

        def fake_main():
            import open3d
            print("dash", "dash" in sys.modules, "plotly", "plotly" in sys.modules, "worker", startup._worker)
            raise SystemExit(0)

        app_main.main = fake_main
        cli.main()
    """)
    assert r.stdout.strip() == "dash False plotly False worker None", r.stdout


# --------------------------------------------------------------------------------------- 2. the MLflow worker

@pytest.mark.parametrize("argv,expected", [
    ([], True),
    (["data=synthetic", "icp.tau=1e-6"], True),
    (["tracking=mlflow"], True),
    (["tracking = mlflow"], True),
    (["tracking.experiment=x"], True),       # a parameter of the tracking backend, not another backend
    (["tracking=none"], False),
    (["tracking = none"], False),
    (["-m", "seed=0,1"], False),
    (["--multirun"], False),
    (["hydra.mode=MULTIRUN"], False),
    (["--help"], False), (["-h"], False), (["--hydra-help"], False),
    (["--cfg", "job"], False), (["-c", "job"], False), (["--info"], False), (["-i", "config"], False),
])
def test_may_track_single_run(argv, expected):
    assert startup.may_track_single_run(argv) is expected


def test_is_multirun():
    assert startup.is_multirun(["-m"]) and startup.is_multirun(["--multirun", "a=1"])
    assert startup.is_multirun(["hydra.mode=MULTIRUN"])
    assert not startup.is_multirun(["data=synthetic", "seed=1"])


def _record(tmp_path: Path) -> RunRecord:
    art = tmp_path / "result.json"
    art.write_text("{}")
    return RunRecord("icp=horn", {"icp.name": "horn", "icp.tau": "1e-06"}, {"group.icp": "horn"}).ended(
        "FINISHED", None, {"rms": 0.25, "icp_iterations": 3, "not_finite": float("nan")},
        {"icp_rms": [3.0, 2.0, 1.0, 1.0]}, [art])


def _request(uri: str, experiment: str, record: RunRecord) -> dict:
    return {"uri": uri, "resolved_uri": uri, "experiment": experiment, "sweep": None, "record": asdict(record)}


def test_tracking_worker_logs_one_run(tmp_path):
    """A run's record handed to the worker (``python -m scanreg.app.tracking``) is logged once, ended: params,
    tags, metrics (finite ones), per-iteration series, artifacts, status; a failed run with its reason."""
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    before = children()
    rec = _record(tmp_path)
    worker = startup.TrackingWorker()
    run_id = worker.log(_request(uri, "worker", rec))
    assert worker.proc.wait(timeout=60) == 0  # one run per worker: it ends after answering
    failed = rec.ended("FAILED", "source s.ply: no such file", {"repair_guard_ok": 0.0})
    second = startup.TrackingWorker()
    failed_id = second.log(_request(uri, "worker", failed))
    assert second.proc.wait(timeout=60) == 0
    assert settled(before, 60)

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("worker")
    assert {r.info.run_id for r in client.search_runs([exp.experiment_id])} == {run_id, failed_id}
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and run.info.run_name == "icp=horn"
    assert run.info.start_time == rec.start_time and run.info.end_time >= rec.start_time
    assert run.data.params == {"icp.name": "horn", "icp.tau": "1e-06"}
    assert run.data.tags["group.icp"] == "horn" and "error" not in run.data.tags
    assert run.data.metrics == {"rms": 0.25, "icp_iterations": 3.0, "icp_rms_step": 1.0}
    hist = client.get_metric_history(run_id, "icp_rms_step")
    assert [(m.step, m.value) for m in sorted(hist, key=lambda m: m.step)] == [(0, 3.0), (1, 2.0), (2, 1.0), (3, 1.0)]
    assert {a.path for a in client.list_artifacts(run_id)} == {"result.json"}
    bad = client.get_run(failed_id)
    assert bad.info.status == "FAILED" and bad.data.tags["error"] == "source s.ply: no such file"
    assert bad.data.metrics == {"repair_guard_ok": 0.0}  # what was measured before the failure


def test_mlflow_tracking_hands_the_run_to_the_prestarted_worker(tmp_path):
    """MlflowTracking.log_run in a process that has not imported MLflow takes the prestarted worker (once) and
    logs through it: MLflow is never imported by the run's own process."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    rec = _record(tmp_path)
    r = _run("""
        import json, sys
        from scanreg.app import startup
        from scanreg.app.tracking import MlflowTracking, RunRecord
        startup.prestart_tracking_worker()
        first = startup._worker
        startup.prestart_tracking_worker()  # once
        assert startup._worker is first
        rec = RunRecord(**json.loads(sys.argv[2]))
        run_id = MlflowTracking(MlflowTracking.Params(uri=sys.argv[1], experiment="handed")).log_run(rec)
        print(json.dumps({"run_id": run_id, "mlflow": "mlflow" in sys.modules,
                          "left": startup.take_tracking_worker() is None, "exit": first.proc.wait(60)}))
    """, uri, json.dumps(asdict(rec)))
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["mlflow"] is False and out["left"] is True and out["exit"] == 0
    from mlflow.tracking import MlflowClient

    run = MlflowClient(uri).get_run(out["run_id"])
    assert run.info.status == "FINISHED" and run.data.metrics["rms"] == 0.25


def test_tracking_worker_errors_are_raised_and_an_unused_worker_is_dropped(tmp_path):
    before = children()
    failing = startup.TrackingWorker()
    with pytest.raises(RuntimeError, match=r"^TypeError: [^\n]*$"):  # the worker's own error, one line
        failing.log({"uri": None, "resolved_uri": "sqlite:///x.db", "experiment": "x", "record": {}})
    assert failing.proc.wait(timeout=60) == 0
    gone = startup.TrackingWorker()
    gone.proc.kill()
    gone.proc.wait()
    with pytest.raises(RuntimeError, match="the MLflow logging process ended"):
        gone.log(_request(f"sqlite:///{tmp_path / 'm.db'}", "x", _record(tmp_path)))
    # a command that logs nothing (untracked, or stopped early) stops its worker
    startup.prestart_tracking_worker()
    worker = startup._worker
    assert worker is not None and worker.proc.poll() is None
    startup.drop_tracking_worker()
    assert worker.proc.poll() is not None and startup.take_tracking_worker() is None
    startup.drop_tracking_worker()  # nothing to drop: no error
    # a worker whose input closes without a request ends quietly
    quiet = startup.TrackingWorker()
    quiet.proc.stdin.close()
    assert quiet.proc.wait(timeout=120) == 0 and quiet.proc.stdout.read() == ""
    assert settled(before, 30)
    assert not (tmp_path / "m.db").exists()


def test_the_worker_opens_the_default_store_early_only_when_it_exists(tmp_path, monkeypatch):
    """The worker opens the default store (``outputs/mlflow.db`` under its working directory) before the run
    ends only when it exists: a command that logs nothing creates no store; with the store there, the run is
    logged into it as before."""
    from mlflow.tracking import MlflowClient

    from scanreg.app.tracking import MlflowTracking

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    idle = startup.TrackingWorker()
    idle.proc.stdin.close()
    assert idle.proc.wait(timeout=120) == 0
    assert not (tmp_path / "outputs").exists()
    uri = MlflowTracking(MlflowTracking.Params()).uri
    assert uri == f"sqlite:///{tmp_path.resolve() / 'outputs' / 'mlflow.db'}"
    ids = []
    for _ in range(2):  # the first creates the store, the second finds it open
        worker = startup.TrackingWorker()
        ids.append(worker.log({**_request(uri, "scanreg", _record(tmp_path)), "uri": None}))
        assert worker.proc.wait(timeout=60) == 0
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("scanreg").experiment_id])
    assert {r.info.run_id for r in runs} == set(ids) and len(set(ids)) == 2


def test_a_single_cli_run_logs_through_the_worker(tmp_path):
    """``scanreg`` with a bad input file: the run ends FAILED with its reason, logged by the worker (the command's
    own process never imports MLflow), and exits 1 with one error line."""
    (tmp_path / "bad.ply").write_bytes(b"this is not a mesh\n")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env = {k: v for k, v in os.environ.items() if k != "SCANREG_SWEEP"}
    env["MLFLOW_TRACKING_URI"] = uri
    r = _run("""
        import sys
        from scanreg.app import cli, startup
        sys.argv = ["scanreg", *sys.argv[1:]]
        exit_now = startup.exit_now

        def spy(code):
            print("mlflow imported:", "mlflow" in sys.modules, flush=True)
            exit_now(code)

        startup.exit_now = spy
        cli.main()
    """, "data.source=bad.ply", "data.target=bad.ply", "tracking.experiment=cli_worker",
        f"hydra.run.dir={tmp_path / 'out'}", cwd=tmp_path, env=env, code_expected=1)
    assert "mlflow imported: False" in r.stdout
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: source bad.ply: not a PLY file"), r.stderr
    from conftest import runs

    df = runs(uri, "cli_worker")
    assert list(df["status"]) == ["FAILED"] and df.iloc[0]["tags.error"] == lines[0].removeprefix("error: ")
    assert df.iloc[0]["tags.group.icp"] == "point_to_plane"


# -------------------------------------------------------------------------------------- 3. exit at once

EXIT_CODE = """
    import atexit, logging, logging.handlers, sys
    from scanreg.app.startup import exit_now
    # a handler that writes only when flushed or closed: what logging.shutdown must do
    target = logging.FileHandler(sys.argv[1])
    logging.getLogger().addHandler(logging.handlers.MemoryHandler(1000, logging.CRITICAL, target))
    logging.getLogger().setLevel(logging.INFO)
    logging.getLogger("t").info("logged before exit")
    atexit.register(lambda: print("teardown ran", flush=True))
    sys.stdout.write("out, no newline")  # block-buffered on a pipe
    sys.stderr.write("err, no newline")
    code = sys.argv[2]
    exit_now(None if code == "None" else int(code) if code.isdigit() else code)
"""


@pytest.mark.parametrize("code,expected", [("0", 0), ("3", 3), ("None", 0), ("a message", 1)])
def test_exit_now_flushes_every_output(tmp_path, code, expected):
    """exit_now skips the interpreter's teardown (atexit handlers do not run) but not the outputs: standard
    output and error and the log handlers are flushed; SystemExit's message convention (a string: printed,
    exit 1) is kept."""
    log = tmp_path / "run.log"
    r = _run(EXIT_CODE, str(log), code, code_expected=expected)
    assert r.stdout == "out, no newline"
    assert r.stderr.startswith("err, no newline")
    if code == "a message":
        assert r.stderr == "err, no newlinea message\n"
    assert log.read_text() == "logged before exit\n"


# ------------------------------------------------------------------------------------------ a sweep's exit

@pytest.mark.slow
def test_a_sweep_set_by_a_config_file_leaves_no_launcher_workers(tmp_path):
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "swept.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /data: synthetic\n  - override /launch: parallel\n"
        "hydra:\n  mode: MULTIRUN\n  sweeper:\n    params:\n      seed: 0,1\n")
    mark = uuid.uuid4().hex
    env = {k: v for k, v in os.environ.items() if k not in ("SCANREG_SWEEP", "MLFLOW_TRACKING_URI")}
    env["SCANREG_TEST_MARK"] = mark
    # output to files, not pipes: leftover workers would hold a pipe open (the caller then waits for them)
    with open(tmp_path / "out.txt", "w") as out, open(tmp_path / "err.txt", "w") as err:
        r = subprocess.run([sys.executable, "-m", "scanreg.app", "--config-dir", str(tmp_path), "experiment=swept",
                            "data.n_points=3000", "sampler.n_points=2000", "tracking=none",
                            f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path, env=env, stdout=out,
                           stderr=err, timeout=600)
    assert r.returncode == 0, (tmp_path / "err.txt").read_text()
    assert (tmp_path / "sweep" / "1" / "result.json").exists()  # it was a sweep

    def marked() -> list[int]:
        found = []
        for p in Path("/proc").glob("[0-9]*/environ"):
            try:
                if f"SCANREG_TEST_MARK={mark}".encode() in p.read_bytes().split(b"\0"):
                    found.append(int(p.parent.name))
            except OSError:
                continue
        return found

    import time

    end = time.monotonic() + 10
    while marked() and time.monotonic() < end:
        time.sleep(0.2)
    left = marked()
    for pid in left:  # started by this test: do not leave them behind
        try:
            os.kill(pid, 9)
        except OSError:
            pass
    assert left == [], f"{len(left)} process(es) of the sweep left running"
