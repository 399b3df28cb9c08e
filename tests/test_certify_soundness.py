"""Soundness of the certificates on hostile input: a refutation only at a finite violating value the design
attains (slopes the dead zone has, states the loop reaches), checked against independent formulas."""

from __future__ import annotations

import copy
import math

import casadi as ca
import numpy as np
import pytest

import symfunnel as sf
from symfunnel.certificates import run_certificates
from symfunnel.certificates.region import parameter_box, slope_ranges
from symfunnel.core.toml_write import dumps
from symfunnel.sx.search import prove_positive_definite


def write(tmp_path, raw: dict, name="s.toml") -> str:
    p = tmp_path / name
    p.write_text(dumps(raw), encoding="utf-8")
    return str(p)


def _paper_with(tmp_path, left, right="(u - b_r)"):
    raw = copy.deepcopy(sf.load_scenario("paper").raw)
    raw["plant"]["dead_zone"]["left"] = left
    raw["plant"]["dead_zone"]["right"] = right
    return write(tmp_path, raw, "dz.toml")


def _input_gain(path):
    sc = sf.load_scenario(path)
    return run_certificates(sc, sf.derive(sc), t_final=sc.simulation.t_final,
                            only=("certify.input_gain",)).certificates[0]


# --- a refutation needs a finite violating value ------------------------------------------------------------

def test_nan_eigenvalue_is_no_refutation():
    """S(x) = sqrt(x) + 1 on [-1, 1] is NaN on x < 0: no finite counterexample exists (old code: refuted, nan)."""
    x = ca.SX.sym("x", 1)
    S = ca.Function("S", [x], [ca.reshape(ca.sqrt(x) + 1, 1, 1)])
    r = prove_positive_definite(S, np.array([-1.0]), np.array([1.0]), np.array([0]), max_boxes=200)
    assert r.status == "undecided"
    assert r.upper is None or np.isfinite(r.upper)


def test_nan_confirmation_is_no_refutation():
    """A confirm that gives NaN (the independent evaluation failed) never turns a box into a counterexample."""
    x = ca.SX.sym("x", 1)
    S = ca.Function("S", [x], [ca.reshape(x, 1, 1)])          # genuinely indefinite on x < 0
    r = prove_positive_definite(S, np.array([-1.0]), np.array([1.0]), np.array([0]), max_boxes=50,
                                confirm=lambda xx: math.nan)
    assert r.status != "refuted"
    r = prove_positive_definite(S, np.array([-1.0]), np.array([1.0]), np.array([0]), max_boxes=50,
                                confirm=lambda xx: float(xx[0]))
    assert r.status == "refuted" and r.upper <= 0 and np.isfinite(r.upper)


# --- dead-zone slopes: endpoint-tight, refutations at attained slopes --------------------------------------

def test_cubic_dead_zone_slope_box_is_the_true_range(tmp_path):
    """left = (u - b_l) + 0.0008 (u - b_l)^3 on [b_l - 10, b_l]: slope 1 + 0.0024 (u - b_l)^2 in [1, 1.24]
    exactly; the box encloses it within 1e-6 (old: arb's midpoint-radius [0.92, 1.24]), and the attained ends are
    the formula's values at the reported u."""
    sc = sf.load_scenario(_paper_with(tmp_path, "(u - b_l) + 0.0008*(u - b_l)^3"))
    r = slope_ranges(sc, parameter_box(sc))
    bl = -1.5                                          # the paper's b_l
    assert np.all(r["lo"] <= 1.0) and np.all(r["lo"] >= 1.0 - 1e-6)
    assert np.all(r["hi"] >= 1.24) and np.all(r["hi"] <= 1.24 + 1e-6)
    for j in range(sc.n):
        for side in ("lo", "hi"):
            w = r["where"][j][side]
            true = 1.0 if w["branch"] == "right" else 1 + 0.0024 * (w["u"] - bl) ** 2
            assert abs(true * w["scale"] - w["slope"]) <= 1e-12
        assert r["lo_seen"][j] >= r["lo"][j] and r["hi_seen"][j] <= r["hi"][j]
        assert abs(r["lo_seen"][j] - 1.0) < 1e-5 and abs(r["hi_seen"][j] - 1.24) < 1e-5


