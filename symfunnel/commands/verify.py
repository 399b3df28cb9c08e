"""`symfunnel verify [SCENARIO] [--json]`: funnel, Lyapunov and boundedness checks on the simulated closed loop."""

from __future__ import annotations


def register(sub, common) -> None:
    """Add the `verify` subcommand."""
    sp = sub.add_parser("verify", help="funnel, Lyapunov and boundedness checks on simulated trajectories")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--t-final", type=float, metavar="T", help="simulate to T seconds (default: the scenario's)")
    sp.add_argument("--samples", type=int, default=10000, metavar="K",
                    help="states sampled inside the funnels for the falsification (default 10000)")
    sp.add_argument("--rate", type=float, metavar="HZ", help="verify the deployed controller sampled at HZ "
                    "(overrides [implementation].rate_hz; adds the implementation.* checks)")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Run every check; print a table (or JSON); exit 1 when any check fails."""
    from ..checks.verify import verify
    from ..cli import _dump, _load, _progress
    from ..errors import InputError
    if args.samples < 1:
        raise InputError(f"is {args.samples}", key="--samples", expected="an integer >= 1")
    if args.rate is not None:
        from ..implementation import check_rate
        check_rate(args.rate, file=None, key="--rate")
    sc = _load(args)
    say = _progress(args.quiet or args.json)
    v = verify(sc, t_final=args.t_final, samples=args.samples, progress=say, rate_hz=args.rate)
    failed = v.failed
    if args.json:
        print(_dump(v.to_json()))
    else:
        print(f"verification of scenario {sc.name} ({sc.file})")
        print(f"  simulation: {v.result.status}: {v.result.message}")
        if v.lyapunov is not None:
            info = v.lyapunov.w_star_info
            print(f"  W* (never given by the paper): estimated along the trajectory, ||W*||_F = "
                  f"{info.get('norm', float('nan')):.4g}, rms residual eps = {info.get('rms_residual', float('nan')):.4g}")
        for c in v.checks:
            mark = {"pass": "PASS", "fail": "FAIL", "skip": "SKIP"}[c.status]
            m = "" if c.margin is None else f"  margin {c.margin:.4g}"
            print(f"  {mark}  {c.id}{m}")
            print(f"        {c.detail}")
        n_pass = sum(c.status == "pass" for c in v.checks)
        n_skip = sum(c.status == "skip" for c in v.checks)
        print(f"{n_pass} passed, {len(failed)} failed" + (f", {n_skip} skipped" if n_skip else ""))
    return 1 if failed else 0
