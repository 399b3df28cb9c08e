"""Robustness campaigns: many runs of one scenario's closed loop, compiled once, over its `[[uncertainty]]`.

Each run's drawn values are a pure function of (seed, run id) (`symfunnel.scenario.uncertainty`) and its row a pure
function of those values (fixed integration chunks, one compiled loop), so rows are identical whatever executes
them: a local process pool or a dask.distributed cluster, with any number of workers, in batches of any size (a task
is a batch of about 1.5 CPU-s, `batches`). Finished batches of rows are written at once as small Parquet files
beside `results.parquet`, which is rewritten (atomically) from them every few seconds and at the end: a killed
sweep loses at most its runs in flight and `resume` completes it.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import math
import os
import shutil
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.io import atomic_write, exclusive_lock, json_safe
from ..simulation.metrics import CAMPAIGN_METRICS, campaign_row
from .cluster import connect
from .statistics import summarize
from .storage import ResultStore

ROW_STATUS = {"ok": "ok", "breach": "breach", "initial_outside": "breach", "timeout": "failed", "failed": "failed"}
#: a campaign caps CVODES' step at this fraction of the output step unless the scenario sets simulation.max_step:
#: fewer rejected steps and Newton-matrix refactorisations (docs/sweep.md, `symfunnel bench --only sweep`)
MAX_STEP_OF_DT = 0.5


@dataclass(frozen=True)
class Job:
    """Everything a worker needs to run chunks of a campaign (picklable; the closed loop is built once per process)."""

    raw: dict
    file: str
    base_dir: str
    name: str
    t_final: float
    runs: int
    fingerprint: str
    files: tuple = ()        # (path, sha256) of every input file besides the TOML: a worker checks it reads the same
    engine: str = "symfunnel"         # "symfunnel": the continuous-time closed loop; else the sampled loop on it


#: what a user adds to a scenario to sweep it (printed when the table is missing)
UNCERTAINTY_EXAMPLE = """[[uncertainty]]
key = "plant.mass_scale"    # any plant, [initial] or [implementation] key; docs/sweep.md lists them
dist = "uniform"
low = 0.8
high = 1.2"""

_STATE: dict = {}        # (fingerprint, thread) -> (scenario, closed loop, compile time, cache hit)


def make_job(scenario, *, runs: int | None = None, engine: str = "symfunnel", rate_hz: float | None = None) -> Job:
    """The campaign of a scenario with its `[[uncertainty]]` (InputError without one); on a physics engine the
    runs are the deployed controller's sampled loop at `rate_hz` (written into the job's scenario, and so into
    worst.toml, with the engine)."""
    c = scenario.campaign
    if c is None or not c.uncertainties:
        from ..scenario import is_builtin
        where = (f"copy it with `symfunnel init --from {scenario.name} --out my.toml` and append to the copy"
                 if is_builtin(scenario.path) else "append to the file")
        raise InputError("has no [[uncertainty]] table", file=scenario.file, key="uncertainty",
                         expected=f"at least one [[uncertainty]] table for a sweep; for example, {where}:",
                         example=UNCERTAINTY_EXAMPLE)
    if engine == "symfunnel":
        for i, u in enumerate(c.uncertainties):
            if u.key.startswith("plant.mujoco."):
                raise InputError(f"is '{u.key}', which only the mujoco plant has, but the sweep runs on symfunnel's "
                                 "plant", file=scenario.file, key=f"uncertainty[{i}].key",
                                 expected="sweep --plant mujoco (or [plant] engine = \"mujoco\")")
    n_runs = c.sweep.runs if runs is None else runs
    tf = float(c.sweep.t_final if c.sweep.t_final is not None else scenario.simulation.t_final)
    raw = copy.deepcopy(scenario.raw)
    sim = raw.setdefault("simulation", {})
    if engine != "symfunnel":
        raw.setdefault("plant", {})["engine"] = engine
        raw.setdefault("implementation", {})["rate_hz"] = float(rate_hz)
    elif scenario.simulation.integrator == "cvodes" and "max_step" not in sim:
        sim["max_step"] = MAX_STEP_OF_DT * float(scenario.simulation.dt)   # in worst.toml too: replays exactly
    files = input_files(scenario)
    from ..core.version import __version__
    blob = json.dumps({"raw": raw, "runs": n_runs, "t_final": tf, "files": files, "version": __version__},
                      sort_keys=True, default=str)
    fp = hashlib.sha256(blob.encode()).hexdigest()[:20]
    return Job(raw, scenario.file, str(Path(scenario.file).resolve().parent), scenario.name, tf, n_runs, fp,
               tuple(sorted(files.items())), engine)


def input_files(scenario) -> dict[str, str]:
    """{path: sha256} of every file besides the scenario's own TOML that its campaign depends on (a URDF, ...)."""
    own = os.path.realpath(scenario.file)
    return {k: v for k, v in getattr(scenario, "inputs", {}).items() if k != own}


