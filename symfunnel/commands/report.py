"""`symfunnel report [SCENARIO] [--out PATH]`: everything in one self-contained HTML file (the main job)."""

from __future__ import annotations


def register(sub, common) -> None:
    """Add the `report` subcommand."""
    sp = sub.add_parser("report", help="everything in one self-contained HTML file (default reports/<scenario>.html)")
    common(sp)
    sp.add_argument("--out", metavar="PATH", help="where to write the report (default: reports/<scenario>.html)")
    sp.add_argument("--t-final", type=float, metavar="T", help="simulate to T seconds (default: the scenario's)")
    sp.add_argument("--samples", type=int, default=10000, metavar="K",
                    help="states sampled inside the funnels for the falsification (default 10000)")
    sp.add_argument("--no-codegen", action="store_true", help="leave out the code-generation section")
    sp.add_argument("--sweep", metavar="DIR", help="the robustness-campaign section of a `symfunnel sweep` "
                                                   "directory alone (default --out: DIR/sweep.html)")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Write the report and print its path. Failed checks are shown in the report; the exit code is still 0."""
    from ..cli import _load, _progress
    from ..errors import InputError
    from ..report import build_report
    if args.samples < 1:
        raise InputError(f"is {args.samples}", key="--samples", expected="an integer >= 1")
    if args.sweep:
        from ..report.sweep import write_sweep_page
        print(write_sweep_page(args.sweep, args.out))
        return 0
    sc = _load(args)
    say = _progress(args.quiet)
    path = build_report(sc, args.out, t_final=args.t_final, samples=args.samples, codegen=not args.no_codegen,
                        progress=say)
    print(path)
    return 0
