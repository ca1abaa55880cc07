"""Work in a forked child process, and the messages between the two (the geometry core: imports no stage).

:func:`run_isolated` runs a function in a child forked for it and returns its value: a library that keeps state
from call to call (pymeshfix leaks about 13 MB per 100k-face repair and gets slower with each repair in one
process: 1.09 s, then 1.43, 1.64, 1.87, 1.84, 1.95 s for the same bunny; in a fresh child each time 1.01-1.11 s)
runs from the same clean state every time, its memory is given back when the child exits (not freed piece by
piece: MeshFix's mesh takes 10-20 ms to free), and a crash in it (a segmentation fault) ends the child, not the
run. The child may ask this process for a value while it works (:func:`run_isolated`'s ``ask``: the repair's
border plan, made beside the backend). On Linux only (elsewhere, and with ``SCANREG_NO_FORK`` set, the function
runs here); the caller's process keeps the GIL free while it waits, so its threads go on.

Messages: a length (8 bytes, little-endian), then that many bytes (:func:`send_message`, :func:`read_message`).
"""

from __future__ import annotations

import functools


class IsolatedCrash(RuntimeError):
    """The child process ended without an answer (killed by a signal, or exited)."""


def send_message(fd: int, payload) -> None:
    """One message (its length, then the bytes: ``bytes`` or a byte ``memoryview``, written without a copy) into
    a pipe."""
    import os

    data = memoryview(payload)
    os.write(fd, len(data).to_bytes(8, "little"))  # 8 bytes: one write, whole (under the pipe's atomic size)
    while len(data):
        data = data[os.write(fd, data):]


def read_message(fd: int) -> bytearray | None:
    """The next message from a pipe (blocking; its bytes read straight into a buffer of their own), or None when
    the pipe ends before a whole message."""
    head = _read_exactly(fd, 8)
    return None if head is None else _read_exactly(fd, int.from_bytes(head, "little"))


def _read_exactly(fd: int, n: int) -> bytearray | None:
    import os

    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if not k:
            return None
        got += k
    return buf


def send_value(fd: int, value) -> None:
    """A picklable value into a pipe: the count of its out-of-band buffers, the pickle, then the buffers (NumPy
    arrays' data, pickle protocol 5) written as they are, without copies."""
    import pickle

    buffers: list = []
    head = pickle.dumps(value, protocol=5, buffer_callback=buffers.append)
    send_message(fd, len(buffers).to_bytes(8, "little"))
    send_message(fd, head)
    for b in buffers:
        send_message(fd, b.raw())


def read_value(fd: int):
    """The value :func:`send_value` wrote (its arrays on writable memory of their own), and whether one came
    (False when the pipe ended first)."""
    import pickle

    count, head = read_message(fd), read_message(fd)
    if count is None or head is None:
        return None, False
    buffers = [read_message(fd) for _ in range(int.from_bytes(count, "little"))]
    if any(b is None for b in buffers):
        return None, False
    return pickle.loads(head, buffers=buffers), True


def forking() -> bool:
    """Whether work beside or apart is done in forked child processes here (Linux, ``SCANREG_NO_FORK`` unset)."""
    import os
    import sys

    return sys.platform.startswith("linux") and not os.environ.get("SCANREG_NO_FORK")


