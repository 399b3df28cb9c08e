"""[implementation], the sampled-data loop around the compiled C step, its verify checks, and `symfunnel rate`."""

from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pytest

from symfunnel.deployed import rate as R
from symfunnel.checks.implementation import implementation_checks
from symfunnel.deployed import loop as S
from symfunnel.cli import main
from symfunnel.design import derive
from symfunnel.core.errors import InputError
from symfunnel.scenario import DATA_DIR, load_scenario


needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not available")


def paper_with(tmp_path, implementation: str, t_final: float | None = None, name: str = "impl.toml"):
    """The paper scenario plus an [implementation] table (and another horizon), as a file."""
    text = (DATA_DIR / "paper_2dof.toml").read_text()
    if t_final is not None:
        assert "t_final = 20.0\n" in text
        text = text.replace("t_final = 20.0\n", f"t_final = {t_final}\n")
    p = tmp_path / name
    p.write_text(text + "\n[implementation]\n" + implementation + "\n")
    return p


# --- [implementation] -----------------------------------------------------------------------------

@pytest.mark.parametrize("body, key", [
    ("rate_hz = 0.0", "implementation.rate_hz"),
    ("rate_hz = -10.0", "implementation.rate_hz"),
    ("rate_hz = 2e6", "implementation.rate_hz"),
    ("delay_samples = 2", "implementation.delay_samples"),
    ("noise_q = -0.1", "implementation.noise_q"),
    ("noise_dq = -1.0", "implementation.noise_dq"),
    ("encoder_resolution = -1e-3", "implementation.encoder_resolution"),
    ("tau_max = -5.0", "implementation.tau_max"),
    ("tau_max = [10.0, -1.0]", "implementation.tau_max[1]"),
    ('tau_max = "urdf"', "implementation.tau_max"),            # paper's model is not a URDF
    ('tau_max = "max"', "implementation.tau_max"),
    ("rate = 100.0", "implementation.rate"),
])
def test_bad_implementation_is_input_error_naming_the_key(tmp_path, capsys, body, key):
    p = paper_with(tmp_path, body)
    with pytest.raises(InputError) as ei:
        load_scenario(p)
    assert ei.value.key == key
    assert main(["simulate", str(p), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0] and str(p) in err[0]


def test_tau_max_urdf_reads_the_effort_limits(tmp_path):
    urdf = (DATA_DIR / "arm7.urdf").read_text()
    efforts = [float(v) for v in re.findall(r'effort="([^"]+)"', urdf)]
    toml = (DATA_DIR / "arm7.toml").read_text()
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    (tmp_path / "a.toml").write_text(toml + '\n[implementation]\ntau_max = "urdf"\n')
    sc = load_scenario(tmp_path / "a.toml")
    assert list(sc.implementation.tau_max) == efforts[:7] and len(efforts) >= 7
    # one joint without an effort limit: exit 2 naming the key
    (tmp_path / "arm7.urdf").write_text(re.sub(r'\s*effort="[^"]+"', "", urdf, count=1))
    with pytest.raises(InputError) as ei:
        load_scenario(tmp_path / "a.toml")
    assert ei.value.key == "implementation.tau_max" and "[1]" in ei.value.reason


# --- the sampled loop -----------------------------------------------------------------------------

class Recorder:
    """A stand-in for the compiled step: records the measurements it gets and returns a fixed torque."""

    def __init__(self, n, tau):
        self.q, self.dq, self.tau = np.zeros(n), np.zeros(n), np.zeros(n)
        self.seen_q, self.seen_dq, self.fixed = [], [], np.asarray(tau, float)

    def init(self):
        return 0

    def raw(self):
        def step(_state, t, *_):
            self.seen_q.append(self.q.copy())
            self.seen_dq.append(self.dq.copy())
            self.tau[:] = self.fixed * (1 + t)
            return 0
        return step, None, ()


@needs_gcc
def test_noise_quantisation_and_delay_reach_the_controller_as_specified(tmp_path):
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 1000.0\nnoise_q = 0.01\nnoise_dq = 0.2\n"
                                            "encoder_resolution = 0.005\ndelay_samples = 1\nseed = 7"))
    rec = Recorder(2, [1.0, -2.0])
    res = S.simulate_sampled(sc, derive(sc), t_final=2.0, controller=rec, stop_on_breach=False)
    qm, dqm = np.array(rec.seen_q), np.array(rec.seen_dq)
    K = res.tau.shape[0]
    assert qm.shape == (K, 2) and K == 2000
    np.testing.assert_allclose(qm / 0.005, np.round(qm / 0.005), atol=1e-9)       # on the encoder grid
    err_dq = dqm - res.dq[:K]
    assert 0.18 < err_dq.std() < 0.22 and abs(err_dq.mean()) < 0.02               # noise_dq = 0.2
    err_q = qm - res.q[:K]
    assert 0.009 < err_q.std() < 0.011                                            # noise 0.01 (+ grid 0.005/sqrt 12)
    # one sample of delay: zero torque first, then the torque computed one period earlier (tau = fixed (1 + t))
    np.testing.assert_array_equal(res.tau[0], 0.0)
    np.testing.assert_allclose(res.tau[1:], np.outer(1 + np.arange(K - 1) / 1000.0, [1.0, -2.0]), rtol=1e-15)
    # seeded: the same run again gives the same measurements
    rec2 = Recorder(2, [1.0, -2.0])
    S.simulate_sampled(sc, derive(sc), t_final=2.0, controller=rec2, stop_on_breach=False)
    np.testing.assert_array_equal(np.array(rec2.seen_q), qm)