def test_cubic_dead_zone_is_not_refuted_at_slopes_it_never_has(tmp_path):
    """left = (u - b_l) + 0.0004 (u - b_l)^3 (slopes [1, 1.12]), right slope 1: sym(M^-1 D M) >= 0.2 at the
    paper's worst q (numpy below), so input_gain is proven; the inflated box [0.96, 1.12] refuted it."""
    path = _paper_with(tmp_path, "(u - b_l) + 0.0004*(u - b_l)^3")
    c = _input_gain(path)
    assert c.status == "proven" and 0.15 < c.lower <= 0.21
    # independent: lambda_min over a q2 grid and the 4 slope vertices of [1, 1.12]^2 (model = plant here)
    d = sf.derive(sf.load_scenario(path))
    fM = d.function("M", ["q"])
    lam = []
    for q2 in np.linspace(-0.49, 0.49, 99):
        M = np.asarray(fM([0.0, q2]), float)
        for D in ([1, 1], [1, 1.12], [1.12, 1], [1.12, 1.12]):
            G = np.linalg.solve(M, np.diag(D) @ M)
            lam.append(np.linalg.eigvalsh(0.5 * (G + G.T))[0])
    assert c.lower <= min(lam) + 1e-9 and min(lam) > 0.19


def test_cubic_dead_zone_refutation_is_at_attained_slopes(tmp_path):
    """With 0.0008 (slopes [1, 1.24]) the gain is indefinite for real (slopes 1.24 and 1 on the two joints, both
    attained): the counterexample's slopes are the formula's at actual u and numpy reproduces lambda_min < 0."""
    path = _paper_with(tmp_path, "(u - b_l) + 0.0008*(u - b_l)^3")
    c = _input_gain(path)
    assert c.status == "refuted"
    ce = c.counterexample
    for s, w in zip(ce["slopes"], ce["slopes_attained_at"]):
        true = 1.0 if w["branch"] == "right" else 1 + 0.0024 * (w["u"] + 1.5) ** 2
        assert abs(s - true * w["scale"]) <= 1e-12 and 1.0 - 1e-12 <= s <= 1.24 + 1e-12
    d = sf.derive(sf.load_scenario(path))
    M = np.asarray(d.function("M", ["q"])(ce["q"]), float)
    G = np.linalg.solve(M, np.diag(ce["slopes"]) @ M)
    assert np.linalg.eigvalsh(0.5 * (G + G.T))[0] < 0


# --- saturation: refuted only on states the loop reaches --------------------------------------------------

def _paper_tau_max(tmp_path, tau_max):
    raw = copy.deepcopy(sf.load_scenario("paper").raw)
    raw.setdefault("implementation", {})["tau_max"] = tau_max
    return write(tmp_path, raw, "tau.toml")


def test_saturation_at_the_initial_state_refutes(tmp_path):
    """tau_max = 50 on the paper: |tau_1(0, x0)| = 501.6 (the design's tau at q0, dq0, W_hat(0), x_esn(0), which
    is on every trajectory): refuted with the initial state as counterexample (old: undecided)."""
    sc = sf.load_scenario(_paper_tau_max(tmp_path, 50.0))
    d = sf.derive(sc)
    c = run_certificates(sc, d, t_final=sc.simulation.t_final, only=("certify.bounds",)).certificates[0]
    assert c.status == "refuted" and c.counterexample["initial_state"] is True
    assert c.counterexample["t"] == 0.0 and c.counterexample["q"] == list(map(float, sc.q0))
    # the design's tau Function of its own inputs at t = 0 (the initial weights and reservoir state)
    init = d.variant.initial_states()
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(0.0))
    tau = np.asarray(d.function("tau")(*[{"t": 0.0, "q": sc.q0, "dq": sc.dq0, "qd": qd, "dqd": dqd, "ddqd": ddqd,
                                            **init}[k] for k in d.inputs_of("tau")]), float).ravel()
    assert np.max(np.abs(tau)) > 50 and abs(abs(tau[0]) - 501.5964766) < 1e-3
    assert np.allclose(c.counterexample["tau"], tau, rtol=1e-12, atol=0)
    # above the initial torque no initial-state refutation
    sc2 = sf.load_scenario(_paper_tau_max(tmp_path, 600.0))
    c2 = run_certificates(sc2, sf.derive(sc2), t_final=sc2.simulation.t_final,
                          only=("certify.bounds",)).certificates[0]
    assert not (c2.counterexample or {}).get("initial_state")


