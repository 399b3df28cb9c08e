"""`symfunnel report [SCENARIO] [--out PATH]`: everything in one self-contained HTML file (the main job)."""

from __future__ import annotations


#: The largest --samples (memory grows linearly with it: about 1 kB per sample).
MAX_SAMPLES = 1_000_000


def register(sub, common) -> None:
    """Add the `report` subcommand."""
    sp = sub.add_parser("report", help="everything in one self-contained HTML file (default reports/<scenario>.html)")
    common(sp)
    sp.add_argument("--out", metavar="PATH",
                    help="where to write the report (default: reports/<built-in name or file stem>.html)")
    sp.add_argument("--t-final", type=float, metavar="T", help="simulate to T seconds (default: the scenario's)")
    sp.add_argument("--samples", type=int, default=10000, metavar="K",
                    help="states sampled inside the funnels for the falsification (default 10000, at most 1000000)")
    sp.add_argument("--no-codegen", action="store_true", help="leave out the code-generation section")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Write the report and print its path. Failed checks are shown in the report; the exit code is still 0."""
    from ..cli import _load, _progress
    from ..report import build_report
    from ..outputs import check_count
    check_count(args.samples, key="--samples", minimum=1, maximum=MAX_SAMPLES, what="a number of samples")
    from ..outputs import check_output_file
    from ..report import default_path
    sc = _load(args)
    check_output_file(args.out if args.out is not None else default_path(sc))
    say = _progress(args.quiet)
    path = build_report(sc, args.out, t_final=args.t_final, samples=args.samples, codegen=not args.no_codegen,
                        progress=say)
    print(path)
    return 0
