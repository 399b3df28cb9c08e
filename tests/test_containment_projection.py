"""`certify.containment` with a projected adaptive law (issue 45): the W_hat face is the projection's ball, and the
faces' enclosures -- with every sign(g) of the faces an input filled per box by Filippov's hull -- contain the faces'
values computed from the unmodified expressions (sign in the graph), at points drawn here, also where dq and e
cross zero inside a box.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symfunnel.certificates import run_certificates
from symfunnel.certificates.containment import _Faces, face_expressions, sign_nodes
from symfunnel.certificates.problem import Context, controller_state_boxes
from symfunnel.certificates.projection_face import W_MARGIN
from symfunnel.certificates.region import parameter_box
from symfunnel.pipeline import derive
from symfunnel.plant.equations import plant_parameters
from symfunnel.scenario import load_scenario

from .conftest import certify_once

ROOT = Path(__file__).resolve().parent.parent
SMALL_DZ = ROOT / "derivations" / "paper_small_dead_zone.toml"
R, EPS = 0.5, 0.05


def _small():
    return load_scenario(str(SMALL_DZ)).replace({"esn.size": 6, "adaptation.projection": R})


def test_the_faces_sign_nodes_are_coulomb_friction_and_the_transformation():
    sc = _small()
    d = derive(sc)
    names, _ = plant_parameters(sc)
    exprs, _ = face_expressions(d, ca.SX.sym("p", len(names)))
    args = {str(v.dep(0)) for v in sign_nodes([exprs["n1"], exprs["n2"]])}
    assert {"dq1", "dq2"} <= args and len(args) >= 4, args


@pytest.mark.slow
def test_filippov_enclosures_contain_the_values_of_the_unmodified_faces():
    sc = _small()
    d = derive(sc)
    ctx = Context(sc, d, 3.0, parameter_box(sc), None, None, w_star_info={}, breach=None)
    fc = _Faces(ctx)
    F = fc.F
    assert "sgn" in F.in_names
    # the unmodified normal components, in the design's own symbols and the plant's full parameter vector
    names, p0 = plant_parameters(sc)
    p = ca.SX.sym("p", len(names))
    exprs, _ = face_expressions(d, p)
    sym = d.sym
    ins = [sym[k] for k in ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat")] + [p]
    f = ca.Function("n", ins, [exprs["n1"], exprs["n2"]])
    alpha2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    bounds = d.function("funnel_bounds", ["t"], ["F1", "F2"])
    phi = d.function("Phi", ["x_esn"])
    wide = ctx.params.lo < ctx.params.hi
    init = d.variant.initial_states()
    W0 = np.zeros_like(init["w_hat"])
    lw, hw = W0.copy(), W0.copy()
    lw[0, :], hw[0, :] = -2.0, 2.0                      # the estimate W_hat^T Phi, carried by W_hat's first row
    states = controller_state_boxes(ctx, (lw, hw))
    lo, hi = fc.box(0.9, 0.9, states)
    rng = np.random.default_rng(11)
    crossed = checked = 0
    i = {k: (F.in_off[F.in_names.index(k)], F.in_off[F.in_names.index(k) + 1]) for k in F.in_names}
    for trial in range(120):
        c = lo + rng.random(lo.size) * (hi - lo)
        # half of the boxes centred where dq_1 = 0 (s2_1 solved from alpha2_1 + s2_1 F2_1 = 0): sign(dq_1) switches
        # inside them; small boxes, so that a wrong Filippov value would show beyond the enclosure's width
        if trial % 2:
            # dq = 0 lies inside the e2 funnel where alpha2 is small: near dqd = 0 (t = pi/2) with e1 near 0
            c[i["t"][0]] = tc = np.pi / 2 + rng.uniform(-0.01, 0.01)
            c[slice(*i["s1"])] = rng.uniform(-0.002, 0.002, 2)
            qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(tc))
            F1, F2 = (np.asarray(v, float).ravel() for v in bounds(tc))
            a2 = np.asarray(alpha2(tc, qd + c[slice(*i["s1"])] * F1, qd, dqd), float).ravel()
            c[slice(*i["s2"])] = np.clip(-a2 / F2, lo[slice(*i["s2"])], hi[slice(*i["s2"])])
        half = np.zeros(lo.size)
        half[i["t"][0]] = 1e-4
        half[slice(*i["s1"])] = half[slice(*i["s2"])] = 1e-3
        half[slice(*i["p"])] = 1e-4
        blo, bhi = np.maximum(c - half, lo), np.minimum(c + half, hi)
        for k in ("x_esn", "w_hat", "sgn", "m"):
            blo[slice(*i[k])], bhi[slice(*i[k])] = lo[slice(*i[k])], hi[slice(*i[k])]
        L, H, _ = F.eval_batch(blo[None, :], bhi[None, :])[:3]
        # points of the box, mapped to states from the funnels and the virtual control (m = 0 in the region)
        t = blo[i["t"][0]] + rng.random(25) * (bhi[i["t"][0]] - blo[i["t"][0]])
        sgn_seen = set()
        for j in range(25):
            u = blo + rng.random(lo.size) * (bhi - blo)
            qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(t[j]))
            F1, F2 = (np.asarray(v, float).ravel() for v in bounds(t[j]))
            q = qd + u[slice(*i["s1"])] * F1
            dq = np.asarray(alpha2(t[j], q, qd, dqd), float).ravel() + u[slice(*i["s2"])] * F2
            sgn_seen.add(tuple(np.sign(dq)))
            pp = p0.copy()
            pp[wide] = u[slice(*i["p"])]
            x = u[slice(*i["x_esn"])]
            est = u[slice(*i["w_hat"])].reshape(W0.shape, order="F")[0, :]
            Phi = np.asarray(phi(x), float).ravel()
            W = np.outer(Phi, est) / (Phi @ Phi)              # a W_hat whose estimate W_hat^T Phi is that row
            n1, n2 = (np.asarray(v, float).ravel() for v in f(t[j], q, dq, qd, dqd, ddqd, x, W, pp))
            got = np.concatenate([n1, n2])
            pos = np.r_[fc.pos["n1"]:fc.pos["n1"] + 2, fc.pos["n2"]:fc.pos["n2"] + 2]
            tol = 1e-9 * np.maximum(1.0, np.abs(got))
            assert np.all(L[0, pos] - tol <= got) and np.all(got <= H[0, pos] + tol), (trial, j, got, L[0, pos],
                                                                                       H[0, pos])
            checked += 1
        crossed += len(sgn_seen) > 1
    assert checked == 3000 and crossed >= 5, crossed


def test_containment_takes_the_projection_ball_as_its_w_hat_face():
    sc = _small()
    cert = run_certificates(sc, derive(sc), t_final=3.0, only=("certify.containment",),
                            work={"certify.containment": 2e6}).certificates[0]
    rows = [r for r in cert.extra["tried"] if "w" in r]
    assert rows and all(abs(r["w"] - R * (1 + EPS) * (1 + W_MARGIN)) < 1e-12 for r in rows)
    assert cert.status in ("proven", "undecided"), cert.detail


@pytest.mark.slow
@pytest.mark.parametrize("slopes", [("0.98", "1.02"), ("0.9", "1.1")])
def test_paper_small_dead_zone_with_projection_is_pinned(slopes, tmp_path_factory):
    """The outcome on paper_small_dead_zone with projection = 2 at the default budget: with its slopes 0.98/1.02
    (derivations/paper_small_dead_zone_projection.toml) the funnels are proven kept at m1 = 0.9, m2 = 0.002 (the
    easiest margin the screen leaves is tried first, with the whole budget); with the paper's own slopes 0.9/1.1
    (where certify.input_gain is refuted) the same margin is left undecided on 0.3 % of the e2 joint 2 faces only,
    every other face proven. The W_hat face is the projection's ball (2.121 instead of sigma-modification's 3.9e8).
    Pinned so that a change of the machinery that closes (or loses) a face is seen. The 0.98/1.02 member is the
    shipped file: its certificate is the one `symfunnel certify` computes on it (conftest's certify_once, shared
    with test_certify_pinned; the same certificate as run_certificates on the scenario below, key for key)."""
    if slopes == ("0.98", "1.02"):
        _, out = certify_once(tmp_path_factory, str(ROOT / "derivations" / "paper_small_dead_zone_projection.toml"))
        cert = next(c for c in out["certificates"] if c["id"] == "certify.containment")
    else:
        sc = load_scenario(str(SMALL_DZ)).replace({
            "adaptation.projection": 2.0, "plant.dead_zone.left": f"{slopes[0]}*(u - b_l)",
            "plant.dead_zone.right": f"{slopes[1]}*(u - b_r)"})
        cert = run_certificates(sc, derive(sc), t_final=sc.simulation.t_final,
                                only=("certify.containment",)).certificates[0].to_json()
    assert cert["w_bound"] == pytest.approx(2.0 * 1.05 * 1.01)
    assert cert["margin"] == {"e1": 0.9, "e2": 0.002}
    tried = {(r["m1"], r["m2"]): r.get("result", "") for r in cert["tried"]}
    if slopes == ("0.98", "1.02"):
        assert cert["status"] == "proven", cert["detail"]
        assert "every one of its 8 e-faces points inward" in cert["detail"]
        assert tried[(0.9, 0.002)].startswith("proven")
        return
    assert cert["status"] == "undecided", cert["detail"]
    assert set(cert["fractions"]) == {"e2 joint 2 +", "e2 joint 2 -"}
    assert max(cert["fractions"].values()) < 0.01
    assert "e1 joint 1 +, e1 joint 1 -, e1 joint 2 +, e1 joint 2 -, e2 joint 1 +, e2 joint 1 - are proven" in \
        cert["detail"]
    assert "sampled points sign n <= -" in cert["detail"]   # the open face points inward where sampled


def test_certify_sampled_takes_the_projection_ball_and_refuses_a_box_without_it():
    """The deployed step clips W_hat onto ||W_hat||_F <= R (1 + eps): certify.sampled's S takes the box of that ball
    (kept at every period), and a declared W_hat box that does not contain the ball is undecided, naming it."""
    import time

    from symfunnel.certificates.problem import Budget
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.certificates.sampled_rate import certify_sampled
    sc = _small()
    d = derive(sc)
    ctx = Context(sc, d, 0.5, parameter_box(sc), None, None, w_star_info={}, breach=None)
    rho = R * (1 + EPS)
    S = declared_set(ctx, 0.5, 0.5)
    lo, hi = S.states["w_hat"]
    assert np.all(lo == -rho) and np.all(hi == rho) and "projection" in S.notes["w_hat"]
    assert OnePeriod(ctx, S).w_ball == pytest.approx(rho)
    nr, n = d.n_regressor, d.n
    small = declared_set(ctx, 0.5, 0.5, w_box=(-0.1 * np.ones((nr, n)), 0.1 * np.ones((nr, n))), w_source="test")
    c = certify_sampled(ctx, Budget(1e6), S=small, theory=False)
    assert c.status == "undecided" and "projection's ball" in c.detail
    c = certify_sampled(ctx, Budget(2e6, time.monotonic() + 60), S=S, theory=False)
    assert c.status in ("proven", "undecided") and "not affine" not in c.detail, c.detail


def test_pieces_of_the_e2_faces_across_the_dead_zones_kink_close():
    """Two pieces of the e2 faces of paper_small_dead_zone with projection = 2 (m1 = 0.9, m2 = 0.05; t 0.5 % of its
    range, the other split coordinates 10 %) on which the torque's dead-zone branch is undecided in some sub-boxes:
    with CasADi's derivative of fmax the mean-value form's Jacobian was infinite there and 20,000 boxes proved
    nothing of either piece; with `kink_quotients` each closes in a few hundred. Where the pieces are drawn from is
    a seed; what the search must show about them is independent of it: they are inside the face."""
    from symfunnel.certificates.containment import _decide
    from symfunnel.certificates.projection_face import projection_face
    from symfunnel.sx.search import extrema
    sc = load_scenario(str(SMALL_DZ)).replace({"adaptation.projection": 2.0})
    d = derive(sc)
    ctx = Context(sc, d, sc.simulation.t_final, parameter_box(sc), None, None, w_star_info={}, breach=None)
    fc = _Faces(ctx)
    w = projection_face(d)["w"]
    init = d.variant.initial_states()
    W0 = np.zeros_like(np.asarray(init["w_hat"], float))
    lo, hi = fc.box(0.9, 0.95, controller_state_boxes(ctx, (W0, W0)), fc.gprob)
    GF = fc.gprob.F
    k = GF.out_names.index("P2")
    phi = np.sqrt(-extrema(GF, lo, hi, fc.gprob.split_indices(lo, hi), [(GF.out_off[k], -1.0)], max_boxes=256,
                           rel_tol=0.2)[0].bound)
    lw, hw = W0.copy(), W0.copy()
    lw[0, :], hw[0, :] = -w * phi, w * phi
    lo, hi = fc.box(0.1, 0.95, controller_state_boxes(ctx, (lw, hw)))
    faces = {f["name"]: f for f in fc.faces(lo, hi)}
    for name, draws in (("e2 joint 1 +", 1), ("e2 joint 2 -", 3)):
        rng = np.random.default_rng(5)
        f = dict(faces[name])
        split = fc.split_indices(f["lo"], f["hi"])
        for _ in range(draws):
            u = rng.random(split.size)
        widths = np.full(split.size, 0.1)
        widths[0] = 0.005
        ext = f["hi"][split] - f["lo"][split]
        a = f["lo"][split] + u * ext * (1 - widths)
        f["lo"], f["hi"] = f["lo"].copy(), f["hi"].copy()
        f["lo"][split], f["hi"][split] = a, a + widths * ext
        res = _decide(fc.F, [f], [split], 5000, None)
        assert res["status"] == "proven", (name, res)
