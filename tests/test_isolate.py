"""scanreg.process.run_isolated: work in a forked child process (values and arrays back, errors and crashes as
exceptions, no child left behind, the same results without forking), and the meshfix backend run that way."""

from __future__ import annotations

import faulthandler
import os
import signal
import sys

import numpy as np
import pytest

from conftest import children, settled
from scanreg.process import IsolatedCrash, forking, run_isolated

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked children on Linux only")


@linux
def test_values_and_arrays_come_back():
    """The child's value (arrays on writable memory of their own, several MB), made from the positional and
    keyword arguments; the work runs in another process, in a thread of its own there; no child is left."""
    import threading

    rng = np.random.default_rng(0)
    big = rng.normal(size=(300_000, 3))  # 7 MB: more than the pipe's buffer

    def work(a, scale, *, label, extra=None):
        return os.getpid(), threading.current_thread().name, a * scale, (label, extra), np.int32(7)

    before = children()
    pid, thread, doubled, named, seven = run_isolated(work, big, 2.0, label="x", extra=[1, 2])
    assert pid != os.getpid() and thread == "scanreg-isolated"
    assert np.array_equal(doubled, big * 2.0) and doubled.flags.writeable
    doubled[0, 0] = 1.0  # its own memory
    assert named == ("x", [1, 2]) and seven == 7 and isinstance(seven, np.int32)
    assert run_isolated(lambda: None) is None
    assert settled(before)


def test_the_same_without_forking(monkeypatch):
    """SCANREG_NO_FORK: the function runs in this process and thread, with its arguments; the same value as
    in a child."""
    import threading

    def work(n, *, times):
        return np.arange(n) * times, os.getpid(), threading.current_thread().name

    monkeypatch.setenv("SCANREG_NO_FORK", "1")
    assert not forking()
    value, pid, thread = run_isolated(work, 5, times=3)
    assert pid == os.getpid() and thread == threading.current_thread().name
    assert np.array_equal(value, np.arange(5) * 3)
    monkeypatch.delenv("SCANREG_NO_FORK")
    if sys.platform.startswith("linux"):
        assert forking()
        forked, pid, _ = run_isolated(work, 5, times=3)
        assert pid != os.getpid() and np.array_equal(forked, value)


class NeedsTwo(Exception):
    def __init__(self, a, b):  # pickling calls the class with args (a message only): unpickling fails
        super().__init__(f"{a} and {b}")


@linux
def test_errors_in_the_child_are_raised_here():
    """An exception in the child is raised here: the same type and message when it survives pickling, else a
    RuntimeError naming its type and first line; the child is reaped either way."""
    def fails(what):
        raise ValueError(f"no {what} left")

    before = children()
    with pytest.raises(ValueError, match="no faces left"):
        run_isolated(fails, "faces")

    def fails_oddly():
        raise NeedsTwo("one", "two")

    with pytest.raises(RuntimeError, match="NeedsTwo: one and two"):
        run_isolated(fails_oddly)
    assert settled(before)


@linux
def test_a_crash_is_an_error_not_the_end_of_the_run():
    """A child killed by a signal (a segmentation fault in a library) raises IsolatedCrash naming the signal;
    this process goes on."""
    def crashes():
        faulthandler.disable()  # (pytest's would print the child's stack)
        os.kill(os.getpid(), signal.SIGSEGV)

    before = children()
    with pytest.raises(IsolatedCrash, match=r"killed by signal 11 \(SIGSEGV\)"):
        run_isolated(crashes)
    assert settled(before)
    with pytest.raises(IsolatedCrash, match=r"exited with code 3 without an answer"):
        run_isolated(os._exit, 3)  # a child that leaves without an answer
    assert settled(before)
    assert run_isolated(lambda: 5) == 5


