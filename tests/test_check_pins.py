"""What each check computes, pinned by numbers: for every check id a case where it must fail and a case near its
boundary where it must pass (issue "Verify the verifier", item 2). The cases are small constructed inputs -- a
one-joint design whose rho is known in closed form, a breach by 1e-3 of F on one joint only, an identity residual
of 1e-7 -- so that a check whose comparison, tolerance, index or constant is wrong fails one of them.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from symfunnel.checks import audit as A
from symfunnel.checks import theory as T
from symfunnel.checks import verify as VF
from symfunnel.checks.implementation import implementation_checks
from symfunnel.checks.lyapunov import LyapunovTrajectory
from symfunnel.core.names import AUDIT_CHECKS, CERTIFY_CHECKS, VERIFY_CHECKS
from symfunnel.deployed.loop import SampledResult
from symfunnel.design import derive
from symfunnel.scenario import load_scenario

from . import test_certify  # noqa: F401 - registers its pins (certify.*)
from . import test_containment  # noqa: F401 - registers its pins (certify.containment)
from . import test_mujoco  # noqa: F401 - registers its pins (plant.engine_agreement)
from . import test_twins  # noqa: F401 - registers its pins (funnel.consistency, reference.derivatives)
from .conftest import MINIMAL_2LINK
from .pins import PINS, pins

#: the christoffel C of MINIMAL_2LINK's M (h = -c sin q2)
CHR = [["-c*sin(q2)*dq2", "-c*sin(q2)*(dq1 + dq2)"], ["c*sin(q2)*dq1", "0"]]


def _c_table(C) -> str:
    return "C = [" + ", ".join("[" + ", ".join(f'"{x}"' for x in row) + "]" for row in C) + "]"


def _two_link(write_scenario, extra: str = "", C=None):
    text = MINIMAL_2LINK.format(C=_c_table(C) if C else "") + extra
    return load_scenario(write_scenario(text))


ONE_JOINT = """
[model]
type = "matrices"
coordinates = ["q1"]
[model.matrices]
M = [["2.0"]]
C = [["0"]]
G = ["0"]
[reference]
q = ["0.3*sin(t)"]
[initial]
q = [{q0}]
dq = [{dq0}]
[funnel.e1]
{F1}
[funnel.e2]
phi0 = 2.0
phi_inf = 0.2
a = 1.0
[controller]
k1 = 1.0
k2 = 2.0
[approximator]
type = "{approx}"
[adaptation]
gamma = 3.0
sigma = {sigma}
[simulation]
t_final = 2.0
"""


def _one_joint(write_scenario, *, q0=0.01, dq0=0.3, F1="phi0 = 0.5\nphi_inf = 0.05\na = 1.0", approx="none",
               sigma=0.1, extra=""):
    text = ONE_JOINT.format(q0=q0, dq0=dq0, F1=F1, approx=approx, sigma=sigma) + extra
    return load_scenario(write_scenario(text))


def _rng():
    return np.random.default_rng(0)


# --- the registry is complete --------------------------------------------------------------------------------

def test_every_check_id_has_a_failing_and_a_near_boundary_passing_case():
    ids = list(AUDIT_CHECKS) + list(VERIFY_CHECKS) + list(CERTIFY_CHECKS) + ["funnel.containment"]
    missing = [(cid, k) for cid in ids for k in ("fail", "pass") if not PINS.get(cid, {}).get(k)]
    assert not missing, f"check ids without a pinning case: {missing}"
    unknown = set(PINS) - set(ids)
    assert not unknown, f"pins of ids that are no check: {unknown}"


# --- model.* ---------------------------------------------------------------------------------------------

@pins("model.M_symmetric", "fail", "pass")
def test_M_symmetric_fails_on_an_asymmetry_of_1e_6_and_passes_on_the_model(write_scenario):
    import casadi as ca
    sc = _two_link(write_scenario)
    d = derive(sc)
    ok = A.check_M_symmetric(d, _rng())
    assert ok.status == "pass" and ok.method == "symbolic"
    m = sc.model
    M = ca.SX(m.M)
    M[0, 1] = M[0, 1] * (1 + 1e-6)                     # one entry off by 1e-6 relative
    object.__setattr__(m, "M", M)
    bad = A.check_M_symmetric(d, _rng())
    assert bad.status == "fail"
    assert bad.evidence["max_rel"] == pytest.approx(bad.evidence["max_abs"] / _max_abs_M(sc, bad.where["q"]),
                                                    rel=1e-9)
    assert 1e-7 < bad.evidence["max_rel"] < 1e-6


def _max_abs_M(sc, q):
    import casadi as ca
    m = sc.model
    f = ca.Function("M", [m.q, m.dq, m.p], [m.M]) if m.p.numel() else ca.Function("M", [m.q, m.dq], [m.M])
    args = [q, [0.0] * len(q)] + ([m.p_values] if m.p.numel() else [])
    return float(np.max(np.abs(np.array(f(*args)))))


@pins("model.M_positive_definite", "fail", "pass")
def test_M_positive_definite_finds_an_eigenvalue_of_minus_1e_6_at_one_joint_angle(write_scenario):
    import casadi as ca
    sc = _two_link(write_scenario)
    d = derive(sc)
    m = sc.model
    q1 = m.q[0]
    for low, status in ((-1e-6, "fail"), (1e-6, "pass")):
        # eigenvalues 1 and low + 100 sin(q1)^2: the smallest, low, only where sin(q1) = 0 (a sample rarely)
        object.__setattr__(m, "M", ca.blockcat([[ca.SX(1.0), ca.SX(0)], [ca.SX(0), low + 100 * ca.sin(q1) ** 2]]))
        c = A.check_M_pd(d, _rng())
        assert c.status == status, (low, c.detail)
        assert c.margin == pytest.approx(low, abs=1e-9)               # Nelder-Mead found the minimum
        assert abs(math.sin(c.where["q"][0])) < 1e-3


def _skew_perturbation(kind: str, eps: float):
    """C + eps A: A skew-symmetric (Property 1 kept, C dq changed) or A dq = 0 with A + A^T != 0 (the converse)."""
    if kind == "skew":
        A_ = [["0", "dq1"], ["-dq1", "0"]]
    else:
        A_ = [["dq2", "-dq1"], ["0", "0"]]
    return [[f"{CHR[i][j]} + {eps}*({A_[i][j]})" for j in range(2)] for i in range(2)]


@pins("model.skew_symmetry", "fail", "pass")
@pins("model.coriolis_consistent", "fail", "pass")
def test_skew_symmetry_and_coriolis_consistency_tell_each_other_apart(write_scenario):
    """A skew-symmetric change of C keeps Property 1 and breaks C dq; a change with A dq = 0 does the converse."""
    got = {}
    for kind in ("skew", "annihilates_dq"):
        sc = _two_link(write_scenario, C=_skew_perturbation(kind, 1e-3))
        d = derive(sc)
        got[kind] = (A.check_skew(d, _rng()), A.check_coriolis(d, _rng()))
    skew, cor = got["skew"]
    assert skew.status == "pass" and cor.status == "fail"
    skew2, cor2 = got["annihilates_dq"]
    assert skew2.status == "fail" and cor2.status == "pass"
    # the exact Christoffel C passes both, symbolically
    d = derive(_two_link(write_scenario, C=CHR))
    assert [c.status for c in (A.check_skew(d, _rng()), A.check_coriolis(d, _rng()))] == ["pass", "pass"]
    # N + N^T of the second case is 2 eps [[2 dq2 ... ]]: its largest entry, relative to the check's scale
    w = skew2.where
    dq = np.array(w["dq"])
    assert skew2.evidence["max_abs"] == pytest.approx(2e-3 * max(abs(2 * dq[1]), abs(dq[0])), rel=1e-6)


# --- funnel.parameters, funnel.initial_condition -----------------------------------------------------------

@pins("funnel.parameters", "fail", "pass")
def test_funnel_parameters_accepts_phi0_equal_to_phi_inf_and_rejects_below_on_one_joint(write_scenario):
    base = "\n[funnel.e2]\nphi0 = [1.0, {p}]\nphi_inf = [0.1, 0.1]\na = [1.0, 1.0]\n"
    ok = A.check_funnel_parameters(derive(_two_link(write_scenario, base.format(p=0.1))))
    assert ok.status == "pass"
    bad = A.check_funnel_parameters(derive(_two_link(write_scenario, base.format(p=0.1 * (1 - 1e-9)))))
    assert bad.status == "fail" and "e2 joint 2" in bad.detail and "e2 joint 1" not in bad.detail


@pins("funnel.initial_condition", "fail", "pass")
def test_initial_condition_fails_by_1e_3_of_F_on_one_joint(write_scenario):
    # F1(0) = phi0 + phi_inf = 0.55; qd(0) = 0 (0.3 sin t)
    for q0, status in ((0.55 * (1 + 1e-3), "fail"), (0.55 * (1 - 1e-3), "pass")):
        z1 = q0 / (0.55 - q0)
        dq0 = 0.3 + (-0.5 / 0.55) * q0 - 1.0 * z1               # = alpha2(0): e2(0) = 0
        d = derive(_one_joint(write_scenario, q0=q0, dq0=dq0 if status == "pass" else 0.0))
        c = A.check_funnel_initial(d)
        if status == "pass":
            assert c.status == "pass", c.detail
            assert c.margin == pytest.approx(1e-3, rel=1e-6)
        else:
            assert c.status == "fail" and "funnel e1" in c.detail and "joint 1" in c.detail
    # the e2 funnel likewise: alpha2(0) computed independently, dq0 placed 1e-3 of F2(0) outside
    d = derive(_one_joint(write_scenario, q0=0.2, dq0=0.0))
    z1 = 0.2 / (0.55 - 0.2)
    alpha2 = 0.3 + (-0.5 / 0.55) * 0.2 - 1.0 * z1                  # dqd + dF1/F1 e1 - k1 z1 at t = 0
    for off, status in ((1 + 1e-3, "fail"), (1 - 1e-3, "pass")):
        d = derive(_one_joint(write_scenario, q0=0.2, dq0=alpha2 + 2.2 * off))
        c = A.check_funnel_initial(d)
        assert c.status == status, c.detail
        assert c.evidence["alpha2(0)"][0] == pytest.approx(alpha2, rel=1e-12)
        if status == "fail":
            assert "funnel e2" in c.detail


# --- simulation.completed, funnel.containment ---------------------------------------------------------------

def _sim(status="ok", t=None, signals=None, breach=None, t_final=2.0, message="done"):
    t = np.linspace(0.0, t_final, 201) if t is None else t
    return SimpleNamespace(status=status, t=t, signals=signals or {}, breach=breach, message=message,
                           stats={"t_final": t_final, "wall_time": 0.1}, gamma=2.0)


@pins("simulation.completed", "fail", "pass")
def test_completed_fails_on_a_run_stopped_1e_3_s_early():
    ok = VF.check_completed(_sim())
    assert ok.status == "pass" and ok.where == {"t": 2.0}
    t = np.linspace(0.0, 2.0 - 1e-3, 201)
    bad = VF.check_completed(_sim("breach", t=t, breach={"time": 1.999, "funnel": "e2", "joint": 2}))
    assert bad.status == "fail" and bad.margin == pytest.approx(-1e-3, rel=1e-9)
    assert bad.where == {"t": 1.999, "funnel": "e2", "joint": 2}


def _funnel_signals(n=2, T=201, breach=None):
    """Logged signals of a run with F = 1 and |e| = 0.5 F, with one joint's margin set at one sample."""
    t = np.linspace(0.0, 2.0, T)
    s = {}
    for key, mk, Fk in (("e1", "m1", "F1"), ("e2", "m2", "F2")):
        F = np.ones((T, n)) * np.linspace(1.0, 0.5, T)[:, None]
        e = 0.5 * F * np.where(np.arange(n) % 2, -1, 1)
        s[key], s[Fk] = e, F
        s[mk] = (F - np.abs(e)) / F
    if breach is not None:
        key, j, k, m = breach
        mk, Fk = {"e1": ("m1", "F1"), "e2": ("m2", "F2")}[key]
        s[key][k, j] = (1 - m) * s[Fk][k, j]
        s[mk][k, j] = m
    return t, s


