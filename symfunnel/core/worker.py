"""The killable worker: a call that no signal can interrupt (a large CasADi Jacobian, code generation of a huge
graph, IPOPT) runs in a forked child that the caller kills at a signal, the command's deadline or its own limit.

The signal policy it serves (who hears a signal, who is killed, what is removed) is `lifecycle`'s.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import select
import signal
import sys
import time

from . import deadline
from .lifecycle import become_worker, check, in_worker, register_child, signals_deferred, unregister_child

__all__ = ["Pending", "WorkerDied", "run_killable", "start_killable"]


class WorkerDied(RuntimeError):
    """The forked worker ended without an answer (killed by the system, e.g. out of memory)."""


def run_killable(fn, *args, wall_limit: float | None = None, what: str | None = None, **kwargs):
    """`fn(*args, **kwargs)` in a forked child process the caller can kill: its result, or its exception raised.

    The caller waits in Python, so a signal, the command's deadline or `wall_limit` (seconds, WallLimitReached
    naming `what`) stops the wait at once and kills the child. The result comes back pickled (a casadi.Function
    whole; bare SX comes back with symbols of its own, so return a Function or data); the arguments are not
    pickled (the child is a fork). Without fork, or inside a worker, the call runs
    in this process.
    """
    return start_killable(fn, *args, **kwargs).result(wall_limit=wall_limit, what=what)


def start_killable(fn, *args, **kwargs) -> "Pending":
    """Start `fn(*args, **kwargs)` in a forked child now and return at once: several calls then run side by side
    (on several cores) and `Pending.result` collects each as `run_killable` would; without fork, or inside a
    worker, the call runs in this process when its result is asked for."""
    if not hasattr(os, "fork") or in_worker():
        return Pending(None, None, time.monotonic(), (fn, args, kwargs))
    started = time.monotonic()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    rfd, wfd = os.pipe()
    with signals_deferred():                                # the child is registered before any signal can land
        pid = os.fork()
        if pid:
            register_child(pid)
    if pid == 0:                                            # the worker
        code = 0
        try:
            os.close(rfd)
            become_worker()
            try:
                result = ("ok", fn(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001 - every outcome goes back to the parent
                result = ("err", exc)
            data = _dumps(result)
            view = memoryview(data)
            while view:
                n = os.write(wfd, view)
                view = view[n:]
        except BaseException:  # noqa: BLE001 - the parent sees the missing answer
            code = 1
        finally:
            os._exit(code)
    os.close(wfd)
    return Pending(pid, rfd, started, (getattr(fn, "__name__", "a call"), None, None))


class Pending:
    """A call `start_killable` started: `result` waits for it (killing the child at a limit or a signal), `kill`
    stops it unheard; either reaps the child, once."""

    def __init__(self, pid, rfd, started: float, call: tuple):
        self.pid, self.rfd, self.started, self.call = pid, rfd, started, call

    def result(self, wall_limit: float | None = None, what: str | None = None):
        """The call's result or its exception raised; `wall_limit` counts from the start of the call."""
        if self.pid is None:
            fn, args, kwargs = self.call
            self.call = (getattr(fn, "__name__", "a call"), None, None)
            return fn(*args, **kwargs)
        started, pid, rfd = self.started, self.pid, self.rfd
        self.pid = self.rfd = None
        limit = None if wall_limit is None else started + float(wall_limit)
        chunks: list[bytes] = []
        status = None
        try:
            with deadline.step(what) if what else contextlib.nullcontext():
                while True:
                    check()
                    deadline.check()
                    wait = 0.2
                    if limit is not None:
                        left = limit - time.monotonic()
                        if left <= 0:
                            raise deadline.WallLimitReached(float(wall_limit), what or deadline.current_step(),
                                                            time.monotonic() - started)
                        wait = min(wait, left)
                    ready, _, _ = select.select([rfd], [], [], max(wait, 0.0))
                    if ready:
                        block = os.read(rfd, 1 << 20)
                        if not block:
                            break
                        chunks.append(block)
        except BaseException:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
            raise
        finally:
            os.close(rfd)
            with contextlib.suppress(ChildProcessError):
                _, status = os.waitpid(pid, 0)
            unregister_child(pid)
        if not chunks:
            raise WorkerDied(f"the worker process for {what or self.call[0]} ended without an "
                             f"answer (exit status {status}; out of memory?)")
        with deadline.step(what) if what else contextlib.nullcontext():
            kind, value = _loads(b"".join(chunks))    # unpickling a large graph is part of the step (0.3 s at 343k nodes)
        if kind == "err":
            raise value
        return value

    def kill(self) -> None:
        """Stop the call if it still runs (its result unheard) and reap its child."""
        if self.pid is None:
            self.call = (self.call[0] if isinstance(self.call[0], str) else "a call", None, None)
            return
        pid, rfd = self.pid, self.rfd
        self.pid = self.rfd = None
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(OSError):
            os.close(rfd)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)
        unregister_child(pid)


def _dumps(result) -> bytes:
    try:
        import casadi
        ctx = casadi.global_pickle_context()
    except (ImportError, AttributeError):
        ctx = contextlib.nullcontext()
    try:
        with ctx:
            return pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - an unpicklable result or exception: say what it was
        kind, value = result
        text = f"{type(value).__name__}: {value}" if kind == "err" else f"a {type(value).__name__}"
        return pickle.dumps(("err", RuntimeError(f"the worker's answer ({text}) could not be returned: {exc}")))


def _loads(data: bytes):
    try:
        import casadi
        ctx = casadi.global_unpickle_context()
    except (ImportError, AttributeError):
        ctx = contextlib.nullcontext()
    with ctx:
        return pickle.loads(data)
