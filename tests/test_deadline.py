"""One wall-clock limit over a whole command: nested deadlines, the compiler killed, derive stopped, one line, exit 1."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from symfunnel.core import deadline
from symfunnel.sx.proof import _Timeout, time_limit

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "symfunnel" / "data" / "paper_2dof.toml"


def _spin(seconds: float) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        pass


def _swallowing(seconds: float) -> None:
    """Spin inside a handler that drops every exception, as SWIG's overload resolution does with one raised in a
    typemap's Python callback (casadi's DM_from_array while `ca.vertcat` tries its overloads): the alarm's
    exception vanishes there and the caller goes on."""
    try:
        _spin(seconds)
    except BaseException:  # noqa: BLE001 - what the C extension does
        pass


def test_an_alarm_whose_exception_was_swallowed_still_ends_the_block():
    """Under load a Run's stage with 10 ms left went on to its end in about half of 300 tries (the alarm's
    exception dropped inside `ca.vertcat`); the block must end in the limit all the same."""
    t0 = time.monotonic()
    with pytest.raises(deadline.WallLimitReached, match="wall-clock limit of 0.05 s reached"):
        with deadline.limit(0.05):
            _swallowing(0.3)                   # the alarm fires in here and its exception is dropped
    assert time.monotonic() - t0 < 2.0
    with pytest.raises(ValueError):            # an inner time limit's own exception, likewise
        with deadline.limit(0.05, on_expiry=lambda: ValueError("inner")):
            _swallowing(0.3)
    with deadline.limit(5.0):                  # a block that ends in time is left alone
        _swallowing(0.01)


def test_a_swallowed_alarm_raised_after_its_step_names_that_step():
    """The limit raised when the block goes on after a swallowed alarm names the step the alarm landed in, not the
    bare "working" of the code around it (a 2000-unit derive under load read "reached while working")."""
    with pytest.raises(deadline.WallLimitReached) as info:
        with deadline.limit(0.05):
            with deadline.step("deriving the design"):
                _swallowing(0.3)
    assert info.value.step == "deriving the design" and "while deriving the design" in str(info.value)


def test_the_alarm_stops_python_code_at_the_limit():
    t0 = time.monotonic()
    with pytest.raises(deadline.WallLimitReached) as info:
        with deadline.limit(0.2), deadline.step("spinning"):
            _spin(5.0)
    assert time.monotonic() - t0 < 2.0
    assert info.value.step == "spinning" and "0.2 s" in str(info.value)
    assert deadline.remaining() == float("inf")          # nothing left armed


def test_an_inner_time_limit_fires_first_and_the_outer_one_still_holds():
    with pytest.raises(deadline.WallLimitReached):
        with deadline.limit(0.6):
            with pytest.raises(_Timeout):
                with time_limit(0.1):
                    _spin(5.0)
            assert 0.0 < deadline.remaining() < 0.6      # the command's limit is re-armed after the proof's
            _spin(5.0)


def test_the_command_limit_is_not_swallowed_as_a_proof_timeout():
    # the audit catches _Timeout around sympy; a command limit reached inside must escape as WallLimitReached
    with pytest.raises(deadline.WallLimitReached):
        with deadline.limit(0.1):
            try:
                with time_limit(30.0):
                    _spin(5.0)
            except _Timeout:
                pytest.fail("the command's limit was turned into the proof's timeout")


def test_paused_blocks_watch_the_limit_themselves_and_check_raises_after():
    seen = {}
    # after the block the expiry is raised by the next check or by the alarm re-armed at 0.1 ms, whichever comes
    # first (under load the alarm can fire before the check is reached); the limit's block must end with it either
    # way (an alarm's exception caught inside the block is raised again at its end: a clean-clone CI run)
    with pytest.raises(deadline.WallLimitReached):
        with deadline.limit(0.1):
            with deadline.paused():
                _spin(0.3)                                # no alarm in here: the block runs to its end
                seen["left"] = deadline.remaining()
            deadline.check("after the pause")
    assert "left" in seen, "the alarm fired inside the paused block"
    assert seen["left"] < 0


def test_the_compiler_is_killed_with_its_children_at_the_limit(tmp_path):
    from symfunnel.core.ccompile import run_compiler
    marker = tmp_path / "child.pid"
    script = f"sleep 30 & echo $! > {marker}; wait"
    t0 = time.monotonic()
    with pytest.raises(deadline.WallLimitReached):
        with deadline.limit(0.5), deadline.step("compiling"):
            run_compiler(["sh", "-c", script], cwd=tmp_path, timeout=600)
    assert time.monotonic() - t0 < 5.0
    pid = int(marker.read_text())
    time.sleep(0.2)
    alive = subprocess.run(["ps", "-o", "stat=", "-p", str(pid)], capture_output=True, text=True).stdout.strip()
    assert alive in ("", "Z"), f"the compiler's child {pid} survived the limit ({alive})"


def _big_esn(tmp_path: Path, size: int, wall_limit: float | None = None, name: str = "big.toml") -> Path:
    """The paper's scenario with a reservoir of `size` units (and `[simulation] wall_limit`, if given)."""
    text = PAPER.read_text()
    lines = text.splitlines()
    out, section = [], None
    for line in lines:
        if line.startswith("["):
            section = line.strip()
        if section == "[esn]" and line.startswith("size ="):
            line = f"size = {size}"
        out.append(line)
        if line.strip() == "[simulation]" and wall_limit is not None:
            out.append(f"wall_limit = {wall_limit:g}")
    p = tmp_path / name
    p.write_text("\n".join(out) + "\n")
    return p