def _job_scenario(job: Job):
    """The job's scenario, loaded in this worker; InputError when one of its input files changed since the start."""
    from ..scenario import from_dict
    sc = from_dict(job.raw, file=job.file, base_dir=Path(job.base_dir), default_name=job.name)
    changed = sorted(p for p, d in job.files if input_files(sc).get(p) != d)
    if changed:
        raise InputError("changed while the campaign ran (its rows would mix two robots)", file=changed[0],
                         expected="the input files of a campaign unchanged until it ends")
    return sc


def _state(job: Job):
    # one closed loop per thread: CasADi function objects are not for concurrent calls (dask --nthreads > 1)
    key = (job.fingerprint, threading.get_ident())
    st = _STATE.get(key)
    if st is None:
        from ..simulation.closedloop import build_closed_loop
        from ..design import derive
        from ..simulation import compile_closed_loop
        sc = _job_scenario(job)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cl = build_closed_loop(sc, derive(sc))
            t0 = time.perf_counter()
            comp = compile_closed_loop(cl)
        cl.__dict__.setdefault("_compiled", {})[(True, True)] = comp
        st = _STATE[key] = (sc, cl, time.perf_counter() - t0, comp.cached)
    return st


def _engine_state(job: Job):
    """(scenario, design, compiled step, engine setup, compile time, cache hit) of an engine campaign, once per
    process and thread."""
    key = (job.fingerprint, threading.get_ident())
    st = _STATE.get(key)
    if st is None:
        from ..deployed.engine import engine_setup
        from ..deployed.loop import step_library
        from ..design import derive
        from ..emit.files import generate
        sc = _job_scenario(job)
        built = []
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            design = derive(sc)
            impl = sc.implementation
            files = generate(design, "c", rate_hz=impl.rate_hz, tau_max=impl.tau_max)
            step = step_library(design, files, on_build=built.append)
            setup = engine_setup(sc, on_build=built.append)
        st = _STATE[key] = (sc, design, step, setup, time.perf_counter() - t0, not built)
    return st


def prepare(job: Job) -> dict:
    """Build and compile the campaign's closed loop in this process; its one compile (or cache load) time."""
    if job.engine != "symfunnel":
        _, _, _, setup, compile_time, cached = _engine_state(job)
        return {"compile_time": compile_time, "cache_hit": cached, "parameters": len(setup.p_names)}
    _, cl, compile_time, cached = _state(job)
    return {"compile_time": compile_time, "cache_hit": cached, "parameters": len(cl.p_names)}