@pins("funnel.containment", "fail", "pass")
def test_containment_fails_on_a_breach_by_1e_3_of_F_on_one_joint_only():
    for m, status in ((-1e-3, "fail"), (0.0, "fail"), (1e-3, "pass")):        # |e| = F is outside: F is open
        t, s = _funnel_signals(breach=("e2", 1, 150, m))
        out = {c.id: c for c in VF.check_containment(_sim(t=t, signals=s), 2)}
        assert list(out) == ["funnel.containment.e1.joint1", "funnel.containment.e1.joint2",
                             "funnel.containment.e2.joint1", "funnel.containment.e2.joint2"]
        c = out["funnel.containment.e2.joint2"]
        assert c.status == status and c.margin == pytest.approx(m, rel=1e-12, abs=1e-15)
        assert c.where == {"t": pytest.approx(t[150]), "joint": 2}
        assert c.evidence["abs_margin"] == pytest.approx(m * s["F2"][150, 1], rel=1e-9, abs=1e-15)
        for other in ("funnel.containment.e1.joint1", "funnel.containment.e1.joint2", "funnel.containment.e2.joint1"):
            assert out[other].status == "pass" and out[other].margin == pytest.approx(0.5)


@pins("funnel.containment", "fail")
def test_containment_reports_a_located_breach_on_its_joint():
    t, s = _funnel_signals()
    b = {"funnel": "e1", "joint": 1, "time": 1.2, "margin": -1e-3, "abs_error": 0.7007, "boundary": 0.7}
    out = {c.id: c for c in VF.check_containment(_sim("breach", t=t, signals=s, breach=b), 2)}
    assert out["funnel.containment.e1.joint1"].status == "fail"
    assert out["funnel.containment.e1.joint1"].margin == -1e-3
    assert [out[k].status for k in ("funnel.containment.e1.joint2", "funnel.containment.e2.joint1",
                                    "funnel.containment.e2.joint2")] == ["pass"] * 3