def _cli(args, **kw):
    env = dict(os.environ, SYMFUNNEL_CACHE=str(kw.pop("cache")))
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "symfunnel", *args], capture_output=True, text=True, env=env,
                       timeout=600)
    return r, time.monotonic() - t0


def _timeout_step(line: str, seconds: str) -> str:
    """The step named by the CLI's timeout line of a `seconds` s limit."""
    head = f"symfunnel: timeout: wall-clock limit of {seconds} s reached while "
    assert line.startswith(head), line
    return line[len(head):line.index(" (after ")]


@pytest.mark.slow
def test_derive_of_the_largest_reservoir_stops_at_the_limit(tmp_path):
    """`derive --wall-limit 2` of a 2000-unit reservoir stops with one line naming one of derive's steps, never the
    bare "working". That limit counts from the command's start, so under load it may land in loading the scenario
    (importing casadi and numpy, reading the file) as well as in the derivation (a clean-clone run under load read
    "while working": the loading ran outside any step). The scenario's `[simulation] wall_limit` counts from the
    derivation's start, so that one must land in the derivation (many seconds at 2000 units): its line names
    "deriving the design". The two runs go at once (each is its interpreter's start and its limit)."""
    from symfunnel.commands import derive
    env = dict(os.environ, SYMFUNNEL_CACHE=str(tmp_path / "cache"))
    runs = []
    for argv in (["derive", str(_big_esn(tmp_path, 2000)), "-q", "--json", "--wall-limit", "2"],
                 ["derive", str(_big_esn(tmp_path, 2000, wall_limit=1, name="staged.toml")), "-q", "--json"]):
        runs.append((subprocess.Popen([sys.executable, "-m", "symfunnel", *argv], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, env=env), time.monotonic()))
    done = []
    for p, t0 in runs:
        out, err = p.communicate(timeout=600)
        done.append((p.returncode, out, err, time.monotonic() - t0))
    steps = []
    for (rc, out, err, wall), seconds in zip(done, ("2", "1")):
        assert rc == 1, err
        lines = err.strip().splitlines()
        assert len(lines) == 1, lines
        steps.append(_timeout_step(lines[0], seconds))
        assert out == ""
        assert wall < 30.0                 # the limit held to within the longest uninterruptible call
    # the step that was interrupted is named: one of derive's, and one it can be in 2 s after its start (deriving
    # 2000 units takes far longer, so counting the signals' operations cannot have started)
    assert steps[0] in derive.STEPS and steps[0] in (derive.LOADING, derive.DERIVING), steps
    assert steps[1] == "deriving the design"


