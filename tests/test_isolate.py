"""scanreg.isolate: work in a forked child process (values and arrays back, questions to the parent, errors and
crashes as exceptions, the same results without forking), and the meshfix backend run that way."""

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
def test_value_arrays_and_questions_come_back():
    """The child's value (arrays on writable memory of their own, several MB) and its questions answered by the
    parent, in order; the work runs in another process, in a thread of its own there."""
    import threading

    rng = np.random.default_rng(0)
    big = rng.normal(size=(300_000, 3))  # 7 MB: more than the pipe's buffer
    asked_here = []

    def ask():
        asked_here.append(len(asked_here))
        return {"n": len(asked_here)}

    def work(asked):
        first, second = asked(), asked()
        return os.getpid(), threading.current_thread().name, big * 2.0, (first["n"], second["n"]), np.int32(7)

    before = children()
    pid, thread, doubled, answers, seven = run_isolated(work, ask=ask)
    assert pid != os.getpid() and thread == "scanreg-isolated"
    assert np.array_equal(doubled, big * 2.0) and doubled.flags.writeable
    doubled[0, 0] = 1.0  # its own memory
    assert answers == (1, 2) and asked_here == [0, 1] and seven == 7
    assert settled(before)


def test_the_same_without_forking(monkeypatch):
    """SCANREG_NO_FORK: the function runs in this process and thread, ``asked`` calling ``ask`` directly; the
    same value as in a child."""
    def work(asked):
        return np.arange(5) * asked(), os.getpid()

    monkeypatch.setenv("SCANREG_NO_FORK", "1")
    assert not forking()
    value, pid = run_isolated(work, ask=lambda: 3)
    assert pid == os.getpid() and np.array_equal(value, np.arange(5) * 3)
    assert run_isolated(lambda asked: asked()) is None  # no ask: None
    monkeypatch.delenv("SCANREG_NO_FORK")
    if sys.platform.startswith("linux"):
        forked, pid = run_isolated(work, ask=lambda: 3)
        assert pid != os.getpid() and np.array_equal(forked, value)


class NeedsTwo(Exception):
    def __init__(self, a, b):  # pickling calls the class with args (a message only): unpickling fails
        super().__init__(f"{a} and {b}")


@linux
def test_errors_in_the_child_are_raised_here():
    """An exception in the child is raised here: the same type and message when it survives pickling, else a
    RuntimeError naming its type and first line."""
    def fails(asked):
        raise ValueError("no faces left")

    with pytest.raises(ValueError, match="no faces left"):
        run_isolated(fails)

    def fails_oddly(asked):
        raise NeedsTwo("one", "two")

    with pytest.raises(RuntimeError, match="NeedsTwo: one and two"):
        run_isolated(fails_oddly)


@linux
def test_a_failing_question_stops_the_child():
    """An exception in ``ask`` (here, in the parent) is raised, and the child waiting for the answer is stopped
    and reaped."""
    def ask():
        raise KeyError("the plan failed")

    before = children()
    with pytest.raises(KeyError, match="the plan failed"):
        run_isolated(lambda asked: asked(), ask=ask)
    assert settled(before)


@linux
def test_a_crash_is_an_error_not_the_end_of_the_run():
    """A child killed by a signal (a segmentation fault in a library) raises IsolatedCrash naming the signal;
    this process goes on."""
    def crashes(asked):
        faulthandler.disable()  # (pytest's would print the child's stack)
        os.kill(os.getpid(), signal.SIGSEGV)

    before = children()
    with pytest.raises(IsolatedCrash, match=r"killed by signal 11 \(SIGSEGV\)"):
        run_isolated(crashes)
    assert settled(before)
    assert run_isolated(lambda asked: 5) == 5


@linux
def test_meshfix_crash_is_one_error_line(monkeypatch):
    """A crash inside MeshFix (simulated: its session kills its own process) fails the repair with the
    backend's one error line, and leaves no child process behind."""
    from scanreg.types import RunContext as Context
    from scanreg.errors import StageError
    from scanreg.io import read_mesh
    from scanreg.stages.registry import REPAIR, load_all, make_params
    import scanreg.stages.repair.meshfix as meshfix_module

    load_all()
    cls = REPAIR.get("meshfix")
    st = cls(make_params(cls.Params, {"cache": "off"}, "meshfix"))

    def crashes(*args):
        faulthandler.disable()  # (pytest's would print the child's stack)
        os.kill(os.getpid(), signal.SIGSEGV)

    monkeypatch.setattr(meshfix_module, "_meshfix_session", crashes)
    mesh = read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj")
    before = children()
    with pytest.raises(StageError, match=r"repair=meshfix: .*cow\.obj: the backend failed \(IsolatedCrash: "
                                         r"the child process that ran it was killed by signal 11") as err:
        st.repair(mesh, Context(seed=0, run_dir=None), "r_")
    assert "\n" not in str(err.value)
    assert settled(before)