@linux
def test_meshfix_crash_is_one_error_line(monkeypatch):
    """A crash inside MeshFix (simulated: its session kills its own process) fails the repair with the
    backend's one error line, and leaves no child process behind."""
    import scanreg.stages.repair.meshfix as meshfix_module
    from scanreg.errors import StageError
    from scanreg.io import read_mesh
    from scanreg.stages.registry import REPAIR, load_all, make_params
    from scanreg.types import RunContext as Context

    load_all()
    cls = REPAIR.get("meshfix")
    st = cls(make_params(cls.Params, {"cache": "off", "scope": "whole"}, "meshfix"))

    def crashes(*args):
        faulthandler.disable()  # (pytest's would print the child's stack)
        os.kill(os.getpid(), signal.SIGSEGV)

    monkeypatch.setattr(meshfix_module, "_meshfix_session", crashes)
    mesh = read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj")
    before = children()
    with pytest.raises(StageError, match=r"repair=meshfix: .*cow\.obj: the backend failed \(IsolatedCrash: "
                                         r"the child process that ran it was killed by signal 11") as err:
        st.repair(mesh, Context(seed=0, run_dir=None))
    assert "\n" not in str(err.value)
    assert settled(before)


@linux
def test_a_value_that_cannot_be_pickled_is_named():
    """A value the child cannot send back raises the pickling error here (it names the reason), not a crash."""
    import pickle
    import threading

    with pytest.raises((TypeError, pickle.PicklingError), match="pickle"):
        run_isolated(lambda: threading.Lock())


def _meshfix_stage(**params):
    from scanreg.stages.registry import REPAIR, load_all, make_params

    load_all()
    cls = REPAIR.get("meshfix")
    return cls(make_params(cls.Params, {"cache": "off", **params}, "meshfix"))


@linux
@pytest.mark.parametrize("scope, session", [("whole", "_meshfix_session"), ("defects", "_region_sessions")])
def test_meshfix_failure_in_its_child_leaves_no_process(monkeypatch, scope, session):
    """An exception inside MeshFix's session (in its child: the whole mesh's, or the defective regions') is the
    backend's one error line, and the child is reaped."""
    import scanreg.stages.repair.meshfix as meshfix_module
    from scanreg.errors import StageError
    from scanreg.io import read_mesh
    from scanreg.types import RunContext as Context

    def breaks(*args):
        raise RuntimeError("MeshFix broke")

    monkeypatch.setattr(meshfix_module, session, breaks)
    before = children()
    with pytest.raises(StageError, match=r"the backend failed \(RuntimeError: MeshFix broke\)"):
        _meshfix_stage(scope=scope).repair(read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"),
                                           Context(seed=0, run_dir=None))
    assert settled(before)


def test_meshfix_in_children_is_meshfix_here(monkeypatch):
    """MeshFix in child processes gives the same mesh and metrics, bit for bit, as in this process
    (SCANREG_NO_FORK), on a mesh of two parts (two sessions) and, with ../shared/data, on MeshLab's
    non-manifold hole (the degeneracy session)."""
    from scanreg.geometry import Mesh
    from scanreg.io import read_mesh, shared_data_dir
    from scanreg.types import RunContext as Context

    cow = read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj")
    shift = cow.vertices.max(axis=0) - cow.vertices.min(axis=0)
    two = Mesh(np.vstack([cow.vertices, cow.vertices + 1.5 * shift]),
               np.vstack([cow.faces, cow.faces + len(cow.vertices)]), "two cows")
    meshes = [two]
    hole = shared_data_dir() / "meshlab_defects" / "non_manif_hole.ply"
    if hole.exists():
        meshes.append(read_mesh(str(hole)))

    def run(mesh):
        res = _meshfix_stage().repair(Mesh(mesh.vertices.copy(), mesh.faces.copy(), mesh.source),
                                      Context(seed=0, run_dir=None))
        return res.mesh, {k: v for k, v in res.metrics.items() if not k.endswith("_time_s")}

    for mesh in meshes:
        monkeypatch.delenv("SCANREG_NO_FORK", raising=False)
        forked = run(mesh)
        monkeypatch.setenv("SCANREG_NO_FORK", "1")
        here = run(mesh)
        assert np.array_equal(forked[0].vertices, here[0].vertices)
        assert np.array_equal(forked[0].faces, here[0].faces)
        assert forked[1] == here[1]
    assert forked[1]["before_components"] >= 1
    if not hole.exists():
        pytest.skip(f"{hole} absent (../shared/data): only the two cows were repaired both ways")
