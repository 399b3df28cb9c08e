"""One wall-clock limit for a whole command: nested deadlines, enforced by SIGALRM in the main thread and by checks.

A command opens a deadline (`limit(seconds)`); inner work may open tighter ones (a sympy proof's few seconds, a
Run's `[simulation] wall_limit`); the earliest expiry is armed as a real-time alarm. When it fires in Python code
the exception of the outermost expired deadline is raised there: `WallLimitReached` for a command's limit (a
BaseException, so no `except Exception` in a stage swallows it), the caller's own exception for an inner time limit.
Code that cannot be interrupted by a signal (one long CasADi call, a compiler subprocess) bounds itself with
`remaining()` and calls `check()` when it returns; long loops that stop gracefully (the integration, which keeps its
trajectory) run under `paused()` and watch `remaining()` themselves.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable

__all__ = ["mark_command_start", "command_elapsed", "WallLimitReached", "limit", "until", "remaining", "check", "paused",
           "step", "current_step", "current_steps",
           "command_expiry", "expired_limit", "MAX_SECONDS", "check_seconds"]

#: the longest limit accepted anywhere (--wall-limit, wall_limit, sympy_timeout, $SYMFUNNEL_COMPILE_TIMEOUT): a week
MAX_SECONDS = 604800.0


class WallLimitReached(BaseException):
    """A command's wall-clock limit was reached while doing `step`."""

    def __init__(self, seconds: float, step: str, elapsed: float):
        self.seconds, self.step, self.elapsed = seconds, step, elapsed
        super().__init__(f"wall-clock limit of {seconds:g} s reached while {step} (after {elapsed:.3g} s); "
                         f"nothing was written (raise --wall-limit or [simulation] wall_limit)")


@dataclass(eq=False)
class _Deadline:
    expiry: float                       # time.monotonic() at which it expires
    seconds: float
    started: float
    make: Callable[[], BaseException] | None    # None: WallLimitReached
    fired: bool = False                 # the alarm's handler raised this deadline's exception
    step: str | None = None             # what the command was doing when the alarm first found it expired


_started = {"at": time.monotonic()}       # when the command began (`mark_command_start`)


def mark_command_start(process: bool = False) -> None:
    """The command begins now, or, with `process` (the CLI's own process), when the process started: Python's
    start-up and imports count against a command's own wall-clock limit (Linux's /proc; elsewhere now)."""
    at = time.monotonic()
    if process:
        try:
            import os
            with open("/proc/self/stat") as fh:
                start_ticks = int(fh.read().rsplit(")", 1)[1].split()[19])
            with open("/proc/uptime") as fh:
                uptime = float(fh.read().split()[0])
            at -= max(0.0, min(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 60.0))
        except (OSError, ValueError, IndexError):
            pass
    _started["at"] = at


def command_elapsed() -> float:
    """Seconds since the command began (`mark_command_start`)."""
    return time.monotonic() - _started["at"]


_stack: list[_Deadline] = []
_steps: list[str] = []
_paused: list[bool] = []
_hooks: list[Callable[[], None]] = []     # lifecycle's re-raise of a swallowed signal, run by every check


def check_seconds(value, *, key: str, file: str | None = None, allow_none: bool = False):
    """A limit in seconds: a finite number in (0, MAX_SECONDS] (InputError naming `key` otherwise)."""
    from .errors import InputError
    if value is None and allow_none:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and 0 < value <= MAX_SECONDS):
        shown = f"{value:g}" if isinstance(value, float) else repr(value)
        raise InputError(f"is {shown}", file=file, key=key,
                         expected=f"a number of seconds > 0 and at most {MAX_SECONDS:g} (a week)")
    return float(value)


def on_check(hook: Callable[[], None] | None) -> None:
    """Run `hook` at every `check()` (None: no hook); the CLI's signal policy re-raises a swallowed signal there."""
    _hooks.clear()
    if hook is not None:
        _hooks.append(hook)


def command_expiry() -> float | None:
    """The earliest expiry of an open wall-clock limit (a WallLimitReached deadline), None without one."""
    ds = [d.expiry for d in list(_stack) if d.make is None]
    return min(ds) if ds else None


def expired_limit() -> "WallLimitReached | None":
    """The exception of an expired wall-clock limit (not an inner time limit), None when none has expired."""
    now = time.monotonic()
    for d in list(_stack):
        if d.make is None and now >= d.expiry:
            return _error(d)
    return None


def rearm() -> None:
    """Fire the alarm again soon (its exception was swallowed where it was raised)."""
    if _main() and _stack and not (_paused and _paused[-1]):
        signal.setitimer(signal.ITIMER_REAL, 0.05)


def _main() -> bool:
    return threading.current_thread() is threading.main_thread()


def current_step() -> str:
    """What the command is doing now (for the message of a reached limit)."""
    return _steps[-1] if _steps else "working"


def current_steps() -> tuple[str, ...]:
    """Every step open now, outermost first (a caller's budget names its own step among them)."""
    return tuple(_steps)


def _error(d: _Deadline) -> BaseException:
    if d.make is not None:
        return d.make()
    return WallLimitReached(d.seconds, d.step or current_step(), time.monotonic() - d.started)


