"""Bench area `tune`: `symfunnel tune` on the paper deployed at 1 kHz with |tau| <= 200 N m, beside one verify.

Ids: `tune.wall_s` (wall time of the whole tune: search plus verify's gate on the result, at the default 240 s
limit; target <= 300 s; the derivative-free search, ended by its default evaluation budget: `ended_by`). Baseline, measured in the same run: one `verify --rate 1000` of the paper's own design
(the check a user runs by hand per guess). `tune.gradient_wall_s`: the same without `[implementation]`
(`tune.tau_max = 200`: the gradient path forced, IPOPT with CVODES sensitivities), beside one continuous-time
simulation of the printed design; target <= 60 s, with the CPU time of the process and its children beside.
`tune.paper_max_evals_10_wall_s`: the built-in paper as a user first tunes it (`symfunnel tune --max-evals 10`,
method auto (IPOPT on the paper, chosen by the problem's size), default 240 s limit: `within_limit`,
`lowers_peak_torque`), beside one continuous-time simulation of it.
`tune.paper_default_wall_s` (issue 43): `symfunnel tune paper` as a user first runs it (default method and limit, a
fresh process, the compiled DAE already cached), beside the same command on the previous schedule
(`SYMFUNNEL_TUNE_PATH=previous`, `synthesis.gradient.PREVIOUS`) in the same run: wall and CPU time of each (the
process and its IPOPT child), ratios previous / now; target <= 60 s wall.
`tune.paper_side_by_side_wall_s` (issue 43): the same default command with its IPOPT starts side by side (now),
beside them one after the other (`SYMFUNNEL_TUNE_STARTS=sequential`, the path before) in the same run, alternating
which goes first over `PAIRS` pairs: median wall and CPU time of each, paired ratios, and whether every pair wrote the
same tuned file (it must: the starts' results are judged in the same order).
Horizon: $SYMFUNNEL_BENCH_T_FINAL (default the paper's 20 s).
"""

from __future__ import annotations

import copy
import os
import time

from ._result import result

TARGET_S = 300.0
GRADIENT_TARGET_S = 60.0       # issue 24: the gradient path on the paper without [implementation]
DEFAULT_TARGET_S = 60.0        # issue 43: `symfunnel tune` on the paper, default method and limit


def scenario(t_final: float | None = None, sampled: bool = True):
    """The paper with `[implementation] rate_hz = 1000, tau_max = 200` and `[tune]` (objective peak_torque);
    sampled=False: no `[implementation]`, `[tune] tau_max = 200` (the continuous-time loop)."""
    from ..scenario import DATA_DIR, from_dict, load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    if sampled:
        raw["implementation"] = {"rate_hz": 1000.0, "tau_max": 200.0}
        raw["tune"] = {"objective": "peak_torque"}
    else:
        raw.pop("implementation", None)
        raw["tune"] = {"objective": "peak_torque", "tau_max": 200.0}
    if t_final is not None:
        raw["simulation"]["t_final"] = float(t_final)
    return from_dict(raw, file=str(DATA_DIR / "paper_2dof.toml"), base_dir=DATA_DIR, default_name="paper")