def test_saturation_witness_lies_in_the_proven_ball(tmp_path):
    """With a proven invariance certificate (m = 0.5, ||W_hat - W*|| <= 0.2; given here), a saturating witness is a
    counterexample only inside that ball (the search runs on its bounding box): the counterexample's W_hat is
    within 0.2 of W* and the design's ordinary tau reproduces |tau| >= tau_max there (old: a box corner)."""
    from symfunnel.certificates.bounds import certify_bounds
    from symfunnel.certificates.problem import Budget, Context
    from symfunnel.certificates.result import Certificate
    sc0 = sf.load_scenario("paper")
    d0 = sf.derive(sc0)
    W = np.zeros((d0.n_regressor, d0.n))
    r = 0.2

    def run(path):
        sc = sf.load_scenario(path)
        d = sf.derive(sc)
        ctx = Context(sc, d, 2.0, parameter_box(sc), W, None)
        ctx.results["certify.invariance"] = Certificate("certify.invariance", "proven", "given",
                                                        extra={"m": 0.5, "w_hat_radius": r})
        return certify_bounds(ctx, Budget(2e6)), d
    base, _ = run(_paper_tau_max(tmp_path, 1e9))
    c, d = run(_paper_tau_max(tmp_path, float(0.5 * base.upper)))
    assert c.status == "refuted"
    ce = c.counterexample
    assert np.linalg.norm(np.asarray(ce["w_hat"], float) - W) <= r
    assert max(abs(v) for v in ce["e_over_F"]["e1"] + ce["e_over_F"]["e2"]) <= 0.5 + 1e-12
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(ce["t"]))
    vals = {"t": ce["t"], "q": ce["q"], "dq": ce["dq"], "qd": qd, "dqd": dqd, "ddqd": ddqd,
            **{k: np.asarray(ce[k], float) for k, _ in d.states}}
    tau = np.asarray(d.function("tau")(*[vals[k] for k in d.inputs_of("tau")]), float).ravel()
    assert np.max(np.abs(tau)) >= 0.5 * base.upper


# --- regularity proven at load, not sampled --------------------------------------------------------------

NONE = "tests/data/certify_none.toml"


def _none_with(tmp_path, reference=None, funnel_e1=None, name="r.toml"):
    from pathlib import Path
    raw = copy.deepcopy(sf.load_scenario(str(Path(__file__).resolve().parent.parent / NONE)).raw)
    if reference is not None:
        raw["reference"]["q"] = reference
    if funnel_e1 is not None:
        raw["funnel"]["e1"] = {"F": funnel_e1}
    return write(tmp_path, raw, name)