def fork_with_pipes(n: int, widen: tuple[int, ...] = ()) -> tuple[int, list[int]] | None:
    """``n`` pipes made, then this process forked: ``(pid, [read end, write end] * n)`` in both processes (pid
    0 in the child), or None when a pipe or the fork failed (nothing left open). The pipes numbered in ``widen``
    get a buffer of :data:`PIPE_BYTES`. Python >= 3.12 warns about forking a process with threads; the warning
    is silenced (the children of this project run their own code and leave with ``os._exit``)."""
    import os
    import warnings

    fds: list[int] = []
    try:
        for k in range(n):
            fds.extend(os.pipe())
            if k in widen:
                _widen(fds[-1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except OSError:
        for fd in fds:
            os.close(fd)
        return None
    return pid, fds


THREAD_STACK = 1 << 26
"""Stack size (bytes) of the thread that runs the function in the child (``own_heap``): 64 MB, more than a
process's usual main thread (8 MB), for libraries that recurse deeply on large meshes."""


def run_isolated(fn, ask=None, own_heap: bool = True, started=None):
    """``fn(asked)`` in a child process forked for it; its value (picklable) returned here. ``asked()``, called
    in the child, returns ``ask()`` computed in this process (None without ``ask``). An exception in ``fn`` is
    raised here (the same exception when it can be pickled, else a RuntimeError with its type and message; so
    is the error of pickling a value that cannot be), and so is one in ``ask`` (the child is then
    stopped). A child that ends without an answer raises :class:`IsolatedCrash`. Without forking
    (:func:`forking`), ``fn`` runs here, ``asked`` calling ``ask``. There is no time limit: a function that hangs
    hangs the caller, as it would in this process.

    ``own_heap``: ``fn`` runs in a new thread of the child, which glibc's malloc serves from an arena that no
    other running thread uses (a fresh one, or one a finished thread of this process left), never from the main
    heap: a library that allocates many small blocks (MeshFix's mesh: about 600 000 for 100k faces) gets them
    side by side, not scattered through the free space of a heap that other work has used. Measured (the
    bunny, one long process that also ran MeshLab and the audits): MeshFix in the child's main thread 1.36, 1.36,
    1.74, 1.61, 1.74, 1.73 s; in a new thread 1.18, 1.10, 1.13, 1.12, 1.10, 1.15 s (in this process itself it
    went from 1.0 to 1.9 s).

    ``started()``, when given, is called here once the child runs (before ``fn`` without forking): work to
    start beside it (the repair's input audit). If it raises, the child is stopped and reaped and the exception
    raised here (without forking ``fn`` does not run): a caller may start the child on a guess and call it off.
    The pipes' ends this process keeps are closed in every child forked later (:func:`keep_from_children`), so
    that such a child never holds them open.

    Standard output and error are flushed before the fork and in the child before it leaves (MeshFix's messages
    with ``verbose``, printed by C code, reach a file or a pipe)."""
    import os

    def here():
        return None if ask is None else ask()

    def run_here():
        if started is not None:
            started()
        return fn(here)

    if not forking():
        return run_here()
    flush = _flush_all
    flush()
    forked = fork_with_pipes(2, widen=(0,))  # child -> here: questions, then the answer; here -> child: replies
    if forked is None:
        return run_here()
    pid, (up_r, up_w, down_r, down_w) = forked
    if pid == 0:  # the child: it never returns into the caller's code
        global _IN_CHILD
        _IN_CHILD = True
        code = 1
        try:
            os.close(up_r)
            os.close(down_w)

            def asked():
                send_value(up_w, ("ask", None))
                reply, ok = read_value(down_r)
                if not ok:  # the parent gave up (its ask failed)
                    os._exit(1)
                return reply

            box = []

            def work():
                try:
                    box.append(("ok", fn(asked)))
                except BaseException as e:  # noqa: BLE001: handed to the parent
                    box.append(("error", _picklable(e)))

            if own_heap:  # a new thread: glibc's malloc gives it an arena of its own
                import threading

                threading.stack_size(THREAD_STACK)
                t = threading.Thread(target=work, name="scanreg-isolated")
                t.start()
                t.join()
            else:
                work()
            try:  # (send_value pickles before it writes: nothing is written when that fails)
                send_value(up_w, box[0])
            except Exception as e:  # noqa: BLE001: a value that cannot be pickled
                send_value(up_w, ("error", _picklable(e)))
            code = 0
        finally:
            flush()
            os._exit(code)
    os.close(up_w)
    os.close(down_r)
    keep_from_children(up_r, down_w)
    done = False
    try:
        if started is not None:
            started()
        while True:
            msg, ok = read_value(up_r)
            if not ok:
                _, status = os.waitpid(pid, 0)
                done = True
                raise IsolatedCrash(_ended(status))
            kind, value = msg
            if kind == "ask":
                reply = here()
                try:
                    send_value(down_w, reply)
                except OSError:  # the child is gone: the next read finds the pipe's end, and says how it ended
                    pass
                continue
            if kind == "error":
                raise value
            return value
    except BaseException:
        if not done:
            kill(pid)
        raise
    finally:
        release(up_r, down_w)
        if not done:  # reaped by a thread: its exit (unmapping its memory) is not waited for here
            import threading

            threading.Thread(target=os.waitpid, args=(pid, 0), daemon=True, name="scanreg-reap").start()


_IN_CHILD = False
"""True in a child process of :func:`run_isolated`."""
_SPARED: list = []


def spare(obj) -> None:
    """Keep ``obj`` alive until the process ends when this is a child of :func:`run_isolated`: its memory is
    then given back with the whole child's at exit, not freed piece by piece before the answer is sent
    (MeshFix's mesh of the bunny, 100k faces, takes 12-14 ms to free). Elsewhere nothing is kept (``obj`` is
    freed as usual)."""
    if _IN_CHILD:
        _SPARED.append(obj)


def kill(pid: int) -> None:
    """Stop a child process at once (SIGKILL; nothing happens when it is gone already)."""
    import os
    import signal

    try:
        os.kill(pid, signal.SIGKILL)
    except OSError:
        pass


_KEPT: set[int] = set()
"""File descriptors of pipes to and from child processes that this process keeps (its ends): every child forked
later closes them at once (an ``os.register_at_fork`` hook), so that no other child holds a pipe open and its
reader or writer sees the pipe's end when its process does."""


def keep_from_children(*fds: int) -> None:
    """Mark ``fds`` (this process's ends of pipes to a child, made before that child was forked) to be closed in
    every child forked from now on; :func:`release` closes them here."""
    _hook()
    _KEPT.update(fds)


def release(*fds: int) -> None:
    """Close ``fds`` here (ends marked with :func:`keep_from_children`, or not) and forget them."""
    import os

    for fd in fds:
        _KEPT.discard(fd)
        try:
            os.close(fd)
        except OSError:
            pass


def _close_kept_in_child() -> None:
    release(*_KEPT)


@functools.cache
def _hook() -> None:
    import os

    if hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=_close_kept_in_child)


@functools.cache
def _fflush():
    """C's ``fflush`` (None where there is no C library to look up), looked up once, before any fork."""
    try:
        import ctypes

        fn = ctypes.CDLL(None).fflush
        fn.argtypes, fn.restype = [ctypes.c_void_p], ctypes.c_int
        return fn
    except Exception:  # noqa: BLE001
        return None


def _flush_all() -> None:
    """Python's standard streams and every C stdio stream flushed (``fflush(NULL)``)."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001: closed or replaced by something without flush
            pass
    fn = _fflush()
    if fn is not None:
        try:
            fn(None)
        except Exception:  # noqa: BLE001
            pass


PIPE_BYTES = 1 << 20
"""The buffer asked for the pipe that brings a child's answer (Linux's limit for a process without privileges;
64 KiB by default): a few large writes and reads instead of many small ones."""


def _widen(fd: int) -> None:
    """The pipe of ``fd`` given a buffer of :data:`PIPE_BYTES` where the system allows it."""
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
    except (ImportError, OSError):  # not Linux, or over the system's limit: the default buffer
        pass


def _picklable(e: BaseException) -> BaseException:
    """``e`` when it survives pickling, else a RuntimeError naming its type and first line."""
    import pickle

    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:  # noqa: BLE001: an exception whose constructor takes other arguments
        first = (str(e).strip().splitlines() or [""])[0][:200]
        return RuntimeError(f"{type(e).__name__}: {first}")


def _ended(status: int) -> str:
    """How a child ended, for an error line."""
    import os
    import signal

    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = str(sig)
        return f"the child process that ran it was killed by signal {sig} ({name})"
    return f"the child process that ran it exited with code {os.WEXITSTATUS(status)} without an answer"