# --- the Lyapunov checks on constructed trajectories -------------------------------------------------------

def _traj(V, V_dot, rho, delta, *, t=None, bound=None, atol=1e-14, W_star=None, rho_lower=1.0, info=None):
    k = len(V)
    t = np.linspace(0.0, 2.0, k) if t is None else t
    nan = np.full(k, np.nan)
    return LyapunovTrajectory(
        t=t, V=np.asarray(V, float), V_dot=np.asarray(V_dot, float), rho_paper=nan, delta_paper=nan,
        rho=np.asarray(rho, float), delta=np.asarray(delta, float), V_z=np.asarray(V, float), V_w=np.zeros(k),
        scale=np.zeros(k), W_star=np.zeros((0, 1)) if W_star is None else W_star, w_star_info=info or {},
        rho_const=float(np.min(rho)), rho_const_lower=rho_lower, delta_max=float(np.max(delta)),
        rho_paper_const=math.nan, delta_paper_const=math.nan,
        bound=np.asarray(bound if bound is not None else nan, float), bound_paper=nan, extra={"atol": atol})


@pins("lyapunov.decay", "fail", "pass")
def test_decay_fails_on_a_violation_of_1e_6_relative_at_one_point_and_allows_round_off():
    k = 50
    V = np.linspace(1.0, 0.1, k)
    rho, delta = np.full(k, 2.0), np.full(k, 0.05)
    rhs = -rho * V + delta
    for excess, status in ((1e-6, "fail"), (1e-10, "pass"), (-1e-6, "pass")):      # round-off allowance 1e-8
        V_dot = rhs - 0.1 * np.abs(rhs)                   # holds with room everywhere ...
        V_dot[17] = rhs[17] + excess * abs(rhs[17])       # ... but at one point
        c = VF.check_decay(_traj(V, V_dot, rho, delta), "corrected")
        assert c.status == status, (excess, c.detail)
        assert c.where["t"] == pytest.approx(np.linspace(0, 2, k)[17])
        assert c.margin == pytest.approx(-excess * abs(rhs[17]), rel=1e-6)
        assert c.evidence["violations"] == (1 if status == "fail" else 0)
        assert c.evidence["rhs"] == pytest.approx(rhs[17])


@pins("lyapunov.bound", "fail", "pass")
def test_bound_fails_when_V_exceeds_the_integrated_bound_by_1e_6():
    from symfunnel.checks.lyapunov import integrated_bound
    t = np.linspace(0.0, 2.0, 41)
    rho, delta, V0 = 1.5, 0.3, 1.0
    B = integrated_bound(t, V0, rho, delta)
    # the closed form: V0 e^{-rho t} + delta/rho (1 - e^{-rho t})
    assert B == pytest.approx(V0 * np.exp(-rho * t) + delta / rho * (1 - np.exp(-rho * t)), rel=1e-14)
    for excess, status in ((1e-6, "fail"), (1e-9, "pass")):
        V = 0.9 * B
        V[0] = B[0]
        V[23] = B[23] * (1 + excess)
        L = _traj(V, np.zeros_like(V), np.full(41, rho), np.full(41, delta), t=t, bound=B)
        c = VF.check_bound(L)
        assert c.status == status, (excess, c.detail)
        assert c.where["t"] == pytest.approx(t[23])
        assert c.margin == pytest.approx(-excess * B[23], rel=1e-6)