def paper_arm_numpy():
    """The paper's 2-link arm written out by hand (eq. 40, Christoffel C, friction, dead zone, disturbance)."""
    l1, l2, m1, m2, m3, m4 = 1.0, 0.8, 1.0, 1.5, 2.0, 1.5
    al, be, ga = m1 / 4 + m2 + m3 + m4, m3 / 4 + m4, m3 / 2 + m4

    def dead_zone(v):
        return 1.1 * (v - 1.0) if v >= 1.0 else (0.9 * (v + 1.5) if v <= -1.5 else 0.0)

    def sign(v):
        return (v > 0) - (v < 0)

    def ddq(t, q, dq, u):
        # in plain floats (the 2 x 2 solve by Cramer's rule): 320,000 calls in the 10 kHz test
        q2, v1, v2 = float(q[1]), float(dq[0]), float(dq[1])
        c2, s2 = math.cos(q2), math.sin(q2)
        m11 = al * l1**2 + be * l2**2 + 2 * ga * l1 * l2 * c2
        m12 = be * l2**2 + ga * l1 * l2 * c2
        m22 = be * l2**2
        hh = ga * l1 * l2 * s2
        d = 0.5 * math.sin(2 * t)
        r1 = dead_zone(float(u[0])) - (-hh * v2 * v1 - hh * (v1 + v2) * v2) - 15 * v1 - 6 * sign(v1) - d
        r2 = dead_zone(float(u[1])) - hh * v1 * v1 - 15 * v2 - 6 * sign(v2) - d
        det = m11 * m22 - m12 * m12
        return np.array([(m22 * r1 - m12 * r2) / det, (m11 * r2 - m12 * r1) / det])
    return ddq


@needs_gcc
@pytest.mark.slow
def test_pstep_at_10khz_drives_an_independent_numpy_plant_inside_its_funnel():
    from symfunnel.emit import generate
    sc = load_scenario("paper")
    design = derive(sc)
    lib = S.step_library(design, generate(design, "c", rate_hz=10000.0))
    f = paper_arm_numpy()
    h, T, sub = 1e-4, 4.0, 2                       # past the transient: by 4 s F2 is within 2 % of phi_inf
    q, dq = np.zeros(2), np.zeros(2)
    worst = math.inf
    for k in range(int(round(T / h))):
        t = k * h
        rc, tau = lib.step(t, q, dq)
        assert rc == 0, t
        hs = h / sub
        for i in range(sub):                      # RK4 with tau held
            ts = t + i * hs
            k1q, k1v = dq, f(ts, q, dq, tau)
            k2q, k2v = dq + hs / 2 * k1v, f(ts + hs / 2, q + hs / 2 * k1q, dq + hs / 2 * k1v, tau)
            k3q, k3v = dq + hs / 2 * k2v, f(ts + hs / 2, q + hs / 2 * k2q, dq + hs / 2 * k2v, tau)
            k4q, k4v = dq + hs * k3v, f(ts + hs, q + hs * k3q, dq + hs * k3v, tau)
            q = q + hs / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
            dq = dq + hs / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        # the funnels and alpha2 of the paper, by hand
        tn = t + h
        F1, F2 = 0.18 * math.exp(-2 * tn) + 0.01, 0.4 * math.exp(-2 * tn) + 0.01
        dF1 = -0.36 * math.exp(-2 * tn)
        e1 = q - 0.3 * math.sin(tn)
        z1 = e1 / (F1 - np.abs(e1))
        alpha2 = 0.3 * math.cos(tn) + dF1 / F1 * e1 - 5.0 * z1
        e2 = dq - alpha2
        worst = min(worst, np.min(1 - np.abs(e1) / F1), np.min(1 - np.abs(e2) / F2))
    assert worst > 0.05


