"""`symfunnel sweep --scheduler` on a real dask.distributed cluster started here (scheduler + 2 workers, 127.0.0.1)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from symfunnel.scenario import load_scenario
from symfunnel.campaigns.campaign import make_job, run_chunk, sweep

from .test_sweep import _campaign_file, _same

pytestmark = pytest.mark.slow
DASK = str(Path(sys.executable).with_name("dask"))


def _start(args, log):
    return subprocess.Popen([DASK, *args], start_new_session=True, stdout=log, stderr=subprocess.STDOUT,
                            env=dict(os.environ))


def _scheduler(tmp_path, log):
    sf = tmp_path / "scheduler.json"
    p = _start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(sf)], log)
    deadline = time.monotonic() + 60
    while not sf.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    return p, (json.loads(sf.read_text())["address"] if sf.exists() else None)


def test_scheduler_without_workers_is_refused(tmp_path):
    from symfunnel.campaigns.cluster import connect
    from symfunnel.core.errors import InputError
    with open(tmp_path / "dask.log", "w") as log:
        p, address = _scheduler(tmp_path, log)
        try:
            assert address, "the scheduler did not start"
            with pytest.raises(InputError, match="has no workers") as exc:
                connect(address, worker_timeout=1.0)
            assert address in str(exc.value)
        finally:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two single-threaded workers (no nanny, so a killed worker stays dead); torn down after."""
    log = open(tmp_path / "dask.log", "w")
    p, address = _scheduler(tmp_path, log)
    procs = [p]
    try:
        assert address, "the scheduler did not start"
        for k in range(2):
            procs.append(_start(["worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                 "--name", f"w{k}"], log))
        from distributed import Client
        with Client(address, timeout="20s") as c:
            c.wait_for_workers(2, timeout=60)
        yield address, procs, tmp_path / "dask.log"
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
        log.close()


def test_dask_rows_identical_and_lost_worker_retried(cluster, tmp_path):
    address, procs, log = cluster
    # runs that stay inside and last 1 s each: work is left for the lost worker's share when it dies
    sc = load_scenario(_campaign_file(tmp_path, runs=12, t_final=1.0, q0=0.005))
    ref = run_chunk(make_job(sc), range(12))
    killed = []

    def progress(msg):
        # after the first finished chunk, kill worker w1 with its work in flight: dask reschedules it
        if msg.startswith("sweep: ") and not killed:
            os.killpg(procs[2].pid, signal.SIGKILL)
            killed.append(msg)

    out = tmp_path / "dask"
    res = sweep(sc, scheduler=address, out=out, chunk_size=1, progress=progress)
    assert killed and procs[2].wait(timeout=30) is not None
    rows = pq.read_table(str(out / "results.parquet")).to_pylist()
    assert [r["run"] for r in rows] == list(range(12))
    _same(rows, ref)
    assert res.summary["workers"] == 2
    assert {r["status"] for r in rows} == {"ok"}
    removed = [ln for ln in log.read_text().splitlines() if "Remove worker" in ln]
    assert removed and "name: w1" in removed[0]       # the scheduler lost w1 during the campaign
    assert (out / "worst.toml").exists()


def test_dask_batches_give_the_rows_of_one_run_per_task(cluster, tmp_path):
    address, procs, log = cluster
    sc = load_scenario(_campaign_file(tmp_path, runs=16, t_final=0.4))
    ref = run_chunk(make_job(sc), range(16))
    res = sweep(sc, scheduler=address, out=tmp_path / "batched")
    assert 2 <= res.summary["batches"] < 16               # a probe per worker, then batches of several runs
    _same(pq.read_table(str(tmp_path / "batched" / "results.parquet")).to_pylist(), ref)
