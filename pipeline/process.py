"""How work runs: in a forked child process where a library demands it, and with one BLAS thread in tight loops.

This is the one module of scanreg that forks, opens pipes or calls the C library; the geometry, mesh and stage
code call :func:`run_isolated` and :func:`blas_single_thread` as plain functions.

:func:`run_isolated` exists for pymeshfix. MeshFix keeps state from call to call: in one long process it leaks
memory and gets slower with every repair, and a crash in it (a segmentation fault) would end the run. Run in a
child forked for it, every repair starts from the same clean state, its memory is given back when the child
exits, and a crash is one error line (``experiments/benchmarks/repair_speed.md`` has the measurements).
"""

from __future__ import annotations

import contextlib
import functools
import os
import pickle
import sys


class IsolatedCrash(RuntimeError):
    """The child process ended without an answer (killed by a signal, or exited)."""


THREAD_STACK = 1 << 26
"""Stack size (bytes) of the thread that runs the function in the child: 64 MB, for libraries that recurse
deeply on large meshes (a process's main thread has 8 MB)."""


def forking() -> bool:
    """Whether :func:`run_isolated` forks here (Linux, ``SCANREG_NO_FORK`` unset); elsewhere it calls in place."""
    return sys.platform.startswith("linux") and not os.environ.get("SCANREG_NO_FORK")


def cores() -> int:
    """The cores this process may run on (its CPU affinity; at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def run_isolated(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a child process forked for it; its (picklable) value is returned here. An
    exception in ``fn`` is raised here (the same exception when it pickles, else a ``RuntimeError`` naming its
    type and message); a child that ends without an answer raises :class:`IsolatedCrash`. Without forking
    (:func:`forking`) ``fn`` is called in place. There is no time limit.

    In the child, ``fn`` runs in a new thread: glibc's malloc serves a new thread from an arena that no other
    running thread uses, so a library that allocates many small blocks (MeshFix's linked mesh) gets them side
    by side instead of scattered through the free space of the parent's heap. Standard output and error (C's
    included) are flushed before the fork and before the child leaves, so that a library's messages reach a
    file or a pipe in order."""
    return start_isolated(fn, *args, **kwargs).result()


class Pending:
    """A value being computed by :func:`start_isolated`: :meth:`result` waits for it (once), :meth:`cancel` ends
    the child without it."""

    def __init__(self, pid: int | None = None, fd: int | None = None, value=None, error: BaseException | None = None):
        self._pid, self._fd, self._value, self._error = pid, fd, value, error

    def result(self):
        """The value (or the exception) of the work, as :func:`run_isolated` returns (raises) it."""
        if self._pid is not None:
            pid, self._pid = self._pid, None
            try:
                msg = _receive(self._fd)
            finally:
                os.close(self._fd)
                _, status = os.waitpid(pid, 0)
            if msg is None:
                self._error = IsolatedCrash(_ended(status))
            elif msg[0] == "error":
                self._error = msg[1]
            else:
                self._value = msg[1]
        if self._error is not None:
            raise self._error
        return self._value

    def cancel(self) -> None:
        """End the child (if it is still at work) and reap it; the value is not wanted."""
        if self._pid is not None:
            pid, self._pid = self._pid, None
            os.close(self._fd)
            with contextlib.suppress(OSError):
                os.kill(pid, 9)
            os.waitpid(pid, 0)


def start_isolated(fn, *args, **kwargs) -> Pending:
    """Start ``fn(*args, **kwargs)`` in a forked child (as :func:`run_isolated` runs it) and return at once: the
    caller works on meanwhile and takes the value with :meth:`Pending.result`. Without forking the value is
    computed here, before the call returns."""
    if not forking():
        return _in_place(fn, args, kwargs)
    _flush_all()
    try:
        r, w = os.pipe()
    except OSError:
        return _in_place(fn, args, kwargs)
    _widen(r)
    try:
        pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        return _in_place(fn, args, kwargs)
    if pid == 0:  # the child never returns into the caller's code
        code = 1
        try:
            os.close(r)
            box = []

            def work():
                try:
                    box.append(("ok", fn(*args, **kwargs)))
                except BaseException as e:  # noqa: BLE001  # handed to the parent
                    box.append(("error", _picklable(e)))

            import threading

            threading.stack_size(THREAD_STACK)
            t = threading.Thread(target=work, name="scanreg-isolated")
            t.start()
            t.join()
            try:
                _send(w, box[0])
            except Exception as e:  # noqa: BLE001  # a value that cannot be pickled
                _send(w, ("error", _picklable(e)))
            code = 0
        finally:
            _flush_all()
            os._exit(code)
    os.close(w)
    return Pending(pid, r)


