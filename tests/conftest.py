"""Shared fixtures: the paper scenario and its design, and a helper that writes scenario variants."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

# Compiled artefacts of a test run go to a private cache, never to the user's.
os.environ.setdefault("SYMFUNNEL_CACHE", str(Path(__file__).parent.parent / ".pytest_cache" / "symfunnel"))

REPO = Path(__file__).resolve().parent.parent
PAPER = REPO / "derivations" / "paper_2dof.toml"


def pytest_xdist_auto_num_workers(config):
    """`-n auto` (addopts): one worker more than the cores this process may use, because about a sixth of the
    suite's wall time is spent waiting (on CLI subprocesses, Chromium, compilers, signal instants): on 2 cores 3
    workers ran the suite in 322 s against 347 s with 2, the same CPU time. $PYTEST_XDIST_AUTO_NUM_WORKERS still
    decides when it is set (xdist's own hook reads it)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    return cores + 1


def pytest_collection_finish(session):
    """The test process collects garbage as the CLI does (symfunnel.cli.GC_THRESHOLDS), and what importing and
    collecting left is frozen out of every later collection: a worker's heap of CasADi and sympy objects otherwise
    made each full collection dearer as the session went on (about 4 % of a worker's CPU time)."""
    import gc

    from symfunnel.cli import GC_THRESHOLDS
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def module_order(items) -> list:
    """The items in the order xdist hands them out: modules with a test marked `slow(first=True)` first, then modules
    with more `slow` tests, each module kept whole in its own order (else in collection order). xdist hands tests out
    in collection order, and alphabetical order put the long tune and twin tests last, where one worker could be left
    running them alone; a module stays contiguous so that its module-scoped fixtures are built no more often. A test
    that takes a fifth of a worker's share of the run (test_guarantees' Panda, 276 of 1250 worker-seconds in a loaded
    run) is marked first: replaying xdist's scheduler on that run's durations, it started at 848 s and ended the run
    (1300 s); started first, the run ends at 1246 s."""
    slow: dict[str, int] = {}
    first: dict[str, int] = {}
    lead: dict[str, bool] = {}
    for i, item in enumerate(items):
        mod = item.nodeid.split("::", 1)[0]
        first.setdefault(mod, i)
        mark = item.get_closest_marker("slow")
        slow[mod] = slow.get(mod, 0) + (mark is not None)
        lead[mod] = lead.get(mod, False) or bool(mark is not None and mark.kwargs.get("first"))

    def key(it):
        mod = it.nodeid.split("::", 1)[0]
        return (not lead[mod], -slow[mod], first[mod])
    return sorted(items, key=key)


def pytest_collection_modifyitems(session, config, items):
    """module_order, in place."""
    items[:] = module_order(items)


@pytest.fixture(scope="session")
def paper():
    """The built-in paper scenario."""
    from symfunnel.scenario import load_scenario
    return load_scenario("paper")


@pytest.fixture(scope="session")
def paper_run(paper):
    """The paper scenario through the pipeline (each stage computed once per session, on first use)."""
    from symfunnel.pipeline import Run
    return Run(paper)


@pytest.fixture(scope="session")
def paper_design(paper_run):
    """The paper scenario's design (derived once per session)."""
    return paper_run.design


def session_dir(tmp_path_factory) -> Path:
    """A directory of this test session shared by its xdist workers (their base temp directories' parent, which
    xdist makes per session), or this process's own base temp directory without xdist."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _session_once(tmp_path_factory, kind: str, key_parts, produce) -> Path:
    """The file of `key_parts` in the session directory, written by produce(path) on the first call of the test session
    (whichever xdist worker asks first; an flock per key, the others wait) and only read by every later call. A
    produce that raises leaves no file, so the next caller tries again (and fails in its own test)."""
    import fcntl
    import hashlib
    import json
    key = hashlib.sha256(json.dumps(key_parts).encode()).hexdigest()[:16]
    d = session_dir(tmp_path_factory) / kind
    d.mkdir(exist_ok=True)
    done = d / f"{key}.out"
    with open(d / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            tmp = done.with_suffix(".tmp")
            produce(tmp)
            tmp.replace(done)
    return done


def _command_once(tmp_path_factory, kind: str, argv: list, call) -> subprocess.CompletedProcess:
    """call() -> (exit code, stdout, stderr) of the command `argv`, run once per test session (_session_once, keyed
    by `argv` in the directory `kind`) and recorded; every caller gets the record as a CompletedProcess."""
    import json

    def run(path: Path) -> None:
        code, out, err = call()
        path.write_text(json.dumps({"returncode": code, "stdout": out, "stderr": err}))
    rec = json.loads(_session_once(tmp_path_factory, kind, argv, run).read_text())
    return subprocess.CompletedProcess(argv, rec["returncode"], rec["stdout"], rec["stderr"])


def cli_once(tmp_path_factory, *args, timeout: float = 600, cwd=None) -> subprocess.CompletedProcess:
    """`python -m symfunnel ARGS` run once per test session, whichever worker asks first (an flock per command; the
    others wait and read its recorded exit code, stdout and stderr): for an expensive command whose result several
    modules check, e.g. one `rate --certify` on the same scenario and horizon. The command's directory (`cwd`, the
    first caller's) is not part of the key: the caller makes sure the command reads and writes nothing there."""
    import sys
    argv = [sys.executable, "-m", "symfunnel", *map(str, args)]

    def call():
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd=cwd)
        return p.returncode, p.stdout, p.stderr
    return _command_once(tmp_path_factory, "cli-once", argv, call)