def row_of(result, run: int, columns: list[str], values) -> dict:
    """One results row of a simulated run (margins and peak torque also between output points)."""
    s = result.signals

    def extreme(key):                   # a result without samples between points: its output points alone
        if hasattr(result, "extreme"):
            return result.extreme(key)
        a = s[key] if key != "tau" else np.abs(s[key])
        return list(a.min(axis=0) if key != "tau" else a.max(axis=0)) if a.size else []
    m1s = [v for v in extreme("m1") if v is not None]
    m2s = [v for v in extreme("m2") if v is not None]
    m1 = float(min(m1s)) if s["m1"].size and m1s else math.nan
    m2 = float(min(m2s)) if s["m2"].size and m2s else math.nan
    b = result.breach
    if b is not None:
        if b["funnel"] == "e1":
            m1 = min(m1, b["margin"]) if not math.isnan(m1) else b["margin"]
        else:
            m2 = min(m2, b["margin"]) if not math.isnan(m2) else b["margin"]
    taus = [v for v in extreme("tau") if v is not None]
    tau = float(max(taus)) if s["tau"].size and np.isfinite(s["tau"]).all() and taus else math.nan
    mg = result.margins()
    post = {}
    for k in ("e1", "e2"):
        vals = [v for v in mg[f"min_margin_{k}_after_transient"] if v is not None]
        v = min(vals) if vals else math.nan
        if b is not None and b["funnel"] == k:          # a breach counts wherever it happened
            v = b["margin"] if math.isnan(v) else min(v, b["margin"])
        post[f"min_margin_{k}_after_transient"] = float(v)
    row = {"run": int(run)}
    row.update({c: float(v) for c, v in zip(columns, values)})
    row.update({"status": ROW_STATUS[result.status], "t_end": float(result.t[-1]) if result.t.size else 0.0,
                "min_margin_e1": m1, "min_margin_e2": m2, "max_abs_tau": tau, **post,
                "settle_time": float(mg["settle_time"]),
                **campaign_row(result.metrics() if hasattr(result, "metrics") else {})})
    return row


def engine_run_plant(scenario, setup, campaign, values):
    """One run's plant on the engine (`deployed.engine.EngineRunPlant`) from its drawn values."""
    import dataclasses

    from ..deployed.engine import EngineRunPlant
    from ..scenario.uncertainty import scenario_edits
    n = scenario.n
    idx = {k: i for i, k in enumerate(setup.p_names)}
    p = setup.p0.copy()
    q0, dq0 = np.asarray(scenario.q0, dtype=float).copy(), np.asarray(scenario.dq0, dtype=float).copy()
    mj = scenario.plant.mujoco
    for key, v in scenario_edits(campaign, n, values).items():
        if key == "initial.q":
            q0 = np.asarray(v, dtype=float)
        elif key == "initial.dq":
            dq0 = np.asarray(v, dtype=float)
        elif key.startswith("plant.mujoco."):
            mj = dataclasses.replace(mj, **{key.rsplit(".", 1)[1]: [float(x) for x in v]})
        elif isinstance(v, list):
            for j in range(n):
                p[idx[f"{key}[{j + 1}]"]] = v[j]
        else:
            p[idx[key]] = v
    return EngineRunPlant(p, mj, q0, dq0)


def sampled_row_of(result, run: int, columns: list[str], values) -> dict:
    """One results row of a sampled-data run (the margins are the true ones at the samples)."""
    n = result.q.shape[1]
    m = result.margins
    ok = np.all(np.isfinite(m), axis=1) if m.size else np.zeros(0, dtype=bool)
    m1 = float(np.min(m[ok, :n])) if ok.any() else math.nan
    m2 = float(np.min(m[ok, n:])) if ok.any() else math.nan
    tau = float(np.max(np.abs(result.tau))) if result.tau.size and np.isfinite(result.tau).all() else math.nan
    # the post-transient margins the campaign ranks its runs by (as row_of's): at the samples from the settle time on
    mg = result._post_transient(n) if m.size else {}
    b = result.breach
    post = {}
    for k in ("e1", "e2"):
        vals = [v for v in mg.get(f"min_margin_{k}_after_transient", []) if v is not None]
        v = min(vals) if vals else math.nan
        if b is not None and b.get("funnel") == k:      # a breach counts wherever it happened
            v = b["margin"] if math.isnan(v) else min(v, b["margin"])
        post[f"min_margin_{k}_after_transient"] = float(v)
    row = {"run": int(run)}
    row.update({c: float(v) for c, v in zip(columns, values)})
    row.update({"status": ROW_STATUS[result.status], "t_end": float(result.t[-1]) if result.t.size else 0.0,
                "min_margin_e1": m1, "min_margin_e2": m2, "max_abs_tau": tau, **post,
                "settle_time": float(result.stats.get("settle_time", math.nan)),
                **campaign_row(result.metrics())})
    return row


