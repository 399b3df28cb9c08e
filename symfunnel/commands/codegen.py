"""`symfunnel codegen [SCENARIO] --lang c|python|fmu --out DIR [--check]`: generated code plus DIR/manifest.json.

`--lang fmu [--fmi 2|3] --rate HZ` writes the deployed controller as DIR/<name>.fmu (FMI Co-Simulation) instead.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..core.outputs import MAX_POINTS


def register(sub, common) -> None:
    """Add the `codegen` subcommand."""
    sp = sub.add_parser("codegen", help="generate C or numpy-only Python for the controller (+ manifest.json), "
                        "or the deployed controller as an FMU",
                        description="Write the controller's functions (funnels, errors, alpha2, alpha2_dot, "
                        "controller) as C (CasADi's C API, one .c and one .h, with main.c, bench.c, a Makefile "
                        "and a recorded trajectory) or as one numpy-only Python module, plus DIR/manifest.json; "
                        "or (--lang fmu) the deployed controller's C step as an FMI 2.0 or 3.0 Co-Simulation FMU, "
                        "DIR/<name>.fmu, with its binary for this platform and its sources.")
    common(sp)
    sp.add_argument("--lang", required=True, choices=["c", "python", "fmu"], help="target language")
    sp.add_argument("--fmi", metavar="VERSION", help="fmu: the FMI version, 2 (default) or 3")
    sp.add_argument("--out", required=True, metavar="DIR", help="output directory (created when missing)")
    sp.add_argument("--check", action="store_true",
                    help="compile (C) or import (Python) the result and compare every function with CasADi at "
                    "random points inside the funnels; exit 1 above 1e-12 (C) or 1e-10 (Python); fmu: FMPy "
                    "validates the FMU and steps it in the sampled loop against the C step, exit 1 when FMPy "
                    "finds a problem or tau differs by more than 1e-9 relative (needs symfunnel[fmu])")
    sp.add_argument("--points", type=int, default=1000, metavar="N", help="check points (default 1000, 1000..100000)")
    sp.add_argument("--seed", type=int, default=0, help="seed of the check points (default 0, >= 0)")
    sp.add_argument("--prefix", metavar="P", help="C: start every exported symbol with P (a C identifier prefix); "
                    "the step API is then Pstate, Pinit, Pstep (default: historical names, symfunnel_step)")
    sp.add_argument("--rate", type=float, metavar="HZ", help="C: sample rate the generated step advances the "
                    "controller state by (default: [implementation].rate_hz; required without it); fmu: required, "
                    "the controller period 1/HZ one DoStep advances")
    sp.add_argument("--json", action="store_true", help="machine-readable summary")
    sp.add_argument("--force", action="store_true", help="overwrite files in DIR that symfunnel did not write")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Generate, write atomically, and optionally cross-check."""
    from ._common import loading
    with loading():
        from ..emit.check import FILL, check_output
        from ..emit.files import foreign_files, write_output
        from ._common import _progress
        from ..core.errors import InputError
        from ..core.outputs import check_count
        from ..pipeline import Run
        from ..emit.step import valid_prefix
        from ..scenario.implementation import check_rate
    check_count(args.points, key="--points", minimum=1000, maximum=MAX_POINTS, what="a number of check points")
    check_count(args.seed, key="--seed", minimum=0, maximum=2**63 - 1, what="a seed")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError("exists and is not a directory", key="--out", expected="a directory (created when missing)")
    if args.prefix is not None and not valid_prefix(args.prefix):
        raise InputError(f"is '{args.prefix}'", key="--prefix",
                         expected="a C identifier prefix: a letter then letters, digits, single '_' (at most "
                         "32) that names none of the C library's functions (as 'init' + 'state' would)")
    if args.rate is not None:
        check_rate(args.rate, file=None, key="--rate")
    if args.lang == "fmu":
        return _run_fmu(args)
    if args.fmi is not None:
        raise InputError(f"is given with --lang {args.lang}", key="--fmi", expected="--lang fmu")
    if args.lang != "c":
        for opt, value in (("--prefix", args.prefix), ("--rate", args.rate)):
            if value is not None:
                raise InputError(f"is given with --lang {args.lang}", key=opt,
                                 expected="--lang c (the Python module has no step API to name or time)")
    with loading():
        run = Run.load(args.scenario, progress=_progress(getattr(args, "quiet", False) or args.json))
    sc, design = run.scenario, run.design
    rate = baked_rate(sc, args.rate, args.scenario) if args.lang == "c" else args.rate
    files = run.code(args.lang, prefix=args.prefix, rate_hz=rate)
    from ..core.lifecycle import committing
    code = 0
    report = None
    if not args.force and foreign_files(files, args.out):
        write_output(files, args.out)          # refused, naming the file, before a check that would be wasted
    if args.check:
        # the check runs on the files in memory before any is written: a command stopped during the check
        # leaves nothing; a failing check still writes them (to read), with exit 1
        try:
            report = check_output(design, args.lang, files, points=args.points, seed=args.seed)
        except RuntimeError as exc:            # compiler diagnostics, a failing main.c: the check failed
            from ..core.errors import CheckFailed
            from ..core.lifecycle import reraise_interrupt
            # unless it is a signal or the limit that a C call turned into a RuntimeError (CasADi's "...
            # KeyboardInterrupt"): a stopped command writes nothing (the twenty-SIGTERM test found it writing)
            reraise_interrupt(exc)
            write_output(files, args.out, force=args.force)
            raise CheckFailed(f"codegen --check: {exc}") from None
        if args.lang == "c":                   # the deployed path at the baked rate: the step must keep the funnels
            from ..checks.implementation import implementation_checks
            sampled = implementation_checks(sc, design, rate_hz=rate)[0]
            report_sampled = sampled.to_json()
        code = 0 if report.passed and (args.lang != "c" or sampled.status == "pass") else 1
    with committing(code):                     # the command's output: from here on it has succeeded
        paths = write_output(files, args.out, force=args.force)
    summary = {"scenario": sc.name, "language": args.lang, "out": str(args.out),
               "files": [{"name": p.name, "bytes": len(files[p.name].encode("utf-8"))} for p in paths]}
    if report is not None:
        summary["check"] = report.to_json()
        if args.lang == "c":
            summary["check"]["sampled_loop"] = report_sampled
    if args.json:
        print(json.dumps(summary, indent=2, allow_nan=False))
        return code
    print(f"wrote {len(paths)} files to {args.out} ({args.lang}, scenario {sc.name}):")
    for f in summary["files"]:
        print(f"  {f['name']:<28} {f['bytes']:>9} bytes")
    if args.lang == "c":
        step = json.loads(files["manifest.json"])["c_api"]["step"]
        print(f"step function: {step['prefix']}step, one call every 1/{step['rate_hz']:g} s (the rate is baked in; "
              f"`symfunnel rate` gives the lowest that keeps the funnels), tau_max {step['tau_max'] or 'none'}")
    if report is not None:
        what = "compiled and loaded" if args.lang == "c" else "imported"
        print(f"check: {what}; {report.points} random points inside the funnels (|e| <= {FILL} F); "
              "error per output: max|gen - casadi| / max(1, max|casadi|)")
        for name, err in {**report.errors, **report.extra}.items():
            print(f"  {name:<28} {err:.3e}")
        verdict = "PASS" if report.passed else "FAIL"
        print(f"worst relative error {report.worst:.3e} (threshold {report.threshold:.0e}): {verdict}")
        if args.lang == "c":
            print(f"sampled loop at the baked rate: {report_sampled['status'].upper()}: {report_sampled['detail']}")
    return code