def run(progress) -> list[dict]:
    """The tune of the paper at 1 kHz, 200 N m, and a single verify of the printed design as the baseline."""
    import warnings

    from ..pipeline import Run, RunOptions
    from ..synthesis.search import tune
    tf = os.environ.get("SYMFUNNEL_BENCH_T_FINAL")
    sc = scenario(float(tf) if tf else None)
    progress("tune: baseline, one verify of the printed design at 1 kHz")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        v = Run(sc, RunOptions(rate_hz=1000.0)).verification
    one = time.perf_counter() - t0
    progress("tune: symfunnel tune (search + verify's gate)")
    r = tune(sc, progress=progress)
    out = [result("tune.wall_s", r.wall_s, "s", "one verify --rate 1000 of the printed design", one, one / r.wall_s,
                   target_s=TARGET_S, meets_target=bool(r.wall_s <= TARGET_S), status=r.status,
                   evaluations=r.evaluations, ended_by=r.ended_by, timing_dependent=r.timing_dependent,
                   objective=r.objective, gate=r.gate["status"],
                   baseline_status=v.status, scenario=sc.name, t_final=sc.simulation.t_final)]
    sc = scenario(float(tf) if tf else None, sampled=False)
    progress("tune: baseline, one continuous-time simulation of the printed design")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _ = Run(sc).simulation
    one = time.perf_counter() - t0
    progress("tune: symfunnel tune without [implementation] (gradient path + verify's gate)")
    c0 = _cpu_with_children()
    r = tune(sc, progress=progress, method="gradient")
    cpu = _cpu_with_children() - c0
    out.append(result("tune.gradient_wall_s", r.wall_s, "s", "one continuous-time simulation of the printed design",
                      one, one / r.wall_s, target_s=GRADIENT_TARGET_S, meets_target=bool(r.wall_s <= GRADIENT_TARGET_S),
                      cpu_s=cpu, meets_target_cpu=bool(cpu <= GRADIENT_TARGET_S),
                      status=r.status, method=r.method, evaluations=r.evaluations, objective=r.objective,
                      gate=r.gate["status"], scenario=sc.name, t_final=sc.simulation.t_final))
    # the built-in paper as a user first tunes it: `symfunnel tune --max-evals 10` within the default limit
    from ..scenario import load_scenario
    paper = load_scenario("paper")
    progress("tune: baseline, one continuous-time simulation of the built-in paper")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _ = Run(paper).simulation
    one = time.perf_counter() - t0
    progress("tune: symfunnel tune paper --max-evals 10 (default limit 240 s, method auto)")
    r = tune(paper, progress=progress, max_evaluations=10)
    out.append(result("tune.paper_max_evals_10_wall_s", r.wall_s, "s", "one continuous-time simulation of the paper",
                      one, one / r.wall_s, limit_s=240.0, within_limit=bool(r.wall_s <= 240.0), status=r.status,
                      method=r.method, evaluations=r.evaluations, objective=r.objective, gate=r.gate["status"],
                      lowers_peak_torque=bool(r.objective["after"] is not None and r.objective["before"] is not None
                                              and r.objective["after"] < r.objective["before"])))
    out.append(paper_default(progress))
    out.append(paper_side_by_side(progress))
    return out


def cli_tune(env_path: str, out_file: str, extra: tuple = (), scenario: str = "paper", starts: str = "") -> dict:
    """`symfunnel tune SCENARIO --json --out FILE` in a fresh process on the schedule `env_path` ("" now, "previous"),
    its IPOPT starts side by side ("") or one after the other (`starts` "sequential"):
    {"wall_s", "cpu_s" (the process and its waited-for children), "json" (its --json output or None), "rc"}."""
    import json
    import subprocess
    import sys
    env = {**os.environ, "SYMFUNNEL_TUNE_PATH": env_path, "SYMFUNNEL_TUNE_STARTS": starts}
    c0, t0 = _children_cpu(), time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "symfunnel", "tune", scenario, "--json", "--out", out_file, *extra],
                       capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    try:
        js = json.loads(p.stdout)
    except ValueError:
        js = None
    return {"wall_s": wall, "cpu_s": cpu, "json": js, "rc": p.returncode}


def paper_default(progress) -> dict:
    """`tune.paper_default_wall_s`: the default tune of the paper now and on the previous schedule, in one run."""
    import tempfile
    from pathlib import Path
    _warm_compile(progress)
    runs = {}
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-tune-") as tmp:
        for label, path in (("now", ""), ("previous", "previous")):
            progress(f"tune: symfunnel tune paper (defaults), schedule {label}")
            runs[label] = cli_tune(path, str(Path(tmp, f"{label}.toml")))
    now, prev = runs["now"], runs["previous"]
    js = now["json"] or {}
    pj = prev["json"] or {}
    return result("tune.paper_default_wall_s", now["wall_s"], "s",
                  "the same command on the previous schedule (SYMFUNNEL_TUNE_PATH=previous)", prev["wall_s"],
                  prev["wall_s"] / now["wall_s"], cpu_s=now["cpu_s"], baseline_cpu_s=prev["cpu_s"],
                  cpu_ratio=prev["cpu_s"] / now["cpu_s"] if now["cpu_s"] > 0 else None,
                  target_s=DEFAULT_TARGET_S, meets_target=bool(now["wall_s"] <= DEFAULT_TARGET_S),
                  meets_target_cpu=bool(now["cpu_s"] <= DEFAULT_TARGET_S), status=js.get("status"),
                  gate=(js.get("gate") or {}).get("status"), objective=js.get("objective"),
                  evaluations=js.get("evaluations"), baseline_status=pj.get("status"),
                  baseline_objective=pj.get("objective"), exit_codes=[now["rc"], prev["rc"]])