def _engine_chunk(job: Job, ids: list[int], values) -> list[dict]:
    from ..deployed.loop import simulate_sampled
    sc, design, step, setup, _, _ = _engine_state(job)
    camp = sc.campaign
    rows = []
    for rid, v in zip(ids, camp.values(ids, job.runs) if values is None else values):
        try:
            plant = engine_run_plant(sc, setup, camp, v)
            r = simulate_sampled(sc, design, t_final=job.t_final, controller=step, engine=job.engine, plant=plant)
        except Exception as exc:  # noqa: BLE001 - one bad run must not stop a campaign: its row says failed
            rows.append(_failed_row(rid, camp.columns, v, exc))
            continue
        rows.append(sampled_row_of(r, rid, camp.columns, v))
    return rows


def run_chunk(job: Job, run_ids, values=None) -> list[dict]:
    """Rows of the given runs (the unit of work of the pool and of dask); `values` are their drawn values
    (`Campaign.values`), when the submitting process has them: drawing them here would import scipy.stats into
    every worker (a second of start-up each) for a few numbers (normal or Latin-hypercube draws; Sobol draws no
    longer need it, `core.sobol`)."""
    if values is not None:
        values = np.asarray(values, dtype=float)
        if values.shape[0] != len(run_ids):
            raise ValueError(f"{values.shape[0]} rows of values for {len(run_ids)} runs")
    if job.engine != "symfunnel":
        return _engine_chunk(job, [int(i) for i in run_ids], values)
    from ..simulation import simulate
    from ..scenario.uncertainty import run_inputs
    sc, cl, _, _ = _state(job)
    camp = sc.campaign
    ids = [int(i) for i in run_ids]
    vals = camp.values(ids, job.runs) if values is None else values
    rows = []
    for rid, v in zip(ids, vals):
        params, x0 = run_inputs(camp, cl, v)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                r = simulate(sc, cl.design, t_final=job.t_final, closed_loop=cl, params=params, x0=x0,
                             fixed_chunks=True)
            except Exception as exc:  # noqa: BLE001 - one bad run must not stop a campaign: its row says failed
                rows.append(_failed_row(rid, camp.columns, v, exc))
                continue
        rows.append(row_of(r, rid, camp.columns, v))
    return rows


def _failed_row(rid, columns, values, exc) -> dict:
    row = {"run": int(rid)}
    row.update({c: float(v) for c, v in zip(columns, values)})
    row.update({"status": "failed", "t_end": 0.0, "min_margin_e1": math.nan, "min_margin_e2": math.nan,
                "max_abs_tau": math.nan, "min_margin_e1_after_transient": math.nan,
                "min_margin_e2_after_transient": math.nan, "settle_time": math.nan,
                **{k: math.nan for k in CAMPAIGN_METRICS}})
    return row


# --- execution -------------------------------------------------------------------------------------------

def _pool_worker_start() -> None:
    """A pool worker dies with its parent and runs one BLAS thread (one process per core already: a second thread
    would only spin against the other workers)."""
    from ..core import lifecycle
    from ..core.threads import pin_blas_threads
    lifecycle.die_with_parent()
    pin_blas_threads()


def run_batch(job: Job, run_ids, values=None) -> tuple[list[dict], float]:
    """run_chunk's rows of a batch and the CPU seconds they took in this worker's thread, without its one build of
    the closed loop (the task of the pool and of dask: the seconds size the next batches, `batches.BatchSizer`).
    CPU, not wall: a task's overhead is CPU, so batches amortise it alike on a loaded machine."""
    prepare(job)
    t0 = time.thread_time()
    rows = run_chunk(job, run_ids, values)
    return rows, time.thread_time() - t0


