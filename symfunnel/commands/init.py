"""`symfunnel init [--urdf FILE] [--out FILE]`: write a commented scenario that runs as written.

Without --urdf: a 2-link planar arm under gravity. With --urdf: the URDF's movable joints, a reference that swings
each joint gently around the middle of its range, an initial state a little off the reference, and funnels that
contain the initial errors (e2's initial funnel width is set from the derived e2(0), with a factor 2 to spare).
"""

from __future__ import annotations

#: the scenario writers, in design.starting (the API's `symfunnel.init` writes with them too), imported on use: the
#: CLI's start-up (`symfunnel --help`) imports no design code
_WRITERS = ("copied_scenario", "scenario_from_urdf", "scenario_two_link")


def __getattr__(name):
    """The writers by their old names here (`symfunnel.commands.init.scenario_from_urdf`), from design.starting."""
    if name in _WRITERS:
        from ..design import starting
        return getattr(starting, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def register(sub, common) -> None:
    """Add the `init` subcommand."""
    sp = sub.add_parser("init", help="write a commented starting scenario (a 2-link arm, or from a URDF)",
                        description="Write a scenario TOML file, with every section commented, that derives, "
                                    "audits and simulates as written; edit it from there (docs/scenario.md).")
    sp.add_argument("--urdf", metavar="FILE", help="build the scenario around this URDF's movable joints")
    sp.add_argument("--from", dest="source", metavar="SCENARIO",
                    help="copy a built-in scenario (paper, arm7) or a scenario file to edit, with a header saying "
                         "where it came from (files it refers to, such as a URDF, are copied beside it)")
    sp.add_argument("--joints", metavar="NAMES",
                    help="with --urdf: the comma-separated joints to control; every other movable joint is held "
                         "fixed at 0 (mimic joints are held fixed without asking)")
    sp.add_argument("--out", metavar="FILE", default="scenario.toml",
                    help="the scenario file to write (default scenario.toml; never overwritten without --force)")
    sp.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    sp.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Write the scenario, check that it loads and that its funnels contain the initial state; print its path."""
    from ..design.starting import write_starting
    print(write_starting(args.out, urdf=args.urdf, source=args.source, joints=args.joints, force=args.force,
                         say=_say(args)))
    return 0


def _say(args):
    import sys
    return (lambda s: None) if args.quiet else (lambda s: print(f"symfunnel: {s}", file=sys.stderr))


