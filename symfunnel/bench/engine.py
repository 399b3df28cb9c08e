"""Bench area `engine`: the deployed controller on MuJoCo beside symfunnel's own plant, in the same run.

Ids: `implementation.mujoco_realtime_factor` (arm7's 20 s sampled loop at twice its minimum rate on MuJoCo, found by
`rate --plant mujoco` in this run, simulated s per wall s; baseline: the same loop, the same compiled step, on
symfunnel's CasADi plant; extra keys: the integrator and substeps of each plant, the largest |q| difference of the
two runs, and the same MuJoCo loop with MuJoCo's RK4 at its stability rule's substeps: its real-time factor and how
far the default's smallest margin is from RK4's) and `plant.engine_agreement_s`
(the wall time of `plant.engine_agreement` on arm7 at 200 states, loading the URDF into MuJoCo included; baseline:
symfunnel's own M and C dq + G at the same 200 states). Without the mujoco package the area reports nothing.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ._result import result

#: targets of the issue
TARGET_REALTIME = 20.0
TARGET_AGREEMENT_S = 2.0


def run(progress) -> list[dict]:
    """The two results above, for arm7."""
    try:
        import mujoco  # noqa: F401
    except ImportError:
        progress("engine: mujoco is not installed (pip install 'symfunnel[mujoco]'); nothing to measure")
        return []
    import casadi as ca

    from ..checks.engine import check_engine_agreement
    from ..deployed.engine import EngineRunPlant, engine_setup
    from ..deployed.loop import simulate_sampled, step_library
    from ..deployed.rate import min_rate
    from ..design import derive
    from ..emit.files import generate
    from ..scenario import load_scenario
    sc = load_scenario("arm7")
    design = derive(sc)
    out = []

    progress("engine: plant.engine_agreement on arm7 (200 states), MuJoCo's URDF load included")
    fresh = load_scenario("arm7")
    t0 = time.perf_counter()
    c = check_engine_agreement(fresh)
    agree_s = time.perf_counter() - t0
    m = sc.model
    Mf = ca.Function("M", [m.q], [m.numeric(m.M)])
    bf = ca.Function("b", [m.q, m.dq], [ca.mtimes(m.numeric(m.C), m.dq) + m.numeric(m.G)])
    rng = np.random.default_rng(0)
    a = sc.audit
    lo, hi, v = (np.asarray(x, dtype=float) for x in (a.joint_lower, a.joint_upper, a.velocity_range))
    t0 = time.perf_counter()
    for _ in range(200):
        q = lo + (hi - lo) * rng.random(sc.n)
        dq = v * (2 * rng.random(sc.n) - 1)
        Mf(q)
        bf(q, dq)
    sym_s = time.perf_counter() - t0
    out.append(result("plant.engine_agreement_s", agree_s, "s", "symfunnel's M and C dq + G at the same 200 states",
                      sym_s, sym_s / agree_s, target_s=TARGET_AGREEMENT_S,
                      meets_target=bool(agree_s <= TARGET_AGREEMENT_S), agreement=c.value, status=c.status,
                      evaluation_s=c.evidence["seconds"], scenario=sc.name))

    progress("engine: minimum rate of arm7 on MuJoCo (rate --plant mujoco)")
    r = min_rate(sc, design, engine="mujoco", progress=progress)
    rate = 2.0 * r["min_rate_hz"]
    files = generate(design, "c", rate_hz=rate)
    step = step_library(design, files, on_build=progress)
    progress(f"engine: 20 s sampled loop at {rate:.6g} Hz on MuJoCo, then on symfunnel's plant")
    simulate_sampled(sc, design, rate_hz=rate, t_final=0.01, engine="mujoco", controller=step)      # load, warm
    mj = simulate_sampled(sc, design, rate_hz=rate, t_final=20.0, engine="mujoco", controller=step)
    sym = simulate_sampled(sc, design, rate_hz=rate, t_final=20.0, engine="symfunnel", controller=step)
    setup = engine_setup(sc)
    rk4 = EngineRunPlant(setup.p0.copy(), dataclasses.replace(sc.plant.mujoco, integrator="RK4"),
                         np.asarray(sc.q0, dtype=float), np.asarray(sc.dq0, dtype=float))
    slow = simulate_sampled(sc, design, rate_hz=rate, t_final=20.0, engine="mujoco", controller=step, plant=rk4)
    rtf = float(mj.t[-1] / mj.wall_time)
    rtf_sym = float(sym.t[-1] / sym.wall_time)
    k = min(mj.t.size, sym.t.size, slow.t.size)
    out.append(result("implementation.mujoco_realtime_factor", rtf, "x real time",
                      "same loop and compiled step on symfunnel's CasADi plant", rtf_sym, rtf / rtf_sym,
                      target=TARGET_REALTIME, meets_target=bool(rtf >= TARGET_REALTIME), scenario=sc.name,
                      rate_hz=rate, min_rate_hz=r["min_rate_hz"], status=mj.status, symfunnel_status=sym.status,
                      mujoco_integrator=mj.stats["engine_integrator"], mujoco_substeps=mj.stats["plant_substeps"],
                      symfunnel_substeps=sym.stats["plant_substeps"],
                      max_abs_q_vs_symfunnel=float(np.abs(mj.q[:k] - sym.q[:k]).max()),
                      min_margin=mj.min_margin, rk4_min_margin=slow.min_margin,
                      rk4_realtime_factor=float(slow.t[-1] / slow.wall_time),
                      rk4_substeps=slow.stats["plant_substeps"], rk4_status=slow.status,
                      max_abs_q_vs_rk4=float(np.abs(slow.q[:k] - mj.q[:k]).max())))
    return out