@needs_gcc
def test_sampled_loop_agrees_with_the_continuous_simulation_at_a_high_rate():
    """At 20 kHz the held torque is nearly continuous: q follows the CVODES closed loop to within 1e-3 rad."""
    from symfunnel.simulation import simulate
    sc = load_scenario("paper")
    res = S.simulate_sampled(sc, derive(sc), rate_hz=20000.0, t_final=2.0)
    ref = simulate(sc, derive(sc), t_final=2.0)
    assert res.ok and ref.ok
    qi = np.stack([np.interp(ref.t, res.t, res.q[:, j]) for j in range(2)], axis=1)
    assert np.max(np.abs(qi - ref.signals["q"])) < 1e-3


@needs_gcc
@pytest.mark.slow
def test_verify_holds_at_twice_the_minimum_rate_and_fails_at_a_quarter(tmp_path, capsys):
    p = paper_with(tmp_path, "rate_hz = 4000.0", t_final=6.0)
    sc = load_scenario(p)
    r = R.min_rate(sc, derive(sc))
    rmin = r["min_rate_hz"]
    assert rmin is not None and 100 < rmin < 1e5
    holds = [d["rate_hz"] for d in r["tried"] if d["holds"]]
    fails = [d["rate_hz"] for d in r["tried"] if not d["holds"]]
    assert min(holds) == rmin and max(fails) < rmin and rmin / max(fails) <= 1.05
    good = implementation_checks(sc, derive(sc), rate_hz=2 * rmin)
    assert [c.id for c in good] == ["implementation.containment"] and good[0].status == "pass"
    bad = implementation_checks(sc, derive(sc), rate_hz=rmin / 4)
    assert bad[0].status == "fail" and bad[0].where["time"] > 0
    assert main(["verify", str(p), "--rate", str(rmin / 4), "--json", "-q", "--samples", "100"]) == 1
    out = capsys.readouterr().out
    assert '"implementation.containment"' in out


@needs_gcc
def test_saturation_check_reports_the_time_fraction_at_the_limit(tmp_path):
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 4000.0\ntau_max = [400.0, 1000.0]"))
    res = S.simulate_sampled(sc, derive(sc), t_final=1.0)
    checks = {c.id: c for c in implementation_checks(sc, None, result=res)}
    sat = checks["implementation.saturation"]
    frac = sat.evidence["saturated_fraction"]
    assert sat.status == "fail" and frac[1] == 0.0
    assert frac[0] == pytest.approx(np.mean(np.abs(res.tau[:, 0]) >= 400.0)) and frac[0] > 0
    assert res.ok and np.max(np.abs(res.tau[:, 0])) == 400.0                      # the step saturates
    sc2 = load_scenario(paper_with(tmp_path, "rate_hz = 4000.0\ntau_max = 1e4", name="b.toml"))
    ok = {c.id: c for c in implementation_checks(sc2, derive(sc2), t_final=1.0)}
    assert ok["implementation.saturation"].status == "pass"
    assert ok["implementation.containment"].status == "pass"


def test_no_implementation_no_checks():
    assert implementation_checks(load_scenario("paper"), None) == []


# --- rate search (plumbing, with a stand-in for the sampled run) ------------------------------------

class _Run:
    def __init__(self, ok, m):
        self.ok, self.min_margin = ok, m
        self.min_margin_after_transient = m          # what the rate search ranks by
        self.status = "ok" if ok else "breach"
        self.breach = None if ok else {"time": 0.5, "funnel": "e2", "joint": 1, "margin": m}
        self.stats = {"settle_time": 0.0}


def _threshold_sim(threshold_of):
    def fake(sc, design, *, rate_hz=None, t_final=None, **_):
        thr = threshold_of(sc)
        return _Run(rate_hz >= thr, 0.3 if rate_hz >= thr else -5.0)
    return fake