def _in_place(fn, args, kwargs) -> Pending:
    try:
        return Pending(value=fn(*args, **kwargs))
    except BaseException as e:  # noqa: BLE001  # raised by result(), as from a child
        return Pending(error=e)


@contextlib.contextmanager
def blas_single_thread():
    """Run the block with OpenBLAS on one thread. An ICP or RANSAC loop makes many small products (N x 3)
    between calls into OpenMP code (k-d trees, Open3D); OpenBLAS's idle threads would spin between them and
    take the cores from those calls."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


# ------------------------------------------------------------------------------------------------ the pipe

def _send(fd: int, value) -> None:
    """A value into a pipe: the pickle (protocol 5) with its out-of-band buffers (NumPy arrays' data) written as
    they are, each preceded by its length."""
    buffers: list = []
    head = pickle.dumps(value, protocol=5, buffer_callback=buffers.append)
    for chunk in (len(buffers).to_bytes(8, "little"), head, *(b.raw() for b in buffers)):
        data = memoryview(chunk)
        os.write(fd, len(data).to_bytes(8, "little"))
        while len(data):
            data = data[os.write(fd, data):]


def _receive(fd: int):
    """The value :func:`_send` wrote, or None when the pipe ended first."""
    count = _message(fd)
    head = _message(fd) if count is not None else None
    if head is None:
        return None
    buffers = [_message(fd) for _ in range(int.from_bytes(count, "little"))]
    if any(b is None for b in buffers):
        return None
    return pickle.loads(head, buffers=buffers)


def _message(fd: int) -> bytearray | None:
    size = _read_exactly(fd, 8)
    return None if size is None else _read_exactly(fd, int.from_bytes(size, "little"))


def _read_exactly(fd: int, n: int) -> bytearray | None:
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if not k:
            return None
        got += k
    return buf


PIPE_BYTES = 1 << 20
"""The buffer asked for the answer's pipe (Linux's limit for a process without privileges; 64 KiB by default)."""


def _widen(fd: int) -> None:
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
    except (ImportError, OSError):  # not Linux, or over the system's limit: the default buffer
        pass


# ------------------------------------------------------------------------------------------ odds and ends

@functools.cache
def _fflush():
    """C's ``fflush`` (None where there is no C library), looked up once, before any fork."""
    try:
        import ctypes

        fn = ctypes.CDLL(None).fflush
        fn.argtypes, fn.restype = [ctypes.c_void_p], ctypes.c_int
        return fn
    except Exception:  # noqa: BLE001
        return None


def _flush_all() -> None:
    """Python's standard streams and every C stdio stream flushed (``fflush(NULL)``)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001  # closed or replaced by something without flush
            pass
    fn = _fflush()
    if fn is not None:
        try:
            fn(None)
        except Exception:  # noqa: BLE001
            pass


def _picklable(e: BaseException) -> BaseException:
    """``e`` when it survives pickling, else a RuntimeError naming its type and first line."""
    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:  # noqa: BLE001  # an exception whose constructor takes other arguments
        first = (str(e).strip().splitlines() or [""])[0][:200]
        return RuntimeError(f"{type(e).__name__}: {first}")


def _ended(status: int) -> str:
    """How a child ended, for an error line."""
    import signal

    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = str(sig)
        return f"the child process that ran it was killed by signal {sig} ({name})"
    return f"the child process that ran it exited with code {os.WEXITSTATUS(status)} without an answer"