def _fz(violations, margin):
    return {"samples": 100, "fill": 0.98, "t_range": [0.0, 2.0], "w_scale": 1.0,
            "corrected": {"violations": violations, "evaluated": 100, "fraction": violations / 100,
                          "worst_margin": margin, "where": {"t": 0.5, "q": [0.1], "dq": [0.2]}, "V_dot": 1.0,
                          "rhs": 1.0 - margin, "V": 0.3}}


@pins("lyapunov.falsification", "fail", "pass")
def test_falsification_kills_a_wrong_gain_at_sampled_states_and_passes_the_design(write_scenario):
    from symfunnel.checks.lyapunov import falsify
    from symfunnel.simulation.closedloop import build_closed_loop
    sc = _one_joint(write_scenario, approx="none")
    out = {}
    for mutant in (None, "flip_k2"):
        d = derive(sc, mutant=mutant)
        cl = build_closed_loop(sc, d)
        fz = falsify(cl, np.zeros((0, 1)), samples=400, seed=0, t_range=(0.0, 2.0))
        out[mutant] = VF.check_falsification(fz, "corrected")
    assert out[None].status == "pass" and out[None].evidence["evaluated"] == 400
    bad = out["flip_k2"]
    assert bad.status == "fail" and bad.evidence["violations"] > 0 and bad.margin < 0
    # the decision is the violation count, not the margin's sign alone
    assert VF.check_falsification(_fz(1, -1e-12), "corrected").status == "fail"
    assert VF.check_falsification(_fz(0, -1e-12), "corrected").status == "pass"


@pins("lyapunov.guarantee", "fail", "pass")
@pytest.mark.parametrize("transform", ["funnel", "log"])
def test_guarantee_warns_1e_3_below_its_threshold_and_passes_1e_3_above(write_scenario, transform):
    sc = _one_joint(write_scenario, extra=f'[design]\ntransform = "{transform}"\n')
    d = derive(sc)
    inverse = {"funnel": lambda u: u / (1 - u), "log": math.atanh}[transform]      # |e|/F = u -> |z|
    for m, status in ((0.05 + 1e-3, "pass"), (0.05 - 1e-3, "warn")):          # documented threshold 0.05
        z = inverse(1 - m)
        L = SimpleNamespace(rho_const_lower=2.0, delta_max=1e-9, V=np.array([z * z / 2]), w_star_info={})
        c = T.check_guarantee(d, L)
        assert c.status == status, (m, c.detail)
        assert c.margin == pytest.approx(m, rel=1e-9)
        assert c.evidence["z_bound"] == pytest.approx(z, rel=1e-12)
    # delta/rho above V(0) sets the bound: V_ult = 0.5 -> |z| <= 1
    L = SimpleNamespace(rho_const_lower=2.0, delta_max=1.0, V=np.array([0.01]), w_star_info={})
    c = T.check_guarantee(d, L)
    assert c.evidence["z_bound"] == pytest.approx(1.0) and c.evidence["delta_over_rho"] == pytest.approx(0.5)
    assert T.check_guarantee(d, None).status == "warn"


@pins("lyapunov.rho_positive", "fail", "pass")
def test_rho_positive_is_the_closed_form_min_of_the_three_rates(write_scenario):
    # k1 = 1, sup F1 = 0.55 (t = 0), k2 = 2, sup F2 = 2.2: min(2/0.55, 2/2.2) = 0.909...
    d = derive(_one_joint(write_scenario, approx="none"))
    c = T.check_rho_positive(d, 2.0)
    assert c.status == "pass" and c.margin == pytest.approx(2.0 / 2.2, rel=1e-12)
    assert c.where["binding"] == "k2/sup F2"
    assert c.evidence["terms"]["2 k1/sup F1"] == pytest.approx(2.0 / 0.55, rel=1e-12)
    # a funnel that grows: sup F1 is at t = pi/2, not at t = 0 (no monotonicity assumed)
    d = derive(_one_joint(write_scenario, approx="none", F1='F = "0.5 + 3*sin(t)"'))
    c = T.check_rho_positive(d, 2.0)
    assert c.margin == pytest.approx(2.0 / 3.5, rel=1e-5) and c.where["binding"] == "2 k1/sup F1"
    # with weights: sigma gamma; sigma = 1e-9 still decays (gamma = 3), sigma = 0 does not
    d = derive(_one_joint(write_scenario, approx="rbf", sigma=1e-9, extra="[rbf]\nsize = 4\n"))
    c = T.check_rho_positive(d, 2.0)
    assert c.status == "pass" and c.margin == pytest.approx(3e-9, rel=1e-12) and c.where["binding"] == "sigma Gamma"
    d = derive(_one_joint(write_scenario, approx="rbf", sigma=0.0, extra="[rbf]\nsize = 4\n"))
    c = T.check_rho_positive(d, 2.0)
    assert c.status == "fail" and c.margin == 0.0


@pins("design.identity.vdot", "fail", "pass")
def test_identity_fails_on_a_residual_of_1e_7_relative_and_passes_on_round_off(write_scenario):
    import casadi as ca
    sc = _one_joint(write_scenario, approx="rbf", extra="[rbf]\nsize = 4\n")
    d = derive(sc)
    ok = T.check_identity(d, _rng(), samples=300)
    assert ok.status == "pass" and ok.evidence["max_relative_residual"] < 1e-12
    got = {}
    for rel in (3e-9, 1e-13):
        bad = derive(sc)
        bad.signals["tau"] = bad.signals["tau"] * (1 + rel) + rel * ca.SX(1.0)
        got[rel] = T.check_identity(bad, _rng(), samples=300)
    res = got[3e-9].evidence["max_relative_residual"]
    assert got[3e-9].status == "fail" and 1e-8 < res < 1e-6             # fails at 1e-9, would pass at 1e-6
    assert got[1e-13].status == "pass"
    assert got[3e-9].margin == pytest.approx(T.IDENTITY_TOL - res)


