"""Bench area `sweep`: robustness campaigns of the paper's closed loop on one compiled loop, in the same run as a plain
loop of `symfunnel.simulate` calls on scenario variants (what a user would otherwise write).

Ids: `sweep.runs_per_second` (campaign throughput with the machine's cores; baseline: the simulate loop in one
process; `extrapolated_10000_runs_s` says how long the issue's 10,000-run target would take at that rate),
`sweep.scaling_2_workers` (throughput of 2 workers over 1 worker, same campaign), `sweep.cpu_per_run` (process CPU
seconds per campaign run, the figure to extrapolate from on a shared machine; baseline: the same runs with CVODES'
step left free, `simulation.max_step = 0`, as campaigns ran before they capped it at dt/2) and `sweep.compile_time`
(the one compilation of a campaign, in a fresh cache) and `sweep.batches` (2 workers, tasks of batches sized to
about 1.5 CPU-s each against one run per task, the same campaign back to back: runs/s, CPU per run of the parent and its
workers, and the 10,000-run time of each; `sweep.batches_dask` the same on a dask scheduler and 2 workers started on
127.0.0.1, a quarter of the runs, with the CPU of client, scheduler and workers) and `sweep.cpu_per_run_vs_previous`
(CPU per run in one process, this path and the previous one alternated on the same runs: paired ratios). Sizes: $SYMFUNNEL_BENCH_SWEEP_RUNS
(default 500 runs per campaign: issue 24's 10,000-run target is extrapolated from at least that many),
$SYMFUNNEL_BENCH_T_FINAL (default the paper's 20 s). Targets (issue 24): 10,000 runs in at most 300 s on 2 workers,
2-worker scaling at least 1.8; both are wall-clock figures, so `cpu_bound_10000_runs_s` (10,000 times the CPU
seconds per run over the cores) says what the CPU time alone allows on a shared machine.
"""

from __future__ import annotations

import copy
import os
import tempfile
import time
from pathlib import Path

from ._result import result

#: Targets of issue 24.
TARGET_10000_S = 300.0
TARGET_SCALING = 1.8

UNCERTAINTY = [
    {"key": "plant.mass_scale", "dist": "uniform", "low": 0.8, "high": 1.2},
    {"key": "plant.coulomb", "dist": "uniform", "low": 4.0, "high": 8.0, "per_joint": True},
    {"key": "plant.dead_zone.b_r", "dist": "uniform", "low": 0.5, "high": 2.0},
]


def campaign(runs: int, t_final: float, max_step: float | None = None):
    """The paper scenario with three [[uncertainty]] tables and a [sweep] of `runs` runs of `t_final` s (and a
    given simulation.max_step; None: the campaign's default)."""
    from ..scenario import DATA_DIR, from_dict, load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    if max_step is not None:
        raw.setdefault("simulation", {})["max_step"] = float(max_step)
    raw["uncertainty"] = copy.deepcopy(UNCERTAINTY)
    raw["sweep"] = {"runs": runs, "design": "sobol", "seed": 0, "t_final": t_final}
    return from_dict(raw, file=str(DATA_DIR / "paper_2dof.toml"), base_dir=DATA_DIR, default_name="paper")


def baseline_loop(sc, runs: int) -> float:
    """Runs per second of one process calling simulate() on each run's scenario (load, derive, build, run)."""
    from ..scenario import from_dict
    from ..simulation import simulate
    from ..campaigns.campaign import make_job, worst_scenario
    from ..design import derive
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib
    job = make_job(sc)
    t0 = time.perf_counter()
    for i in range(runs):
        text = worst_scenario(job, sc.campaign, i, sc.n)
        raw = tomllib.loads(text)
        variant = from_dict(raw, file=sc.file, base_dir=Path(job.base_dir), default_name="variant")
        simulate(variant, derive(variant), t_final=job.t_final)
    return runs / (time.perf_counter() - t0)