def _expired() -> _Deadline | None:
    now = time.monotonic()
    for d in _stack:                    # outermost first: a command's limit wins over an inner time limit
        if now >= d.expiry:
            return d
    return None


def _handler(signum, frame):
    d = _expired()
    if d is not None:
        if d.step is None:
            d.step = current_step()      # what the command was doing when the limit was reached (not after an import)
        if _importing(frame):
            # a module interrupted half-way through its import stays broken in sys.modules for the rest of the
            # process (the API's, a test worker's: "module 'sympy' has no attribute 'polys'"): raise after it
            signal.setitimer(signal.ITIMER_REAL, 0.01)
            return
        d.fired = True
        raise _error(d)
    _arm()                               # woke early (an outer deadline was re-armed): wait for the next one


def _importing(frame) -> bool:
    """Whether `frame` runs inside an import (importlib's frames are on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _arm() -> None:
    if not _main() or not _stack:          # no deadline of ours: leave any other use of the timer alone
        return
    if _paused and _paused[-1]:
        signal.setitimer(signal.ITIMER_REAL, 0)
        return
    wait = min(d.expiry for d in _stack) - time.monotonic()
    signal.signal(signal.SIGALRM, _handler)
    signal.setitimer(signal.ITIMER_REAL, min(max(wait, 1e-4), MAX_SECONDS))


def remaining() -> float:
    """Seconds left before the earliest open deadline (inf without one)."""
    if not _stack or not _main():
        return math.inf
    return min(d.expiry for d in _stack) - time.monotonic()


def check(what: str | None = None) -> None:
    """Raise the expired deadline's exception, if one has expired (for code a signal cannot interrupt)."""
    if not _main():
        return
    for hook in _hooks:
        hook()
    d = _expired()
    if d is not None:
        signal.setitimer(signal.ITIMER_REAL, 0)         # raised here: the alarm must not fire again in the unwinding
        if what:
            _steps.append(what)
        try:
            raise _error(d)
        finally:
            if what:
                _steps.pop()


#: what an exception raised by the alarm's handler inside a C extension's call can come out as (TypeError: CasADi's
#: wrapper, when the interrupted conversion falls through to its "Implicit conversion of symbolic CasADi type")
SWALLOWED = (NotImplementedError, SystemError, RuntimeError, TypeError)


@contextlib.contextmanager
def _push(d: _Deadline):
    if not _main():
        yield
        return
    old = signal.getsignal(signal.SIGALRM) if not _stack else None
    try:
        _stack.append(d)
        _arm()
        try:
            yield
            if d.fired:
                # the block went on after its alarm's exception: SWIG's overload resolution drops an exception
                # raised inside a typemap's Python callback (DM_from_array) and tries the next overload, so the
                # exception vanished without a trace; the limit was reached all the same
                raise _error(d)
        except SWALLOWED as exc:
            # the alarm's exception raised inside a CasADi call comes out as SWIG's or CasADi's own error (e.g.
            # "Wrong number or type of arguments" while converting arguments): past the expiry, it is the limit
            if time.monotonic() >= d.expiry:
                raise _error(d) from exc
            raise
    finally:
        # Off the stack first, in one C call (identity equality: no Python code runs, so no signal handler either):
        # an alarm already delivered runs its handler at the next Python call and raises out of this block, and a
        # deadline left behind would expire every later check and make the watchdog stop the process.
        try:
            _stack.remove(d)
        except ValueError:
            pass
        signal.setitimer(signal.ITIMER_REAL, 0)
        if _stack:
            _arm()
        elif old is not None:
            signal.signal(signal.SIGALRM, old)


def limit(seconds: float | None, *, on_expiry: Callable[[], BaseException] | None = None):
    """A deadline `seconds` from now for the block (None or inf: none). `on_expiry` makes the exception raised
    (default: WallLimitReached naming the current step). Main thread only; elsewhere the block runs unbounded."""
    if seconds is None or not math.isfinite(seconds):
        return contextlib.nullcontext()
    now = time.monotonic()
    return _push(_Deadline(now + max(float(seconds), 0.0), float(seconds), now, on_expiry))


def until(expiry: float, seconds: float, started: float):
    """The deadline at monotonic time `expiry` (of a limit of `seconds` started at `started`) for the block."""
    if not math.isfinite(expiry):
        return contextlib.nullcontext()
    return _push(_Deadline(expiry, seconds, started, None))


@contextlib.contextmanager
def paused():
    """No alarm inside the block (it watches `remaining()` itself); an expiry is raised by the next check."""
    if not _main():
        yield
        return
    mark = object()
    try:
        _paused.append(mark)
        _arm()
        yield
    finally:
        try:
            _paused.remove(mark)
        except ValueError:
            pass
        _arm()


@contextlib.contextmanager
def step(what: str):
    """Name what the block does, for the message of a limit reached inside it; checks the deadline on entry."""
    mark = what
    try:
        _steps.append(mark)
        check()
        yield
    finally:
        try:
            _steps.remove(mark)
        except ValueError:
            pass