def test_min_rate_brackets_and_bisects_on_a_log_scale(monkeypatch):
    monkeypatch.setattr(S, "simulate_sampled", _threshold_sim(lambda sc: 3000.0))
    r = R.min_rate(load_scenario("paper"), object())
    assert 3000.0 <= r["min_rate_hz"] <= 3000.0 * 1.05
    rates = [d["rate_hz"] for d in r["tried"]]
    assert rates[:2] == [1000.0, 4000.0]
    for d in r["tried"]:
        assert d["holds"] == (d["rate_hz"] >= 3000.0)
    # the bracket shrinks geometrically: successive midpoints are geometric means
    assert any(math.isclose(x, math.sqrt(1000.0 * 4000.0)) for x in rates)


def test_a_run_that_starts_outside_its_funnel_ends_the_rate_search_at_once(tmp_path, capsys):
    """The state at t = 0 is the same at every rate: one probe, then `reason` (and the CLI's line) says why; the
    claim is re-checked at another rate, and a breach later in the run still lets the search go on (above)."""
    p = paper_with(tmp_path, "rate_hz = 1000.0", t_final=1.0)
    p.write_text(p.read_text().replace("phi0 = 0.4 ", "phi0 = 0.18 ", 1))
    sc = load_scenario(p)
    design = derive(sc)
    r = R.min_rate(sc, design)
    assert r["min_rate_hz"] is None and [d["rate_hz"] for d in r["tried"]] == [1000.0]
    assert "outside funnel e2 of joint 1 at t = 0" in r["reason"]
    other = S.simulate_sampled(sc, design, rate_hz=64000.0, t_final=0.01)
    assert other.breach is not None and other.breach["time"] == 0.0 and other.margins[0].min() < 0
    assert main(["rate", str(p)]) == 1
    assert "none (the initial state is outside funnel e2" in capsys.readouterr().out


def test_rate_sensitivity_changes_the_named_parameter(monkeypatch):
    sc = load_scenario("paper")
    # a stand-in whose threshold is proportional to the inner-loop gain k2 / phi_inf of e2
    monkeypatch.setattr(S, "simulate_sampled",
                        _threshold_sim(lambda s: 100.0 * s.k2[0] / s.funnels["e2"].phi_inf[0]))
    monkeypatch.setattr("symfunnel.design.derive", lambda sc: object())
    out = R.rate_sensitivity(sc, object(), variations=R.VARIATIONS)
    by = {v["key"]: v for v in out["variations"]}
    assert out["inner_loop_gain"] == [1000.0, 1000.0]
    assert by["funnel.e2.phi_inf"]["after"] == pytest.approx(0.02)
    assert by["funnel.e2.phi_inf"]["ratio"] == pytest.approx(0.5, rel=0.06)
    assert by["controller.k2"]["ratio"] == pytest.approx(0.5, rel=0.06)
    assert by["funnel.e2.a"]["ratio"] == pytest.approx(1.0, rel=0.06)


def test_rate_command_bad_margin_is_input_error(capsys):
    assert main(["rate", "--margin", "1.5"]) == 2
    assert "--margin" in capsys.readouterr().err
    assert main(["simulate", "--rate", "0"]) == 2
    assert main(["verify", "--rate", "-3"]) == 2


@needs_gcc
def test_report_figures_draw_the_sampled_torque_and_the_rate_search(tmp_path):
    from symfunnel.deployed.summary import torque_figure
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 2000.0\ntau_max = 450.0"))
    res = S.simulate_sampled(sc, derive(sc), t_final=0.5)
    fig = torque_figure(res, t_max=0.2)
    steps = fig.axes[0].patches[0]                     # the stairs of joint 1
    assert np.max(np.abs(steps.get_path().vertices[:, 1])) == pytest.approx(450.0)
    fig2 = R.margin_rate_figure({"margin": 0.05, "min_rate_hz": 1200.0,
                                 "tried": [{"rate_hz": 1000.0, "min_margin": -3.0},
                                           {"rate_hz": 4000.0, "min_margin": 0.27}]})
    assert fig2.axes[0].get_xscale() == "log"


@needs_gcc
@pytest.mark.slow
def test_design_help_computes_the_minimum_rate_per_parameter(tmp_path):
    """Computed, not asserted by hand; the one expectation is theory: a wider e2 funnel (phi_inf x 2) halves the
    lower bound 1/F2 of mu2, the gain of both the torque's e2 term and the adaptation, so it lowers the rate."""
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 2000.0", t_final=6.0))
    out = R.rate_sensitivity(sc, derive(sc))
    by = {v["key"]: v for v in out["variations"]}
    assert out["baseline"]["min_rate_hz"] is not None
    assert by["funnel.e2.phi_inf"]["ratio"] < 0.9
    for v in out["variations"]:
        assert v["min_rate_hz"] is not None and v["tried"]
        assert v["after"] == pytest.approx(v["before"] * v["factor"])


