"""Campaign batches (`campaigns.batches`): every run handed out once and in order, sizes from the measured rate, and
rows identical to one run per task on a local pool."""

from __future__ import annotations

import math

import pytest

from symfunnel.campaigns.batches import MAX_BATCH, TAIL_SHARES, BatchSizer


def _drain(sizer, seconds_per_run):
    """Hand out every batch as two workers would (two in flight each), reporting `seconds_per_run(run)` per run."""
    out, flight = [], []
    while sizer.remaining or flight:
        while sizer.ready() and len(flight) < 2 * sizer.workers:
            b = sizer.next()
            out.append(b)
            flight.append(b)
        b = flight.pop(0)
        sizer.record(len(b), sum(seconds_per_run(r) for r in b))
    return out


def test_every_run_once_in_order_and_sized_to_the_target():
    todo = [i for i in range(3000) if i % 7]            # a resume: some runs already on disk
    s = BatchSizer(todo, workers=2, target=1.0)
    batches = _drain(s, lambda r: 2.0 ** -7)             # 7.8 ms per run (exact in binary): 128 runs make 1 s
    assert [r for b in batches for r in b] == todo
    assert [len(b) for b in batches[:2]] == [1, 1]       # one probe per worker before any rate is known
    assert max(len(b) for b in batches) == 128
    # the tail: no batch holds more than the remaining runs over TAIL_SHARES x workers when it is cut
    left = len(todo)
    for b in batches:
        if len(b) > 1:
            assert len(b) <= math.ceil(left / (TAIL_SHARES * 2))
        left -= len(b)
    assert s.seconds_per_run == 2.0 ** -7


def test_slow_runs_go_one_per_task_and_short_runs_stop_at_the_cap():
    slow = _drain(BatchSizer(list(range(20)), workers=2, target=1.5), lambda r: 4.0)
    assert [len(b) for b in slow] == [1] * 20
    fast = _drain(BatchSizer(list(range(5000)), workers=1, target=1.5), lambda r: 1e-6)
    assert max(len(b) for b in fast) == MAX_BATCH


def test_fixed_size_and_a_rate_that_never_comes():
    s = BatchSizer(list(range(10)), workers=3, fixed=4)
    assert [s.next(), s.next(), s.next(), s.next()] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9], []]
    # results without a measured time: one probe per worker, then one run at a time once none is in flight
    s = BatchSizer(list(range(5)), workers=2)
    assert [s.next(), s.next(), s.next()] == [[0], [1], []]
    s.record(1, None)
    assert s.next() == []                               # [1] still in flight
    s.record(1, None)
    assert s.next() == [2]


def test_batched_rows_identical_to_one_run_per_task_on_a_local_pool(tmp_path):
    from symfunnel.campaigns.campaign import make_job, run_chunk, sweep
    from symfunnel.scenario import load_scenario

    from .test_sweep import _campaign_file, _rows, _same
    sc = load_scenario(_campaign_file(tmp_path, runs=16, t_final=0.4))
    ref = run_chunk(make_job(sc), range(16))             # one process, no pool: the per-run reference
    per_run = sweep(sc, workers=2, out=tmp_path / "one", chunk_size=1)
    batched = sweep(sc, workers=2, out=tmp_path / "batched")
    assert per_run.summary["batches"] == 16
    assert batched.summary["batches"] < 16                # runs of a few ms: batches after the probes
    _same(_rows(tmp_path / "one" / "results.parquet"), ref)
    _same(_rows(tmp_path / "batched" / "results.parquet"), ref)
    assert {r["status"] for r in ref} == {"ok", "breach"}


@pytest.mark.slow
def test_bench_compares_batches_with_one_run_per_task_on_the_same_rows(tmp_path):
    from symfunnel.bench.sweep import batches_vs_per_run, campaign

    from .test_sweep import _rows, _same
    r = batches_vs_per_run(campaign(12, 0.2), tmp_path, lambda s: None)
    assert r["id"] == "sweep.batches" and r["ratio"] == pytest.approx(r["value"] / r["baseline_value"])
    assert [x["batches"] for x in r["per_run"]] == [12, 12] and all(x["batches"] < 12 for x in r["batched"])
    assert r["extrapolated_10000_runs_s"] == pytest.approx(10000 / r["value"])
    assert all(x["workers_cpu_s_per_run"] > 0 and x["parent_cpu_s_per_run"] > 0 for x in r["per_run"] + r["batched"])
    ref = _rows(tmp_path / "b0" / "results.parquet")
    assert [x["run"] for x in ref] == list(range(12))
    for i in (1, 2, 3):
        _same(_rows(tmp_path / f"b{i}" / "results.parquet"), ref)


@pytest.mark.slow
def test_bench_on_dask_compares_the_same_rows_and_stops_its_cluster(tmp_path):
    import psutil

    from symfunnel.bench.sweep import batches_on_dask, campaign

    from .test_sweep import _rows, _same
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    r = batches_on_dask(campaign(12, 0.2), tmp_path, lambda s: None, 12)
    assert r["id"] == "sweep.batches_dask" and [x["batches"] for x in r["per_run"]] == [12, 12]
    assert all(x["batches"] < 12 for x in r["batched"])
    assert all(x["scheduler_cpu_s_per_run"] > 0 and x["workers_cpu_s_per_run"] > 0 for x in r["batched"])
    ref = _rows(tmp_path / "dask0" / "results.parquet")
    assert [x["run"] for x in ref] == list(range(12))
    for i in (1, 2, 3):
        _same(_rows(tmp_path / f"dask{i}" / "results.parquet"), ref)
    assert {p.pid for p in psutil.Process().children(recursive=True)} <= before     # scheduler and workers gone


def test_bench_compares_this_path_with_the_previous_one_on_identical_rows(monkeypatch):
    """`sweep.cpu_per_run_vs_previous` alternates the two paths on the same runs, and both give the same rows."""
    from symfunnel.bench.sweep import campaign, vs_previous
    from symfunnel.campaigns.campaign import make_job, run_chunk
    from symfunnel.simulation import between, crun

    from .test_sweep import _same
    sc = campaign(4, 0.5)
    defaults = crun.SAMPLES_IN_PLACE, between.SHARE_REFINED_STEPS
    r = vs_previous(sc, 2, rounds=2)
    assert r["id"] == "sweep.cpu_per_run_vs_previous" and len(r["now"]) == len(r["previous"]) == 2
    assert r["ratio"] == pytest.approx(sum(p / n for n, p in zip(r["now"], r["previous"])) / 2)   # median of 2
    assert (crun.SAMPLES_IN_PLACE, between.SHARE_REFINED_STEPS) == defaults          # restored
    job = make_job(sc)
    monkeypatch.setattr(crun, "SAMPLES_IN_PLACE", True)
    monkeypatch.setattr(between, "SHARE_REFINED_STEPS", True)
    now = run_chunk(job, range(4))
    monkeypatch.setattr(crun, "SAMPLES_IN_PLACE", False)
    monkeypatch.setattr(between, "SHARE_REFINED_STEPS", False)
    _same(run_chunk(job, range(4)), now)
