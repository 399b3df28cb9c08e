"""`symfunnel verify [SCENARIO] [--json]`: funnel, Lyapunov and boundedness checks on the simulated closed loop."""

from __future__ import annotations

from ..core.outputs import MAX_SAMPLES


def register(sub, common) -> None:
    """Add the `verify` subcommand."""
    sp = sub.add_parser("verify", help="funnel, Lyapunov and boundedness checks on simulated trajectories")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--t-final", type=float, metavar="T", help="simulate to T seconds (default: the scenario's)")
    sp.add_argument("--samples", type=int, default=10000, metavar="K",
                    help="states sampled inside the funnels for the falsification (default 10000, at most 1000000)")
    sp.add_argument("--mutants", action="store_true",
                    help="mutation testing: run the design's seeded errors through the same checks; print the score")
    sp.add_argument("--rate", type=float, metavar="HZ", help="verify the deployed controller sampled at HZ "
                    "(overrides [implementation].rate_hz; adds the implementation.* checks)")
    from ._common import add_plant_option
    add_plant_option(sp)
    sp.set_defaults(func=run)


def _mark(c) -> str:
    """The outcome against its declaration, labelled as in the report: FINDING (expected), FAIL (unexpected), ..."""
    from ..checks.gate import verdict
    return verdict(c)[0]


def print_checks(checks, indent: str = "  ") -> None:
    """The checks as a table: mark, id, margin, detail (and the reason of an expected failure)."""
    for c in checks:
        m = "" if c.margin is None else f"  margin {c.margin:.4g}"
        if getattr(c, "value", None) is not None:
            m += f"  value {c.value:.3g}"
        print(f"{indent}{_mark(c)}  {c.id}{m}")
        print(f"{indent}      {c.detail}")
        if c.reason:
            print(f"{indent}      declared: {c.reason}")


def run(args) -> int:
    """Run every check; print a table (or JSON); exit 1 exactly when an outcome is not the declared one."""
    from ._common import loading
    with loading():
        from ._common import _dump, _engine, _load, _progress
        from ..core.outputs import check_count
        from ..pipeline import Run, RunOptions
    check_count(args.samples, key="--samples", minimum=1, maximum=MAX_SAMPLES, what="a number of samples")
    if args.rate is not None:
        from ..scenario.implementation import check_rate
        check_rate(args.rate, file=None, key="--rate")
    sc = _load(args)
    engine = _engine(args, sc)
    say = _progress(args.quiet or args.json)
    if args.mutants:
        from ..pipeline import run_mutants
        out = run_mutants(sc, t_final=args.t_final, samples=min(args.samples, 2000), progress=say)
        if args.json:
            print(_dump(out))
        else:
            print(f"mutation testing of scenario {sc.name} ({sc.file})")
            for m in out["mutants"]:
                verdict = "equivalent" if m["equivalent"] else ("killed" if m["killed"] else "SURVIVED")
                print(f"  {verdict:<10} {m['id']:<28} {m['description']}")
                print(f"             {'by ' + ', '.join(m['by']) if m['by'] else m.get('proof') or ''}")
            print(f"mutation score {out['score']:.3f} ({out['killed']} killed of {out['total'] - out['equivalent']} "
                  f"non-equivalent mutants)")
        return 0
    v = Run(sc, RunOptions(t_final=args.t_final, samples=args.samples, rate_hz=args.rate, engine=engine),
            say).verification
    if args.json:
        print(_dump(v.to_json()))
    else:
        from ..checks.gate import counts_line, outcome_hint
        print(f"verification of scenario {sc.name} ({sc.file})")
        vd = v.verdicts()
        from .simulate import status_text
        print(f"  continuous-time run: {status_text(vd['continuous']['status'])}: {vd['continuous']['message']}")
        if vd["sampled"] is not None:
            print(f"  sampled run (deployed C step): {status_text(vd['sampled']['status'])}: "
                  f"{vd['sampled']['message']}")
        if v.lyapunov is not None and sc.design.approximator != "none":
            info = v.lyapunov.w_star_info
            whence = "not given by the source" if sc.source else "the ideal weight"
            print(f"  W* ({whence}): estimated along the trajectory, ||W*||_F = "
                  f"{info.get('norm', float('nan')):.4g}, rms residual eps = {info.get('rms_residual', float('nan')):.4g}")
        print_checks(v.checks)
        print(counts_line(v.checks))
        print(f"gate: {v.status.upper()}" + (f" (unexpected: {', '.join(c.id for c in v.unexpected)})"
                                              if v.unexpected else " (every outcome as the scenario declares)"))
        for c in v.unexpected:
            h = outcome_hint(sc, c)
            if h:
                print(f"  hint: {h}")
    return 1 if v.unexpected else 0

