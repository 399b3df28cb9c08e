"""The one derivation against independent ones: sympy mechanics, finite differences, sympy derivatives."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import sympy

from symfunnel.design.sampling import eval_mapped, funnel_states
from symfunnel.design import derive, evaluate
from symfunnel.model.base import christoffel_C, symbols
from symfunnel.scenario import load_scenario
from symfunnel.sx.tosympy import sx_to_sympy

from .conftest import MINIMAL_2LINK, PAPER, alpha2_dot_fd_error


def _symbolic_skew_zero(M: ca.SX, q, dq, p) -> bool:
    C = christoffel_C(M, q, dq)
    N = ca.jtimes(M, q, dq) - 2 * C
    S = sx_to_sympy(N + N.T, [q, dq, p])
    return all(sympy.simplify(e) == 0 for e in S)


def test_christoffel_C_is_skew_symmetric_symbolically_2link():
    q, dq = symbols(["q1", "q2"])
    p = ca.SX.sym("p", 3)
    M = ca.blockcat([[p[0] + 2 * p[2] * ca.cos(q[1]), p[1] + p[2] * ca.cos(q[1])],
                     [p[1] + p[2] * ca.cos(q[1]), p[1]]])
    assert _symbolic_skew_zero(M, q, dq, p)


def test_christoffel_C_is_skew_symmetric_symbolically_3dof_with_prismatic():
    # A cylindrical (R-P-R) arm: configuration-dependent M in two coordinates.
    q, dq = symbols(["q1", "q2", "q3"])
    p = ca.SX.sym("p", 2)
    r = q[1]
    M = ca.blockcat([[p[0] + p[1] * r ** 2 + ca.cos(q[2]) ** 2, 0, ca.sin(q[2])],
                     [0, p[1], 0],
                     [ca.sin(q[2]), 0, 1 + p[1] * r]])
    assert _symbolic_skew_zero(M, q, dq, p)


def test_non_christoffel_C_is_not_skew_symmetric():
    """The check is not vacuous: the printed eq. 41 form of C breaks Property 1 symbolically."""
    q, dq = symbols(["q1", "q2"])
    M = ca.blockcat([[3 + 2 * ca.cos(q[1]), 1 + ca.cos(q[1])], [1 + ca.cos(q[1]), 1]])
    h = -ca.sin(q[1])
    C = ca.blockcat([[2 * h * dq[1], h * dq[1]], [-h * dq[1], 0]])
    N = ca.jtimes(M, q, dq) - 2 * C
    S = sx_to_sympy(N + N.T, [q, dq])
    assert any(sympy.simplify(e) != 0 for e in S)


def test_paper_M_with_christoffel_C_matches_lagrange(write_scenario):
    """Paper eq. 40 with C derived from M equals an independent sympy.physics.mechanics derivation."""
    from sympy.physics.mechanics import LagrangesMethod, Particle, Point, ReferenceFrame, dynamicsymbols

    text = PAPER.read_text()
    start = text.index("# eq. 41 exactly as printed")
    end = text.index('G = ["0", "0"]')
    sc = load_scenario(write_scenario(text[:start] + text[end:]))
    assert sc.model.C_source == "christoffel"
    prm = sc.model.parameter_dict()

    # Point masses: m1 at l1/2, m2 at l1 (joint 2), m3 at l2/2 on link 2, m4 at l2 (the tip), relative q2.
    q1, q2 = dynamicsymbols("q1 q2")
    dq1, dq2 = dynamicsymbols("q1 q2", 1)
    N = ReferenceFrame("N")
    O = Point("O")
    O.set_vel(N, 0)
    l1, l2 = prm["l1"], prm["l2"]

    def pos(r1, r2):
        return (r1 * sympy.cos(q1) + r2 * sympy.cos(q1 + q2)) * N.x + (r1 * sympy.sin(q1) + r2 * sympy.sin(q1 + q2)) * N.y

    parts = []
    for i, (r1, r2, m) in enumerate([(l1 / 2, 0, prm["m1"]), (l1, 0, prm["m2"]), (l1, l2 / 2, prm["m3"]),
                                     (l1, l2, prm["m4"])]):
        P = O.locatenew(f"P{i}", pos(r1, r2))
        P.set_vel(N, P.pos_from(O).dt(N))
        parts.append(Particle(f"p{i}", P, m))
    from sympy.physics.mechanics import Lagrangian
    L = Lagrangian(N, *parts)
    lm = LagrangesMethod(L, [q1, q2])
    lm.form_lagranges_equations()
    M_L = lm.mass_matrix
    # forcing = -(C dq) for a horizontal arm (no gravity, no input)
    Cdq_L = -lm.forcing
    s_q1, s_q2, s_d1, s_d2 = sympy.symbols("s_q1 s_q2 s_d1 s_d2")
    sub = {dq1: s_d1, dq2: s_d2}
    sub2 = {q1: s_q1, q2: s_q2}
    fM = sympy.lambdify([s_q1, s_q2], M_L.subs(sub).subs(sub2))
    fC = sympy.lambdify([s_q1, s_q2, s_d1, s_d2], Cdq_L.subs(sub).subs(sub2))

    m = sc.model
    f = ca.Function("f", [m.q, m.dq], [m.numeric(m.M), m.numeric(ca.mtimes(m.C, m.dq))])
    rng = np.random.default_rng(3)
    for _ in range(100):
        qq = rng.uniform(-np.pi, np.pi, 2)
        dd = rng.uniform(-3, 3, 2)
        Ms, Cs = (np.array(v) for v in f(qq, dd))
        np.testing.assert_allclose(Ms, np.array(fM(*qq), dtype=float), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(Cs.ravel(), np.array(fC(*qq, *dd), dtype=float).ravel(), rtol=1e-10, atol=1e-12)


def _points(design, k, seed):
    pts = funnel_states(design, k, np.random.default_rng(seed), fill=0.9)
    return pts


def test_alpha2_has_no_dq(paper_design):
    free = paper_design.free_symbols("alpha2")
    assert free and not any(s.startswith("dq") and not s.startswith("dqd") for s in free)
    assert "t" in free and "q1" in free
    assert paper_design.inputs_of("alpha2") == ["t", "q", "qd", "dqd"]


def test_alpha2_dot_equals_central_differences_along_the_flow(paper_design):
    """alpha2_dot(t, q, dq) = d/dt alpha2(t, q + s dq, qd(t + s), dqd(t + s)) at s = 0."""
    worst, used = alpha2_dot_fd_error(paper_design, 300, 7, fill=0.9)
    assert used > 250
    assert worst <= 1e-6, worst


def test_alpha2_dot_equals_sympy_derivative_of_converted_alpha2(paper_design):
    d = paper_design
    n = d.n
    ins = [d.sym[k] for k in ("t", "q", "qd", "dqd")]
    A = sx_to_sympy(d.signals["alpha2"], ins)
    names = lambda prefix: sympy.symbols(" ".join(f"{prefix}{i + 1}" for i in range(n)), real=True)
    t = sympy.Symbol("t", real=True)
    q, dq, qd, dqd, ddqd = (names(p) for p in ("q", "dq", "qd", "dqd", "ddqd"))
    Ad = A.diff(t) + sum((A.diff(q[i]) * dq[i] + A.diff(qd[i]) * dqd[i] + A.diff(dqd[i]) * ddqd[i]
                          for i in range(n)), sympy.zeros(n, 1))
    B = sx_to_sympy(d.signals["alpha2_dot"], [d.sym[k] for k in ("t", "q", "dq", "qd", "dqd", "ddqd")])
    args = [t, *q, *dq, *qd, *dqd, *ddqd]
    fA, fB = sympy.lambdify(args, Ad, "numpy"), sympy.lambdify(args, B, "numpy")
    pts = _points(d, 200, 11)
    for j in range(200):
        vals = [pts["t"][0, j], *pts["q"][:, j], *pts["dq"][:, j], *pts["qd"][:, j], *pts["dqd"][:, j],
                *pts["ddqd"][:, j]]
        a, b = np.array(fA(*vals), dtype=float).ravel(), np.array(fB(*vals), dtype=float).ravel()
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def test_z1_dot_is_the_exact_derivative(paper_design):
    """z1_dot from AD equals zeta1*(F1*zeta1*de1 - z1*dF1), the hand derivation of docs/derivation.md."""
    d = paper_design
    s = d.signals
    hand = s["zeta1"] * (s["F1"] * s["zeta1"] * s["de1"] - s["z1"] * s["dF1"])
    f = ca.Function("f", [d.sym[k] for k in d.inputs], [s["z1_dot"], hand], list(d.inputs), ["a", "b"])
    pts = _points(d, 500, 5)
    a, b = eval_mapped(f, pts, 500)
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)


def test_inner_loop_cancels_to_the_designed_z_dynamics(paper_design):
    """With f_true = W_hat^T Phi (perfect estimate) the nominal closed loop gives
    V_z_dot = -sum k1 mu1 z1^2 - sum k2 mu2 z2^2 exactly (the Lyapunov argument of docs/derivation.md)."""
    d = paper_design
    s = d.signals
    Vdot = ca.dot(s["z1"], s["z1_dot"]) + ca.dot(s["z2"], s["z2_dot"])
    k1, k2 = d.constants["k1"], d.constants["k2"]
    target = -ca.dot(k1 * s["mu1"], s["z1"] ** 2) - ca.dot(k2 * s["mu2"], s["z2"] ** 2)
    # ddq of the nominal model is v - W_hat^T Phi; a perfect estimate adds W_hat^T Phi back: ddq = v
    w = d.sym["w_hat"]
    Vdot_perfect = ca.substitute(Vdot, w, ca.SX.zeros(w.shape))
    target = ca.substitute(target, w, ca.SX.zeros(w.shape))
    f = ca.Function("f", [d.sym[k] for k in d.inputs], [Vdot_perfect, target], list(d.inputs), ["a", "b"])
    pts = _points(d, 500, 9)
    a, b = eval_mapped(f, pts, 500)
    np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-8)
    assert np.all(b <= 0)


def test_evaluate_outside_funnel_gives_null_and_warning(paper_design):
    msgs = []
    out = evaluate(paper_design, {"t": 0.5, "q": [0.4, 0.2], "dq": [0.0, 0.0]}, warn=msgs.append)
    assert out["z1"] is None and out["tau"] is None and out["e1"] is not None
    assert msgs and "funnel e1" in msgs[0]


def test_evaluate_matches_functions(paper_design):
    d = paper_design
    pt = {"t": 0.7, "q": [0.19, 0.18], "dq": [0.2, 0.25]}
    qd, dqd, ddqd = (np.array(v).ravel() for v in d.reference(0.7))
    out = evaluate(d, pt, warn=lambda s: None)
    e1 = np.array(pt["q"]) - qd
    F1 = 0.18 * np.exp(-2 * 0.7) + 0.01
    np.testing.assert_allclose(out["e1"], e1, rtol=1e-14)
    np.testing.assert_allclose(out["z1"], e1 / (F1 - np.abs(e1)), rtol=1e-12)
    np.testing.assert_allclose(out["F1"], [F1, F1], rtol=1e-14)


def test_tau_is_inverse_dynamics_of_v(paper_design):
    """tau = M (v - W^T Phi) + C dq + G, so the nominal model accelerates by exactly `ddq`."""
    d = paper_design
    s = d.signals
    resid = ca.solve(s["M"], s["tau"] - ca.mtimes(s["C"], d.sym["dq"]) - s["G"]) - s["ddq"]
    f = ca.Function("f", [d.sym[k] for k in d.inputs], [resid], list(d.inputs), ["r"])
    pts = _points(d, 200, 13)
    (r,) = eval_mapped(f, pts, 200)
    scale = np.max(np.abs(eval_mapped(d.function("ddq", d.inputs), pts, 200)[0]))
    assert np.max(np.abs(r)) <= 1e-10 * max(scale, 1)


@pytest.mark.parametrize("text", [MINIMAL_2LINK.format(C="")])
def test_minimal_scenario_derives_with_defaults(write_scenario, text):
    sc = load_scenario(write_scenario(text))
    d = derive(sc)
    assert sc.model.C_source == "christoffel"
    assert d.signals["tau"].shape == (2, 1)
    assert sc.esn.size == 50 and sc.k1 == [5.0, 5.0]