@pytest.mark.parametrize("phase", ["loading", "counting", "evaluating", "writing"])
def test_each_phase_of_derive_names_its_step_at_the_limit(tmp_path, monkeypatch, capsys, phase):
    """Every phase of `derive` runs under a named step: a limit reached while reading the scenario, counting the
    signals' operations (tens of seconds at 2000 units), evaluating them at --eval points or writing --latex names
    that phase, not "working" (the first two ran outside any step)."""
    import symfunnel.design as design_mod
    import symfunnel.pipeline as pipeline
    import symfunnel.scenario as scenario_mod
    from symfunnel.cli import main
    from symfunnel.commands import derive

    def slow(*a, **k):
        time.sleep(30.0)                          # the alarm interrupts the sleep

    class FakeDesign:
        signal_info, signals = {"tau": None}, {"tau": type("SX", (), {"shape": (2, 1)})()}
        ops = staticmethod(slow if phase == "counting" else (lambda k: 1))
        free_symbols = staticmethod(lambda k: [])

    class FakeRun:
        def __init__(self, sc, *a, **k):
            self.design = FakeDesign()

    monkeypatch.setattr(scenario_mod, "load_scenario", slow if phase == "loading" else (lambda name: object()))
    monkeypatch.setattr(pipeline, "Run", FakeRun)
    monkeypatch.setattr(design_mod, "evaluate", slow)
    monkeypatch.setattr(derive, "_write_latex", slow)
    points = tmp_path / "p.json"
    points.write_text('{"t": 0, "q": [0, 0], "dq": [0, 0]}')
    argv = ["derive", "-q", "--wall-limit", "0.3"]
    argv += {"evaluating": ["--eval", str(points)], "writing": ["--latex", str(tmp_path / "d.tex")]}.get(phase, [])
    t0 = time.monotonic()
    assert main(argv) == 1
    assert time.monotonic() - t0 < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    expected = {"loading": "loading the scenario", "counting": "counting the signals' operations and free variables",
                "evaluating": "evaluating the signals at the points", "writing": "writing the LaTeX"}[phase]
    assert len(err) == 1 and _timeout_step(err[0], "0.3") == expected, err
    assert not (tmp_path / "d.tex").exists()


@pytest.mark.slow
def test_simulate_stops_in_the_compile_step_and_leaves_no_cache_entry(tmp_path):
    big = _big_esn(tmp_path, 300)
    cache = tmp_path / "cache"
    r, wall = _cli(["simulate", str(big), "-q", "--t-final", "1", "--wall-limit", "4"], cache=cache)
    assert r.returncode == 1, r.stderr
    assert "timeout: wall-clock limit of 4 s reached while" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    # the closed loop it was compiling is not in the cache; what is (the interval interpreter, compiled when the
    # scenario's regularity was proven) is a complete entry
    from symfunnel.core.ccompile import verify_entry
    libs = list(cache.glob("**/*.so"))
    assert not [p for p in libs if p.name == "symfunnel_cl.so"], "a half-built library was left in the cache"
    assert all(verify_entry(p.parent, p.name) is None for p in libs), libs
    assert wall < 60.0


def test_bad_limit_is_bad_input(capsys, tmp_path):
    from symfunnel.cli import main
    for cmd in (["derive"], ["verify"], ["report"], ["codegen", "--lang", "c", "--rate", "2000", "--out", str(tmp_path / "c")],
                ["audit"]):
        assert main([*cmd, "-q", "--wall-limit", "-1"]) == 2
        err = capsys.readouterr().err
        assert "--wall-limit" in err and "> 0" in err