def main_once(tmp_path_factory, *args) -> subprocess.CompletedProcess:
    """`symfunnel ARGS` run once per test session as cli_once runs it, but in this process (symfunnel.cli.main, its
    stdout and stderr captured): for a command several modules check whose own start-up would cost more than a
    subprocess saves, e.g. `certify SCENARIO --json` (certify_once)."""
    import contextlib
    import io
    argv = [str(a) for a in args]

    def call():
        from symfunnel.cli import main
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:           # argparse's usage errors end the process, as they would the CLI
                code = exc.code if isinstance(exc.code, int) else 1
        return code, out.getvalue(), err.getvalue()
    return _command_once(tmp_path_factory, "main-once", ["symfunnel", *argv], call)


def certify_once(tmp_path_factory, scenario) -> tuple[int, dict]:
    """`symfunnel certify SCENARIO --json -q` (the full work budget) once per session: its exit code and its JSON.
    test_certify reads paper's and certify_none's certificates from it, test_certify_pinned every shipped scenario's
    outcomes, test_containment_projection and test_regressor_jacobian the projection file's containment; each module
    computed them again on its own xdist worker before (the in-process certificate cache is per worker)."""
    import json
    p = main_once(tmp_path_factory, "certify", scenario, "--json", "-q")
    assert p.stdout.strip(), f"certify {scenario}: exit {p.returncode}, no JSON: {p.stderr[-500:]}"
    return p.returncode, json.loads(p.stdout)


def text_once(tmp_path_factory, key: str, build) -> str:
    """build() (a text, e.g. a report several modules check) computed once per test session across the xdist
    workers, as cli_once runs a command: a module-scoped fixture is built once per worker that runs the module's
    tests. `key` names what build computes: one key, one text."""
    def write(path: Path) -> None:
        path.write_text(build(), encoding="utf-8")
    return _session_once(tmp_path_factory, "text-once", key, write).read_text(encoding="utf-8")


#: `rate --certify` on tests/data/certify_none.toml over a 2 s horizon: checked by test_report_deployed (against the
#: report's bracket) and test_sampled_certificate (the proven rate against the simulated one), computed once
CERTIFY_NONE_RATE = ("rate", REPO / "tests" / "data" / "certify_none.toml", "--certify", "--json", "--t-final", "2.0",
                     "-q")


#: `rate --certify` on tests/data/sampled_1dof.toml: test_sampled_certificate checks its bracket, test_api_contract
#: compares it with `symfunnel.rate(certify=True)`, computed once
SAMPLED_1DOF_RATE = ("rate", REPO / "tests" / "data" / "sampled_1dof.toml", "--certify", "--json", "-q")


@pytest.fixture
def certify_none_rate(tmp_path_factory) -> subprocess.CompletedProcess:
    """CERTIFY_NONE_RATE's run, once per session."""
    return cli_once(tmp_path_factory, *CERTIFY_NONE_RATE)


#: the paper scenario's report as test_report_layout measures it (issue 22's height was measured on this one) and
#: test_report_deployed reads its rate bracket: 2 s, 200 samples, the generated code and the deployed section, no
#: mutants
PAPER_REPORT_2S = "report paper t_final=2.0 samples=200 codegen deployed no-mutants"


@pytest.fixture
def paper_report_2s(tmp_path_factory) -> str:
    """PAPER_REPORT_2S's HTML, written once per session (text_once)."""
    def build() -> str:
        from symfunnel.pipeline import Run, RunOptions
        from symfunnel.reporting import build_report
        from symfunnel.scenario import load_scenario
        run = Run(load_scenario("paper"), RunOptions(t_final=2.0, samples=200))
        out = tmp_path_factory.mktemp("paper-report") / "paper.html"
        return build_report(run, out, codegen=True, mutants=False, deployed=True).read_text(encoding="utf-8")
    return text_once(tmp_path_factory, PAPER_REPORT_2S, build)


def private_cache(tmp_path_factory):
    """Generator for a module-scoped fixture: a fresh compile cache for the module (its hits and misses are its own),
    the previous $SYMFUNNEL_CACHE restored afterwards."""
    path = tmp_path_factory.mktemp("cache")
    old = os.environ.get("SYMFUNNEL_CACHE")
    os.environ["SYMFUNNEL_CACHE"] = str(path)
    yield path
    if old is None:
        os.environ.pop("SYMFUNNEL_CACHE", None)
    else:
        os.environ["SYMFUNNEL_CACHE"] = old