def execute(job: Job, todo: list[int], on_rows, *, workers: int = 1, client=None, chunk_size=None,
            progress=None, campaign=None) -> dict:
    """Run `todo` (run ids) on a local process pool or a dask client in batches (`chunk_size` runs each, else
    about `batches.TASK_SECONDS` of a worker's CPU each), calling on_rows(rows) as batches finish; with
    `campaign` (the job's), each batch is sent with its drawn values."""
    from .batches import BatchSizer
    say = progress or (lambda s: None)

    def work(chunk):
        return (job, chunk) if campaign is None else (job, chunk, campaign.values(chunk, job.runs))
    if client is not None:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
    sizer = BatchSizer(todo, workers, fixed=chunk_size)
    total, done = len(todo), 0
    t0 = time.perf_counter()
    last = 0.0
    first = None            # (time, runs) when the first batch came back: the workers had started by then

    def tick(k):
        nonlocal done, last, first
        done += k
        now = time.perf_counter()
        if first is None:
            first = (now, done)
        if now - last > 1.0 or done == total:
            rate = done / max(now - t0, 1e-9)
            eta = (total - done) / rate if rate > 0 else float("inf")
            say(f"sweep: {done}/{total} runs, {rate:.2f} runs/s, about {eta:.0f} s left")
            last = now

    def finished(result):
        rows, seconds = result
        sizer.record(len(rows), seconds)
        on_rows(rows)
        tick(len(rows))

    window = 2 * workers            # batches in flight: each worker has its next one queued
    if client is not None:
        from distributed import as_completed

        def submit():
            return client.submit(run_batch, *work(sizer.next()), pure=False, retries=3)
        ac = as_completed([], loop=client.loop)
        while sizer.ready() and ac.count() < window:
            ac.add(submit())
        for fut in ac:
            finished(fut.result())
            while sizer.ready() and ac.count() < window:
                ac.add(submit())
    elif todo:
        import concurrent.futures as cf
        import multiprocessing as mp
        from ..core import lifecycle
        pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                      initializer=_pool_worker_start)
        try:
            running = set()

            def fill():
                # submit starts worker processes (spawn: the parent writes each child's start-up data into a pipe);
                # a signal landing there would close that pipe under a child that then dies printing a traceback,
                # unregistered: deferred until the children are registered
                with lifecycle.signals_deferred():
                    while sizer.ready() and len(running) < window:
                        running.add(pool.submit(run_batch, *work(sizer.next())))
                    for pid in list(getattr(pool, "_processes", {}) or {}):
                        lifecycle.register_child(pid)
            fill()
            while running:
                done_now, running = cf.wait(running, timeout=0.5, return_when=cf.FIRST_COMPLETED)
                lifecycle.check()
                for fut in done_now:
                    finished(fut.result())
                fill()
        except BaseException:
            # a signal, a limit or a failed batch: the workers stop now, not after their batches
            procs = list((getattr(pool, "_processes", {}) or {}).values())
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.kill()
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.join(timeout=1.0)
            raise
        else:
            pool.shutdown(wait=True)
        finally:
            for pid in list(getattr(pool, "_processes", {}) or {}):
                lifecycle.unregister_child(pid)
    end = time.perf_counter()
    wall = end - t0
    steady = None
    if first is not None and done > first[1] and end > first[0]:
        steady = (done - first[1]) / (end - first[0])
    return {"wall": wall, "runs": total, "workers": workers,
            "runs_per_second": total / wall if wall > 0 and total else None,
            "steady_runs_per_second": steady, "batches": len(sizer.sizes),
            "max_batch": max(sizer.sizes, default=0), "seconds_per_run": sizer.seconds_per_run}


# --- worst case ------------------------------------------------------------------------------------------

def worst_scenario(job: Job, campaign, run: int, n: int) -> str:
    """A complete scenario (TOML text) that `symfunnel simulate` replays to run `run` of the campaign."""
    from ..core.toml_write import dumps
    from ..scenario.uncertainty import scenario_edits
    values = campaign.values([run], job.runs)[0]
    raw = copy.deepcopy(job.raw)
    raw.pop("uncertainty", None)
    raw.pop("sweep", None)
    for key, v in scenario_edits(campaign, n, values).items():
        *path, leaf = key.split(".")
        t = raw
        for p in path:
            t = t.setdefault(p, {})
        t[leaf] = v
    model = raw.get("model", {})
    if isinstance(model.get("path"), str):
        model["path"] = str((Path(job.base_dir) / model["path"]).resolve())
    mj = raw.get("plant", {}).get("mujoco", {})
    if isinstance(mj, dict) and isinstance(mj.get("mjcf"), str):     # the user's MJCF, like the URDF
        mj["mjcf"] = str((Path(job.base_dir) / mj["mjcf"]).resolve())
    raw["name"] = f"{job.name}-worst"[:64]
    raw["title"] = f"{raw.get('title', job.name)} - worst run {run} of a sweep"
    raw.setdefault("simulation", {})["t_final"] = float(job.t_final)
    return dumps(raw)