@pins("assumption.input_gain", "fail", "pass")
def test_input_gain_changes_sign_where_numpy_says_it_does(write_scenario):
    """Constant M, slopes 1 (left) and s (right) on both joints: lambda_min(sym(M^-1 D M)) over the four slope
    combinations, computed here with numpy, crosses 0 at s*; the check must fail just beyond and pass just before."""
    Mc = np.array([[3.0, 1.0], [1.0, 0.5]])

    def lam(s):
        out = np.inf
        for d in ((1, 1), (1, s), (s, 1), (s, s)):
            G = np.linalg.solve(Mc, np.diag(d) @ Mc)
            out = min(out, np.linalg.eigvalsh(0.5 * (G + G.T))[0])
        return out
    lo, hi = 1e-3, 1.0                       # lam(hi) > 0 > lam(lo)
    assert lam(hi) > 0 > lam(lo)
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if lam(mid) < 0 else (lo, mid)
    s_star = hi
    for s, status in ((s_star * (1 - 1e-3), "fail"), (s_star * (1 + 1e-3), "pass")):
        text = f"""
[model]
type = "matrices"
coordinates = ["q1", "q2"]
[model.matrices]
M = [["3.0", "1.0"], ["1.0", "0.5"]]
C = [["0", "0"], ["0", "0"]]
G = ["0", "0"]
[reference]
q = ["0.3*sin(t)", "0.2*cos(t)"]
[initial]
q = [0.0, 0.2]
dq = [0.3, 0.0]
[plant.dead_zone]
b_l = -0.1
b_r = 0.1
left = "u - b_l"
right = "{s!r}*(u - b_r)"
"""
        d = derive(load_scenario(write_scenario(text)))
        c = T.check_input_gain(d, _rng(), samples=20)
        assert c.status == status, (s, c.detail)
        assert c.margin == pytest.approx(lam(s), rel=1e-6, abs=1e-12)
        assert c.evidence["slope_combinations"] == 4


# --- bounded.* --------------------------------------------------------------------------------------------------

def _bounded_run(tau_late=1.1, w_scale=0.5, x_scale=0.5):
    T_ = 100
    t = np.linspace(0.0, 2.0, T_)
    tau = np.ones((T_, 2))
    tau[10, 1] = -10.0                       # the early peak, joint 2
    tau[60, 1] = -10.0                       # as high in the third quarter: no growth at the end (issue 44)
    tau[80, 0] = 10.0 * tau_late             # the last quarter's peak, joint 1
    w = np.zeros((T_, 3, 1))
    w[:, 0, 0] = 0.1
    w[60, 0, 0] = w_scale
    x = np.zeros((T_, 4))
    x[30, 2] = -x_scale
    return _sim(t=t, signals={"tau": tau, "w_hat": w, "x_esn": x})


DESIGN_LEAK2 = SimpleNamespace(scenario=SimpleNamespace(esn=SimpleNamespace(leak=2.0)))     # box 1/leak = 0.5


@pins("bounded.tau", "fail", "pass")
def test_tau_growth_fails_1e_3_above_its_allowance():
    top = 1.1                                  # documented: at most 1.1 x the peak before the last quarter
    for f, status in ((top * (1 + 1e-3), "fail"), (top * (1 - 1e-3), "pass")):
        c = VF.check_bounded(_bounded_run(tau_late=f), DESIGN_LEAK2, None)[0]
        assert c.id == "bounded.tau" and c.status == status
        assert c.margin == pytest.approx(0.1 - (f - 1), rel=1e-9)
        assert c.evidence["early_peak"] == 10.0 and c.where == {"t": pytest.approx(2.0 * 80 / 99), "joint": 1}
    r = _bounded_run()
    r.signals["tau"][5, 0] = np.nan
    assert VF.check_bounded(r, DESIGN_LEAK2, None)[0].status == "fail"
    # the last quarter starts at sample int(0.75 T) = 75 of 100: a peak at 74 is "before", one at 75 "late"
    r = _bounded_run(tau_late=0.1)
    r.signals["tau"][10, 1] = 1.0
    r.signals["tau"][60, 1] = 1.0
    r.signals["tau"][74, 0] = 10.0
    r.signals["tau"][75, 0] = 10.0 * 1.1 * (1 - 1e-3)
    assert VF.check_bounded(r, DESIGN_LEAK2, None)[0].status == "pass"
    r.signals["tau"][74, 0] = 1.0
    assert VF.check_bounded(r, DESIGN_LEAK2, None)[0].status == "fail"


@pins("bounded.w_hat", "fail", "pass")
def test_w_hat_fails_1e_3_outside_the_lyapunov_bound():
    W_star = np.array([[0.3], [0.0], [0.0]])
    B = np.full(100, 0.5)
    L = _traj(np.full(100, 0.5), np.zeros(100), np.ones(100), np.ones(100), bound=B, atol=1e-8, W_star=W_star)
    lim = 0.3 + math.sqrt(2 * 2.0 * (0.5 + 100 * 1e-8))             # ||W*|| + sqrt(2 gamma (B + allowance))
    for f, status in ((1 + 1e-3, "fail"), (1 - 1e-3, "pass")):
        c = VF.check_bounded(_bounded_run(w_scale=lim * f), DESIGN_LEAK2, L)[1]
        assert c.id == "bounded.w_hat" and c.status == status, c.detail
        assert c.margin == pytest.approx(lim * (1 - f), rel=1e-6)
        assert c.where["t"] == pytest.approx(2.0 * 60 / 99)


