"""`plant.engine_agreement`: does the physics engine's robot have the controller's model's dynamics?

Before a sampled run on MuJoCo means anything, MuJoCo's mass matrix and bias forces C(q, dq) dq + G(q) are compared
with symfunnel's M(q) and C(q, dq) dq + G(q) (the controller's model, derived from the same URDF or link table) at
random states in the joint ranges (`audit.joint_range`, `audit.velocity_range`), and, where Pinocchio is installed
and the model is a URDF, with Pinocchio's too, which tells which side a disagreement comes from. The comparison is
of the nominal robot: the plant's mass scale and the engine-only dynamics are differences on purpose, reported
beside it (the URDF's joint damping and friction, `[plant.mujoco]`'s mass scale, damping and armature). A
disagreement is a finding: the check fails with the size of the error and the joint whose column of M (or entry
of the bias) disagrees most, and the deepest such joint (in tree order, the first place the models part).
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np

from .result import CheckResult

__all__ = ["check_engine_agreement", "TOLERANCE", "SAMPLES"]

#: the largest relative error of M and of the bias forces at which the engine counts as the same robot
TOLERANCE = 1e-8
SAMPLES = 200


def _pinocchio(urdf, names: list[str], gravity, held=()):
    """(M_fn, bias_fn) of Pinocchio on the URDF in symfunnel's coordinate order, or None without Pinocchio; the
    joints in `held` (model.fixed_joints) are locked at their zero position, as in symfunnel's model."""
    try:
        import pinocchio as pin
    except ImportError:
        return None
    try:
        pm = pin.buildModelFromUrdf(str(urdf))
    except Exception:  # noqa: BLE001 - a third opinion only: a URDF Pinocchio refuses simply has none
        return None
    if held:
        if not all(pm.existJointName(nm) for nm in held):
            return None
        pm = pin.buildReducedModel(pm, [pm.getJointId(nm) for nm in held], pin.neutral(pm))
    pm.gravity.linear = np.asarray(gravity, dtype=float)
    pd = pm.createData()
    idq, nq, idv = [], [], []
    for nm in names:
        if not pm.existJointName(nm):
            return None
        j = pm.joints[pm.getJointId(nm)]
        idq.append(j.idx_q)
        nq.append(j.nq)           # 2 for a continuous joint (cos, sin)
        idv.append(j.idx_v)
    if pm.nv != len(names):
        return None
    iv = np.array(idv)

    def state(q, dq):
        qp, vp = pin.neutral(pm), np.zeros(pm.nv)
        for k in range(len(names)):
            if nq[k] == 2:
                qp[idq[k]:idq[k] + 2] = (math.cos(q[k]), math.sin(q[k]))
            else:
                qp[idq[k]] = q[k]
            vp[idv[k]] = dq[k]
        return qp, vp

    def M_fn(q):
        qp, _ = state(q, np.zeros(len(names)))
        M = pin.crba(pm, pd, qp)
        M = np.triu(M) + np.triu(M, 1).T
        return M[np.ix_(iv, iv)]

    def bias_fn(q, dq):
        qp, vp = state(q, dq)
        return pin.nonLinearEffects(pm, pd, qp, vp)[iv]
    return M_fn, bias_fn


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def check_engine_agreement(scenario, *, samples: int = SAMPLES, seed: int = 0,
                           tolerance: float = TOLERANCE, setup=None, progress=None) -> CheckResult:
    """`plant.engine_agreement` on the scenario's engine setup (see the module doc); value = the larger error."""
    from ..deployed.engine import _LOCK, EngineRunPlant, configure, engine_setup
    from ..plant.mujoco import agreement
    say = progress or (lambda s: None)
    say(f"engine agreement: MuJoCo's M and bias forces against symfunnel's model at {samples} states")
    setup = setup or engine_setup(scenario, on_build=say)
    eng = setup.engine
    n = scenario.n
    m = scenario.model          # the controller's model: the M, C, G its design is derived from
    Mf = ca.Function("M", [m.q], [m.numeric(m.M)])
    Cf = ca.Function("C", [m.q, m.dq], [m.numeric(m.C)])
    Gf = ca.Function("G", [m.q], [m.numeric(m.G)])

    def M_fn(q):
        return np.array(Mf(q))

    def bias_fn(q, dq):
        return (np.array(Cf(q, dq)) @ np.asarray(dq).reshape(-1, 1)).ravel() + np.array(Gf(q)).ravel()
    others = {}
    if scenario.model.kind == "urdf":
        pin = _pinocchio(scenario.model.tree.file, eng.names, scenario.model.gravity, eng.notes.held)
        if pin is not None:
            others["pinocchio"] = pin
    a = scenario.audit
    t0 = time.perf_counter()
    with _LOCK:
        run = EngineRunPlant(setup.p0.copy(), scenario.plant.mujoco, np.asarray(scenario.q0, dtype=float),
                             np.asarray(scenario.dq0, dtype=float))
        configure(setup, run)
        engine_only = eng.engine_only()
        eng.configure()          # the nominal robot for the comparison
        r = agreement(eng, M_fn, bias_fn, a.joint_lower, a.joint_upper, a.velocity_range, samples=samples,
                      seed=seed, others=others)
    seconds = time.perf_counter() - t0
    value = float(r["value"])
    names = eng.names
    pj_M, pj_b = np.array(r["per_joint_M"]), np.array(r["per_joint_bias"])
    worst_M, worst_b = int(np.argmax(pj_M)), int(np.argmax(pj_b))
    bad = [k for k in range(n) if max(pj_M[k], pj_b[k]) > tolerance]
    deepest = names[bad[-1]] if bad else None
    src = eng.notes.source
    box = f"{samples} random states (q in audit.joint_range, |dq| <= audit.velocity_range)"
    third = ""
    if "pinocchio" in r.get("others", {}):
        p = r["others"]["pinocchio"]
        third = (f"; Pinocchio vs symfunnel: M {p['M']:.2g}, bias {p['bias']:.2g}; Pinocchio vs MuJoCo: M "
                 f"{p['M_vs_engine']:.2g}, bias {p['bias_vs_engine']:.2g}")
        if value > tolerance:
            sym_ok = max(p["M"], p["bias"]) <= tolerance
            mj_ok = max(p["M_vs_engine"], p["bias_vs_engine"]) <= tolerance
            if sym_ok and not mj_ok:
                third += " (Pinocchio sides with symfunnel: MuJoCo's reading of the file differs)"
            elif mj_ok and not sym_ok:
                third += " (Pinocchio sides with MuJoCo: symfunnel's model of the file differs)"
    extras = []
    for key, what in (("damping", "joint damping"), ("frictionloss", "friction loss"), ("armature", "armature")):
        if key in engine_only:
            extras.append(f"{what} {_fmt(engine_only[key])}")
    mass = scenario.plant.mass_scale
    ms = scenario.plant.mujoco.mass_scale
    deliberate = []
    if mass != 1.0:
        deliberate.append(f"mass scale {mass:g} (plant.mass_scale)")
    if ms is not None and any(v != 1.0 for v in ms):
        deliberate.append(f"engine mass scale {_fmt(ms)} (plant.mujoco.mass_scale)")
    tail = ""
    if eng.notes.held:
        tail += "; held fixed at 0 by both (model.fixed_joints): " + ", ".join(eng.notes.held)
    if eng.notes.mimic:
        tail += "; <mimic> ignored on " + ", ".join(eng.notes.mimic) + " (by both: each joint is a coordinate)"
    if eng.notes.floored:
        tail += "; zero principal moments raised for MuJoCo on " + ", ".join(eng.notes.floored)
    if extras:
        tail += "; in the engine, not in the controller's model: " + ", ".join(extras)
    if deliberate:
        tail += "; left out of the comparison on purpose: " + ", ".join(deliberate)
    if value <= tolerance:
        detail = (f"MuJoCo ({src}) agrees with symfunnel's model at {box}: M to {r['M']:.2g}, C dq + G to "
                  f"{r['bias']:.2g} (relative, tolerance {tolerance:g}){third}{tail}")
        status = "pass"
    else:
        detail = (f"MuJoCo ({src}) and symfunnel's model disagree at {box}: M by {r['M']:.3g} (largest in the column "
                  f"of joint '{names[worst_M]}'), C dq + G by {r['bias']:.3g} (largest at joint '{names[worst_b]}'), "
                  f"relative, tolerance {tolerance:g}; the deepest joint that disagrees is '{deepest}' (look at the "
                  f"links it carries){third}{tail}")
        status = "fail"
    evidence = {"M": r["M"], "bias": r["bias"], "abs_M": r["abs_M"], "abs_bias": r["abs_bias"],
                "per_joint_M": dict(zip(names, r["per_joint_M"])),
                "per_joint_bias": dict(zip(names, r["per_joint_bias"])),
                "worst_state": r["worst_state"], "samples": samples, "seed": seed, "tolerance": tolerance,
                "source": src, "notes": eng.notes.lines(), "engine_only": engine_only,
                "deliberate": deliberate, "seconds": seconds}
    if "others" in r:
        evidence["others"] = r["others"]
    where = None if status == "pass" else {"joint": deepest, "largest_M": names[worst_M],
                                            "largest_bias": names[worst_b], **(r["worst_state"] or {})}
    return CheckResult("plant.engine_agreement", status, detail, method="MuJoCo vs symfunnel's model (and Pinocchio)",
                       margin=tolerance - value, where=where, evidence=evidence, value=value)