@linux
def test_started_runs_once_beside_and_a_failure_stops_the_child():
    """``started`` runs here once the child runs (before ``fn`` without forking); a later child does not hold
    this process's ends of the pipes (they are closed in it at once); a failure in ``started`` stops the child."""
    import scanreg.isolate as iso

    calls = []

    def started():
        calls.append(set(iso._KEPT))
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # a child forked beside (as the repair's audit is): are this process's ends open in it?
            open_here = sum(1 for fd in calls[-1] if _is_open(fd))
            os.write(w, bytes([open_here]))
            os._exit(0)
        os.close(w)
        calls.append(os.read(r, 1)[0])
        os.close(r)
        os.waitpid(pid, 0)

    assert run_isolated(lambda asked: 3, started=started) == 3
    kept, open_in_later_child = calls
    assert len(kept) == 2 and open_in_later_child == 0  # the answer's read end and the replies' write end

    def fails():
        raise OSError("could not start the audit")

    before = children()
    with pytest.raises(OSError, match="could not start the audit"):
        run_isolated(lambda asked: asked(), ask=lambda: 1, started=fails)
    assert settled(before)
    order = []
    os.environ["SCANREG_NO_FORK"] = "1"
    try:
        run_isolated(lambda asked: order.append("fn"), started=lambda: order.append("started"))
    finally:
        del os.environ["SCANREG_NO_FORK"]
    assert order == ["started", "fn"]


def _is_open(fd: int) -> bool:
    try:
        os.fstat(fd)
        return True
    except OSError:
        return False


@linux
def test_a_value_that_cannot_be_pickled_is_named():
    """A value the child cannot send back raises the pickling error here (it names the reason), not a crash."""
    import pickle
    import threading

    with pytest.raises((TypeError, pickle.PicklingError), match="pickle"):
        run_isolated(lambda asked: threading.Lock())


def _meshfix_stage():
    from scanreg.stages.registry import REPAIR, load_all, make_params

    load_all()
    cls = REPAIR.get("meshfix")
    return cls(make_params(cls.Params, {"cache": "off"}, "meshfix"))


@linux
def test_meshfix_failure_in_its_child_leaves_no_process(monkeypatch):
    """An exception inside MeshFix's session is the backend's one error line, and the input audit's child,
    started beside it and waiting for its request, is closed and reaped."""
    from scanreg.types import RunContext as Context
    from scanreg.errors import StageError
    from scanreg.io import read_mesh
    import scanreg.stages.repair.meshfix as meshfix_module

    def breaks(*args):
        raise RuntimeError("MeshFix broke")

    monkeypatch.setattr(meshfix_module, "_meshfix_session", breaks)
    before = children()
    with pytest.raises(StageError, match=r"the backend failed \(RuntimeError: MeshFix broke\)"):
        _meshfix_stage().repair(read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"),
                                Context(seed=0, run_dir=None), "r_")
    assert settled(before)


def test_meshfix_in_children_is_meshfix_here(monkeypatch):
    """MeshFix in child processes gives the same mesh and metrics, bit for bit, as in this process
    (SCANREG_NO_FORK), on a mesh of two parts (two sessions) and, with ../shared/data, on MeshLab's
    non-manifold hole (the degeneracy session)."""
    from scanreg.types import RunContext as Context
from scanreg.io import shared_data_dir
    from scanreg.geometry import Mesh
    from scanreg.io import read_mesh

    cow = read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj")
    shift = cow.vertices.max(axis=0) - cow.vertices.min(axis=0)
    two = Mesh(np.vstack([cow.vertices, cow.vertices + 1.5 * shift]),
               np.vstack([cow.faces, cow.faces + len(cow.vertices)]), "two cows")
    meshes = [two]
    hole = shared_data_dir() / "meshlab_defects" / "non_manif_hole.ply"
    if hole.exists():
        meshes.append(read_mesh(str(hole)))

    def run(mesh):
        out, m = _meshfix_stage().repair(Mesh(mesh.vertices.copy(), mesh.faces.copy(), mesh.source),
                                         Context(seed=0, run_dir=None), "r_")
        return out, {k: v for k, v in m.items() if not k.endswith("_time_s")}

    for mesh in meshes:
        monkeypatch.delenv("SCANREG_NO_FORK", raising=False)
        forked = run(mesh)
        monkeypatch.setenv("SCANREG_NO_FORK", "1")
        here = run(mesh)
        assert np.array_equal(forked[0].vertices, here[0].vertices)
        assert np.array_equal(forked[0].faces, here[0].faces)
        assert forked[1] == here[1]
    assert forked[1]["r_before_components"] >= 1


class _Marks:
    """An object that writes ``freed`` to a file when it is freed."""

    def __init__(self, path):
        self.path = path

    def __del__(self):
        with open(self.path, "a") as fh:
            fh.write("freed\n")


@linux
def test_spared_objects_are_not_freed_in_the_child(tmp_path):
    """``spare`` keeps an object alive in a child of run_isolated (given back with the child at exit, not freed
    before the answer); without it the object is freed when the function returns; in this process ``spare``
    keeps nothing."""
    from scanreg import isolate

    log = tmp_path / "log"

    def work(spared):
        def inner(_):
            obj = _Marks(log)
            if spared:
                isolate.spare(obj)
            return 7
        return inner

    assert run_isolated(work(False)) == 7
    assert log.read_text() == "freed\n"
    log.unlink()
    assert run_isolated(work(True)) == 7
    assert not log.exists()
    before = len(isolate._SPARED)
    isolate.spare(_Marks(log))  # here: not kept
    assert len(isolate._SPARED) == before and log.read_text() == "freed\n"