MINIMAL_2LINK = """
[model]
type = "matrices"
coordinates = ["q1", "q2"]
[model.parameters]
a = 3.0
b = 1.0
c = 0.8
[model.matrices]
M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["b + c*cos(q2)", "b"]]
{C}
[reference]
q = ["0.3*sin(t)", "0.2*cos(t)"]
[initial]
q = [0.0, 0.2]
dq = [0.3, 0.0]
"""


@pytest.fixture
def write_scenario(tmp_path):
    """Write a scenario text to a file in tmp_path and return its path."""
    def write(text: str, name: str = "s.toml") -> Path:
        p = tmp_path / name
        p.write_text(text, encoding="utf-8")
        return p
    return write


def alpha2_dot_fd_error(design, k: int, seed: int, fill: float = 0.9) -> tuple[float, int]:
    """Worst relative gap between alpha2_dot and fourth-order central differences of alpha2 along the flow.

    d/ds alpha2(t + s, q + s dq, qd(t + s), dqd(t + s)) at s = 0, at k points inside the funnels; points whose
    stencil straddles the |e1| kink at e1 = 0 are skipped. Returns (worst, points used).
    """
    from symfunnel.design.sampling import funnel_states
    a2 = design.function("alpha2", ["t", "q", "qd", "dqd"])
    a2d = design.function("alpha2_dot", ["t", "q", "dq", "qd", "dqd", "ddqd"])
    pts = funnel_states(design, k, np.random.default_rng(seed), fill=fill)
    worst, used = 0.0, 0
    for j in range(k):
        t, q, dq = pts["t"][0, j], pts["q"][:, j], pts["dq"][:, j]
        h = 1e-5 / (1.0 + np.max(np.abs(dq)))
        qd, dqd, ddqd = design.reference(t)
        if np.any(np.abs(q - np.array(qd).ravel()) < 4 * h * (np.abs(dq) + 1)):
            continue

        def alpha(s):
            r = design.reference(t + s)
            return np.array(a2(t + s, q + s * dq, r[0], r[1])).ravel()
        fd = (8 * (alpha(h) - alpha(-h)) - (alpha(2 * h) - alpha(-2 * h))) / (12 * h)
        ex = np.array(a2d(t, q, dq, qd, dqd, ddqd)).ravel()
        worst = max(worst, float(np.max(np.abs(fd - ex)) / max(np.max(np.abs(ex)), 1e-3)))
        used += 1
    return worst, used


@pytest.fixture
def read_only_dir(tmp_path):
    """A directory nobody can write: mode 0555, or for root (who ignores modes) a read-only tmpfs mount."""
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:
        ro.chmod(0o555)
        yield ro
        ro.chmod(0o755)
        return
    if not shutil.which("mount") or subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)],
                                                    capture_output=True).returncode != 0:
        pytest.skip("running as root without permission to mount a read-only file system")
    try:
        yield ro
    finally:
        subprocess.run(["umount", str(ro)], capture_output=True)


@pytest.fixture(autouse=True)
def _rounding_stays_to_nearest():
    """Every test leaves the process rounding to nearest: a library that switches the mode (codac does at import)
    would otherwise change every later computation of the run without anyone noticing."""
    yield
    from symfunnel.sx import rounding
    if not rounding.rounds_to_nearest():
        mode = rounding.get_mode()
        rounding.set_mode(0)
        pytest.fail(f"the test left the process's floating-point rounding mode at {mode:#x}, not to nearest")


@pytest.fixture(autouse=True)
def _no_deadline_or_signal_policy_left_behind():
    """Every test leaves no open wall-clock deadline, step, pause or installed signal policy: one left behind expires
    every later check of the run, and the CLI's watchdog would stop the whole test process at the next `main()`."""
    yield
    from symfunnel.core import deadline, lifecycle
    left = {"deadlines": list(deadline._stack), "steps": list(deadline._steps), "paused": list(deadline._paused),
            "signal policy": list(lifecycle._saved), "pending signals": list(lifecycle._pending)}
    left = {k: v for k, v in left.items() if v}
    if left:
        deadline._stack.clear()
        deadline._steps.clear()
        deadline._paused.clear()
        lifecycle.uninstall()
        lifecycle._pending.clear()
        pytest.fail(f"the test left process-wide state behind: {left}")


#: `verify paper --json` over 2 s with 2000 falsification samples: test_verify checks its JSON and exit code,
#: test_certify the certificates among its checks (before, a second run over the paper's whole 20 s horizon)
VERIFY_PAPER_2S = ("verify", "paper", "--json", "--t-final", "2", "--samples", "2000")
