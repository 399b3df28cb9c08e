"""`symfunnel report [SCENARIO] [--out PATH]`: everything in one self-contained HTML file (the main job)."""

from __future__ import annotations

from ..core.outputs import MAX_SAMPLES


def register(sub, common) -> None:
    """Add the `report` subcommand."""
    sp = sub.add_parser("report", help="everything in one self-contained HTML file (default reports/<scenario>.html)")
    common(sp)
    sp.set_defaults(scenario=None)       # omitted: paper; with --sweep, omitted means "whichever campaign DIR holds"
    sp.add_argument("--out", metavar="PATH",
                    help="where to write the report (default: reports/<built-in name or file stem>.html)")
    sp.add_argument("--t-final", type=float, metavar="T", help="simulate to T seconds (default: the scenario's)")
    sp.add_argument("--samples", type=int, default=10000, metavar="K",
                    help="states sampled inside the funnels for the falsification (default 10000, at most 1000000)")
    sp.add_argument("--figures", metavar="DIR",
                    help="also write every figure as PNG and PDF into DIR (created if missing)")
    sp.add_argument("--no-codegen", action="store_true", help="leave out the code-generation section")
    sp.add_argument("--no-mutants", action="store_true", help="leave out the mutation score")
    sp.add_argument("--no-deployed", action="store_true",
                    help="leave out the deployed controller (minimum sample rate, design help, sampled torque)")
    sp.add_argument("--sweep", metavar="DIR", help="the robustness-campaign section of a `symfunnel sweep` "
                                                   "directory alone (default --out: DIR/sweep.html)")
    from ._common import add_force_option, add_plant_option
    add_plant_option(sp)
    add_force_option(sp)
    sp.set_defaults(func=run)


def run(args) -> int:
    """Write the report and print its path. Failed checks are shown in the report; the exit code is still 0."""
    from ._common import loading
    with loading():
        from ._common import _engine, _load, _progress
        from ..core.outputs import check_count
        from ..pipeline import Run, RunOptions
        from ..reporting import build_report, default_path
    check_count(args.samples, key="--samples", minimum=1, maximum=MAX_SAMPLES, what="a number of samples")
    if args.sweep:
        from ..reporting.sweep import write_sweep_page
        name = None
        if args.scenario is not None:   # `report arm7 --sweep DIR` of another scenario's campaign: refused
            name = _load(args).name
        print(write_sweep_page(args.sweep, args.out, scenario_name=name))
        return 0
    if args.scenario is None:
        args.scenario = "paper"
    figures = figures_dir(args.figures, force=args.force) if args.figures is not None else None
    sc = _load(args)
    from ..core.outputs import check_replaceable
    from ._common import scenario_inputs
    check_replaceable(args.out if args.out is not None else default_path(sc), key="--out",
                      inputs=scenario_inputs(sc), force=args.force)
    engine = _engine(args, sc)
    run = Run(sc, RunOptions(t_final=args.t_final, samples=args.samples, engine=engine), _progress(args.quiet))
    from ..core.io import staged
    with staged(commit=True):           # the report and its --figures files all at the end, or none of them
        path = build_report(run, args.out, codegen=not args.no_codegen, mutants=not args.no_mutants,
                            deployed=not args.no_deployed, figures_dir=figures)
    print(path)
    return 0


def figures_dir(arg: str, *, force: bool = False):
    """The --figures directory, created now and checked writable, so that a bad one fails before any work; a
    figure file of our names (figNN-ID.png/.pdf) already there that symfunnel did not write needs --force."""
    import os
    import re
    from pathlib import Path

    from ..core.errors import InputError
    from ..core.outputs import written_by_symfunnel
    p = Path(arg)
    if p.exists() and not p.is_dir():
        raise InputError(f"{arg} exists and is not a directory", key="--figures", expected="a directory")
    if p.is_dir() and not force:
        theirs = sorted(f for f in p.iterdir() if re.fullmatch(r"fig\d\d-.+\.(png|pdf)", f.name)
                        and f.is_file() and not written_by_symfunnel(f))
        if theirs:
            raise InputError(f"holds {theirs[0].name}" + (f" and {len(theirs) - 1} more figure file(s)"
                                                          if len(theirs) > 1 else "")
                             + " not written by symfunnel", file=str(theirs[0]), key="--figures",
                             expected="--force to replace them, or another directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create {arg} ({exc.strerror or exc})", key="--figures",
                         expected="a directory that can be created") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{arg} is not writable", key="--figures", expected="a writable directory")
    return p