def cpu_per_run(sc, runs: int) -> dict:
    """CPU and wall seconds per campaign run in this process (after one warm-up run), and the process's peak RSS."""
    import resource

    from ..campaigns.campaign import make_job, run_chunk
    job = make_job(sc)
    run_chunk(job, [0])
    t, c = time.perf_counter(), time.process_time()
    run_chunk(job, range(1, runs + 1))
    return {"cpu_s_per_run": (time.process_time() - c) / runs, "wall_s_per_run": (time.perf_counter() - t) / runs,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def vs_previous(sc, runs: int, rounds: int = 4) -> dict:
    """`sweep.cpu_per_run_vs_previous`: CPU per campaign run in this process, the same runs alternately on this path
    and on the previous one (the samples between output points copied into time order after they were taken,
    `crun.SAMPLES_IN_PLACE`; refine_peaks integrating a step once per joint peaking in it,
    `between.SHARE_REFINED_STEPS`), the order swapped every round: paired ratios previous / now."""
    from ..campaigns.campaign import make_job, run_chunk
    from ..simulation import between, crun
    job = make_job(sc)
    ids = list(range(1, runs + 1))
    vals = sc.campaign.values(ids, job.runs)
    run_chunk(job, [0])
    got = {"now": [], "previous": []}
    defaults = crun.SAMPLES_IN_PLACE, between.SHARE_REFINED_STEPS
    try:
        for r in range(rounds):
            for kind in (("now", "previous") if r % 2 == 0 else ("previous", "now")):
                crun.SAMPLES_IN_PLACE = between.SHARE_REFINED_STEPS = kind == "now"
                c = time.process_time()
                run_chunk(job, ids, vals)
                got[kind].append((time.process_time() - c) / runs)
    finally:
        crun.SAMPLES_IN_PLACE, between.SHARE_REFINED_STEPS = defaults
    from statistics import median
    ratios = [p / n for n, p in zip(got["now"], got["previous"])]
    now, prev = median(got["now"]), median(got["previous"])
    return result("sweep.cpu_per_run_vs_previous", now, "CPU s",
                  "the previous path (samples copied into time order, a step refined once per joint)",
                  prev, median(ratios), now=got["now"], previous=got["previous"],
                  paired_ratios=ratios, runs=runs, rounds=rounds, load_average_1min=os.getloadavg()[0],
                  cpu_bound_10000_runs_s=10000 * now / 2,
                  cpu_bound_10000_runs_previous_s=10000 * prev / 2, target_10000_runs_s=250.0,
                  note="medians over the rounds; ratio: the median paired ratio previous / now (> 1: now is faster)")


def _children_cpu() -> float:
    import resource
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed_sweep(sc, out: Path, workers: int, chunk_size=None) -> dict:
    """One campaign on a local pool, with the CPU seconds of this process and of its (reaped) workers."""
    from ..campaigns.campaign import sweep
    c, k = time.process_time(), _children_cpu()
    s = sweep(sc, workers=workers, out=out, chunk_size=chunk_size).summary
    parent, children = time.process_time() - c, _children_cpu() - k
    rps = s["steady_runs_per_second"] or s["runs_per_second"]
    return {"runs_per_second": rps, "extrapolated_10000_runs_s": 10000 / rps, "batches": s["batches"],
            "parent_cpu_s_per_run": parent / s["runs"], "workers_cpu_s_per_run": children / s["runs"],
            "cpu_s_per_run": (parent + children) / s["runs"], "wall_s": s["wall_time"],
            "load_average_1min": os.getloadavg()[0]}


def batches_vs_per_run(sc, tmp: Path, say) -> dict:
    """`sweep.batches`: 2 workers with batched tasks and with one run per task (the path before), interleaved
    twice (per-run, batched, batched, per-run) so that a drifting load falls on both alike."""
    runs = {"per_run": [], "batched": []}
    for i, kind in enumerate(("per_run", "batched", "batched", "per_run")):
        say(f"sweep: {sc.campaign.sweep.runs} runs on 2 workers, {kind.replace('_', ' ')} tasks")
        runs[kind].append(timed_sweep(sc, tmp / f"b{i}", 2, chunk_size=1 if kind == "per_run" else None))

    def mean(kind, key):
        return sum(r[key] for r in runs[kind]) / len(runs[kind])
    b, p = mean("batched", "runs_per_second"), mean("per_run", "runs_per_second")
    # the parent's CPU per task: what a task costs beyond its runs (both paths run the same runs)
    n = sc.campaign.sweep.runs
    extra_tasks = mean("per_run", "batches") - mean("batched", "batches")
    per_task = ((mean("per_run", "parent_cpu_s_per_run") - mean("batched", "parent_cpu_s_per_run")) * n
                / extra_tasks if extra_tasks > 0 else None)
    return result("sweep.batches", b, "runs/s", "one run per task (the same 2 workers)", p, b / p,
                  extrapolated_10000_runs_s=10000 / b, extrapolated_10000_runs_per_run_s=10000 / p,
                  target_10000_runs_s=250.0, cpu_s_per_run=mean("batched", "cpu_s_per_run"),
                  cpu_s_per_run_per_run_tasks=mean("per_run", "cpu_s_per_run"),
                  cpu_ratio=mean("per_run", "cpu_s_per_run") / mean("batched", "cpu_s_per_run"),
                  cpu_bound_10000_runs_s=10000 * mean("batched", "cpu_s_per_run") / 2,
                  cpu_bound_10000_runs_per_run_tasks_s=10000 * mean("per_run", "cpu_s_per_run") / 2,
                  parent_cpu_s_per_task=per_task,
                  paired_ratios=[x["runs_per_second"] / y["runs_per_second"]
                                 for x, y in zip(runs["batched"], runs["per_run"])],
                  batched=runs["batched"], per_run=runs["per_run"], runs=sc.campaign.sweep.runs,
                  note="ratio = runs/s batched over one run per task (steady rates, after the first task came "
                       "back); the CPU figures include the parent's and the workers' start-up; cpu_bound_*: "
                       "10,000 runs at that CPU per run on 2 free cores")


def _process_cpu(proc) -> float:
    import psutil           # a dependency of distributed
    t = psutil.Process(proc.pid).cpu_times()
    return t.user + t.system


def batches_on_dask(sc, tmp: Path, say, runs: int) -> dict:
    """`sweep.batches_dask`: the same comparison on a dask scheduler and 2 single-threaded workers started here on
    127.0.0.1, with the CPU of the client, the scheduler and the workers per run (a dask task costs all three)."""
    import json
    import subprocess
    import sys

    from ..campaigns.campaign import sweep
    dask = str(Path(sys.executable).with_name("dask"))
    sf = tmp / "scheduler.json"
    log = open(tmp / "dask.log", "w")
    procs = []
    try:
        # in this process's session, as the local pool's workers: the kernel's autogroup scheduling gives each
        # session an equal share of a loaded machine, so workers in sessions of their own would run faster there
        procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                       "--scheduler-file", str(sf)], stdout=log, stderr=log))
        deadline = time.monotonic() + 60
        while not sf.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(sf.read_text())["address"]
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-nanny",
                                           "--no-dashboard"], stdout=log, stderr=log))
        sweep(sc, scheduler=address, out=tmp / "dask-warm", runs=4)      # each worker builds its loop once
        got = {"per_run": [], "batched": []}
        for i, kind in enumerate(("per_run", "batched", "batched", "per_run")):
            say(f"sweep: {runs} runs on a dask scheduler + 2 workers, {kind.replace('_', ' ')} tasks")
            c, p0 = time.process_time(), [_process_cpu(p) for p in procs]
            s = sweep(sc, scheduler=address, out=tmp / f"dask{i}", runs=runs,
                      chunk_size=1 if kind == "per_run" else None).summary
            d = [_process_cpu(p) - a for p, a in zip(procs, p0)]
            got[kind].append({"runs_per_second": s["steady_runs_per_second"] or s["runs_per_second"],
                              "batches": s["batches"], "client_cpu_s_per_run": (time.process_time() - c) / runs,
                              "scheduler_cpu_s_per_run": d[0] / runs, "workers_cpu_s_per_run": sum(d[1:]) / runs,
                              "load_average_1min": os.getloadavg()[0]})
            r = got[kind][-1]
            r["cpu_s_per_run"] = r["client_cpu_s_per_run"] + r["scheduler_cpu_s_per_run"] + r["workers_cpu_s_per_run"]
    finally:
        for p in procs:             # no nanny: each is one process
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)
        log.close()

    def mean(kind, key):
        return sum(r[key] for r in got[kind]) / len(got[kind])
    b, p = mean("batched", "runs_per_second"), mean("per_run", "runs_per_second")
    cb, cp = mean("batched", "cpu_s_per_run"), mean("per_run", "cpu_s_per_run")
    extra_tasks = mean("per_run", "batches") - mean("batched", "batches")
    return result("sweep.batches_dask", b, "runs/s", "one run per task (the same dask workers)", p, b / p,
                  extrapolated_10000_runs_s=10000 / b, extrapolated_10000_runs_per_run_s=10000 / p,
                  cpu_s_per_run=cb, cpu_s_per_run_per_run_tasks=cp, cpu_ratio=cp / cb,
                  cpu_bound_10000_runs_s=10000 * cb / 2, cpu_bound_10000_runs_per_run_tasks_s=10000 * cp / 2,
                  cpu_s_per_task=(cp - cb) * runs / extra_tasks if extra_tasks > 0 else None,
                  paired_ratios=[x["runs_per_second"] / y["runs_per_second"]
                                 for x, y in zip(got["batched"], got["per_run"])],
                  batched=got["batched"], per_run=got["per_run"], runs=runs,
                  note="CPU of the client, the scheduler and the 2 workers together (psutil), per run; "
                       "cpu_s_per_task: what one more task costs them")