@pins("bounded.x_esn", "fail", "pass")
def test_x_esn_fails_1e_3_outside_its_box_and_passes_within_round_off():
    for f, status in ((1 + 1e-3, "fail"), (1 + 1e-7, "fail"), (1 + 1e-10, "pass"), (1 - 1e-3, "pass")):
        c = VF.check_bounded(_bounded_run(x_scale=0.5 * f), DESIGN_LEAK2, None)[2]
        assert c.id == "bounded.x_esn" and c.status == status
        assert c.margin == pytest.approx(0.5 - 0.5 * f, abs=1e-15)
        assert c.where == {"t": pytest.approx(2.0 * 30 / 99), "unit": 3}


# --- the deployed controller's checks on constructed sampled runs -----------------------------------------------

def _sampled(margins, tau, tau_max=None, status="ok"):
    K = tau.shape[0]
    n = tau.shape[1]
    return SampledResult("s", 100.0, np.arange(K + 1) / 100.0, np.zeros((K + 1, n)), np.zeros((K + 1, n)), tau,
                         margins, status, "done", None if status == "ok" else {"margin": float(np.min(margins))},
                         tau_max, 0.1)


@pins("implementation.containment", "fail", "pass")
def test_implementation_containment_fails_at_a_margin_of_minus_1e_3_on_one_joint():
    for m, status in ((-1e-3, "fail"), (1e-3, "pass")):
        M = np.full((11, 4), 0.5)
        M[7, 3] = m                           # e2 of joint 2
        (c,) = implementation_checks(None, None, result=_sampled(M, np.zeros((10, 2))))
        assert c.status == status and c.margin == pytest.approx(m)
    (c,) = implementation_checks(None, None, result=_sampled(np.full((11, 4), 0.5), np.zeros((10, 2)),
                                                             status="breach"))
    assert c.status == "fail"


@pins("implementation.saturation", "fail", "pass")
def test_saturation_counts_the_samples_at_tau_max_per_joint():
    tau = np.zeros((10, 2))
    tau[3, 1] = -5.0                          # at the limit, one sample of joint 2
    tau[4, 0] = 5.0 * (1 - 1e-6)              # just below, joint 1
    c = implementation_checks(None, None, result=_sampled(np.full((11, 4), 0.5), tau, tau_max=(5.0, 5.0)))[1]
    assert c.status == "fail" and c.evidence["saturated_fraction"] == [0.0, 0.1] and c.margin == -0.1
    tau[3, 1] = -5.0 * (1 - 1e-6)
    c = implementation_checks(None, None, result=_sampled(np.full((11, 4), 0.5), tau, tau_max=(5.0, 5.0)))[1]
    assert c.status == "pass" and c.evidence["saturated_fraction"] == [0.0, 0.0]


def test_identity_sees_the_unknown_term_eps(write_scenario, monkeypatch):
    """A target form whose eps coupling is wrong (z2 instead of mu2 z2) fails the identity: eps is drawn, not 0."""
    import casadi as ca
    sc = _one_joint(write_scenario, approx="none")
    d = derive(sc)
    real = type(d.variant).lyapunov

    def wrong(self, design, W_star, eps):
        out = real(self, design, W_star, eps)
        s = design.signals
        out["target"] = out["target"] - ca.dot(s["mu2"] * s["z2"], eps) + ca.dot(s["z2"], eps)
        return out
    monkeypatch.setattr(type(d.variant), "lyapunov", wrong)
    c = T.check_identity(d, _rng(), samples=200)
    assert c.status == "fail" and c.evidence["max_relative_residual"] > 1e-3


def test_the_variants_rho_and_delta_in_closed_form_at_a_point(write_scenario):
    """rho = min(2 k1 mu1, k2 mu2, sigma gamma), delta = sigma/2 ||W*||^2 + mu2 eps^2/(2 k2), mu = F/(F - |e|)^2, at
    one state of a one-joint design (k1 = 1, k2 = 2, gamma = 3, sigma = 0.1), computed by hand."""
    import casadi as ca
    sc = _one_joint(write_scenario, approx="rbf", sigma=10.0, extra="[rbf]\nsize = 4\n")
    d = derive(sc)
    nr = d.n_regressor
    Ws = np.linspace(-0.5, 0.7, nr).reshape(nr, 1)
    eps = 0.3
    lyap = d.variant.lyapunov(d, ca.DM(Ws), ca.DM([eps]))
    f = ca.Function("l", [d.sym[k] for k in d.inputs], [lyap["rho"], lyap["delta"], lyap["V"]])
    t, q, dq = 0.4, 0.12, -0.2
    qd, dqd, ddqd = 0.3 * math.sin(t), 0.3 * math.cos(t), -0.3 * math.sin(t)
    w_hat = np.linspace(0.1, 0.2, nr).reshape(nr, 1)
    rho, delta, V = (float(v) for v in f(t, q, dq, qd, dqd, ddqd, w_hat))
    F1, dF1 = 0.5 * math.exp(-t) + 0.05, -0.5 * math.exp(-t)
    F2 = 2.0 * math.exp(-t) + 0.2
    e1 = q - qd
    z1 = e1 / (F1 - abs(e1))
    mu1 = F1 / (F1 - abs(e1)) ** 2
    alpha2 = dqd + dF1 / F1 * e1 - 1.0 * z1
    e2 = dq - alpha2
    z2 = e2 / (F2 - abs(e2))
    mu2 = F2 / (F2 - abs(e2)) ** 2
    assert 2.0 * mu2 < min(2 * 1.0 * mu1, 10.0 * 3.0)            # the k2 term binds at this state
    assert rho == pytest.approx(min(2 * 1.0 * mu1, 2.0 * mu2, 10.0 * 3.0), rel=1e-12)
    assert delta == pytest.approx(10.0 / 2 * np.sum(Ws ** 2) + mu2 * eps ** 2 / (2 * 2.0), rel=1e-12)
    assert V == pytest.approx(0.5 * z1 ** 2 + 0.5 * z2 ** 2 + np.sum((Ws - w_hat) ** 2) / (2 * 3.0), rel=1e-12)
    # the constant lower bound: mu >= 1/sup F, sup F1 = 0.55 and sup F2 = 2.2 at t = 0
    assert d.variant.rho_lower(np.array([0.55]), np.array([2.2])) == pytest.approx(min(2 / 0.55, 2 / 2.2, 30.0))
    assert d.variant.rho_lower(np.array([3.5]), np.array([2.2])) == pytest.approx(2 / 3.5)    # the k1 term binds