#: pairs of the side-by-side bench (each pair runs both paths, the first of the pair alternating)
PAIRS = 2


def paper_side_by_side(progress, pairs: int = PAIRS) -> dict:
    """`tune.paper_side_by_side_wall_s`: the default tune of the paper with its IPOPT starts side by side and one
    after the other, interleaved in one run (the VM's speed drifts: only paired ratios compare)."""
    import statistics
    import tempfile
    from pathlib import Path
    _warm_compile(progress)
    runs: dict[str, list] = {"now": [], "sequential": []}
    same = []
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-tune-") as tmp:
        for k in range(pairs):
            order = ("sequential", "now") if k % 2 == 0 else ("now", "sequential")
            for label in order:
                progress(f"tune: symfunnel tune paper (defaults), IPOPT starts {label}, pair {k + 1} of {pairs}")
                runs[label].append(cli_tune("", str(Path(tmp, f"{label}{k}.toml")),
                                            starts="sequential" if label == "sequential" else ""))
            same.append(Path(tmp, f"now{k}.toml").read_bytes() == Path(tmp, f"sequential{k}.toml").read_bytes())
    now, seq = runs["now"], runs["sequential"]
    med = statistics.median
    js = now[-1]["json"] or {}
    wall, base = med(r["wall_s"] for r in now), med(r["wall_s"] for r in seq)
    cpu, base_cpu = med(r["cpu_s"] for r in now), med(r["cpu_s"] for r in seq)
    return result("tune.paper_side_by_side_wall_s", wall, "s",
                  "the same command, its IPOPT starts one after the other (SYMFUNNEL_TUNE_STARTS=sequential)", base,
                  base / wall, cpu_s=cpu, baseline_cpu_s=base_cpu,
                  paired_wall_ratios=[s["wall_s"] / n["wall_s"] for s, n in zip(seq, now)],
                  paired_cpu_ratios=[s["cpu_s"] / n["cpu_s"] for s, n in zip(seq, now) if n["cpu_s"] > 0],
                  same_file=all(same), target_s=DEFAULT_TARGET_S, meets_target=bool(wall <= DEFAULT_TARGET_S),
                  status=js.get("status"), gate=(js.get("gate") or {}).get("status"),
                  objective=js.get("objective"), exit_codes=[r["rc"] for r in now + seq])


def _warm_compile(progress) -> None:
    """Build (and cache) the paper's sensitivity DAE before either timed run, so that neither pays the first compile."""
    import warnings

    from ..scenario import load_scenario
    from ..scenario.tune import TuneSpec
    from ..synthesis.candidates import variables
    from ..synthesis.gradient import GradientProblem
    progress("tune: compiling the paper's sensitivity DAE once (cached) before the timed runs")
    sc = load_scenario("paper")
    spec = sc.tune or TuneSpec()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        GradientProblem(sc, spec, variables(sc, spec), t_final=1.0, coarse=None, grid_points=10)


def _children_cpu() -> float:
    """CPU seconds of this process's waited-for children (and theirs)."""
    import resource
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ch.ru_utime + ch.ru_stime


def _cpu_with_children() -> float:
    """CPU seconds of this process plus its waited-for children (IPOPT runs in a killable child)."""
    import resource
    me = resource.getrusage(resource.RUSAGE_SELF)
    return me.ru_utime + me.ru_stime + _children_cpu()
