"""`symfunnel simulate [SCENARIO] [--t-final T] [--out FILE.npz|.csv|.mat] [--json]`: the closed loop (CasADi)."""

from __future__ import annotations

import sys


def register(sub, common) -> None:
    """Add the `simulate` subcommand."""
    sp = sub.add_parser("simulate", help="closed-loop simulation (plant with dead zone, friction, disturbance; "
                                         "controller, ESN, adaptation)")
    common(sp)
    sp.add_argument("--t-final", type=float, metavar="T", help="simulated time in s (default: the scenario's)")
    sp.add_argument("--out", metavar="FILE", help="write the whole trajectory (time first) by the suffix: .npz, "
                    ".csv (units in its # header) or .mat (MATLAB)")
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
    if args.out:
        from ..simulation.export import check_suffix
        check_suffix(args.out)
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
            path = res.save(args.out, arrays)
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


def _unit(s: dict, key: str) -> str:
    """The unit of a metric over the joints ('rad', or 'rad | m' when they differ)."""
    seen = []
    for u in ((s.get("metrics") or {}).get("units") or {}).get(key) or ["?"]:
        if u not in seen:
            seen.append(u)
    return " | ".join(seen)


#: the metrics' rows of the text tables: (label, key)
METRIC_LABELS = (("e1 RMS after the transient", "e1_rms_after_transient"),
                 ("max |e1| after the transient", "e1_max_after_transient"),
                 ("overshoot of e1", "overshoot"), ("settling time of e1 (2 % band)", "settling_time"),
                 ("peak |tau| after the initial decay", "peak_tau_after_t0"),
                 ("control energy (integral of tau^2)", "control_energy"),
                 ("chattering (total variation of tau per s)", "chattering"))


def _metric_rows(s: dict) -> list[tuple[str, str]]:
    """The metrics (`simulation.metrics`) as rows 'label [unit]', one value per joint."""
    per = (s.get("metrics") or {}).get("per_joint") or []
    if not per:
        return []
    rows = []
    for label, key in METRIC_LABELS:
        if key == "settling_time":
            label = f"settling time of e1 ({100 * s['metrics'].get('settling_band_fraction', 0.02):g} % band)"
        if key.endswith("after_transient") and s["metrics"].get("settle_time") is not None:
            label += f" (t >= {s['metrics']['settle_time']:g} s)"
        rows.append((f"{label} [{_unit(s, key)}]", _fmt([m.get(key) for m in per])))
    return rows


#: the event counters of a summary (`event_counts`) in words
EVENT_WORDS = {"e1_zero_crossings": "e1 zero crossings", "e2_zero_crossings": "e2 zero crossings",
               "dead_zone_transitions": "dead-zone transitions", "friction_sign_changes": "friction sign changes"}


def _events(s: dict) -> str:
    """'18: e1 zero crossings 7, e2 zero crossings 7, ...' (a counter not in EVENT_WORDS by its key in words)."""
    parts = [f"{EVENT_WORDS.get(k, k.replace('_', ' '))} {v}" for k, v in (s.get("event_counts") or {}).items()]
    return _fmt(s["events"]) + (": " + ", ".join(parts) if parts else "")


def _table(s: dict) -> None:
    print(f"simulation of scenario {s['scenario']}: {status_text(s['status'])}")
    print(f"  {s['message']}")
    rows = [
        ("simulated time [s]", f"{_fmt(s['t_end'])} of {_fmt(s['t_final'])} ({s['points']} points)"),
        ("min funnel margin e1 (per joint)", _fmt(s["min_margin_e1"])),
        ("min funnel margin e2 (per joint)", _fmt(s["min_margin_e2"])),
        (f"max |e1| [{_unit(s, 'e1_max_after_transient')}]", _fmt(s["max_abs_e1"])),
        (f"max |tau| commanded [{_unit(s, 'peak_tau')}]", _fmt(s["max_abs_tau"])),
        (f"max |tau| applied (after dead zone) [{_unit(s, 'peak_tau')}]", _fmt(s["max_abs_tau_applied"])),
        (f"RMS ESN error |W^T Phi - f_true| [{_unit(s, 'e1_max_after_transient')}/s^2]", _fmt(s["rms_esn_error"])),
        (f"RMS f_true (scale) [{_unit(s, 'e1_max_after_transient')}/s^2]", _fmt(s["rms_f_true"])),
        ("integrator", f"{s['integrator']} ({s['code']} code), smoothing width {_fmt(s['smoothing_width'])}"),
        ("steps / RHS / Jacobian evaluations",
         f"{_fmt(s['steps'])} / {_fmt(s['rhs_evaluations'])} / {_fmt(s['jacobian_evaluations'])}"),
        ("events (switches on the output grid)", _events(s)),
        ("wall time [s]", f"{_fmt(s['wall_time'], '.3g')} (compile/load {_fmt(s['compile_time'], '.3g')}, "
                          f"real-time factor {_fmt(s['realtime_factor'], '.4g')})"),
    ]
    rows += _metric_rows(s)
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
    from ..api import sampled_simulation
    from ..pipeline import Run
    design = Run(sc, progress=say).design
    res = sampled_simulation(sc, design, rate_hz=args.rate, t_final=args.t_final, engine=engine, progress=say)
    summary = res.summary()
    if args.out:
        from ..core.lifecycle import committing
        with committing(0 if res.status == "ok" else 1):
            res.save(args.out)
        say(f"trajectory written to {args.out}")
    if args.json:
        print(_dump(summary))
    else:
        print(f"sampled-data simulation of scenario {sc.name} at {res.rate_hz:g} Hz on the {engine} plant: "
              f"{status_text(res.status)}")
        print(f"  {res.message}")
        keys = ["min_margin_e1", "min_margin_e2", "max_abs_tau", "tau_max", "saturated_fraction", "samples",
                "plant_substeps", "wall_time", "realtime_factor"]
        if engine != "symfunnel":
            keys[7:7] = ["engine_timestep", "engine_mass_scale", "engine_only", "engine_warnings"]
        tau_u = _unit(summary, "peak_tau")
        units = {"max_abs_tau": tau_u, "tau_max": tau_u, "wall_time": "s", "engine_timestep": "s"}
        rows = [(k + (f" [{units[k]}]" if k in units else ""), _fmt(summary.get(k))) for k in keys]
        rows += _metric_rows(summary)
        width = max(len(r[0]) for r in rows)
        for k, v in rows:
            print(f"  {k:<{width}} {v}")
    if res.status != "ok":
        print(f"symfunnel: {status_text(res.status)}: {res.message}", file=sys.stderr)
        return 1
    return 0


def status_text(status: str) -> str:
    """A run's status in words (simulation.hints.status_text, imported when needed: the CLI starts without it)."""
    from ..simulation.hints import status_text as text
    return text(status)

