"""`[adaptation] projection = R` (issue 45): the projected adaptive law against an independent numpy implementation
of the operator, the loader's errors, a simulation that stays in the ball where the unprojected law leaves it, the
deployed step (SX core and the compiled C) against a second implementation of its update, the mutants the identity
check kills, and the W_hat face of `certify.containment` shown on the graph (a wrong law is not proven invariant).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.pipeline import derive
from symfunnel.scenario import load_scenario

from .test_hostile_second_pass import one_error

ROOT = Path(__file__).resolve().parent.parent
SMALL_DZ = ROOT / "derivations" / "paper_small_dead_zone.toml"
R, EPS = 0.5, 0.05


def _small(**changes):
    """paper_small_dead_zone with a 6-unit reservoir and the projection (cheap to derive and compile)."""
    sc = load_scenario(str(SMALL_DZ))
    base = {"esn.size": 6, "adaptation.projection": R, "adaptation.projection_layer": EPS}
    base.update(changes)
    return sc.replace({k: v for k, v in base.items()})


def _lw_projection(W, Y, R_in, R_out):
    """Lavretsky & Wise's projection operator written from its textbook form: f(theta) = ((1 + e) |theta|^2 -
    theta_max^2) / (e theta_max^2) with theta_max the outer radius and e chosen so that f = 0 on the inner radius;
    Proj = Y - f grad f grad f^T Y / |grad f|^2 where f > 0 and Y^T grad f > 0, else Y."""
    e = (R_out / R_in) ** 2 - 1.0
    th = W.ravel()
    f = ((1.0 + e) * th @ th - R_out ** 2) / (e * R_out ** 2)
    g = 2.0 * (1.0 + e) * th / (e * R_out ** 2)
    y = Y.ravel()
    if f > 0 and y @ g > 0:
        y = y - f * g * (g @ y) / (g @ g)
    return y.reshape(W.shape)


def _points(design, k, rng, radii):
    """k design-input points inside the funnels (numbers drawn here), W_hat of the given Frobenius norms."""
    from symfunnel.design.sampling import funnel_states
    pts = funnel_states(design, k, rng, fill=0.9)
    nr, n = design.sym["w_hat"].shape
    Ws = []
    for j in range(k):
        W = rng.normal(size=(nr, n))
        Ws.append(W / np.linalg.norm(W) * radii[j])
    return pts, Ws


def test_the_projected_law_equals_an_independent_projection_operator():
    d = derive(_small())
    nr, n = d.sym["w_hat"].shape
    rng = np.random.default_rng(3)
    k = 60
    radii = np.concatenate([rng.uniform(0.0, R, 20), rng.uniform(R, R * (1 + EPS), 20),
                            rng.uniform(R * (1 + EPS), 2 * R, 20)])
    pts, Ws = _points(d, k, rng, radii)
    names = ["t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"]
    f = d.function("law", names, ["w_hat_dot", "Phi", "mu2", "z2"])
    sc = d.scenario
    corrected = 0
    for j in range(k):
        args = [pts[a][:, j] for a in names[:6]] + [pts["x_esn"][:, j], Ws[j]]
        wdot, Phi, mu2, z2 = (np.asarray(v, float) for v in f(*args))
        # the unprojected law of the paper's eq. 33 (corrected): Gamma (Phi (mu2 z2)^T - sigma W)
        Y = sc.gamma * (np.outer(Phi.ravel(), (mu2 * z2).ravel()) - sc.sigma * Ws[j])
        want = _lw_projection(Ws[j], Y, R, R * (1 + EPS))
        corrected += not np.allclose(want, Y)
        assert np.allclose(wdot, want, rtol=1e-10, atol=1e-10 * np.abs(Y).max()), (j, radii[j])
    # the points exercised the correction, and only outside the inner ball
    assert corrected >= 10


def test_without_projection_the_law_is_bit_identical():
    sc = load_scenario(str(SMALL_DZ)).replace({"esn.size": 6})
    d = derive(sc)
    import casadi as ca
    W = d.sym["w_hat"]
    # the law as it was written before the projection existed, evaluated bit for bit against the derived one
    want = ca.DM(sc.gamma) * (1 * ca.mtimes(d.signals["Phi"], (d.signals["mu2"] * d.signals["z2"]).T)
                              - 1 * ca.DM(sc.sigma) * W)
    names = ["t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"]
    f = ca.Function("f", [d.sym[k] for k in names], [d.signals["w_hat_dot"], want])
    rng = np.random.default_rng(1)
    for _ in range(20):
        args = [rng.normal(size=d.sym[k].shape) for k in names]
        got, ref = (np.asarray(v, float) for v in f(*args))
        assert np.array_equal(got, ref)
    assert "projection" not in d.parts and not any("projection" in m.id for m in d.variant.mutants())


@pytest.mark.parametrize("value, needle", [
    ("0.0", "adaptation.projection"), ("-1.0", "adaptation.projection"), ('"big"', "adaptation.projection"),
    ("inf", "adaptation.projection")])
def test_a_bad_radius_is_one_line_naming_the_key(tmp_path, capsys, value, needle):
    text = SMALL_DZ.read_text().replace("w_hat0 = 0.0", f"w_hat0 = 0.0\nprojection = {value}", 1)
    p = tmp_path / "bad.toml"
    p.write_text(text)
    assert main(["derive", str(p)]) == 2
    one_error(capsys, needle, str(p))


def test_w_hat0_outside_the_ball_and_a_bad_layer_are_refused(tmp_path, capsys):
    # ||W_hat(0)||_F = 0.1 sqrt(51 * 2) = 1.01 > 1
    text = SMALL_DZ.read_text().replace("w_hat0 = 0.0", "w_hat0 = 0.1\nprojection = 1.0", 1)
    p = tmp_path / "out.toml"
    p.write_text(text)
    assert main(["derive", str(p)]) == 2
    one_error(capsys, "adaptation.projection", "outside the ball", "1.00995")
    text = SMALL_DZ.read_text().replace("w_hat0 = 0.0", "w_hat0 = 0.0\nprojection = 1.0\nprojection_layer = 0", 1)
    p.write_text(text)
    assert main(["derive", str(p)]) == 2
    one_error(capsys, "adaptation.projection_layer")


def test_simulation_stays_in_the_ball_the_unprojected_law_leaves():
    import symfunnel as sf
    free = sf.simulate(_small(**{"adaptation.projection": None}), t_final=3.0)
    proj = sf.simulate(_small(), t_final=3.0)
    norm = {k: np.sqrt((np.asarray(r.signals["w_hat"]) ** 2).sum(axis=(1, 2))) for k, r in
            (("free", free), ("proj", proj))}
    assert free.status == proj.status == "ok"
    assert norm["free"].max() > 2 * R                       # the unprojected law leaves the ball
    # the projected one stays in R (1 + eps) up to the integrator's tolerance, and reaches the layer
    assert norm["proj"].max() <= R * (1 + EPS) * (1 + 1e-5)
    assert norm["proj"].max() > R


def test_the_deployed_step_is_euler_then_radial_clip_in_sx_and_in_c():
    from symfunnel.emit import check
    from symfunnel.emit.files import generate
    from symfunnel.emit.step import etd_factors, step_core
    d = derive(_small())
    rng = np.random.default_rng(5)
    k = 40
    radii = np.concatenate([rng.uniform(0.0, R, 10), rng.uniform(R, 1.2 * R, 30)])
    pts, Ws = _points(d, k, rng, radii)
    core = step_core(d)
    law = d.function("law", ["t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"], ["w_hat_dot"])
    ref = d.reference
    files = generate(d, "c", rate_hz=100.0)
    base = next(n[:-2] for n in files if n.endswith(".c") and not n.startswith("main"))
    lib = check.CLibrary(check.c_library(files[base + ".c"], files[base + ".h"], base).path)
    cf = lib.function("step_core")
    etd = np.array(etd_factors(d.scenario, 20.0))          # a long period: steps leave the ball
    clipped = 0
    for j in range(k):
        t, q, dq, x = float(pts["t"][0, j]), pts["q"][:, j], pts["dq"][:, j], pts["x_esn"][:, j]
        qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in ref(t))
        # inside the funnels the step's projection onto them is the identity: the design's own law
        wdot = np.asarray(law(t, q, dq, qd, dqd, ddqd, x, Ws[j]), float)
        Wn = Ws[j] + etd[1] * wdot
        nrm = np.linalg.norm(Wn)
        want = Wn * min(1.0, R * (1 + EPS) / nrm)
        clipped += nrm > R * (1 + EPS)
        got = np.asarray(core(t, q, dq, x, Ws[j], etd)[2], float)
        assert np.allclose(got, want, rtol=1e-9, atol=1e-12), j
        assert np.linalg.norm(got) <= R * (1 + EPS) * (1 + 1e-12)
        gc = cf(np.array([t]), q, dq, x, Ws[j], etd)[2]
        assert np.allclose(np.asarray(gc).reshape(want.shape, order="F"), want, rtol=1e-9, atol=1e-12), j
    assert clipped >= 5


@pytest.mark.parametrize("radius", [R, 50.0])
def test_the_identity_check_kills_both_projection_mutants_and_passes_the_design(radius):
    # R = 50: W_hat's sampling box (entries in +-1, ||W_hat|| ~ 2) never reaches the layer; the check samples it
    from symfunnel.checks.theory import check_identity
    sc = _small(**{"adaptation.projection": radius})
    assert {"flip_projection", "drop_projection_test"} <= {m.id for m in derive(sc).variant.mutants()}
    rng = np.random.default_rng(0)
    assert check_identity(derive(sc), rng).status == "pass"
    for m in ("flip_projection", "drop_projection_test"):
        assert check_identity(derive(sc, mutant=m), np.random.default_rng(0)).status == "fail", m


def test_the_w_hat_face_is_proven_on_the_graph_and_not_for_a_wrong_law():
    from symfunnel.certificates.projection_face import W_MARGIN, projection_face
    sc = _small()
    ok = projection_face(derive(sc))
    assert ok["ok"] and ok["w"] == pytest.approx(R * (1 + EPS) * (1 + W_MARGIN))
    for m in ("flip_projection", "drop_projection_test"):
        assert not projection_face(derive(sc, mutant=m))["ok"], m
    # d/dt ||W||^2 along the law on the sphere of the proven radius, at random states (independent of the proof)
    d = derive(sc)
    rng = np.random.default_rng(9)
    pts, Ws = _points(d, 50, rng, np.full(50, ok["w"]))
    law = d.function("law", ["t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"], ["w_hat_dot"])
    for j in range(50):
        args = [pts[a][:, j] for a in ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn")] + [Ws[j]]
        assert float(np.sum(Ws[j] * np.asarray(law(*args), float))) <= 0.0


@pytest.mark.slow
def test_verify_with_mutants_passes_the_design_and_kills_both_projection_mutants():
    import symfunnel as sf
    v = sf.verify(_small(), t_final=2.0, mutants=True)
    assert v.status == "pass", v.unexpected
    rows = {r["id"]: r for r in v.mutation["mutants"]}
    for m in ("flip_projection", "drop_projection_test"):
        assert rows[m]["killed"] and rows[m]["by"] == ["design.identity.vdot"], rows[m]
    assert v.mutation_score == 1.0