def _run_fmu(args) -> int:
    """codegen --lang fmu: build DIR/<name>.fmu, optionally check it with FMPy, write it atomically."""
    from ._common import _progress, loading
    from ..core.errors import CheckFailed
    with loading():
        from ..deployed.fmu import TOLERANCE, export_fmu, fmu_options
        from ..pipeline import Run
    fmi = fmu_options(args.fmi, args.rate, args.prefix, check=args.check)     # before any work
    quiet = getattr(args, "quiet", False) or args.json
    with loading():
        run = Run.load(args.scenario, progress=_progress(quiet))
    try:
        res = export_fmu(run.scenario, run.design, args.out, args.rate, fmi=fmi, check=args.check, force=args.force,
                         progress=_progress(quiet))
    except RuntimeError as exc:                # compiler diagnostics: the generated FMU does not build
        from ..core.lifecycle import reraise_interrupt
        reraise_interrupt(exc)
        raise CheckFailed(f"codegen --lang fmu: the FMU does not compile: {exc}") from None
    report = res.check
    code = 0 if report is None or report.passed else 1
    if args.json:
        from ..core.io import json_safe
        print(json.dumps(json_safe(res.to_json(run.scenario.name, args.out)), indent=2, allow_nan=False))
        return code
    src = res.sources
    print(f"wrote {res.path} ({len(res.data)} bytes): FMI {src.fmi}.0 Co-Simulation, model identifier "
          f"{src.identifier}, one fmi{src.fmi}DoStep period = 1/{src.rate_hz:g} s, binary for this platform and "
          f"sources/ ({len(src.sources)} files)")
    if report is not None:
        found = "found no problem" if not report.problems else "found: " + "; ".join(report.problems)
        print(f"check: FMPy validation {found}")
        print(f"  sampled loop, FMU stepped by FMPy against the C step: {report.samples} periods "
              f"(C step: {report.samples_reference}), status {report.status} (C step: {report.status_reference})")
        print(f"  max |tau difference| {report.max_abs_tau:.3e}, relative {report.max_rel_tau:.3e}, states "
              f"{report.max_rel_state:.3e} (threshold {TOLERANCE:.0e}); same breach: {report.same_breach}")
        if report.error:
            print(f"  {report.error}")
        if report.breach_reference is not None:
            print(f"  note: at {src.rate_hz:g} Hz the sampled loop leaves funnel {report.breach_reference['funnel']} "
                  f"(joint {report.breach_reference['joint']}) at t = {report.breach_reference['time']:.6g} s, in "
                  f"both runs; the check compares the FMU with the C step, `symfunnel rate` gives a rate that keeps "
                  "the funnels")
        print(f"check: {'PASS' if report.passed else 'FAIL'}")
    return code


def baked_rate(scenario, rate: float | None, name: str | None) -> float:
    """The rate a generated step is baked at: --rate, else [implementation].rate_hz, else InputError (a silent
    default can sit below the plant's minimum rate, where the deployed loop leaves its funnels)."""
    from ..core.errors import InputError
    if rate is not None:
        return rate
    impl = getattr(scenario, "implementation", None)
    if impl is not None:
        return float(impl.rate_hz)
    raise InputError("is missing and the scenario has no [implementation] rate_hz", key="--rate",
                     expected="the rate the step is called at, at least the minimum that `symfunnel rate "
                     f"{name or scenario.name}` finds")