@pytest.mark.parametrize("reference, funnel, key, why", [
    (["0.3*sin(t) + 0.2*sign(t - 1)", "0.2*cos(t)"], None, "reference.q[0]", "argument of sign"),
    (["0.3*abs(sin(2*t))", "0.2*cos(t)"], None, "reference.q[0]", "argument of abs"),
    (["0.2*cos(t)", "min(t, 1)"], None, "reference.q[1]", "argument of min"),
    (["sqrt((t - 1)^2)", "0.2*cos(t)"], None, "reference.q[0]", "argument of abs"),
    (None, "0.1 - 0.099*sign(t - 1)", "funnel.e1.F", "argument of sign"),
    (None, "(0.2*exp(-t) + 0.01)*(1 - exp(-((t - 1.00321)/1e-6)^2))", "funnel.e1.F", "not proven positive"),
])
def test_kinks_jumps_and_dips_are_refused_at_load_with_the_key(tmp_path, capsys, reference, funnel, key, why):
    """The issue's examples (q_d or F switching inside [0, T], and the funnel that touches 0 between grid points)
    pass the old loader; now `symfunnel certify` exits 2 with one line naming the key and why."""
    from symfunnel.cli import main
    from symfunnel.core.errors import InputError
    path = _none_with(tmp_path, reference, funnel)
    with pytest.raises(InputError) as ei:
        sf.load_scenario(path)
    assert ei.value.key == key and why in str(ei.value)
    capsys.readouterr()
    assert main(["certify", path, "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and key in err and "Traceback" not in err


def test_the_pinch_funnel_really_touches_zero():
    """Independent of the loader: the pinch F is exactly 0 at t = 1.00321 (mpmath) and positive on the old grid."""
    import mpmath
    F = lambda t: (0.2 * mpmath.exp(-t) + 0.01) * (1 - mpmath.exp(-((t - mpmath.mpf("1.00321")) / mpmath.mpf("1e-6")) ** 2))
    assert F(mpmath.mpf("1.00321")) == 0
    grid = np.linspace(0.0, 5.0, 2001)
    assert min(float(F(mpmath.mpf(float(t)))) for t in grid) > 0.009


def test_smooth_uses_of_abs_and_max_are_accepted_and_audit_runs(tmp_path, capsys):
    """abs and max of arguments that never reach their switch on [0, T] are smooth: accepted, and the audit's
    sympy derivatives (whose sign / Heaviside would carry DiracDelta) run and pass."""
    from symfunnel.cli import main
    path = _none_with(tmp_path, ["0.3*abs(2 + sin(2*t)) - 0.6", "0.2*cos(t)"],
                      "0.2*exp(-t) + 0.05 + 0.01*max(sin(t), -2)")
    sc = sf.load_scenario(path)
    assert sc.reference[0].text.startswith("0.3*abs")
    capsys.readouterr()
    assert main(["audit", path]) == 0
    assert "reference.derivatives" in capsys.readouterr().out


def test_prove_on_horizon_against_known_roots():
    """prove_on_horizon: t - c (c drawn uniformly in (0, T)) fails 'nonzero' on a box containing c; exp(-t) + 1e-3
    is proven positive; 1/(t - c) fails 'finite' near c; floor(t/2) fails 'same_floor' at t = 2 and 4."""
    from symfunnel.sx.regularity import prove_on_horizon
    t = ca.SX.sym("t")
    rng = np.random.default_rng(3)
    for c in rng.uniform(0.1, 4.9, 8):
        f = ca.Function("g", [t], [ca.vertcat(t - c, ca.exp(-t) + 1e-3, 1 / (t - c))])
        fails = prove_on_horizon(f, ["nonzero", "positive", "finite"], 5.0)
        assert [x.output for x in fails] == [0, 2]
        for x in fails:
            assert x.t_lo <= c <= x.t_hi and x.t_hi - x.t_lo < 1e-6
    f = ca.Function("g", [t], [(t + 0.5) / 2])
    (x,) = prove_on_horizon(f, ["same_floor"], 5.0)
    assert x.t_lo <= 1.5 <= x.t_hi
    assert prove_on_horizon(f, ["same_floor"], 1.4) == []


# --- the run-time self-check ------------------------------------------------------------------------------

def _cheap_none(only):
    from pathlib import Path
    sc = sf.load_scenario(str(Path(__file__).resolve().parent.parent / NONE))
    return run_certificates(sc, sf.derive(sc), t_final=2.0, only=only,
                            work={"certify.bounds": 2e6, "certify.invariance": 2e6})


_EXP_C = "rl[b] = nmax(wdn(exp(l)), 0.0); rh[b] = wup(exp(xh[b]));"


def _unsound_exp(monkeypatch, which, backend, cache):
    """The batched backend's exp rule made unsound: collapsed onto its upper end [exp(hi), exp(hi)] (too narrow:
    misses every value below the top of a box), or halved (wrong at points too); in the numpy rules or in the
    compiled interpreter's C."""
    from symfunnel.sx import batch, batch_vm
    if backend == "numpy":
        good = batch._RULES["EXP"]

        def narrow(al, ah):
            lo, hi, bad = good(al, ah)
            return (hi, hi, bad) if which == "narrow" else (0.5 * lo, 0.5 * hi, bad)
        monkeypatch.setitem(batch._RULES, "EXP", narrow)
        return
    from tests.test_interval_vm import mutant_interpreter
    new = ("rh[b] = wup(exp(xh[b])); rl[b] = rh[b];" if which == "narrow"
           else "rl[b] = 0.5 * nmax(wdn(exp(l)), 0.0); rh[b] = 0.5 * wup(exp(xh[b]));")
    monkeypatch.setattr(batch_vm, "_LIB", [mutant_interpreter(cache, _EXP_C, new)])


@pytest.mark.parametrize("backend", ["c", "numpy"])
@pytest.mark.parametrize("only, which", [(("certify.bounds",), "narrow"), (("certify.invariance",), "halved")])
def test_an_unsound_interval_rule_stops_certify_with_an_internal_error(monkeypatch, tmp_path, only, which, backend):
    """With exp's rule too narrow (the funnels are exponentials, so every signal goes through it), the enclosures
    miss values the ordinary Functions attain at the searches' own witnesses: EnclosureViolation, no verdict.
    The same run with the sound rule gives a verdict; on either backend."""
    from symfunnel.certificates.selfcheck import EnclosureViolation
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", backend)
    assert _cheap_none(only).certificates[0].status in ("proven", "refuted", "undecided")
    _unsound_exp(monkeypatch, which, backend, tmp_path)
    with pytest.raises(EnclosureViolation, match="self-check failed"):
        _cheap_none(only)


def test_the_self_check_compares_with_a_tolerance_of_round_off_only():
    from symfunnel.certificates.selfcheck import EnclosureViolation, check_contains
    check_contains("x", 1.0, 2.0, 2.0 + 1e-12)
    check_contains("x", 1.0, None, math.nan)
    with pytest.raises(EnclosureViolation):
        check_contains("x", 1.0, 2.0, 2.0 + 1e-6)
    with pytest.raises(EnclosureViolation):
        check_contains("x", 1.0, None, 0.999)
    # the point evaluation's own width (a cancelling signal's round-off) widens the allowance, nothing else
    check_contains("x", 1.0, 2.0, 2.5, slack=0.6)
    with pytest.raises(EnclosureViolation):
        check_contains("x", 1.0, 2.0, 2.5, slack=0.4)


def test_a_longer_certify_horizon_is_proven_regular_too(tmp_path, capsys):
    """sign(t - 7) never switches on the file's [0, 5] (loads), but certify --t-final 8 would certify across the
    jump: exit 2 naming the key (the regularity is proven again over the longer horizon)."""
    from symfunnel.cli import main
    path = _none_with(tmp_path, ["0.3*sin(t) + 0.2*sign(t - 7)", "0.2*cos(t)"])
    sf.load_scenario(path)
    capsys.readouterr()
    assert main(["certify", path, "--t-final", "8", "--only", "input_gain", "-q"]) == 2
    err = capsys.readouterr().err
    assert "reference.q[0]" in err and "sign" in err and len(err.strip().splitlines()) == 1
    assert main(["certify", path, "--t-final", "6", "--only", "input_gain", "-q"]) == 0


def test_the_self_check_is_an_internal_error_of_the_command(monkeypatch, capsys, tmp_path):
    """`symfunnel certify` with an unsound rule: exit 3 (internal error) with one line naming the self-check, and
    no verdict on stdout."""
    from pathlib import Path

    from symfunnel.cli import main
    _unsound_exp(monkeypatch, "halved", "c", tmp_path)
    path = str(Path(__file__).resolve().parent.parent / NONE)
    code = main(["certify", path, "--only", "bounds", "--t-final", "1", "--json"])
    out, err = capsys.readouterr()
    assert code == 3 and "self-check failed" in err and "internal error" in err
    assert '"status"' not in out
