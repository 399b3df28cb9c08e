"""`symfunnel simulate [SCENARIO] [--t-final T] [--out FILE.npz] [--json]`: the closed loop, with CasADi integrators."""

from __future__ import annotations

import sys


def register(sub, common) -> None:
    """Add the `simulate` subcommand."""
    sp = sub.add_parser("simulate", help="closed-loop simulation (plant with dead zone, friction, disturbance; "
                                         "controller, ESN, adaptation)")
    common(sp)
    sp.add_argument("--t-final", type=float, metavar="T", help="simulated time in s (default: the scenario's)")
    sp.add_argument("--out", metavar="FILE.npz", help="write the whole trajectory (time first) to an .npz file")
    sp.add_argument("--json", action="store_true", help="print the JSON summary")
    from ..family.integrators import INTEGRATORS
    sp.add_argument("--integrator", choices=INTEGRATORS.names(),
                    help="integrator (default: the scenario's, normally cvodes)")
    sp.add_argument("--width", type=float, metavar="W", help="smoothing width of the non-smooth plant terms "
                                                             "(default: the scenario's simulation.smoothing_width)")
    sp.add_argument("--wall-limit", type=float, metavar="S", help="wall-clock limit in s (default: the scenario's)")
    sp.add_argument("--convergence", action="store_true",
                    help="also run the smoothing-width convergence study and put it in the summary")
    sp.add_argument("--no-jit", action="store_true", help="do not compile to C; use the CasADi virtual machine")
    sp.add_argument("--rate", type=float, metavar="HZ", help="simulate the deployed controller sampled at HZ "
                    "(overrides [implementation].rate_hz; with [implementation] the sampled loop is the default)")
    from ._common import add_plant_option
    add_plant_option(sp)
    sp.set_defaults(func=run)


def run(args) -> int:
    """Simulate, print the summary (table or JSON), write the npz; exit 1 unless the run stayed in its funnels."""
    import math
    import warnings

    from ._common import _dump, _engine, _load, _progress
    from ..core.errors import InputError
    from ..pipeline import Run, RunOptions
    from ..simulation import convergence_study

    if args.t_final is not None and not (math.isfinite(args.t_final) and args.t_final > 0):
        raise InputError(f"is {args.t_final:g}", key="--t-final", expected="a number > 0")
    from ..core.deadline import check_seconds
    check_seconds(args.wall_limit, key="--wall-limit", allow_none=True)
    if args.width is not None and not (math.isfinite(args.width) and args.width >= 0):
        raise InputError(f"is {args.width:g}", key="--width", expected="a number >= 0")
    if args.out and not args.out.endswith(".npz"):
        raise InputError(f"is '{args.out}'", key="--out", expected="a file name ending in .npz")
    if args.out:
        from ..core.outputs import check_output_file
        check_output_file(args.out)
    say = _progress(args.quiet)
    if args.rate is not None:
        from ..scenario.implementation import check_rate
        check_rate(args.rate, file=None, key="--rate")
    sc = _load(args)
    if args.out:
        from ..core.outputs import check_not_input
        from ._common import scenario_inputs
        check_not_input(args.out, scenario_inputs(sc), key="--out")
    engine = _engine(args, sc)
    if args.rate is not None or sc.implementation is not None or engine != "symfunnel":
        return _sampled(args, sc, say, engine)
    run = Run(sc, RunOptions(t_final=args.t_final, integrator=args.integrator, width=args.width,
                             wall_limit=args.wall_limit, jit=not args.no_jit), say)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run.simulation
    for w in caught:
        print("symfunnel: warning: " + " ".join(str(w.message).split()), file=sys.stderr)
    if args.convergence:
        res.convergence = convergence_study(sc, run.design, t_final=args.t_final, integrator=args.integrator,
                                            progress=say)
    summary = res.summary()
    if args.out:
        from ..core.lifecycle import committing
        arrays = run.trajectory_arrays() if res.t.size else None
        with committing(0 if res.status == "ok" else 1):    # the command's one file: from here on it has succeeded
            path = res.save_npz(args.out, arrays)
        say(f"trajectory written to {path}")
    if args.json:
        print(_dump(summary))
    else:
        _table(summary)
    if res.status != "ok":
        print(f"symfunnel: {status_text(res.status)}: {res.message}", file=sys.stderr)
        return 1
    return 0