def test_rate_command_json_has_the_contract_keys(monkeypatch, capsys):
    import json
    monkeypatch.setattr(S, "simulate_sampled", _threshold_sim(lambda sc: 2500.0))
    monkeypatch.setattr("symfunnel.design.derive", lambda sc, **_: object())     # the command's Run derives
    assert main(["rate", "paper", "--json", "--margin", "0.1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"min_rate_hz", "margin", "tried", "engine"} and out["margin"] == 0.1 and out["engine"] == "symfunnel"
    assert 2500.0 <= out["min_rate_hz"] <= 2500.0 * 1.05
    assert all({"rate_hz", "status", "min_margin"} <= set(d) for d in out["tried"])
    monkeypatch.setattr(S, "simulate_sampled", _threshold_sim(lambda sc: 5e6))   # nothing holds up to 1 MHz
    assert main(["rate", "paper", "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["min_rate_hz"] is None


@needs_gcc
def test_simulate_rate_cli_writes_the_sampled_run_and_exits_1_on_a_breach(tmp_path, capsys):
    import json
    out = tmp_path / "run.npz"
    assert main(["simulate", "paper", "--rate", "4000", "--t-final", "0.5", "--out", str(out), "-q", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["status"] == "ok" and s["rate_hz"] == 4000.0 and s["samples"] == 2000
    data = np.load(out)
    assert data["tau"].shape == (2000, 2) and data["q"].shape == (2001, 2)
    assert main(["simulate", "paper", "--rate", "400", "-q"]) == 1
    assert "left funnel e" in capsys.readouterr().err         # the breach, in words (JSON keeps "breach")


@needs_gcc
@pytest.mark.slow
def test_arm7_has_a_finite_minimum_rate_and_holds_at_twice_it(tmp_path):
    text = (DATA_DIR / "arm7.toml").read_text()
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    text = re.sub(r"^t_final = .*$", "t_final = 4.0", text, count=1, flags=re.M)
    assert "t_final = 4.0" in text
    (tmp_path / "arm7.toml").write_text(text)
    sc = load_scenario(tmp_path / "arm7.toml")
    design = derive(sc)
    r = R.min_rate(sc, design, rel_tol=0.2)
    assert r["min_rate_hz"] is not None and r["min_rate_hz"] < 1e5
    assert implementation_checks(sc, design, rate_hz=2 * r["min_rate_hz"])[0].status == "pass"


@needs_gcc
def test_the_c_loop_and_the_python_loop_apply_noise_quantisation_and_delay_alike(tmp_path):
    """The fast loop in C (used with the compiled step) against the Python loop (checked above) on the same step."""
    from symfunnel.emit import generate
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 4000.0\nnoise_q = 1e-4\nnoise_dq = 1e-3\n"
                                            "encoder_resolution = 1e-4\ndelay_samples = 1\nseed = 3"))
    design = derive(sc)
    lib = S.step_library(design, generate(design, "c", rate_hz=4000.0))

    class Wrapped:                       # the same compiled step, but not a StepLibrary: the Python loop runs
        q, dq, tau = lib.q, lib.dq, lib.tau
        init, raw = lib.init, lib.raw
    fast = S.simulate_sampled(sc, t_final=0.5, design=design, controller=lib)
    slow = S.simulate_sampled(sc, t_final=0.5, design=design, controller=Wrapped())
    assert fast.status == slow.status == "ok" and fast.tau.shape == (2000, 2)
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.tau, slow.tau, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(fast.tau[0], 0.0)                       # the delay


@needs_gcc
def test_implementation_report_puts_the_peak_torque_beside_the_limits(tmp_path):
    from symfunnel.deployed.summary import implementation_report
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 3000.0\ntau_max = [600.0, 300.0]", t_final=2.0))
    out = implementation_report(sc, derive(sc), sensitivity=False)
    assert out["min_rate"]["min_rate_hz"] is not None and out["sensitivity"] is None
    res = out["run"]["result"]
    assert res.rate_hz == 3000.0
    assert out["peak_tau"] == np.max(np.abs(res.tau), axis=0).tolist()
    assert out["tau_max"] == [600.0, 300.0] and out["effort_limits"] is None
    assert out["peak_tau"][0] > 500.0                     # the paper's start asks for ~502 N m on joint 1
