"""`symfunnel certify [SCENARIO] [--json] [--only ID ...] [--wall-limit S]`: proofs over whole regions by interval
branch and bound on the design's own graph; exit 1 when an outcome is not the one the scenario declares."""

from __future__ import annotations


def register(sub, common) -> None:
    """Add the `certify` subcommand."""
    sp = sub.add_parser("certify", help="proofs over regions (input gain, bounds and saturation, invariance) by "
                                        "interval branch and bound on the design's own graph",
                        description="Each certificate is proven, refuted (with a counterexample the ordinary "
                        "CasADi Functions reproduce) or undecided (with the fraction left); docs/certify.md.")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--only", nargs="+", metavar="ID", help="certificates to compute: certify.input_gain, "
                    "certify.bounds, certify.invariance (or input_gain, bounds, invariance); certify.sampled (a proven sample "
                    "rate) only when named here")
    sp.add_argument("--wall-limit", type=float, metavar="S", dest="certify_wall_limit",
                    help="seconds for the whole command; reached, the searches end with 'undecided' and the "
                         "fraction left (never with a wrong verdict)")
    sp.add_argument("--t-final", type=float, metavar="T", help="horizon in s (default: the scenario's)")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Compute the certificates; print a table (or JSON); exit 1 exactly when an outcome is not the declared one."""
    import math

    from ._common import _dump, _load, _progress
    from ..api import CertifyResult, certify_ids
    from ..core.errors import InputError
    from ..pipeline import Run, RunOptions
    wl = args.certify_wall_limit
    from ..core.deadline import check_seconds          # the cap every other command's --wall-limit has (a week)
    check_seconds(wl, key="--wall-limit", allow_none=True)
    if args.t_final is not None and not (math.isfinite(args.t_final) and args.t_final > 0):
        raise InputError(f"is {args.t_final:g}", key="--t-final", expected="a number > 0")
    only = certify_ids(args.only)
    sc = _load(args)
    say = _progress(args.quiet or args.json)
    r = Run(sc, RunOptions(t_final=args.t_final, certify_only=only, certify_wall_limit=wl, wall_limit=wl, certify_work=1.0), say)
    res = CertifyResult(sc, r.certification)
    if args.json:
        print(_dump(res.to_json()))
    else:
        checks = {c.id: c for c in res.certification.checks(sc)}
        print(f"certificates of scenario {sc.name} ({sc.file})")
        for c in res.certificates:
            ck = checks[c.id]
            mark = c.status.upper()
            if ck.expected == "fail":
                mark += " (expected)" if c.status == "refuted" else " (UNEXPECTED: declared to be refuted)"
            elif ck.unexpected:
                mark += " (UNEXPECTED)"
            elif ck.status == "warn" and c.status == "refuted":
                mark += " (finding: warn)"      # a finding about an argument (the Lyapunov level set)
            elif ck.status == "warn" and c.status == "proven":
                mark += " (stand-in region: warn)"      # a bound on a region the loop is not shown to stay in
            print(f"  {mark:<12} {c.id}  ({c.boxes} boxes, {c.seconds:.1f} s)")
            print(f"      {c.detail}")
            if ck.reason:
                print(f"      declared: {ck.reason}")
        print(f"gate: {res.status.upper()}" + (f" (unexpected: {', '.join(res.unexpected)})" if res.unexpected
                                               else " (every outcome as the scenario declares)"))
    return 1 if res.unexpected else 0