def test_an_error_a_c_call_makes_of_the_alarm_after_the_expiry_is_the_limit():
    """The alarm's WallLimitReached raised inside a CasADi call comes out as SWIG's NotImplementedError ("Wrong
    number or type of arguments", seen from `verify --wall-limit 0.5`): past the expiry the limit block reports the
    limit (the error as its cause); before it, such an error is the block's own and passes through."""
    msg = "Wrong number or type of arguments for function 'Function_call'"
    with pytest.raises(deadline.WallLimitReached) as ei:
        with deadline.limit(0.05):
            try:
                time.sleep(1.0)                 # the alarm fires here ...
            except deadline.WallLimitReached:
                pass                            # ... and is swallowed, as inside a C extension
            raise NotImplementedError(msg)
    assert isinstance(ei.value.__cause__, NotImplementedError) and ei.value.seconds == 0.05
    with pytest.raises(NotImplementedError, match="Wrong number"):
        with deadline.limit(60.0):
            raise NotImplementedError(msg)
    assert deadline.remaining() == float("inf")


@pytest.mark.parametrize("exc", [NotImplementedError, TypeError])
def test_each_form_the_swallowed_alarm_takes_after_the_expiry_is_the_limit(exc):
    """The forms seen from `verify --wall-limit 0.5`: SWIG's NotImplementedError and CasADi's TypeError ("Implicit
    conversion of symbolic CasADi type to numeric matrix not supported", a conversion the alarm interrupted)."""
    with pytest.raises(deadline.WallLimitReached) as ei:
        with deadline.limit(0.05):
            try:
                time.sleep(1.0)
            except deadline.WallLimitReached:
                pass
            raise exc("Implicit conversion of symbolic CasADi type to numeric matrix not supported")
    assert isinstance(ei.value.__cause__, exc)
    with pytest.raises(exc):
        with deadline.limit(60.0):
            raise exc("a real error of the block")


