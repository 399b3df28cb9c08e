"""The `symfunnel` command line: the entry point that parses arguments, runs one command of `symfunnel.commands` and
turns every outcome into an exit code and at most one line on stderr (never a traceback)."""

from __future__ import annotations

import argparse
import os
import sys

from .core.errors import InputError, SymfunnelError

EXIT_INTERNAL = 3


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors as one line (what is wrong and where to read the usage), exit 2; argparse prints the
    whole usage block first, several lines for one bad option."""

    def error(self, message: str):
        from .core.text import one_line
        self.exit(2, f"symfunnel: error: {self.prog}: {one_line(message)} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    p = OneLineParser(prog="symfunnel", description="Symbolic design and verification of funnel "
                                "controllers for robot manipulators (CasADi).", epilog=EPILOG,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version="symfunnel " + _version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def common(sp):
        sp.add_argument("scenario", nargs="?", default="paper",
                        help="scenario TOML file or built-in name (default: paper)")
        sp.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")

    for extra in _extra_commands():
        extra(sub, common)
    for name in BOUNDED:
        sub.choices[name].add_argument(
            "--wall-limit", type=float, metavar="S", dest="command_wall_limit",
            help="wall-clock limit in s for the whole command (deriving, building, compiling, simulating, checking); "
                 "reached, it stops with one line and exit 1, writing nothing")
    return p


#: the end of `symfunnel --help`: which command is the gate, and the exit codes (docs/limits.md)
EPILOG = """\
`symfunnel verify SCENARIO` is the gate: it exits 0 only when every check's outcome is the one the
scenario declares (CI runs it); the other commands design, explain, prove, deploy and report.

exit codes:
  0    success
  1    a check failed, a simulation left its funnel, or a --wall-limit was reached
  2    bad input: one line naming the file, the key and what was expected
  3    internal error (a bug: SYMFUNNEL_DEBUG=1 shows the traceback; please report it)
  130  interrupted (Ctrl-C); 143 terminated (SIGTERM)

`symfunnel COMMAND --help` lists a command's options; docs/cli.md all of them."""


#: commands whose `--wall-limit` bounds the whole command (simulate's bounds its run: derive, compile, integrate)
BOUNDED = ("derive", "audit", "verify", "codegen", "report", "rate")


#: the order of `symfunnel --help` (the pipeline's); a command module not listed here comes after, by name
ORDER = ("derive", "audit", "simulate", "verify", "certify", "codegen", "rate", "sweep", "tune", "report", "bench",
         "init")


def _extra_commands():
    """The subcommands: one module each under symfunnel/commands, discovered, each with `register(sub, common)`."""
    import pkgutil
    from . import commands
    names = [m.name for m in pkgutil.iter_modules(commands.__path__) if not m.name.startswith("_")]
    names.sort(key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n))
    out = []
    for name in names:
        m = __import__(f"symfunnel.commands.{name}", fromlist=["register"])
        if hasattr(m, "register"):
            out.append(m.register)
    return out


def _version() -> str:
    from .core.version import __version__
    return __version__


#: CPython's cyclic garbage collector thresholds while a command runs (restored after it, for a caller of `main`):
#: the defaults (700, 10, 10) walk the whole heap of CasADi, sympy and matplotlib objects every few hundred thousand
#: allocations; measured, `report arm7 --t-final 0.3 --samples 20` took 12.6-13.7 CPU-s at the defaults against
#: 11.8-12.1 at these, with the same peak memory (docs/performance.md)
GC_THRESHOLDS = (100_000, 50, 100)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; bad input ends in one line and exit 2, failed checks exit 1, never a traceback."""
    import gc

    from .core import deadline, lifecycle
    lifecycle.install()                 # first: a signal from here on ends in 130/143 and one line
    if os.environ.get("SYMFUNNEL_EAGER_IMPORTS"):
        from .bench.startup import import_eagerly   # the start-up bench's baseline: dependencies imported first
        import_eagerly()
    deadline.mark_command_start(process=argv is None)
    thresholds = gc.get_threshold()
    gc.set_threshold(*GC_THRESHOLDS)
    code = None
    try:
        code = _run(argv, deadline, lifecycle)
    finally:
        lifecycle.decided(code)         # a signal from here on (a second one, one during the unwinding) changes nothing
        gc.set_threshold(*thresholds)
        late = lifecycle.late_signal()
        if argv is None:
            # the process's own command line: its exit code is decided, and a signal during the interpreter's
            # shutdown would only turn a finished command into a killed one (it is said, once); set before the
            # policy is uninstalled, so that no instant has the default handlers
            lifecycle.finished(late)
        lifecycle.uninstall(restore_signals=argv is not None)
    return code


def _run(argv, deadline, lifecycle) -> int:
    def closing(code: int, line: str) -> int:
        lifecycle.announce(line)
        return code

    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        seconds = getattr(args, "command_wall_limit", None)
        deadline.check_seconds(seconds, key="--wall-limit", allow_none=True)
        with deadline.limit(seconds):
            code = args.func(args)
        lifecycle.check()               # a signal swallowed on its way (a finalizer, a C callback) still counts
    except SystemExit:
        raise
    except deadline.WallLimitReached as exc:
        return closing(*(lifecycle.exit_code(exc) or (1, f"symfunnel: timeout: {exc}")))
    except InputError as exc:
        code = closing(*(lifecycle.exit_code(exc) or (2, f"symfunnel: error: {_line(exc)}")))
        if code == 2 and exc.example:      # what to write instead, below the one-line message
            print("\n".join("    " + _line(line) for line in exc.example.splitlines()), file=sys.stderr)
        return code
    except SymfunnelError as exc:
        return closing(*(lifecycle.exit_code(exc) or (exc.exit_code, f"symfunnel: {_line(exc)}")))
    except (KeyboardInterrupt, lifecycle.Terminated) as exc:
        return closing(*lifecycle.exit_code(exc))
    except BrokenPipeError:
        return 0
    except Exception as exc:  # noqa: BLE001 - the contract: nothing escapes as a traceback
        stopped = lifecycle.exit_code(exc)          # a signal or the limit that a C call turned into this error
        if stopped is not None:
            return closing(*stopped)
        if os.environ.get("SYMFUNNEL_DEBUG"):
            raise
        return closing(EXIT_INTERNAL, f"symfunnel: internal error: {type(exc).__name__}: {_line(exc)} "
                                      f"(set SYMFUNNEL_DEBUG=1 for the traceback; please report it)")
    return code


def _line(exc: BaseException) -> str:
    """An error's message as one printable line of bounded length (control characters escaped)."""
    from .core.text import one_line
    return one_line(str(exc))


if __name__ == "__main__":
    sys.exit(main())