@dataclass
class SweepResult:
    """A finished (or resumed) campaign: summary figures and where the files are."""

    summary: dict
    out: Path
    table: object = field(repr=False, default=None)

    def __repr__(self) -> str:
        """Short: where the campaign is and how many runs (not the summary)."""
        return f"SweepResult(out={str(self.out)!r}, runs={self.summary.get('runs')!r})"

    def to_json(self) -> dict:
        """The `--json` output (= summary.json)."""
        return json_safe(self.summary)


def sweep(scenario, *, runs=None, workers=None, scheduler=None, out=None, resume=False, progress=None,
          chunk_size=None, engine: str | None = None) -> SweepResult:
    """Run a scenario's campaign; write results.parquet (and the same as results.csv), summary.json and worst.toml
    into `out`.

    On symfunnel's plant every run is the continuous-time closed loop (as before); on a physics engine (`engine`,
    default the scenario's `[plant] engine`) every run is the deployed controller's sampled loop on it, at the
    scenario's `[implementation]` rate, else at twice the minimum rate of the nominal scenario on that engine."""
    from ..scenario.uncertainty import check_runs
    say = progress or (lambda s: None)
    if runs is not None:
        check_runs(runs, file=None, key="--runs")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InputError(f"is {workers}", key="--workers", expected="an integer >= 1")
    engine = engine or getattr(scenario.plant, "engine", "symfunnel")
    rate = None
    if engine != "symfunnel":
        make_job(scenario, runs=runs, engine=engine, rate_hz=1.0)       # bad input first, before a rate search
        if scenario.implementation is not None:
            rate = scenario.implementation.rate_hz
        else:
            from ..deployed.rate import min_rate
            from ..design import derive
            say(f"sweep on the {engine} plant without [implementation]: minimum rate of the nominal scenario")
            found = min_rate(scenario, derive(scenario), progress=say, engine=engine)
            if found["min_rate_hz"] is None:
                raise InputError(f"keeps no funnel at any rate up to 1 MHz on the {engine} plant", file=scenario.file,
                                 key="implementation.rate_hz", expected="a rate to sweep at ([implementation])")
            rate = 2.0 * found["min_rate_hz"]
            say(f"sweep at {rate:.6g} Hz, twice the minimum rate {found['min_rate_hz']:.6g} Hz")
    job = make_job(scenario, runs=runs, engine=engine, rate_hz=rate)
    camp = scenario.campaign
    out = Path(out) if out is not None else Path("reports") / f"{scenario.name}-sweep"
    if out.exists() and not out.is_dir():
        raise InputError("is a file", file=str(out), key="--out", expected="a directory")
    if resume and not out.is_dir():
        raise InputError("does not exist", file=str(out), key="--resume",
                         expected="the directory of an interrupted sweep")
    with exclusive_lock(out, what="sweep"):
        return _sweep_locked(scenario, job, camp, out, resume=resume, workers=workers, scheduler=scheduler,
                             say=say, chunk_size=chunk_size)


def _read_meta(path: Path) -> dict:
    """campaign.json of an interrupted sweep (InputError naming it when it is not one)."""
    from ..core.inputs import loads_json, read_text
    meta = loads_json(read_text(path, expected="campaign.json written by `symfunnel sweep`"), file=str(path),
                      expected="campaign.json written by `symfunnel sweep`")
    if not isinstance(meta, dict) or not isinstance(meta.get("fingerprint"), str):
        raise InputError("is not a campaign record (no fingerprint)", file=str(path), key="--resume",
                         expected="campaign.json written by `symfunnel sweep`")
    return meta


