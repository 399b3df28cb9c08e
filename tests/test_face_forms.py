"""The e2 faces of `certify.containment` with alpha2_dot written through de1 = g + e2 (issue 45): the same function
as the design's forward-AD alpha2_dot (checked at random states against the design's own graph), and on boxes 3 %
wide of face e2 joint 1 + of paper_small_dead_zone (projection = 2) the interval bound proves most boxes, where the
AD form (dq and dq_d apart) proved 6 %; f_true's M_p^-1 by the adjugate proves more of them again.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from symfunnel.certificates import containment as C
from symfunnel.certificates.face_forms import alpha2_dot_through_e1
from symfunnel.certificates.problem import Context, controller_state_boxes
from symfunnel.certificates.projection_face import projection_face
from symfunnel.certificates.region import parameter_box
from symfunnel.pipeline import derive
from symfunnel.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent
SMALL_DZ = ROOT / "derivations" / "paper_small_dead_zone.toml"


def _design(extra=None):
    sc = load_scenario(str(SMALL_DZ)).replace({"adaptation.projection": 2.0, **(extra or {})})
    return sc, derive(sc)


def test_alpha2_dot_through_e1_is_the_designs_alpha2_dot():
    _, d = _design({"esn.size": 6})
    adot, why = alpha2_dot_through_e1(d)
    assert adot is not None, why
    sym = d.sym
    ins = [sym[k] for k in ("t", "q", "dq", "qd", "dqd", "ddqd")]
    f = ca.Function("f", ins, [adot, d.signals["alpha2_dot"]])
    rng = np.random.default_rng(3)
    for _ in range(200):
        t = rng.uniform(0, 20)
        qd = rng.uniform(-0.3, 0.3, 2)
        F1 = 0.18 * np.exp(-2 * t) + 0.01
        q = qd + rng.uniform(-0.95, 0.95, 2) * F1            # inside the e1 funnel, where z1 is defined
        a, b = (np.asarray(v, float).ravel() for v in f(t, q, rng.uniform(-2, 2, 2), qd, rng.uniform(-1, 1, 2),
                                                             rng.uniform(-1, 1, 2)))
        assert np.allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b))), (a, b)


def _proven_share(ctx, rewrite: bool, adjugate: bool = False, face: str = "e2 joint 1 +") -> float:
    """The share of 200 random boxes (3 % of the face's width in every split coordinate) of the face at m1 = 0.9,
    m2 = 0.05 on which the interval bound proves sign n < 0."""
    saved = C.with_alpha2_dot_through_e1, C.ADJUGATE
    if not rewrite:
        C.with_alpha2_dot_through_e1 = lambda design, e: (e, False)
    C.ADJUGATE = adjugate
    try:
        fc = C._Faces(ctx)
    finally:
        C.with_alpha2_dot_through_e1, C.ADJUGATE = saved
    d = ctx.design
    w, phi = projection_face(d)["w"], 7.15                    # sup ||Phi|| <= sqrt(51) (tanh states and a bias)
    W0 = np.zeros_like(d.variant.initial_states()["w_hat"])
    lw, hw = W0.copy(), W0.copy()
    lw[0, :], hw[0, :] = -w * phi, w * phi
    lo, hi = fc.box(0.1, 0.95, controller_state_boxes(ctx, (lw, hw)))
    f = next(f for f in fc.faces(lo, hi) if f["name"] == face)
    split = fc.split_indices(f["lo"], f["hi"])
    rng = np.random.default_rng(1)
    LO, HI = np.repeat(f["lo"][None], 200, 0), np.repeat(f["hi"][None], 200, 0)
    c = f["lo"][split] + rng.random((200, split.size)) * (f["hi"] - f["lo"])[split]
    half = 0.015 * (f["hi"] - f["lo"])[split]
    LO[:, split] = np.maximum(c - half, f["lo"][split])
    HI[:, split] = np.minimum(c + half, f["hi"][split])
    _, H, _ = fc.F.eval_batch(LO, HI)
    return float(np.mean(H[:, f["pos"]] < 0))


def test_e2_face_boxes_are_proven_with_alpha2_dot_through_e1():
    sc, d = _design()
    ctx = Context(sc, d, sc.simulation.t_final, parameter_box(sc), None, None, w_star_info={}, breach=None)
    after = _proven_share(ctx, True)
    before = _proven_share(ctx, False)
    assert before < 0.2 and after > 0.5, (before, after)
    # M_p^-1 by the adjugate: more of the boxes again, on both joints
    adj = _proven_share(ctx, True, adjugate=True)
    two = _proven_share(ctx, True, face="e2 joint 2 +"), _proven_share(ctx, True, adjugate=True, face="e2 joint 2 +")
    assert adj > after + 0.05 and two[1] > two[0] + 0.05, (after, adj, two)


def test_solve2_is_the_inverse():
    from symfunnel.sx.linalg import solve2
    rng = np.random.default_rng(5)
    M, b = ca.SX.sym("M", 2, 2), ca.SX.sym("b", 2)
    f = ca.Function("f", [M, b], [solve2(M, b)])
    for _ in range(50):
        A = rng.normal(size=(2, 2)) + 3 * np.eye(2)
        v = rng.normal(size=2)
        assert np.allclose(np.asarray(f(A, v), float).ravel(), np.linalg.solve(A, v), rtol=1e-12, atol=1e-12)


def test_alpha2_not_of_the_form_dqd_plus_g_of_e1_is_left_alone():
    """alpha2 with dq_d entering twice, or q beyond e1 = q - q_d, is not rewritten (the identity would not hold)."""
    from types import SimpleNamespace
    sym = {k: ca.SX.sym(k, 1) for k in ("t", "q", "dq", "qd", "dqd", "ddqd")}
    e1 = sym["q"] - sym["qd"]
    F1 = 0.1 + ca.exp(-sym["t"])
    for alpha2, why in ((2 * sym["dqd"] - 5 * e1 / F1, "depends on dq_d"),
                        (sym["dqd"] - 5 * e1 / F1 + 0.1 * sym["q"], "beyond e1"),
                        (sym["dqd"] - 5 * e1 / F1 + 0.1 * sym["dq"], "more than t and e1")):
        S = {"alpha2": alpha2, "e1": e1, "e2": sym["dq"] - alpha2}
        S["alpha2_dot"] = ca.jtimes(alpha2, ca.vertcat(sym["t"], sym["q"], sym["qd"], sym["dqd"]),
                                    ca.vertcat(1, sym["dq"], sym["dqd"], sym["ddqd"]))
        d = SimpleNamespace(signals=S, sym=sym, n=1)
        adot, reason = alpha2_dot_through_e1(d)
        assert adot is None and why in reason, reason
    # the form itself: alpha2 = dq_d + g(t, e1) is rewritten, and equals the AD form at a point
    alpha2 = sym["dqd"] - 5 * e1 / F1 + e1 * ca.sin(sym["t"])
    S = {"alpha2": alpha2, "e1": e1, "e2": sym["dq"] - alpha2}
    S["alpha2_dot"] = ca.jtimes(alpha2, ca.vertcat(sym["t"], sym["q"], sym["qd"], sym["dqd"]),
                                ca.vertcat(1, sym["dq"], sym["dqd"], sym["ddqd"]))
    adot, _ = alpha2_dot_through_e1(SimpleNamespace(signals=S, sym=sym, n=1))
    f = ca.Function("f", list(sym.values()), [adot - S["alpha2_dot"]])
    assert abs(float(f(0.7, 0.3, -1.2, 0.25, 0.4, 2.0))) < 1e-12
