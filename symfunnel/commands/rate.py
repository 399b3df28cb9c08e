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
                    help="with --certify: S's margins, |e_i| <= (1 - E_i) F_i at the samples (default 0.5 0.5)")
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
    import time
    started = time.monotonic()
    for k, v in zip(("e1", "e2"), args.set_margin or ()):
        if not (math.isfinite(v) and 1e-3 <= v < 1):
            raise InputError(f"is {v:g} for {k}", key="--set-margin", expected="margins in [0.001, 1)")
    sc = _load(args)
    engine = _engine(args, sc)
    say = _progress(args.quiet or args.json)
    from ..pipeline import Run, RunOptions
    run = Run(sc, RunOptions(t_final=args.t_final), progress=say)     # W_hat's box (--certify) from this horizon
    r = min_rate(sc, run.design, margin=args.margin, t_final=args.t_final, progress=say, engine=engine)
    if args.certify:
        # the command's --wall-limit: the proof gets half of what the simulated search left, and ends undecided
        wl = getattr(args, "command_wall_limit", None)
        left = None if wl is None else max(0.0, 0.5 * (wl - (time.monotonic() - started)))
        r.update(_certified(args, sc, run, r, say, left))
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
        if args.certify:
            c = r["certificate"]
            fmt = (lambda v: "-" if v is None else f"{v:.6g} Hz")
            print(f"proven rate (certify.sampled, {c['status']}): {fmt(r['proven_rate_hz'])}; simulated "
                  f"{fmt(r['min_rate_hz'])}; theory bound {fmt(r['theory_rate_hz'])}"
                  + ("" if r["ratio"] is None else f"; proven / simulated = {r['ratio']:.3g}"))
            print(f"  {c['detail']}")
    return 0 if r["min_rate_hz"] is not None else 1


def _certified(args, sc, run, r: dict, say, wall_limit) -> dict:
    """certify.sampled beside the simulated search: the contract's keys (docs/certify.md)."""
    from ..certificates.sampled import DEFAULT_SET_MARGIN
    from ..certificates.sampled_rate import sampled_bracket, simulated_w_hat_range
    design = run.design
    wr = (simulated_w_hat_range(design, run.closed_loop, run.simulation) if design.n_regressor else None)
    T = args.t_final if args.t_final is not None else sc.simulation.t_final
    return sampled_bracket(sc, design, t_final=T, margin=args.margin, set_margin=tuple(args.set_margin or DEFAULT_SET_MARGIN),
                           f_sim=r["min_rate_hz"], w_hat_range=wr, wall_limit=wall_limit, progress=say)
