"""`symfunnel rate [SCENARIO] [--json] [--margin M]`: the lowest sample rate keeping both funnels with a margin."""

from __future__ import annotations


def register(sub, common) -> None:
    """Add the `rate` subcommand."""
    sp = sub.add_parser("rate", help="minimum sample rate of the deployed controller (sampled loop keeps both "
                                     "funnels with margin >= M)",
                        description="Bisection on a log scale over sampled-data runs of the generated C step "
                        "function; every tried rate is listed.")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--margin", type=float, default=0.05, metavar="M",
                    help="required min funnel margin 1 - |e|/F over the horizon (default 0.05)")
    sp.add_argument("--t-final", type=float, metavar="T", help="horizon in s (default: the scenario's)")
    from ._common import add_plant_option
    add_plant_option(sp)
    sp.set_defaults(func=run)


def run(args) -> int:
    """Search, print (table or JSON); exit 1 when no rate up to 1 MHz holds."""
    import math

    from ._common import loading
    with loading():
        from ._common import _dump, _engine, _load, _progress
        from ..core.errors import InputError
        from ..deployed.rate import min_rate
    if not (math.isfinite(args.margin) and 0 <= args.margin < 1):
        raise InputError(f"is {args.margin:g}", key="--margin", expected="a number in [0, 1)")
    if args.t_final is not None and not (math.isfinite(args.t_final) and args.t_final > 0):
        raise InputError(f"is {args.t_final:g}", key="--t-final", expected="a number > 0")
    sc = _load(args)
    engine = _engine(args, sc)
    say = _progress(args.quiet or args.json)
    from ..pipeline import Run
    r = min_rate(sc, Run(sc, progress=say).design, margin=args.margin, t_final=args.t_final, progress=say,
                 engine=engine)
    if args.json:
        print(_dump(r))
    else:
        found = (f"none ({r['reason']})" if r.get("reason") else "none up to 1 MHz") if r["min_rate_hz"] is None \
            else f"{r['min_rate_hz']:.6g} Hz"
        print(f"minimum sample rate of scenario {sc.name} on the {engine} plant (margin >= {r['margin']:g} after the transient): {found}")
        for d in r["tried"]:
            m = "-" if d["min_margin"] is None else f"{d['min_margin']:.4g}"
            mt = d.get("min_margin_after_transient")
            mt = "-" if mt is None else f"{mt:.4g}"
            print(f"  {d['rate_hz']:>12.6g} Hz  {d['status']:<8} min margin after the transient {mt:>10} "
                  f"(whole run {m})  {'holds' if d['holds'] else 'does not hold'}")
    return 0 if r["min_rate_hz"] is not None else 1
