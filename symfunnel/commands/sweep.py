"""`symfunnel sweep [SCENARIO] [--runs N] [--workers K] [--scheduler ADDRESS] [--out DIR] [--resume] [--json]`."""

from __future__ import annotations


def register(sub, common) -> None:
    """Add the `sweep` subcommand."""
    sp = sub.add_parser("sweep", help="robustness campaign over the scenario's [[uncertainty]] on one compiled "
                                      "closed loop (local processes or a dask cluster)")
    common(sp)
    sp.add_argument("--runs", type=int, metavar="N", help="number of runs (default: [sweep] runs)")
    sp.add_argument("--workers", type=int, metavar="K", help="local worker processes (default: number of cores)")
    sp.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing dask.distributed cluster "
                                                           "(tcp://HOST:PORT)")
    sp.add_argument("--out", metavar="DIR", help="output directory (default: reports/<name>-sweep/)")
    sp.add_argument("--resume", action="store_true", help="complete an interrupted sweep in DIR")
    sp.add_argument("--json", action="store_true", help="print summary.json")
    from ._common import add_plant_option
    add_plant_option(sp)
    sp.set_defaults(func=run)


def run(args) -> int:
    """Run the campaign and print its summary; exit 0 (breaches are results, not errors)."""
    from ._common import _dump, _engine, _load, _progress
    from ..campaigns.campaign import sweep
    from ..scenario.uncertainty import check_runs
    if args.runs is not None:
        check_runs(args.runs, file=None, key="--runs")
    say = _progress(args.quiet)
    sc = _load(args)
    engine = _engine(args, sc)
    res = sweep(sc, runs=args.runs, workers=args.workers, scheduler=args.scheduler, out=args.out,
                resume=args.resume, progress=say, engine=engine)
    s = res.to_json()
    if args.json:
        print(_dump(s))
        return 0
    lo, hi = s["ci95"]
    p = s["breach_probability"]
    plant = (f", sampled at {s['rate_hz']:.6g} Hz on the {engine} plant" if engine != "symfunnel" else "")
    print(f"sweep of scenario {s['scenario']}: {s['runs']} runs ({s['design']}, seed {s['seed']}, "
          f"{s['t_final']:g} s each{plant}), {s['workers']} workers")
    print(f"  breaches        {s['breaches']} (failed runs: {s['failed']})")
    print(f"  P(breach)       {'-' if p is None else format(p, '.4g')}  (95% Clopper-Pearson: [{lo:.4g}, {hi:.4g}])")
    if s.get("worst"):
        w = s["worst"]
        pt = w.get("min_margin_after_transient")
        print(f"  worst run       {w['run']}: {w['status']}, min margin after the transient "
              f"{'-' if pt is None else format(pt, '.4g')} (t >= {w.get('settle_time') or 0:.3g} s; whole run "
              f"{w['min_margin']:.4g}); replay: symfunnel simulate {res.out / 'worst.toml'}")
    for key, label in (("min_margin_after_transient", "after transient"), ("min_margin", "whole run")):
        q = s.get(key) or {}
        if q:
            print(f"  margin {label:<16} p01 {q['p01']:.5g}, median {q['median']:.5g}, p99 {q['p99']:.5g}")
    rps = s.get("runs_per_second")
    print(f"  throughput      {'-' if rps is None else format(rps, '.3g')} runs/s "
          f"(compile once: {s['compile_time']:.2f} s)")
    print(f"  written         {res.out}/results.parquet, summary.json" + (", worst.toml" if s.get("worst") else ""))
    return 0