def _fmt(v, spec=".4g") -> str:
    if v is None:
        return "-"
    if isinstance(v, list):
        return ", ".join(_fmt(x, spec) for x in v)
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _table(s: dict) -> None:
    print(f"simulation of scenario {s['scenario']}: {status_text(s['status'])}")
    print(f"  {s['message']}")
    rows = [
        ("simulated time [s]", f"{_fmt(s['t_end'])} of {_fmt(s['t_final'])} ({s['points']} points)"),
        ("min funnel margin e1 (per joint)", _fmt(s["min_margin_e1"])),
        ("min funnel margin e2 (per joint)", _fmt(s["min_margin_e2"])),
        ("max |e1| [rad]", _fmt(s["max_abs_e1"])),
        ("max |tau| commanded", _fmt(s["max_abs_tau"])),
        ("max |tau| applied (after dead zone)", _fmt(s["max_abs_tau_applied"])),
        ("RMS ESN error |W^T Phi - f_true|", _fmt(s["rms_esn_error"])),
        ("RMS f_true (scale)", _fmt(s["rms_f_true"])),
        ("integrator", f"{s['integrator']} ({s['code']} code), smoothing width {_fmt(s['smoothing_width'])}"),
        ("steps / RHS / Jacobian evaluations",
         f"{_fmt(s['steps'])} / {_fmt(s['rhs_evaluations'])} / {_fmt(s['jacobian_evaluations'])}"),
        ("events (switches on the output grid)", f"{_fmt(s['events'])} {s['event_counts']}"),
        ("wall time [s]", f"{_fmt(s['wall_time'], '.3g')} (compile/load {_fmt(s['compile_time'], '.3g')}, "
                          f"real-time factor {_fmt(s['realtime_factor'], '.4g')})"),
    ]
    if s.get("breach"):
        b = s["breach"]
        rows.append(("breach", f"t = {_fmt(b['time'])} s, funnel {b['funnel']}, joint {b['joint']}, "
                               f"margin {_fmt(b['margin'], '.3g')}"))
    if s.get("convergence"):
        c = s["convergence"]
        for r in c["runs"]:
            rows.append((f"convergence w = {r['width']:g}", f"max |q - q(w={c['reference_width']:g})| = "
                                                             f"{_fmt(r['max_abs_q_diff_vs_smallest'], '.3g')}"))
        rate = (_fmt(c["observed_rates"], ".3g") + " (1 expected: the smoothing error is O(w))"
                if c["observed_rates"] else "n/a: the differences are zero (no smoothed term was active)")
        rows.append(("observed rate", rate))
    width = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")


def _sampled(args, sc, say, engine: str = "symfunnel") -> int:
    """The sampled-data loop around the generated C step (symfunnel.deployed.loop); exit 1 unless it kept its funnels.

    On a physics engine without a rate (no --rate, no [implementation]): at twice the minimum rate on that engine."""
    from ._common import _dump
    from ..core.io import atomic_write
    from ..deployed.loop import simulate_sampled
    from ..pipeline import Run
    design = Run(sc, progress=say).design
    rate = args.rate
    if rate is None and sc.implementation is None:
        from ..deployed.rate import min_rate
        found = min_rate(sc, design, t_final=args.t_final, progress=say, engine=engine)
        if found["min_rate_hz"] is None:
            print(f"symfunnel: breach: no sample rate up to 1 MHz keeps both funnels on the {engine} plant",
                  file=sys.stderr)
            return 1
        rate = 2.0 * found["min_rate_hz"]
        say(f"sampled at {rate:.6g} Hz: twice the minimum rate {found['min_rate_hz']:.6g} Hz on the {engine} plant")
    res = simulate_sampled(sc, design, rate_hz=rate, t_final=args.t_final, progress=say, engine=engine)
    summary = res.summary()
    if args.out:
        import io

        import numpy as np
        buf = io.BytesIO()
        np.savez_compressed(buf, t=res.t, q=res.q, dq=res.dq, tau=res.tau, margins=res.margins)
        from ..core.lifecycle import committing
        with committing(0 if res.status == "ok" else 1):
            atomic_write(args.out, buf.getvalue())
        say(f"trajectory written to {args.out}")
    if args.json:
        print(_dump(summary))
    else:
        print(f"sampled-data simulation of scenario {sc.name} at {res.rate_hz:g} Hz on the {engine} plant: "
              f"{res.status}")
        print(f"  {res.message}")
        keys = ["min_margin_e1", "min_margin_e2", "max_abs_tau", "tau_max", "saturated_fraction", "samples",
                "plant_substeps", "wall_time", "realtime_factor"]
        if engine != "symfunnel":
            keys[7:7] = ["engine_timestep", "engine_mass_scale", "engine_only", "engine_warnings"]
        for k in keys:
            print(f"  {k:<20} {_fmt(summary.get(k))}")
    if res.status != "ok":
        print(f"symfunnel: {status_text(res.status)}: {res.message}", file=sys.stderr)
        return 1
    return 0


def status_text(status: str) -> str:
    """A run's status in words (simulation.hints.status_text, imported when needed: the CLI starts without it)."""
    from ..simulation.hints import status_text as text
    return text(status)

