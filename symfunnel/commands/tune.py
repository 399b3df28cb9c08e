"""`symfunnel tune [SCENARIO] [--out FILE.toml] [--json]`: gains and inner funnel for the `[tune]` constraints."""

from __future__ import annotations

import contextlib
import math


def register(sub, common) -> None:
    """Add the `tune` subcommand."""
    sp = sub.add_parser("tune", help="search gains and the e2 funnel that keep both funnels with a margin within the "
                                     "torque limit (reference and e1 funnel fixed)",
                        description="Without [implementation]: IPOPT with exact sensitivities of the simulated "
                        "constraints; with it (or as fallback): derivative-free search (Nelder-Mead, multi-start) over "
                        "the [tune] parameters; the best design goes through verify's gate. Exit 0 ok, 1 infeasible, "
                        "2 bad input.")
    common(sp)
    sp.add_argument("--out", metavar="FILE.toml", help="write the tuned scenario (with a [[deviations]] entry per "
                                                       "change)")
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--wall-limit", type=float, default=240.0, metavar="S",
                    help="the whole command's wall time, a safety net: the search stops at 80 %% of it, the rest is "
                         "kept for the re-check of the rounded gains and verify's gate (default 240); a result it "
                         "ended is marked timing-dependent")
    sp.add_argument("--t-final", type=float, metavar="T", help="horizon of each candidate's runs (default: the "
                                                             "scenario's)")
    sp.add_argument("--max-evals", type=int, metavar="K",
                    help="stop the search after K candidate evaluations (the derivative-free search's default: "
                         f"{_budget()}, a count, so the same scenario gives the same file)")
    sp.add_argument("--method", choices=("auto", "gradient", "derivative-free"), default="auto",
                    help="auto (default): IPOPT without [implementation] when a timed forward solve says it fits "
                         "the wall-clock limit, else derivative-free")
    sp.set_defaults(func=run)


def _budget() -> int:
    """The derivative-free search's default evaluation budget (for the help text)."""
    from ..synthesis.choice import DERIVATIVE_FREE_EVALUATIONS
    return DERIVATIVE_FREE_EVALUATIONS


@contextlib.contextmanager
def _stdout_to_stderr():
    """File descriptor 1 onto 2 while tuning: CasADi prints a failed integrator call's inputs to the C stdout, which
    would corrupt --json (a candidate that does not integrate is an expected event of the search)."""
    import os
    import sys
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:                  # no file descriptor 1 (embedded): nothing to protect
        yield
        return
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def run(args) -> int:
    """Tune, write --out atomically, print a summary (or JSON); exit 1 when no feasible design was found."""
    from pathlib import Path

    from ..core.errors import InputError
    from ..core.io import atomic_write
    from ..core.toml_write import dumps
    from ..synthesis.search import tune
    from ._common import _dump, _load, _progress
    from ..core.deadline import check_seconds
    check_seconds(args.wall_limit, key="--wall-limit")
    if args.t_final is not None and not (math.isfinite(args.t_final) and args.t_final > 0):
        raise InputError(f"is {args.t_final:g}", key="--t-final", expected="a number > 0")
    if args.max_evals is not None and args.max_evals < 1:
        raise InputError(f"is {args.max_evals}", key="--max-evals", expected="an integer >= 1")
    if args.out is not None and Path(args.out).is_dir():
        raise InputError("is a directory", file=args.out, key="--out", expected="a .toml file path")
    sc = _load(args)
    if args.out is not None:
        from ..core.outputs import check_not_input
        from ._common import scenario_inputs
        check_not_input(args.out, scenario_inputs(sc), key="--out")
    say = _progress(args.quiet or args.json)
    with _stdout_to_stderr():
        # the limit bounds the whole command: it counts from the command's start (start-up and loading)
        import time

        from ..core.deadline import command_elapsed
        r = tune(sc, wall_limit=args.wall_limit, t_final=args.t_final, progress=say,
                 max_evaluations=args.max_evals, method=args.method,
                 started=time.monotonic() - command_elapsed())
    if args.out is not None:
        from ..core.lifecycle import committing
        text = r.tuned_text or dumps(r.tuned_raw)
        with committing(0 if r.status == "ok" else 1):      # the command's one file: from here on it has succeeded
            atomic_write(args.out, text)
    if args.json:
        print(_dump(r.to_json()))
    else:
        o = r.objective
        fmt = (lambda v: "-" if v is None else f"{v:.6g}")
        print(f"tune {sc.name}: {r.status.upper()} after {r.evaluations} evaluations in {r.wall_s:.1f} s "
              f"(since the command started, of --wall-limit {args.wall_limit:g} s)")
        print(f"  method: {r.method}")
        print(f"  why: {r.why}")
        print(f"  objective {o['name']}: {fmt(o['before'])} -> {fmt(o['after'])}")
        for c in r.changes:
            print(f"  {c['key']}: {c['before']:.6g} -> {c['after']:.4g}")
        cmp_ = r.comparison
        from ..core.names import joint_units, unit_label
        units = joint_units(sc.model.joint_types, sc.n)
        tu, eu = unit_label(units, "tau"), unit_label(units, "e1")
        sq, per_s = (f"{eu}^2" if " " not in eu else f"({eu})^2"), (f"{tu}/s" if "|" not in tu else f"({tu})/s")
        if cmp_:
            print(f"  {'':<30}{'original':>14}{'tuned':>14}")
            for k, label in (("feasible", "feasible"), ("reached_horizon", "reached horizon"),
                             ("peak_torque", f"peak |tau| [{tu}]"), ("ise", f"ISE e1 [{sq} s]"),
                             ("e1_rms_after_transient", f"e1 RMS after transient [{eu}]"),
                             ("chattering", f"chattering [{per_s}]"),
                             ("min_margin", "min margin after transient"), ("min_rate_hz", "min rate [Hz]"),
                             ("sample_violations", "violating samples")):
                a, b = cmp_["original"].get(k), cmp_["tuned"].get(k)
                if a is None and b is None:
                    continue
                cell = (lambda v: "-" if v is None else (str(v) if isinstance(v, (bool, int)) else f"{v:.4g}"))
                print(f"  {label:<30}{cell(a):>14}{cell(b):>14}")
        for k, g in r.constraints["values"].items():
            print(f"  constraint {k}: {g:+.4g} ({'holds' if g >= 0 else 'violated'}; worst on "
                  f"{r.constraints['worst_run'].get(k, 'nominal')})")
        if r.samples:
            print(f"  uncertainty: {r.samples} samples + nominal; no violation gives P(violation) <= 0.05 with "
                  f"confidence {r.confidence:.3f} (scenario approach)")
        print(f"  verify gate: {r.gate['status']}" + (f" (unexpected: {', '.join(r.gate['unexpected'])})"
                                                      if r.gate.get("unexpected") else ""))
        if r.binding:
            print(f"  binding: {', '.join(r.binding)}")
        for e in r.at_bounds:
            print(f"  at a bound: {e['key']} = {e['value']:.4g}, its {e['bound']} bound (was {e['before']:.4g})")
        for n in r.notes:
            print(f"  note: {n}")
        if args.out is not None:
            print(f"  wrote {args.out} (the scenario's own file, comments kept, gains to 4 significant digits)")
    return 0 if r.status == "ok" else 1
