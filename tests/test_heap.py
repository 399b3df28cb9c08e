"""simulation.heap.keep_heap: the arrays a run frees after each chunk stay in the process instead of being handed
back to the kernel and faulted in again at the next chunk (counted as minor page faults)."""

import os
import subprocess
import sys

import pytest

PROBE = """
import resource
from symfunnel.pipeline import Run
from symfunnel.simulation import simulate
from symfunnel.simulation.heap import keep_heap
pr = Run.load("paper")
simulate(pr.scenario, pr.design, t_final=5.0, closed_loop=pr.closed_loop)      # compiled, warm
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    simulate(pr.scenario, pr.design, t_final=5.0, closed_loop=pr.closed_loop)
print(int(keep_heap()), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _faults(env_value: str) -> tuple[int, int]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["SYMFUNNEL_KEEP_HEAP"] = env_value
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    ok, faults = out.stdout.split()[-2:]
    return int(ok), int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_heap_stops_refaulting_a_runs_arrays():
    ok_off, off = _faults("0")
    ok_on, on = _faults("1")
    assert ok_off == 0
    if not ok_on:
        pytest.skip("not glibc")
    # glibc's defaults: thousands of faults per 5 s paper run (its chunk arrays handed back and faulted in again;
    # ~3,000 per run measured); kept, at most a tenth of them
    assert off > 1000
    assert on < off / 10
