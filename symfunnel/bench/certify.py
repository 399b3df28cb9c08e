"""Bench area `certify`: the certificates' searches against the sampled checks they replace, in the same run, and
the interval evaluator's throughput against the same function in floating point.

- certify.input_gain_paper_s: certify.input_gain on `paper` (refuted: slopes 0.9/1.1); baseline the sampled
  assumption.input_gain check.
- certify.input_gain_box_s: on `paper_small_dead_zone` (the 7-D box q2, four masses +-5 %, two slopes in
  [0.98, 1.02]; proven); baseline the sampled check on the same scenario.
- certify.input_gain_arm7_s: on `arm7` (joint tube, slope box [0.9, 1.1]^7); baseline the sampled check.
- certify.paper_wall_s: the whole `symfunnel certify paper` (derive, simulate for W*, every certificate; target
  15 s); baseline `verify paper` without the certificates.
- certify.arm7_wall_s: the whole `symfunnel certify arm7` (target 60 s on the 2-core machine); no baseline.
- certify.sampled_none_s, certify.sampled_box_s: `rate --certify` on `tests/data/certify_none.toml` (proven) and
  on `paper_small_dead_zone` (undecided: what is left in the detail): the proof's seconds; baseline the simulated
  rate search; f_sim, f_proven, f_theory and the ratio beside it.
- certify.tau_boxes_per_s: boxes per second of the batched interval evaluator on the paper's tau over the funnel
  region (natural form, batches of 256); baseline CasADi evaluating the same tape in double at mapped points
  (the overhead ratio of interval over floating point).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ._result import result

_SMALL = Path(__file__).resolve().parent.parent.parent / "derivations" / "paper_small_dead_zone.toml"
_NONE = Path(__file__).resolve().parent.parent.parent / "tests" / "data" / "certify_none.toml"


def _sampled(rid: str, path: Path, progress) -> dict:
    """`rate --certify` on one scenario: the simulated search (baseline) and the proof (value), timed apart."""
    from ..certificates.sampled_rate import sampled_bracket
    from ..deployed.rate import min_rate
    from ..pipeline import Run
    r = Run.load(str(path))
    progress(f"certify: the simulated rate search on {r.scenario.name}")
    t0 = time.perf_counter()
    sim = min_rate(r.scenario, r.design, t_final=r.t_final)
    base = time.perf_counter() - t0
    wr = None
    if r.design.n_regressor:
        wh = r.closed_loop.unpack(r.simulation.x).get("w_hat")
        wr = (np.min(wh, axis=0), np.max(wh, axis=0))
    progress(f"certify: certify.sampled on {r.scenario.name}")
    t0 = time.perf_counter()
    b = sampled_bracket(r.scenario, r.design, t_final=r.t_final, f_sim=sim["min_rate_hz"], w_hat_range=wr)
    wall = time.perf_counter() - t0
    c = b["certificate"]
    return result(rid, wall, "s", "the simulated rate search", base, base / wall, status=c["status"],
                  min_rate_hz=sim["min_rate_hz"], proven_rate_hz=b["proven_rate_hz"],
                  theory_rate_hz=b["theory_rate_hz"], ratio_proven_simulated=b["ratio"], detail=c["detail"],
                  boxes=c["boxes"])


def _input_gain(name, progress):
    from ..checks.theory import check_input_gain
    from ..pipeline import Run
    r = Run.load(name, certify_only=("certify.input_gain",))
    d = r.design
    t0 = time.perf_counter()
    check_input_gain(d, np.random.default_rng(13))
    sampled = time.perf_counter() - t0
    progress(f"certify: input gain on {name}")
    from ..certificates import run_certificates
    t0 = time.perf_counter()
    c = run_certificates(r.scenario, d, t_final=r.t_final, only=("certify.input_gain",)).certificates[0]
    wall = time.perf_counter() - t0
    return c, wall, sampled


def _throughput(progress):
    import casadi as ca

    from ..certificates.problem import Context, RegionProblem, controller_state_boxes
    from ..certificates.region import parameter_box
    from ..scenario import load_scenario
    from ..design import derive
    sc = load_scenario("paper")
    d = derive(sc)
    ctx = Context(sc, d, sc.simulation.t_final, parameter_box(sc), None, None)
    p = ca.SX.sym("p", len(ctx.params.names))
    prob = RegionProblem(ctx, {"tau": d.signals["tau"]}, p, "tau")
    nr, n = d.n_regressor, d.n
    states = controller_state_boxes(ctx, (-np.ones((nr, n)), np.ones((nr, n))))
    lo, hi = prob.flat(prob.region(0.05, states))
    rng = np.random.default_rng(0)
    K = 256
    a = lo + rng.random((K, lo.size)) * (hi - lo)
    b = lo + rng.random((K, lo.size)) * (hi - lo)
    LO, HI = np.minimum(a, b), np.maximum(a, b)
    F = prob.F.natural
    progress("certify: interval evaluator throughput on the paper's tau")

    def rate(fn, units):
        n_, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < 1.0:
            fn()
            n_ += 1
        return n_ * units / (time.perf_counter() - t0)
    boxes = rate(lambda: F.eval_batch(LO, HI), K)
    points = rate(lambda: F.eval_points(a), K)
    from ..sx.tape import count_ops
    return boxes, points, count_ops(prob.function)["operations"]


def run(progress) -> list[dict]:
    """Results certify.* (see the module docstring)."""
    out = []
    targets = {"paper": 2.0, str(_SMALL): 2.0, "arm7": 120.0}
    ids = {"paper": "certify.input_gain_paper_s", str(_SMALL): "certify.input_gain_box_s",
           "arm7": "certify.input_gain_arm7_s"}
    for name in ("paper", str(_SMALL), "arm7"):
        c, wall, sampled = _input_gain(name, progress)
        out.append(result(ids[name], wall, "s", "sampled assumption.input_gain", sampled, sampled / wall,
                          target=targets[name], meets_target=bool(wall <= targets[name] or c.status == "undecided"),
                          status=c.status, lower=c.lower, upper=c.upper, boxes=c.boxes,
                          undecided_fraction=c.undecided_fraction,
                          first_proof=c.extra.get("first_proof")))
    from ..pipeline import Run
    progress("certify: the whole certify paper")
    t0 = time.perf_counter()
    cert = Run.load("paper", certify_work=1.0).certification
    wall = time.perf_counter() - t0
    progress("certify: verify paper without the certificates (baseline)")
    t0 = time.perf_counter()
    Run.load("paper", certify=False).verification
    base = time.perf_counter() - t0
    out.append(result("certify.paper_wall_s", wall, "s", "verify paper without certificates", base, base / wall,
                      target=15.0, meets_target=bool(wall <= 15.0),
                      statuses={c.id: c.status for c in cert.certificates},
                      seconds={c.id: c.seconds for c in cert.certificates}))
    progress("certify: the whole certify arm7")
    t0 = time.perf_counter()
    cert = Run.load("arm7", certify_work=1.0).certification
    wall = time.perf_counter() - t0
    out.append(result("certify.arm7_wall_s", wall, "s", None, None, None, target=60.0,
                      meets_target=bool(wall <= 60.0), statuses={c.id: c.status for c in cert.certificates},
                      seconds={c.id: c.seconds for c in cert.certificates}))
    for rid, path in (("certify.sampled_none_s", _NONE), ("certify.sampled_box_s", _SMALL)):
        out.append(_sampled(rid, path, progress))
    boxes, points, ops = _throughput(progress)
    out.append(result("certify.tau_boxes_per_s", boxes, "boxes/s", "CasADi double at mapped points (points/s)",
                      points, boxes / points, operations=ops, overhead=points / boxes))
    return out

