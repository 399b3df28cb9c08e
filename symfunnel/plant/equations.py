"""The plant's equations as every loop simulates them: the true robot under a commanded torque (SX).

    M_p(q) ddq + C_p(q, dq) dq + G_p(q) + friction(dq) + d(t, q, dq) = D(tau)

with M_p, G_p = plant.mass_scale * the model's matrices at the model parameters overridden by
`plant.parameters`, C_p the Christoffel-symbol Coriolis matrix of M_p (physical, whatever C the controller's model
types in; `plant.coriolis = "model"` takes the model's C instead), friction = viscous*dq + coulomb*sign_w(dq), D the
dead zone of eq. 2 (smoothed with the same width w, see `nonlinearities`), d the disturbance expressions. ddq is
obtained by an LDL^T factorisation of M_p written out in SX (n^3/6 operations, no symbolic blow-up for n ~ 7, no
pivoting needed as M_p is positive definite).

The plant's uncertain quantities (mass scale, parameters, friction, disturbance scale, dead-zone breakpoints and
branch scales; layout `plant_parameters`) can be symbols p, so that one compiled loop runs every plant of a campaign.
The continuous closed loop (`simulation.closedloop`), the deployed controller's sampled loop (`deployed.loop`), a
physics engine's forces (`deployed.engine`), the certificates' regions and the theory checks all take the plant from
here.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..model.base import christoffel_C
from ..sx.linalg import ldl_solve
from . import nonlinearities as P


def dead_zone_branches(scenario) -> tuple[list, list]:
    """Per joint, the dead zone's left and right branch as callables u -> D(u) (scenario expressions times their
    scales, SX), for the checks that need the branches one by one (the input-gain assumption)."""
    dz = scenario.plant.dead_zone
    u = ca.SX.sym("u")
    left, right = [], []
    for j in range(scenario.n):
        envj = {"u": u, "b_l": dz.b_l[j], "b_r": dz.b_r[j]}
        fl = ca.Function("left", [u], [ca.SX(dz.left.to_casadi(envj))])
        fr = ca.Function("right", [u], [ca.SX(dz.right.to_casadi(envj))])
        ls = 1.0 if dz.left_scale is None else np.broadcast_to(np.asarray(dz.left_scale, float), (scenario.n,))[j]
        rs = 1.0 if dz.right_scale is None else np.broadcast_to(np.asarray(dz.right_scale, float), (scenario.n,))[j]
        left.append(lambda v, fl=fl, s=ls: s * fl(v))
        right.append(lambda v, fr=fr, s=rs: s * fr(v))
    return left, right


def plant_parameters(scenario) -> tuple[list[str], np.ndarray]:
    """Names and values of the plant's quantities the compiled closed loop takes as its parameter vector p.

    Names are scenario keys, per-joint entries as key[j] (1-based): plant.mass_scale, plant.parameters.<name>,
    plant.viscous[j], plant.coulomb[j], plant.disturbance_scale[j] and, with a dead zone,
    plant.dead_zone.{b_l, b_r, left_scale, right_scale}[j]. The layout depends on the scenario's structure only,
    so every variant of a scenario's values runs on the same compiled code.
    """
    pl = scenario.plant
    n = scenario.model.n
    names, vals = ["plant.mass_scale"], [float(pl.mass_scale)]
    pv = scenario.model.parameter_dict() if scenario.model.p.numel() else {}
    pv.update(pl.parameters)
    for k in scenario.model.p_names:
        names.append(f"plant.parameters.{k}")
        vals.append(float(pv[k]))

    def joints(key, v):
        a = np.broadcast_to(np.asarray(1.0 if v is None else v, dtype=float), (n,))
        names.extend(f"{key}[{j + 1}]" for j in range(n))
        vals.extend(float(x) for x in a)
    joints("plant.viscous", pl.viscous)
    joints("plant.coulomb", pl.coulomb)
    joints("plant.disturbance_scale", pl.disturbance_scale)
    dz = pl.dead_zone
    if dz is not None:
        joints("plant.dead_zone.b_l", dz.b_l)
        joints("plant.dead_zone.b_r", dz.b_r)
        joints("plant.dead_zone.left_scale", dz.left_scale)
        joints("plant.dead_zone.right_scale", dz.right_scale)
    return names, np.array(vals, dtype=float)


def plant_acceleration(scenario, q, dq, t, tau, width: float, p=None, solve=None) -> dict:
    """The true plant's ddq under commanded torque tau, with its parts (SX in q, dq, t, tau, and p if given).

    `p` (SX, laid out as `plant_parameters`) makes the plant's uncertain quantities symbols; without it they are
    the scenario's numbers. `solve(M, rhs)`: how M^-1 rhs is written (the same function; a certificate picks the
    form whose interval enclosure is narrowest), by default LDL^T.
    """
    model = scenario.model
    pl = scenario.plant
    par = _plant_values(scenario, p)
    M, G = model.M, model.G
    # The true plant is physical: its Coriolis matrix comes from M (Christoffel symbols), whatever C the
    # controller's model was given, unless the scenario asks for the model's C (plant.coriolis = "model").
    C = christoffel_C(M, model.q, model.dq) if pl.coriolis == "christoffel" and model.C_source == "given" else model.C
    if model.p.numel():
        pv = ca.vertcat(*[par[f"plant.parameters.{k}"] for k in model.p_names])
        M, C, G = (ca.substitute(E, model.p, pv) for E in (M, C, G))
    # the model's q/dq are the design's; substitute ours in case they differ
    M, C, G = (ca.substitute(E, ca.vertcat(model.q, model.dq), ca.vertcat(q, dq))
               for E in (M, C, G))
    s = par["plant.mass_scale"]
    M, C, G = s * M, s * C, s * G
    parts = plant_forces(scenario, q, dq, t, tau, width, p)
    rhs = parts["tau_applied"] - ca.mtimes(C, dq) - G - parts["friction"] - parts["disturbance"]
    n = model.n
    ddq = ca.solve(M, rhs) if n == 1 else (solve or ldl_solve)(M, rhs)
    return {"ddq": ddq, "M": M, "C": C, "G": G, **parts}


def dead_zone_deviation(scenario, tau, p=None):
    """D(tau) - tau at width 0 (SX, per joint), or None without a dead zone: the same function in a form where tau
    does not enter twice. With R = max(tau - b_r, 0), L = max(b_l - tau, 0) and b_l < b_r, tau = R - L +
    clamp(tau, b_l, b_r), so D(tau) - tau = (rs right(b_r + R) - R) + (ls left(b_l - L) + L) - clamp(tau, b_l, b_r),
    each bracket expanded and collected in R (L) by sympy: for a linear branch s (u - b_r) it is (s rs - 1) R, whose
    interval enclosure is |s rs - 1| times R's width, where D(tau) - tau evaluated as written has (s rs + 1) times
    it (tau ~ 3,000 N m and s = 1.02: width 2.02 w against 0.02 w). For the interval forms of the certificates;
    None also where a branch does not come back through the expression parser (then D(tau) - tau as written)."""
    import sympy as sp

    from ..expr.parse import parse_expression
    dz = scenario.plant.dead_zone
    if dz is None:
        return None
    par = _plant_values(scenario, p)
    R, L, rs, ls, bl, br = sp.symbols("R L rs ls bl br")
    names = ["R", "L", "rs", "ls", "bl", "br"]
    try:
        gr = sp.collect(sp.expand(rs * dz.right.to_sympy({"u": br + R, "b_l": bl, "b_r": br}) - R), R)
        gl = sp.collect(sp.expand(ls * dz.left.to_sympy({"u": bl - L, "b_l": bl, "b_r": br}) + L), L)
        tr, tl = parse_expression(str(gr), names), parse_expression(str(gl), names)
    except Exception:           # a branch sympy's printer writes in a form the parser does not read: as written
        return None
    out = []
    for j in range(scenario.model.n):
        b_l, b_r = par[f"plant.dead_zone.b_l[{j + 1}]"], par[f"plant.dead_zone.b_r[{j + 1}]"]
        env = {"R": ca.fmax(tau[j] - b_r, 0), "L": ca.fmax(b_l - tau[j], 0), "bl": b_l, "br": b_r,
               "rs": par[f"plant.dead_zone.right_scale[{j + 1}]"], "ls": par[f"plant.dead_zone.left_scale[{j + 1}]"]}
        out.append(ca.SX(tr.to_casadi(env)) + ca.SX(tl.to_casadi(env)) - ca.fmin(ca.fmax(tau[j], b_l), b_r))
    return ca.vertcat(*out)


def _plant_values(scenario, p=None) -> dict:
    """Plant quantity name (layout `plant_parameters`) -> SX entry of p, or its number without p."""
    names, values = plant_parameters(scenario)
    entries = [p[i] for i in range(len(names))] if p is not None else [float(v) for v in values]
    return dict(zip(names, entries))


def plant_forces(scenario, q, dq, t, tau, width: float, p=None) -> dict:
    """The plant's forces beyond its rigid body (SX): friction (viscous + Coulomb), disturbance and the torque the
    actuators apply after the dead zone, so that M ddq + C dq + G = tau_applied - friction - disturbance. One
    source for every plant: symfunnel's (`plant_acceleration`) and a physics engine's (`deployed.engine`)."""
    model = scenario.model
    pl = scenario.plant
    n = model.n
    par = _plant_values(scenario, p)

    def joints(key):
        return [par[f"{key}[{j + 1}]"] for j in range(n)]

    fric = ca.vertcat(*joints("plant.viscous")) * dq + ca.vertcat(*joints("plant.coulomb")) * P.sign(dq, width)
    env = {"t": t}
    for i, c in enumerate(model.coordinates):
        env[c] = q[i]
        env["d" + c] = dq[i]
    ds = joints("plant.disturbance_scale")
    dist = ca.vertcat(*[ds[j] * ca.SX(e.to_casadi(env)) for j, e in enumerate(pl.disturbance)])
    dz = pl.dead_zone
    if dz is None:
        tau_applied = tau
    else:
        b_l, b_r = joints("plant.dead_zone.b_l"), joints("plant.dead_zone.b_r")
        ls, rs = joints("plant.dead_zone.left_scale"), joints("plant.dead_zone.right_scale")
        out = []
        for j in range(n):
            # eq. 2 as in plant.dead_zone: each branch evaluated only inside its own domain (smooth ramp)
            ur = b_r[j] + P.ramp(tau[j] - b_r[j], width)
            ul = b_l[j] - P.ramp(b_l[j] - tau[j], width)
            right = ca.SX(dz.right.to_casadi({"u": ur, "b_l": b_l[j], "b_r": b_r[j]}))
            left = ca.SX(dz.left.to_casadi({"u": ul, "b_l": b_l[j], "b_r": b_r[j]}))
            out.append(rs[j] * right + ls[j] * left)
        tau_applied = ca.vertcat(*out)
    return {"friction": fric, "disturbance": dist, "tau_applied": tau_applied}
