"""Process-level behaviour of the CLI: one signal policy for every long call, and warnings as one line on stderr.

The policy (docs/architecture.md, "Signals and long calls"):

- SIGINT, SIGTERM and SIGHUP are recorded and raised in the main thread (`KeyboardInterrupt`, `Terminated`), so
  every `finally` / `except BaseException` clean-up runs (atomic writes remove their temporary files, the compile
  cache its half-built directory, the compiler and forked workers are killed).
- A raise that lands where Python cannot deliver it (a weakref callback, a finalizer or a Cython `noexcept`
  function swallows it, the last after printing it through `sys.excepthook`, which stays quiet for it; a C callback
  turns it into a SystemError or CasADi's "... KeyboardInterrupt" RuntimeError) is not lost: `check()` re-raises a
  recorded signal, a swallowed one is re-delivered to the main thread, and the CLI reads the record.
- A watchdog thread hears every signal at once (through the wakeup fd, also while the main thread is inside one
  long C call) and watches the command's wall-clock limit. When the main thread has not finished unwinding
  `GRACE` seconds after a signal (or after the limit), the watchdog stops the process itself: it kills the
  registered child processes, removes the registered temporary files, prints the one line and exits with
  128 + signal (1 for the limit).
- Heavy calls that no signal can interrupt (a large CasADi Jacobian, code generation of a huge graph, IPOPT) run
  in a forked worker, `worker.run_killable(fn, *args, wall_limit=S)`, which the caller kills at a signal or a
  deadline, so the Python API's `wall_limit=` bounds them too.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import select
import shutil
import signal
import sys
import threading
import time
import warnings

from . import deadline

__all__ = ["Terminated", "install", "uninstall", "check", "pending", "reraise_interrupt",
           "become_worker", "in_worker", "register_temporary", "unregister_temporary", "register_child", "unregister_child", "announce",
           "exit_code", "die_with_parent", "quiet_c_output", "user_stderr", "signals_deferred", "committing", "late_signal", "too_late", "finished", "decided", "GRACE"]

#: seconds the main thread has to unwind after a signal or the wall-clock limit before the watchdog stops the process
GRACE = 1.0
#: exit code per terminating signal
TERMINATING = {int(getattr(signal, n)): 128 + int(getattr(signal, n)) for n in ("SIGINT", "SIGTERM", "SIGHUP")
               if hasattr(signal, n)}

_saved: dict = {}
_pending: list[int] = []          # signals received and not yet turned into an exit code by the CLI
_temporaries: dict[str, None] = {}    # paths (files or directories) a stopped process must not leave behind
_children: dict[int, bool] = {}   # pid -> True when it leads its own process group (kill the group)
_lock = threading.Lock()
_announced: list[str] = []
_done = threading.Event()
_state = {"worker": False, "thread": None, "wakeup": None, "redeliver": None, "deferred": 0,
          "committed": None, "late": None, "redelivered": 0}
_user: dict = {"err": None}       # the terminal's stderr while quiet_c_output captures the rest


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM (or SIGHUP)."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = signum


def _exception(signum: int) -> BaseException:
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def _raise(signum, frame):
    if _pending:                            # a signal is already stopping the command: one exit code, one line
        if _state["redelivered"]:           # unless this is the watchdog delivering a swallowed one again
            _state["redelivered"] -= 1
            raise _exception(_pending[-1])
        return
    if _state["committed"] is not None:     # the command's output is complete: too late to stop it (`committing`)
        too_late(signum)
        return
    _pending.append(int(signum))
    if _state["deferred"]:                  # inside signals_deferred(): raised when that block ends
        return
    raise _exception(int(signum))


@contextlib.contextmanager
def signals_deferred():
    """A block no terminating signal interrupts: one that arrives is recorded and raised as the block ends. For
    the few statements between starting a child process and registering it (`register_child`): a signal landing
    there would leave a child nobody kills."""
    _state["deferred"] += 1
    try:
        yield
    finally:
        _state["deferred"] -= 1
        if not _state["deferred"]:
            check()


@contextlib.contextmanager
def committing(code: int = 0):
    """The block that writes a command's last output (nothing but reporting follows it). No signal interrupts the
    block; once it has completed, the command has succeeded, and a signal that arrived during it or arrives later
    neither undoes nor denies that: the command prints what is left and exits with its own code (`code`, should the
    watchdog have to end a process that does not get there), one line saying the signal came too late
    (`late_signal`). A block that fails raises the signal as `signals_deferred` does. A signal recorded before the
    block and swallowed on its way (a C call turned it into an error that a report section showed) stops the
    command here: it came before the output, not after."""
    check()
    _state["deferred"] += 1
    ok = False
    try:
        yield
        ok = True
    finally:
        _state["deferred"] -= 1
        if ok:
            _state["committed"] = int(code)
            if _pending:
                too_late(_pending[-1])
                _pending.clear()
        elif not _state["deferred"]:
            check()


LATE = "symfunnel: signal {} came after the command's work was complete; its exit code stands"


def too_late(signum, frame=None) -> None:
    """Record a signal that came after the command's output was complete and say so on stderr, once (a signal
    handler too: the CLI's after its exit code is decided, so the line is never lost)."""
    first = _state["late"] is None
    _state["late"] = int(signum)
    if first:
        with contextlib.suppress(OSError):
            os.write(2, (LATE.format(int(signum)) + "\n").encode())


