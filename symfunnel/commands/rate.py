"""`symfunnel rate [SCENARIO] [--json] [--margin M] [--certify [--set-margin E1 E2]]`: the lowest
sample rate keeping both funnels with a margin, simulated; with --certify also the proven rate (certify.sampled)
and the sampled-data funnel theory's bound with rigorous constants."""

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
    sp.add_argument("--certify", action="store_true",
                    help="also prove a rate (certify.sampled: one sampling period from the set S, by interval "
                         "branch and bound) and evaluate the sampled-data funnel theory's bound; docs/certify.md")
    sp.add_argument("--set-margin", type=float, nargs=2, default=None, metavar=("E1", "E2"),
                    help="with --certify: S's margins, |e_i| <= (1 - E_i) F_i at the samples (default: the set "
                         "certify.containment proves invariant, else 0.5 0.5)")
    from ._common import add_plant_option
    add_plant_option(sp)
    sp.set_defaults(func=run)


def run(args) -> int:
    """Search, print (table or JSON); exit 1 when no rate up to 1 MHz holds."""
    from ._common import loading
    with loading():
        from ._common import _dump, _engine, _load, _progress
        from ..api import rate_search
    sc = _load(args)
    engine = _engine(args, sc)
    say = _progress(args.quiet or args.json)
    r = rate_search(sc, margin=args.margin, t_final=args.t_final, plant=args.plant, certify=args.certify,
                    set_margin=args.set_margin, wall_limit=getattr(args, "command_wall_limit", None), progress=say)
    if args.json:
        print(_dump(r))
    else:
        found = (f"none ({r['reason']})" if r.get("reason") else "none up to 1 MHz") if r["min_rate_hz"] is None \
            else f"{r['min_rate_hz']:.6g} Hz"
        print(f"minimum sample rate of scenario {sc.name} on the {engine} plant (margin >= {r['margin']:g} after the transient): {found}")
        from ..core.text import number
        for d in r["tried"]:
            m, mt = number(d["min_margin"]), number(d.get("min_margin_after_transient"))
            print(f"  {d['rate_hz']:>12.6g} Hz  {d['status']:<8} min margin after the transient {mt:>10} "
                  f"(whole run {m})  {'holds' if d['holds'] else 'does not hold'}")
        if args.certify:
            c = r["certificate"]
            fmt = (lambda v: number(v, ".6g", "Hz"))
            print(f"proven rate (certify.sampled, {c['status']}): {fmt(r['proven_rate_hz'])}; simulated "
                  f"{fmt(r['min_rate_hz'])}; theory bound {fmt(r['theory_rate_hz'])}"
                  + ("" if r["ratio"] is None else f"; proven / simulated = {r['ratio']:.3g}"))
            print(f"  {c['detail']}")
    return 0 if r["min_rate_hz"] is not None else 1