# --- the generated step's discrete update, saturation and projection -------------------------------------------

def _esn_one_joint(write_scenario):
    return _one_joint(write_scenario, approx="esn", extra="[esn]\nsize = 5\nleak = 2.0\ntime_constant = 0.1\n")


def test_step_saturates_both_signs_and_projects_both_sides(write_scenario):
    from symfunnel.emit.step import CLIP, step_core
    sc = _esn_one_joint(write_scenario)
    d = derive(sc)
    free, sat = step_core(d, None), step_core(d, 0.5)
    x0 = np.full(5, 0.1)
    w0 = np.full(d.sym["w_hat"].shape, 0.05)
    etd = [1e-3, 1e-3]
    t = 0.3
    qd = 0.3 * math.sin(t)
    F1 = 0.5 * math.exp(-t) + 0.05
    taus = []
    for e in (0.4 * F1, -0.4 * F1):                       # torques of both signs
        tau = float(free(t, qd + e, 0.0, x0, w0, etd)[0])
        got = float(sat(t, qd + e, 0.0, x0, w0, etd)[0])
        assert got == pytest.approx(math.copysign(min(abs(tau), 0.5), tau), rel=1e-14)
        taus.append(tau)
    assert max(abs(v) for v in taus) > 0.5 and taus[0] * taus[1] < 0
    # outside the funnel on either side: the design at the state projected onto CLIP F1, and margin 1 - |e|/F
    for sign in (1, -1):
        out = free(t, qd + sign * 1.5 * F1, 0.0, x0, w0, etd)
        ref = free(t, qd + sign * CLIP * F1, 0.0, x0, w0, etd)
        assert float(out[0]) == pytest.approx(float(ref[0]), rel=1e-12)
        assert float(out[3][0]) == pytest.approx(1 - 1.5, rel=1e-12)


def test_step_advances_the_controller_states_by_exponential_euler(write_scenario):
    """x+ = x + phi(leak/tc) x_dot, W+ = W + phi(gamma sigma) W_dot, phi(l) = (1 - e^{-l h})/l, by hand; the
    reservoir update is a convex combination, so it stays in [-1/leak, 1/leak] even at a long period."""
    from symfunnel.emit.step import etd_factors, step_function
    sc = _esn_one_joint(write_scenario)
    d = derive(sc)
    rate = 50.0
    h = 1 / rate
    phi_x = (1 - math.exp(-(2.0 / 0.1) * h)) / (2.0 / 0.1)
    phi_w = (1 - math.exp(-(3.0 * 0.1) * h)) / (3.0 * 0.1)
    assert etd_factors(sc, rate) == pytest.approx((phi_x, phi_w), rel=1e-14)
    step = step_function(d, rate)
    t, q, dq = 0.3, 0.3 * math.sin(0.3) + 0.02, 0.25
    x0 = np.array([0.4, -0.45, 0.1, 0.0, 0.49])
    w0 = np.full(d.sym["w_hat"].shape, 0.05)
    rates = d.function("rates", d.inputs, ["x_esn_dot", "w_hat_dot"])
    ref = [np.array(v).ravel() for v in d.reference(t)]
    xdot, wdot = (np.array(v) for v in rates(t, q, dq, *ref, x0, w0))
    out = step(t, q, dq, x0, w0)
    assert np.array(out[1]).ravel() == pytest.approx(x0 + phi_x * xdot.ravel(), rel=1e-13)
    assert np.array(out[2]) == pytest.approx(w0 + phi_w * wdot, rel=1e-13)
    slow = step_function(d, 0.5)                          # h = 2 s >> 2 tc/leak: explicit Euler would leave the box
    x = x0
    for k in range(20):
        x = np.array(slow(t + 2 * k, q, dq, x, w0)[1]).ravel()
        assert np.all(np.abs(x) <= 0.5 + 1e-12)


# --- the campaign's statistics and the rate search --------------------------------------------------------------