def _sweep_locked(scenario, job, camp, out: Path, *, resume, workers, scheduler, say, chunk_size) -> SweepResult:
    client = connect(scheduler) if scheduler else None
    try:
        store = ResultStore(out, camp.columns)
        meta = {"fingerprint": job.fingerprint, "scenario": scenario.name, "runs": job.runs,
                "design": camp.sweep.design, "seed": camp.sweep.seed, "t_final": job.t_final,
                "columns": camp.columns, "files": dict(job.files)}
        meta_path = out / "campaign.json"
        if resume and meta_path.exists():
            old = _read_meta(meta_path)
            if old.get("fingerprint") != job.fingerprint:
                changed = [p for p, d in job.files if (old.get("files") or {}).get(p) != d]
                what = f"{changed[0]} changed" if changed and isinstance(old.get("files"), dict) else \
                    "scenario, its files, runs or horizon changed"
                raise InputError(f"holds a different campaign ({what})", file=str(out),
                                 key="--resume", expected="the same scenario, input files and --runs as the "
                                 "interrupted sweep")
        elif resume and store.has_rows():
            raise InputError("holds results but no campaign.json: which campaign they belong to cannot be told",
                             file=str(out), key="--resume", expected="a directory of an interrupted sweep "
                             "(or run without --resume to start afresh)")
        elif not resume:
            store.clear()
        say(f"sweep of {scenario.name}: {job.runs} runs ({camp.sweep.design}, seed {camp.sweep.seed}) of "
            f"{job.t_final:g} s over {', '.join(camp.columns)}")
        t0 = time.perf_counter()
        info = prepare(job)
        say(f"closed loop compiled once in {info['compile_time']:.2f} s "
            f"({'cache hit' if info['cache_hit'] else 'compiled'}); {info['parameters']} plant parameters")
        atomic_write(meta_path, json.dumps(meta, indent=2))
        done = store.done() if resume else set()
        todo = [i for i in range(job.runs) if i not in done]
        if resume:
            say(f"resume: {len(done)} runs on disk, {len(todo)} to go")
        w = workers or os.cpu_count() or 1
        ex = execute(job, todo, store.add, workers=w, client=client, chunk_size=chunk_size, progress=say,
                     campaign=camp)
    finally:
        if client is not None:
            client.close()
    table = store.merge()
    shutil.rmtree(store.parts, ignore_errors=True)
    from .results_csv import write_results_csv
    write_results_csv(table, out / "results.csv", scenario.model.joint_types, scenario.n)
    s = summarize(table, camp.columns)
    from .sensitivity import sensitivity
    summary = {k: s[k] for k in ("runs", "breaches", "breach_probability", "ci95", "worst_run")}
    summary["sensitivity"] = sensitivity(table.to_pydict(), camp.columns)
    from .results_csv import column_units
    summary["units"] = column_units(list(table.column_names), scenario.model.joint_types, scenario.n)
    summary.update({"runs_per_second": ex["runs_per_second"], "workers": ex["workers"],
                    "steady_runs_per_second": ex["steady_runs_per_second"], "batches": ex["batches"],
                    "scenario": scenario.name, "design": camp.sweep.design, "seed": camp.sweep.seed,
                    "t_final": job.t_final, "failed": s["failed"], "compile_time": info["compile_time"],
                    "compile_cache_hit": info["cache_hit"], "wall_time": time.perf_counter() - t0,
                    "columns": camp.columns, "worst": s["worst"], "min_margin": s["min_margin"],
                    "min_margin_after_transient": s["min_margin_after_transient"],
                    "min_margin_e1_after_transient": s["min_margin_e1_after_transient"],
                    "min_margin_e2_after_transient": s["min_margin_e2_after_transient"],
                    "max_abs_tau": s["max_abs_tau"], "metrics": s["metrics"], "out": str(out),
                    "engine": job.engine})
    if job.engine != "symfunnel":
        summary["rate_hz"] = float(job.raw["implementation"]["rate_hz"])
    if s["worst_run"] is not None:
        atomic_write(out / "worst.toml", worst_scenario(job, camp, s["worst_run"], scenario.n))
    atomic_write(out / "summary.json", json.dumps(json_safe(summary), indent=2, allow_nan=False))
    return SweepResult(summary, out, table)
