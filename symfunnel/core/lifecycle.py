"""Process-level behaviour of the CLI: SIGTERM unwinds like Ctrl-C, and warnings print as one line on stderr.

SIGTERM is turned into the `Terminated` exception so that every `finally` / `except BaseException` clean-up runs
(atomic writes remove their temporary files, the compile cache removes its half-built directory and kills the
compiler), exactly as for SIGINT.
"""

from __future__ import annotations

import signal
import sys
import warnings

_saved: dict = {}
_pending: list[int] = []          # signals received (CasADi may swallow the exception raised for them)


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM (or SIGHUP)."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = signum


def _raise(signum, frame):
    _pending.append(signum)
    raise Terminated(signum)


def reraise_interrupt(exc: BaseException) -> None:
    """Re-raise a termination or Ctrl-C that a CasADi call turned into a RuntimeError ('... KeyboardInterrupt')."""
    if _pending:
        raise Terminated(_pending[-1]) from None
    if "KeyboardInterrupt" in str(exc):
        raise KeyboardInterrupt from None


def _one_line(message, category, filename, lineno, file=None, line=None):
    text = " ".join(str(message).split())
    print(f"symfunnel: warning: {text}", file=sys.stderr if file is None else file, flush=True)


def install() -> None:
    """Route SIGTERM/SIGHUP to `Terminated` and warnings to one stderr line each (CLI only; undone by `uninstall`)."""
    if _saved:
        return
    _saved["showwarning"] = warnings.showwarning
    warnings.showwarning = _one_line
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None:
            continue
        try:
            _saved[sig] = signal.signal(sig, _raise)
        except ValueError:          # not the main thread: leave signals alone
            pass


def uninstall() -> None:
    """Restore what `install` changed."""
    if not _saved:
        return
    warnings.showwarning = _saved.pop("showwarning")
    for sig in [k for k in _saved if not isinstance(k, str)]:
        signal.signal(sig, _saved.pop(sig))
    _saved.clear()