def decided(code: int | None) -> None:
    """The CLI's exit code is decided (`code`; None when argparse exits): a signal from now on neither raises nor
    changes it -- said once (`too_late`), or not at all when a signal already stopped the command."""
    if _state["committed"] is None and not _pending:
        _state["committed"] = 0 if code is None else int(code)


def finished(late: int | None = None) -> None:
    """The CLI's exit code is decided (call before `uninstall(restore_signals=False)`, so no instant has the default
    handlers): a terminating signal during the interpreter's shutdown would only turn a finished command into a
    killed one, so from now on it is only said (`too_late`), or ignored after a command a signal stopped."""
    if threading.current_thread() is not threading.main_thread():
        return
    stopped = bool(_pending)
    _state["late"] = late
    for sig in TERMINATING:
        signal.signal(sig, signal.SIG_IGN if stopped else too_late)
    import atexit
    atexit.register(_ignore_terminating)


def _ignore_terminating() -> None:
    # the interpreter's finalisation resets Python's handlers to the default action, which would kill a finished
    # command; ignored from the last atexit call on, a signal there leaves the exit code as it is
    for sig in TERMINATING:
        with contextlib.suppress(OSError, ValueError):
            signal.signal(sig, signal.SIG_IGN)


def late_signal() -> int | None:
    """A terminating signal that arrived after the command's output was complete (`committing`), or None."""
    return _state["late"]


def pending() -> int | None:
    """The last terminating signal received and not yet handled by the CLI (None: none)."""
    return _pending[-1] if _pending else None


def check() -> None:
    """Raise the recorded signal again (for a raise that was swallowed on its way: finalizers, C callbacks)."""
    if _pending and threading.current_thread() is threading.main_thread():
        raise _exception(_pending[-1])


def reraise_interrupt(exc: BaseException) -> None:
    """Re-raise a signal or a reached limit that a C call turned into another exception (a RuntimeError
    '... KeyboardInterrupt' from CasADi, a SystemError 'returned a result with an exception set', ...)."""
    check()
    cause = _cause(exc)
    if cause is not None:
        raise cause from None
    deadline.check()
    if "KeyboardInterrupt" in str(exc):
        raise KeyboardInterrupt from None


def _cause(exc: BaseException | None) -> BaseException | None:
    """A signal's or a limit's exception in the chain of `exc` (its causes and contexts), if any."""
    seen = 0
    while exc is not None and seen < 20:
        if isinstance(exc, (Terminated, KeyboardInterrupt, deadline.WallLimitReached)):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def exit_code(exc: BaseException) -> tuple[int, str] | None:
    """(exit code, one line) when `exc` is, hides or follows a signal or the command's wall-clock limit."""
    c = _cause(exc)
    if isinstance(c, deadline.WallLimitReached):
        return 1, f"symfunnel: timeout: {c}"
    if _pending or isinstance(c, (Terminated, KeyboardInterrupt)):
        signum = _pending[-1] if _pending else (c.signum if isinstance(c, Terminated) else int(signal.SIGINT))
        return _signal_exit(signum)
    expired = deadline.expired_limit()
    if expired is not None:
        return 1, f"symfunnel: timeout: {expired}"
    return None


def _signal_exit(signum: int) -> tuple[int, str]:
    if signum == signal.SIGINT:
        return 130, "symfunnel: interrupted"
    return 128 + signum, f"symfunnel: terminated by signal {signum}"


def announce(line: str) -> None:
    """Print the command's one closing line on stderr, once per process (the watchdog and the CLI both may)."""
    with _lock:
        if _announced:
            return
        _announced.append(line)
    try:
        print(line, file=user_stderr(), flush=True)
    except (OSError, ValueError):
        pass


# --- what a stopped process must not leave behind ---------------------------------------------------------

def register_temporary(path) -> None:
    """Remove `path` (a file or a directory) if the process is stopped before `unregister_temporary(path)`."""
    _temporaries[str(path)] = None


def unregister_temporary(path) -> None:
    """`path` is finished (renamed into place or removed): forget it."""
    _temporaries.pop(str(path), None)


