"""The certify area's certify.sampled figures: the bracket (f_sim, f_proven, ratio) per shipped scenario beside the
simulated rate search timed in the same run, and the per-period certificate's scaling over planar arms of n = 2, 3,
4 joints generated here (model-based, no approximator, the plant the model plus a small disturbance)."""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path


from ._result import result

#: the rate the per-period scaling is measured at, and the box budget of that one branch and bound
SCALING_RATE_HZ = 1e5
SCALING_BOXES = 40000
#: S's margins in the scaling runs (declared: containment is proven at n = 2 only within its budget)
SCALING_SET = (0.5, 0.5)


def bracket(rid: str, path: Path, progress) -> dict:
    """`rate --certify` on one scenario: the simulated search (baseline) and the proof (value), each timed apart
    in wall and CPU seconds."""
    from ..certificates.sampled_rate import sampled_bracket, simulated_w_hat_range
    from ..deployed.rate import min_rate
    from ..pipeline import Run
    r = Run.load(str(path))
    progress(f"certify: the simulated rate search on {r.scenario.name}")
    t0, c0 = time.perf_counter(), time.process_time()
    sim = min_rate(r.scenario, r.design, t_final=r.t_final)
    base, base_cpu = time.perf_counter() - t0, time.process_time() - c0
    wr = simulated_w_hat_range(r.design, r.closed_loop, r.simulation)
    progress(f"certify: certify.sampled on {r.scenario.name}")
    t0, c0 = time.perf_counter(), time.process_time()
    b = sampled_bracket(r.scenario, r.design, t_final=r.t_final, f_sim=sim["min_rate_hz"], w_hat_range=wr)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    c = b["certificate"]
    return result(rid, wall, "s", "the simulated rate search", base, base / wall, cpu_s=cpu, baseline_cpu_s=base_cpu,
                  status=c["status"], min_rate_hz=sim["min_rate_hz"], proven_rate_hz=b["proven_rate_hz"],
                  theory_rate_hz=b["theory_rate_hz"], ratio_proven_simulated=b["ratio"], detail=c["detail"],
                  boxes=c["boxes"], set=c.get("set_choice"))


def planar_text(n: int) -> str:
    """A planar arm of n revolute joints (links shortening and lightening outward), its reference a sine per joint,
    model-based (no approximator), the plant the model plus 0.02 sin(t) N m: certify_none's design at any n."""
    links = ", ".join(f"{{ mass = {2.0 - 0.4 * i:g}, length = {0.5 - 0.08 * i:g} }}" for i in range(n))
    ref = ", ".join(f'"{0.3 / (i + 1):g}*sin(t + {i:g})"' for i in range(n))
    q0 = [0.3 / (i + 1) * math.sin(i) for i in range(n)]
    dq0 = [0.3 / (i + 1) * math.cos(i) for i in range(n)]
    return (f'name = "planar{n}_none"\n[model]\ntype = "planar"\nlinks = [{links}]\n[reference]\nq = [{ref}]\n'
            f"[initial]\nq = {q0!r}\ndq = {dq0!r}\n[funnel.e1]\nphi0 = 0.2\nphi_inf = 0.05\na = 1.0\n"
            "[funnel.e2]\nphi0 = 1.0\nphi_inf = 0.3\na = 1.0\n[approximator]\ntype = \"none\"\n"
            "[controller]\nk1 = 2.0\nk2 = 5.0\n[plant]\nviscous = 0.0\ncoulomb = 0.0\n"
            "disturbance = \"0.02*sin(t)\"\n[simulation]\nt_final = 1.0\n")


def period_scaling(n: int, *, rate_hz: float = SCALING_RATE_HZ, max_boxes: int = SCALING_BOXES) -> dict:
    """One period's branch and bound at `rate_hz` over S (SCALING_SET) of the generated planar arm of n joints:
    CPU seconds of building the one-period map and of the search, boxes, whether proven, the fraction of S left,
    and the form of M_p^-1 the map uses (`face_forms.solver_form`)."""
    from ..certificates.problem import Context
    from ..certificates.region import parameter_box
    from ..certificates.sampled import OnePeriod, declared_set, prove_period
    from ..design import derive
    from ..scenario import load_scenario
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / f"planar{n}.toml"
        p.write_text(planar_text(n))
        sc = load_scenario(str(p))
    c0 = time.process_time()
    d = derive(sc)
    ctx = Context(sc, d, float(sc.simulation.t_final), parameter_box(sc), None, None)
    op = OnePeriod(ctx, declared_set(ctx, *SCALING_SET))
    build = time.process_time() - c0
    c0, t0 = time.process_time(), time.perf_counter()
    r = prove_period(op, 1.0 / rate_hz, 0.05, ctx.t_final, max_boxes=max_boxes)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    return {"n": n, "build_cpu_s": build, "cpu_s": cpu, "wall_s": wall, "boxes": int(r["boxes"]),
            "proven": bool(r["proven"]), "left": float(r["left"]), "reason": r["reason"],
            "ms_per_box": 1e3 * cpu / max(int(r["boxes"]), 1), "split_dims": int(op.split_vars(*op.box(1.0)).size),
            "solve": op.forms["solve"]}


def run(progress) -> list[dict]:
    """certify.sampled_*: the brackets and the planar scaling (see the module docstring)."""
    out = []
    root = Path(__file__).resolve().parent.parent.parent
    for rid, path in (("certify.sampled_one_s", root / "tests" / "data" / "sampled_1dof.toml"),
                      ("certify.sampled_none_s", root / "tests" / "data" / "certify_none.toml"),
                      ("certify.sampled_box_s", root / "derivations" / "paper_small_dead_zone.toml")):
        out.append(bracket(rid, path, progress))
    rows = []
    for n in (2, 3, 4):
        progress(f"certify: one period's certificate on a planar arm of {n} joints")
        rows.append(period_scaling(n))
    base = rows[0]["cpu_s"]
    for row in rows:
        out.append(result(f"certify.sampled_period_planar{row['n']}_s", row["cpu_s"], "s CPU",
                          "the same search at n = 2", base, base / row["cpu_s"] if row["cpu_s"] else None,
                          rate_hz=SCALING_RATE_HZ, set_margin=list(SCALING_SET), **row))
    return out
