"""The e2 faces of `certify.containment` with alpha2_dot written through de1 = g + e2 (issue 45): the same function
as the design's forward-AD alpha2_dot (checked at random states against the design's own graph), and on boxes 3 %
wide of face e2 joint 1 + of paper_small_dead_zone (projection = 2) the interval bound proves most boxes, where the
AD form (dq and dq_d apart) proved 6 %.
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


def _proven_share(ctx, rewrite: bool) -> float:
    """The share of 200 random boxes (3 % of the face's width in every split coordinate) of face e2 joint 1 + at
    m1 = 0.9, m2 = 0.05 on which the interval bound proves sign n < 0."""
    saved = C.with_alpha2_dot_through_e1
    if not rewrite:
        C.with_alpha2_dot_through_e1 = lambda design, e: (e, False)
    try:
        fc = C._Faces(ctx)
    finally:
        C.with_alpha2_dot_through_e1 = saved
    d = ctx.design
    w, phi = projection_face(d)["w"], 7.15                    # sup ||Phi|| <= sqrt(51) (tanh states and a bias)
    W0 = np.zeros_like(d.variant.initial_states()["w_hat"])
    lw, hw = W0.copy(), W0.copy()
    lw[0, :], hw[0, :] = -w * phi, w * phi
    lo, hi = fc.box(0.1, 0.95, controller_state_boxes(ctx, (lw, hw)))
    f = next(f for f in fc.faces(lo, hi) if f["name"] == "e2 joint 1 +")
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