def register_child(pid: int, group: bool = False) -> None:
    """Kill process `pid` (its whole process group with `group`) if the process is stopped."""
    _children[int(pid)] = bool(group)


def unregister_child(pid: int) -> None:
    """Process `pid` has been reaped: forget it."""
    _children.pop(int(pid), None)


def _kill_children() -> None:
    for pid, group in list(_children.items()):
        with contextlib.suppress(OSError):
            (os.killpg if group else os.kill)(pid, signal.SIGKILL)


def _remove_temporaries() -> None:
    for path in list(_temporaries):
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(path)


def die_with_parent() -> None:
    """Make the kernel SIGKILL this process when its parent dies (Linux; elsewhere a thread watches the parent)."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)          # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:                               # the parent died before prctl
        os._exit(1)

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)
    threading.Thread(target=watch, name="symfunnel-parent-watch", daemon=True).start()


# --- the watchdog -----------------------------------------------------------------------------------------

def _hard_stop(code: int, line: str) -> None:
    if _state["committed"] is not None:         # the output is complete: the command succeeded, only its report hangs
        why = "the wall-clock limit" if _state["late"] is None else f"signal {_state['late']}"
        code, line = _state["committed"], f"symfunnel: {why} came after the output was complete; stopped " \
            "before the rest of the report"
    _kill_children()
    _remove_temporaries()
    announce(line)
    os._exit(code)


def _watch(rfd: int) -> None:
    stop_at, why, ignore = None, None, 0
    while not _done.is_set():
        try:
            ready, _, _ = select.select([rfd], [], [], 0.02 if _state.get("redeliver") else 0.1)
            data = os.read(rfd, 512) if ready else b""
        except (OSError, ValueError):
            return
        now = time.monotonic()
        for b in data:
            if b in TERMINATING and ignore:                 # our own re-delivery (interrupt_main writes it too)
                ignore -= 1
            elif b in TERMINATING:
                if stop_at is not None:                     # a second signal: stop now
                    stop_at = now
                else:
                    stop_at, why = now + GRACE, _signal_exit(b)
        again = _state.get("redeliver")
        if again is not None and now >= again and _pending:
            _state["redeliver"] = None
            import _thread
            ignore += 1
            _state["redelivered"] += 1
            with contextlib.suppress(Exception):
                _thread.interrupt_main(_pending[-1])
        if stop_at is None:
            expiry = deadline.command_expiry()
            if expiry is not None and now >= expiry + GRACE:
                d = deadline.expired_limit()
                if d is not None:
                    stop_at, why = now, (1, f"symfunnel: timeout: {d}")
        if stop_at is not None and now >= stop_at and not _done.is_set():
            _hard_stop(*why)


def _unraisable(hook):
    def unraisable(u):
        # a signal's exception raised inside a finalizer or a weakref callback is swallowed there: deliver it again
        if isinstance(u.exc_value, (Terminated, KeyboardInterrupt, deadline.WallLimitReached)):
            if isinstance(u.exc_value, (Terminated, KeyboardInterrupt)) and _pending:
                _state["redeliver"] = time.monotonic() + 0.02     # by the watchdog, once we are out of here
            elif isinstance(u.exc_value, deadline.WallLimitReached):
                deadline.rearm()
            return
        hook(u)
    return unraisable


def _excepthook(hook):
    def excepthook(kind, value, tb):
        # a Cython `noexcept` function prints the exception it cannot raise through sys.excepthook before handing it
        # to sys.unraisablehook (which re-delivers it): a signal's exception is not a crash to print
        if isinstance(value, (Terminated, KeyboardInterrupt)) and _pending:
            return
        if isinstance(value, deadline.WallLimitReached):
            return
        hook(kind, value, tb)
    return excepthook


def install() -> None:
    """The CLI's signal policy and one-line warnings (main thread only for signals; undone by `uninstall`)."""
    if _saved:
        return
    _saved["showwarning"] = warnings.showwarning
    warnings.showwarning = _one_line
    _saved["unraisablehook"] = sys.unraisablehook
    sys.unraisablehook = _unraisable(sys.unraisablehook)
    _saved["excepthook"] = sys.excepthook
    sys.excepthook = _excepthook(sys.excepthook)
    _pending.clear()
    _announced.clear()
    _done.clear()
    _state["committed"] = _state["late"] = None
    _state["redelivered"] = 0
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in TERMINATING:
        _saved[sig] = signal.signal(sig, _raise)
    deadline.on_check(check)
    rfd, wfd = os.pipe()
    os.set_blocking(wfd, False)
    _saved["wakeup"] = signal.set_wakeup_fd(wfd, warn_on_full_buffer=False)
    _state["wakeup"] = (rfd, wfd)
    t = threading.Thread(target=_watch, args=(rfd,), name="symfunnel-watchdog", daemon=True)
    _state["thread"] = t
    t.start()


