"""The `symfunnel` command line: the entry point that parses arguments, runs one command of `symfunnel.commands` and
turns every outcome into an exit code and at most one line on stderr (never a traceback)."""

from __future__ import annotations

import argparse
import math
import os
import sys

from .core.errors import InputError, SymfunnelError

EXIT_INTERNAL = 3


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    p = argparse.ArgumentParser(prog="symfunnel", description="Symbolic design and verification of funnel "
                                "controllers for robot manipulators (CasADi).")
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


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; bad input ends in one line and exit 2, failed checks exit 1, never a traceback."""
    from .core import lifecycle
    parser = build_parser()
    args = parser.parse_args(argv)
    from .core import deadline
    lifecycle.install()
    try:
        seconds = getattr(args, "command_wall_limit", None)
        if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
            raise InputError(f"is {seconds:g}", key="--wall-limit", expected="a number of seconds > 0")
        with deadline.limit(seconds):
            code = args.func(args)
    except deadline.WallLimitReached as exc:
        print(f"symfunnel: timeout: {exc}", file=sys.stderr)
        return 1
    except InputError as exc:
        print(f"symfunnel: error: {exc}", file=sys.stderr)
        if exc.example:
            print("\n".join("    " + line for line in exc.example.splitlines()), file=sys.stderr)
        return 2
    except SymfunnelError as exc:
        print(f"symfunnel: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("symfunnel: interrupted", file=sys.stderr)
        return 130
    except lifecycle.Terminated as exc:
        print(f"symfunnel: terminated by signal {exc.signum}", file=sys.stderr)
        return 128 + exc.signum
    except BrokenPipeError:
        return 0
    except Exception as exc:  # noqa: BLE001 - the contract: nothing escapes as a traceback
        if os.environ.get("SYMFUNNEL_DEBUG"):
            raise
        print(f"symfunnel: internal error: {type(exc).__name__}: {exc} "
              f"(set SYMFUNNEL_DEBUG=1 for the traceback; please report it)", file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        lifecycle.uninstall()
    return code


if __name__ == "__main__":
    sys.exit(main())