def run(progress=None) -> list[dict]:
    """Measure the campaign throughput (cores, 1 and 2 workers), the simulate loop and the one compile time."""
    from ..campaigns.campaign import sweep
    say = progress or (lambda s: None)
    runs = int(os.environ.get("SYMFUNNEL_BENCH_SWEEP_RUNS", 500))
    tf = float(os.environ.get("SYMFUNNEL_BENCH_T_FINAL", 20.0))
    sc = campaign(runs, tf)
    cores = os.cpu_count() or 1
    out = {}
    old_cache = os.environ.get("SYMFUNNEL_CACHE")
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-sweep-") as tmp:
        os.environ["SYMFUNNEL_CACHE"] = str(Path(tmp) / "cache")     # a fresh cache: the compile is real
        try:
            from ..simulation import compiled
            compiled._LOADED.clear()
            for w in sorted({cores, 1, 2}):
                say(f"sweep: {runs} runs of {tf:g} s with {w} worker(s)")
                res = sweep(sc, workers=w, out=Path(tmp) / f"w{w}")
                out[w] = res.summary
            compiled = len(list((Path(tmp) / "cache").rglob("*.so")))
            batches = batches_vs_per_run(sc, Path(tmp), say)
            on_dask = batches_on_dask(sc, Path(tmp), say, max(8, runs // 4))
        finally:
            if old_cache is None:
                os.environ.pop("SYMFUNNEL_CACHE", None)
            else:
                os.environ["SYMFUNNEL_CACHE"] = old_cache
    say("sweep: CPU time per run in one process, with CVODES' step capped (the campaign) and free (before)")
    cpu_runs = max(2, min(runs // 4, 100))
    one = cpu_per_run(sc, cpu_runs)
    free = cpu_per_run(campaign(runs, tf, max_step=0.0), cpu_runs)
    old_backend = os.environ.get("SYMFUNNEL_CVODES")
    os.environ["SYMFUNNEL_CVODES"] = "casadi"
    try:
        via_casadi = cpu_per_run(sc, max(2, cpu_runs // 4))
    finally:
        if old_backend is None:
            os.environ.pop("SYMFUNNEL_CVODES", None)
        else:
            os.environ["SYMFUNNEL_CVODES"] = old_backend
    say("sweep: CPU time per run, this path and the previous one alternated")
    previous = vs_previous(sc, max(2, min(runs // 20, 25)))
    base_runs = max(2, min(runs // 4, 6))        # each compiles its own closed loop: a few show the rate
    say(f"sweep baseline: a loop of {base_runs} simulate() calls on scenario variants")
    base_rps = baseline_loop(sc, base_runs)
    # steady rate: after the first chunk came back (worker start-up, a fixed cost, excluded), see sweep.execute
    def steady(w):
        return out[w]["steady_runs_per_second"] or out[w]["runs_per_second"]
    rps = steady(cores)
    first = out[min(out)]
    rps2 = steady(2)
    info = {"runs": runs, "t_final": tf, "workers": cores, "baseline_runs": base_runs,
            "extrapolated_10000_runs_s": 10000 / rps, "target_10000_runs_s": TARGET_10000_S,
            "extrapolated_10000_runs_2_workers_s": 10000 / rps2,
            "meets_target": bool(10000 / rps2 <= TARGET_10000_S),
            "meets_target_cpu": bool(10000 * one["cpu_s_per_run"] / 2 <= TARGET_10000_S),
            "extrapolated_from_runs": runs,
            "runs_per_second_with_startup": out[cores]["runs_per_second"], "breaches": out[cores]["breaches"],
            "one_process": one, "load_average_1min": os.getloadavg()[0],
            "cpu_bound_runs_per_second": cores / one["cpu_s_per_run"],
            "cpu_bound_10000_runs_s": 10000 * one["cpu_s_per_run"] / cores,
            "note": "steady rate after the workers started; 10,000-run time extrapolated from it"}
    return [
        result("sweep.runs_per_second", rps, "runs/s", "loop of symfunnel.simulate calls, one process", base_rps,
               rps / base_rps, **info),
        result("sweep.scaling_2_workers", steady(2) / steady(1), "x", "1 worker", 1.0, steady(2) / steady(1),
               runs_per_second_1=steady(1), runs_per_second_2=steady(2), target=TARGET_SCALING,
               meets_target=bool(steady(2) / steady(1) >= TARGET_SCALING), runs=runs, t_final=tf,
               load_average_1min=os.getloadavg()[0],
               note="wall-clock throughput: on a machine whose cores are busy with other work it cannot scale"),
        result("sweep.cpu_per_run", one["cpu_s_per_run"], "CPU s", "the same runs with CVODES' step free "
               "(simulation.max_step = 0)", free["cpu_s_per_run"], free["cpu_s_per_run"] / one["cpu_s_per_run"],
               runs=cpu_runs, t_final=tf, capped=one, free=free, max_step=sc.simulation.dt / 2,
               runs_per_second_per_core=1 / one["cpu_s_per_run"],
               runs_per_second_per_core_free=1 / free["cpu_s_per_run"],
               casadi_backend=via_casadi, ratio_vs_casadi_backend=via_casadi["cpu_s_per_run"] / one["cpu_s_per_run"],
               note="ratio = CPU per run free / capped (> 1: the campaign's cap is faster); casadi_backend: the "
                    "capped runs through casadi.integrator instead of the direct CVODES backend"),
        previous, batches, on_dask,
        result("sweep.compile_time", first["compile_time"], "s", None, None, None,
               compilations=compiled, campaigns=len(out), runs_per_campaign=runs,
               cache_hit_first=first["compile_cache_hit"]),
    ]