def test_clopper_pearson_is_scipys_exact_interval_on_both_sides():
    from scipy.stats import binomtest

    from symfunnel.campaigns.statistics import clopper_pearson
    for k, n in ((0, 20), (3, 50), (17, 40), (40, 40)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
        assert clopper_pearson(k, n) == pytest.approx([ci.low, ci.high], rel=1e-9, abs=1e-15)


def test_summary_leaves_failed_runs_out_of_the_breach_probability():
    import pyarrow as pa

    from symfunnel.campaigns.statistics import summarize
    rows = {"run": [0, 1, 2, 3, 4], "x": [0.1, 0.2, 0.3, 0.4, 0.5],
            "status": ["ok", "breach", "failed", "ok", "breach"], "t_end": [2.0, 1.0, 0.0, 2.0, 0.5],
            "min_margin_e1": [0.5, -1e-3, math.nan, 0.4, 0.2], "min_margin_e2": [0.3, 0.2, math.nan, 0.1, -0.2],
            "max_abs_tau": [1.0, 2.0, math.nan, 3.0, 4.0]}
    s = summarize(pa.table(rows), ["x"])
    assert s["breaches"] == 2 and s["failed"] == 1 and s["breach_probability"] == pytest.approx(2 / 4)
    assert s["worst_run"] == 4 and s["worst"]["min_margin"] == -0.2 and s["worst"]["values"] == {"x": 0.5}


def test_summary_ranks_a_run_without_a_post_transient_margin_by_its_whole_run_margin():
    """Runs that ended before their settle time (NaN after the transient) still have a worst run: by the whole run's
    margin, beside the others' post-transient ones."""
    import pyarrow as pa

    from symfunnel.campaigns.statistics import summarize
    nan = math.nan
    rows = {"run": [0, 1, 2], "x": [0.1, 0.2, 0.3], "status": ["ok", "ok", "ok"], "t_end": [1.0, 1.0, 1.0],
            "min_margin_e1": [0.5, 0.3, 0.6], "min_margin_e2": [0.4, 0.35, 0.2], "max_abs_tau": [1.0, 2.0, 3.0],
            "min_margin_e1_after_transient": [nan, nan, nan], "min_margin_e2_after_transient": [nan, nan, nan]}
    s = summarize(pa.table(rows), ["x"])
    assert s["worst_run"] == 2 and s["worst"]["min_margin"] == 0.2
    rows["min_margin_e1_after_transient"] = [0.55, nan, 0.7]
    rows["min_margin_e2_after_transient"] = [0.45, nan, 0.65]
    s = summarize(pa.table(rows), ["x"])
    assert s["worst_run"] == 1 and s["worst"]["min_margin"] == 0.3          # its whole run: 0.3 < 0.45, 0.65


def test_row_of_takes_the_located_breach_margin_of_its_funnel():
    from symfunnel.campaigns.campaign import row_of
    from symfunnel.simulation.margins import margin_summary
    sig = {"m1": np.array([[0.4, 0.5]]), "m2": np.array([[0.3, 0.2]]), "tau": np.array([[1.0, -3.0]])}
    t = np.array([0.0, 1.0])
    # settled at t = 0.5: the post-transient minima are the second sample's (m1 0.5, m2 0.2, then the breach's)
    r = SimpleNamespace(signals=sig, breach={"funnel": "e2", "margin": -1e-3}, status="breach", t=t,
                        margins=lambda: margin_summary(t, sig["m1"].T, sig["m2"].T, 0.5, "declared"))
    row = row_of(r, 7, ["x"], [0.5])
    assert row["min_margin_e2"] == -1e-3 and row["min_margin_e1"] == 0.4 and row["max_abs_tau"] == 3.0
    assert row["min_margin_e2_after_transient"] == -1e-3 and row["min_margin_e1_after_transient"] == 0.5
    assert row["settle_time"] == 0.5 and row["status"] == "breach" and row["run"] == 7


def test_rate_search_brackets_and_bisects_to_within_its_tolerance(monkeypatch):
    """A loop whose margin is known as a function of the rate (holds with margin >= 0.05 above 1234 Hz)."""
    import symfunnel.deployed.loop as loop
    from symfunnel.deployed.rate import min_rate

    def fake(scenario, design, *, rate_hz, t_final=None, search_build=None):
        m = 0.05 + 0.1 * math.log(rate_hz / 1234.0)
        return SimpleNamespace(ok=m > -0.3, min_margin=m, min_margin_after_transient=m, stats={},
                               status="ok" if m > -0.3 else "breach", breach=None)
    monkeypatch.setattr(loop, "simulate_sampled", fake)
    monkeypatch.setattr(loop, "min_rate_hz", lambda scenario: 1.0)          # no plant-step floor in this fake
    sc = SimpleNamespace(file=None, implementation=None)
    for start in (100.0, 1e5):
        out = min_rate(sc, None, margin=0.05, rel_tol=0.05, start=start)
        assert 1234.0 <= out["min_rate_hz"] <= 1234.0 * 1.05
        tried = {round(r["rate_hz"], 6): r["holds"] for r in out["tried"]}
        assert all(h == (r >= 1234.0 * (1 - 1e-12)) for r, h in tried.items())
        assert tried[round(out["min_rate_hz"], 6)]
    # a run that breaches never holds, whatever its margin before the breach
    monkeypatch.setattr(loop, "simulate_sampled",
                        lambda s, d, *, rate_hz, t_final=None, **kw: SimpleNamespace(ok=rate_hz > 500, min_margin=0.9,
                                                                              min_margin_after_transient=0.9,
                                                                              stats={}, status="ok",
                                                                              breach=None))
    out = min_rate(sc, None, margin=0.05, rel_tol=0.05, start=1000.0)
    assert 500 < out["min_rate_hz"] <= 500 * 1.05


def test_a_claim_wrong_on_one_joint_only_fails(write_scenario):
    """A printed z1 exact on joint 1 and off by 1e-3 (q2 - q1) on joint 2: the claim is judged by its worst entry."""
    text = MINIMAL_2LINK.format(C="") + '''
[[claims]]
name = "z1_joint2_wrong"
signal = "z1"
expression = "e1/(F1 - abs(e1)) + 1e-3*(q - q1)"
[[claims]]
name = "z1_right"
signal = "z1"
expression = "e1/(F1 - abs(e1))"
'''
    sc = load_scenario(write_scenario(text))
    d = derive(sc)
    bad, good = (A.check_claim(d, c, _rng()) for c in sc.claims)
    assert bad.status == "fail" and good.status == "pass"
    assert bad.evidence["exact_at_worst"][0] == pytest.approx(bad.evidence["printed_at_worst"][0], rel=1e-14)
    # refuted by the samples themselves (joint 2 disagrees almost everywhere), not left to the sympy stage behind
    # them: a claim judged by its best entry shows no disagreeing sample at all
    assert bad.method.startswith("sampled") and bad.evidence["fraction_disagreeing"] > 0.5
    assert bad.evidence["max_rel"] > 1e-3
