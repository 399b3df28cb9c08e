"""Bench area `startup`: what a CLI process pays before and around its work, in CPU seconds of the child process.

Ids: `startup.version_cpu_s` (`symfunnel --version`) and `startup.audit_cpu_s` (`symfunnel audit paper --json`);
baseline: the same command with SYMFUNNEL_EAGER_IMPORTS=1, which imports EAGER_IMPORTS at start as a CLI with its
dependencies imported at the top would (for audit: what the previous code loaded, scipy.optimize for Nelder-Mead
and sympy.physics.units inside sympy.simplify, plus scipy.stats that only verify and sampling commands loaded).
Runs alternate (baseline, ours, ours, baseline, ...) and each figure is the median of ROUNDS; ratio = baseline /
ours (higher is better). Extra keys: every run's CPU seconds and the median paired ratio.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile

from ._result import result

#: the environment variable the CLI reads (symfunnel.cli.main) and the modules it then imports first
ENV = "SYMFUNNEL_EAGER_IMPORTS"
EAGER_IMPORTS = ("numpy", "casadi", "sympy", "sympy.physics.units", "scipy.optimize", "scipy.stats")
ROUNDS = 3
COMMANDS = {"startup.version_cpu_s": ["--version"], "startup.audit_cpu_s": ["audit", "paper", "--json"]}


def import_eagerly() -> None:
    """Import EAGER_IMPORTS (the baseline's start-up; spelled out, so that the import graph stays readable)."""
    import numpy  # noqa: F401
    import casadi  # noqa: F401
    import sympy  # noqa: F401
    import sympy.physics.units  # noqa: F401
    import scipy.optimize  # noqa: F401
    import scipy.stats  # noqa: F401


def child_cpu(args: list[str], eager: bool) -> float:
    """CPU seconds (user + system) of one `python -m symfunnel ARGS` child process, its output discarded."""
    env = dict(os.environ)
    env.pop(ENV, None)
    if eager:
        env[ENV] = "1"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-") as cwd:
        subprocess.run([sys.executable, "-m", "symfunnel", *args], env=env, cwd=cwd, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, check=False)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run(progress) -> list[dict]:
    """The two results above."""
    out = []
    for rid, args in COMMANDS.items():
        progress(f"startup: symfunnel {' '.join(args)}, {ROUNDS} paired runs with and without {ENV}")
        ours, base = [], []
        for i in range(ROUNDS):
            for eager in ((True, False) if i % 2 == 0 else (False, True)):
                (base if eager else ours).append(child_cpu(args, eager))
        b, o = statistics.median(base), statistics.median(ours)
        out.append(result(rid, o, "CPU-s", f"the same command with {ENV}=1 (imports {', '.join(EAGER_IMPORTS)})",
                          b, b / o if o > 0 else None, runs=ours, baseline_runs=base,
                          paired_ratio=statistics.median([x / y for x, y in zip(base, ours) if y > 0])))
    return out