def uninstall(restore_signals: bool = True) -> None:
    """Restore what `install` changed (the command has finished: the watchdog stands down); without
    `restore_signals` the signal handlers `finished` set stay (the CLI's own process, about to exit)."""
    if not _saved:
        return
    _done.set()
    warnings.showwarning = _saved.pop("showwarning")
    sys.unraisablehook = _saved.pop("unraisablehook")
    sys.excepthook = _saved.pop("excepthook")
    if "wakeup" in _saved:
        signal.set_wakeup_fd(_saved.pop("wakeup"))
        t = _state.pop("thread", None)
        if t is not None:
            t.join(timeout=1.0)
        for fd in _state.pop("wakeup", None) or ():
            with contextlib.suppress(OSError):
                os.close(fd)
        deadline.on_check(None)
    for sig in [k for k in _saved if not isinstance(k, str)]:
        saved = _saved.pop(sig)
        if restore_signals:
            signal.signal(sig, saved)
    _saved.clear()
    _pending.clear()
    _state["committed"] = _state["late"] = None


def _one_line(message, category, filename, lineno, file=None, line=None):
    from .text import one_line
    text = one_line(str(message))
    print(f"symfunnel: warning: {text}", file=user_stderr() if file is None else file, flush=True)


def user_stderr():
    """Where the lines meant for the user (progress, warnings, the closing line) go: sys.stderr, or the terminal's
    stderr while `quiet_c_output` captures everything else."""
    return _user["err"] or sys.stderr


@contextlib.contextmanager
def quiet_c_output(what: str):
    """Everything CasADi and the solvers print during the block -- their C-level writes to fds 1 and 2 (IPOPT's banner,
    SUNDIALS' messages) and what CasADi routes through Python's sys.stdout / sys.stderr (its warnings and the
    argument dumps of a failed evaluation) -- goes to a temporary file; the lines meant for the user still reach
    the terminal (`user_stderr`). Afterwards one warning line says how many lines were silenced and shows the first
    message among them. Yields a dict that holds "lines" (the count) and "first" at the end."""
    import io
    import tempfile
    out = {"lines": 0, "first": None}
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    try:
        saved = [os.dup(fd) for fd in (1, 2)]
    except OSError:
        yield out
        return
    cap = tempfile.TemporaryFile()
    prev = (sys.stdout, sys.stderr, _user["err"])
    err = _user["err"] or os.fdopen(os.dup(saved[1]), "w", buffering=1, encoding="utf-8", errors="backslashreplace")
    py = io.TextIOWrapper(os.fdopen(os.dup(cap.fileno()), "wb"), encoding="utf-8", errors="replace",
                          line_buffering=True)
    try:
        for fd in (1, 2):
            os.dup2(cap.fileno(), fd)
        sys.stdout = sys.stderr = py
        _user["err"] = err
        yield out
    finally:
        with contextlib.suppress(Exception):
            py.flush()
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)            # C stdio buffers (printf) into the file, not after the block
        for fd, keep in zip((1, 2), saved):
            os.dup2(keep, fd)
            os.close(keep)
        sys.stdout, sys.stderr, _user["err"] = prev
        with contextlib.suppress(Exception):
            py.close()
        if err is not prev[2]:
            with contextlib.suppress(Exception):
                err.close()
        cap.seek(0)
        text = cap.read().decode("utf-8", "replace")
        cap.close()
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        out["lines"] = len(lines)
        if lines:
            from .text import one_line
            first = next((ln for ln in lines if 'returned "' in ln), None) or \
                next((ln for ln in lines if "WARNING" in ln or "rror" in ln), lines[0])
            out["first"] = one_line(first.split('WARNING("', 1)[-1], 200)
            warnings.warn(f"{what}: {len(lines)} line(s) of CasADi/solver output silenced, the first message: "
                          f"{out['first']}", RuntimeWarning, stacklevel=3)


def become_worker() -> None:
    """In a forked worker: signals are the parent's to decide (it kills the worker when it stops), the parent's
    children, temporaries and timers are not ours."""
    _state["worker"] = True
    _state["deferred"] = 0
    die_with_parent()
    with contextlib.suppress(ValueError, OSError):
        signal.set_wakeup_fd(-1)
    for sig in TERMINATING:                                  # the parent decides; it kills us when it stops
        with contextlib.suppress(ValueError, OSError):
            signal.signal(sig, signal.SIG_IGN if sig == signal.SIGINT else signal.SIG_DFL)
    signal.setitimer(signal.ITIMER_REAL, 0)
    _children.clear()
    _temporaries.clear()


def in_worker() -> bool:
    """Whether this process is a forked worker of `worker.run_killable`."""
    return bool(_state["worker"])