def test_a_limit_never_interrupts_an_import_half_way(tmp_path):
    """The alarm during an import waits for the import to finish, then raises: a module interrupted half-way stays
    broken in sys.modules for the rest of the process (an API session, a test worker: after a limit that fired 0.2 s
    into the lazy `import sympy`, "module 'sympy' has no attribute 'polys'")."""
    (tmp_path / "slow_module.py").write_text("import time\ntime.sleep(0.3)\nDONE = True\n")
    # nothing is printed inside the block: the alarm, due 10 ms after the import, may land in any statement after it
    # (seen under load: in the middle of a print)
    code = textwrap.dedent("""
        import sys, time
        from symfunnel.core import deadline
        t0 = time.monotonic()
        try:
            with deadline.limit(0.05):
                import slow_module
                while True:
                    time.sleep(0.01)
        except deadline.WallLimitReached:
            t = time.monotonic() - t0
        m = sys.modules.get("slow_module")
        print(round(t, 3), getattr(m, "DONE", False))
        """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert r.returncode == 0, r.stderr[-2000:]
    t, done = r.stdout.split()
    assert done == "True"                         # the import ran to its end and the module is whole ...
    assert 0.3 <= float(t) < 0.3 + 0.5            # ... and the limit was raised after it, soon


def test_a_limit_reached_during_an_import_names_the_step_it_was_reached_in(tmp_path):
    """The alarm that waits for an import to finish raises naming the step the limit was reached in, not the one
    the command has moved on to (a clean-clone CI run: `derive --wall-limit 2` expired in its loading step's imports
    and said "while working", the gap between loading and deriving, where the deferred alarm landed)."""
    (tmp_path / "slow_import.py").write_text("import time\ntime.sleep(0.3)\n")
    code = textwrap.dedent("""
        import time
        from symfunnel.core import deadline
        try:
            with deadline.limit(0.05):
                with deadline.step("loading the scenario"):
                    import slow_import
                while True:                         # outside any step: where the deferred alarm lands
                    time.sleep(0.01)
        except deadline.WallLimitReached as exc:
            print(exc.step)
        """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "loading the scenario"


def test_verify_under_a_limit_too_short_for_the_integration_stops_with_one_line(capsys):
    from symfunnel.cli import main
    assert main(["verify", "-q", "--wall-limit", "0.5"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "wall-clock limit of 0.5 s reached" in err[0]


def test_the_api_raises_a_simulation_error_at_its_wall_limit():
    from symfunnel import api
    from symfunnel.core.errors import SimulationError
    with pytest.raises(SimulationError, match="wall-clock limit of 0.3 s reached"):
        api.verify("paper", wall_limit=0.3)
    assert deadline.remaining() == float("inf")


def test_a_runs_limit_counts_its_stages_not_the_time_between_them():
    """A Run kept after its design was derived (a session fixture, a notebook) and used again later than its
    limit: the limit counts the stages' own time, so the later simulation runs (it raised at once before, after
    the idle time); the spent part still counts, and a stage past what is left still stops."""
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.scenario import load_scenario
    sc = load_scenario("paper")
    assert Run(sc, RunOptions(t_final=0.5)).simulation.ok          # compiled once, cached for what follows
    run = Run(sc, RunOptions(t_final=0.5, wall_limit=5.0))
    run.design
    time.sleep(5.2)                                                 # idle longer than the whole limit
    res = run.simulation
    assert res.ok and res.status == "ok"
    spent = run.__dict__["_budget"]["spent"]
    assert 0.0 < spent < 5.0
    late = Run(sc, RunOptions(t_final=0.5, wall_limit=5.0))
    late.design
    late.__dict__["_budget"]["spent"] = 5.0 - 1e-3                 # as if the earlier stages had used it all
    with pytest.raises(deadline.WallLimitReached, match="wall-clock limit of 5 s reached"):
        late.closed_loop


def test_large_reservoirs_get_the_same_spectral_radius_from_arpack_as_from_lapack():
    import numpy as np

    from symfunnel.family.esn import DENSE_UP_TO, _draw_reservoir, _norm2, _spectral_radius
    W = _draw_reservoir(np.random.default_rng(3), DENSE_UP_TO + 100, 0.9)
    dense_rho = float(np.max(np.abs(np.linalg.eigvals(W))))
    assert _spectral_radius(W) == pytest.approx(dense_rho, rel=1e-11)
    assert _norm2(W) == pytest.approx(float(np.linalg.norm(W, 2)), rel=1e-11)


def test_a_limit_raised_while_its_block_exits_leaves_no_deadline_behind(monkeypatch):
    """An alarm delivered as the block ends runs its handler at the first call of the clean-up and raises from
    there: the deadline must already be off the stack (else every later check of the process expires)."""
    import signal as _signal
    from symfunnel.core import deadline
    real = _signal.setitimer
    fired = []

    def setitimer(which, seconds, *rest):
        if seconds == 0 and not fired:
            fired.append(True)
            raise deadline.WallLimitReached(1.0, "the clean-up", 1.0)
        return real(which, seconds, *rest)

    monkeypatch.setattr(deadline.signal, "setitimer", setitimer)
    with pytest.raises(deadline.WallLimitReached):
        with deadline.limit(30.0):
            with deadline.step("inner"):
                pass
    monkeypatch.setattr(deadline.signal, "setitimer", real)
    assert fired and deadline._stack == [] and deadline._steps == []
    assert deadline.remaining() == float("inf")
    deadline.check()                                        # nothing expired is left to raise


def test_a_signal_while_a_pause_starts_leaves_the_alarm_armed(monkeypatch):
    """A signal raised as `paused()` arms its block leaves no pause behind (else no later alarm would fire)."""
    from symfunnel.core import deadline
    calls = []
    real = deadline._arm

    def arm():
        calls.append(1)
        if len(calls) == 2:                                 # the pause's own arming (the limit's is the first)
            raise KeyboardInterrupt
        return real()

    monkeypatch.setattr(deadline, "_arm", arm)
    with pytest.raises(KeyboardInterrupt):
        with deadline.limit(30.0):
            with deadline.paused():
                pass
    assert deadline._paused == [] and deadline._stack == []
