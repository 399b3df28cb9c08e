"""tune's gradient path: IPOPT over the log-scaled `[tune]` parameters with CVODES forward sensitivities.

Used when the scenario has no `[implementation]`: the continuous-time closed loop is smooth in its gains and e2
funnel, so the simulated constraints have exact derivatives. The closed loop (`simulation.closedloop.loop_sx`)
takes all the design's numbers as parameters zd (`design.derive(values=...)`): p = [zd; plant quantities], and the
tunable parameters z in [0, 1]^d (log scale of their bounds) map into zd outside the compiled DAE, so every tune of
a scenario shares one. One CVODES call returns the states on a fixed output grid of K points, and CasADi
differentiates it (forward sensitivities, d directions). Constraints per grid point and joint,
on the nominal plant and every uncertainty sample: m1, m2 >= margin (m = 1 - |e|/F) and |tau| <= tau_max when
given. Objective: peak torque through an epigraph variable s (|tau_i(t_k)| <= s ref on the nominal run) or the
integral of |e1|^2 by the trapezoidal rule on the grid, both divided by the user's design's value.
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np

__all__ = ["GradientProblem", "ipopt_available", "GRID_POINTS", "TOLERANCE"]

#: output grid points over the horizon (the constraints are imposed there; the result is checked by a full run)
GRID_POINTS = 200
#: CVODES tolerances (abstol, reltol) of the sensitivity runs: tighter than a simulation's so the derivatives of
#: the grid states are accurate enough for IPOPT's line search
TOLERANCE = (1e-8, 1e-7)
#: the tolerances before (issue 43): the Jacobian costs ~30 % more CPU for constraints that differ by ~5e-5 from
#: these (a 1e-3 share of the margin the constraints keep); kept as the bench's baseline (`PREVIOUS`)
PREVIOUS_TOLERANCE = (1e-9, 1e-8)
#: CVODES steps allowed per output interval (a design this stiff is not worth the time: IPOPT backs off)
MAX_STEPS = 2000
#: IPOPT iterations per start
MAX_ITER = 40
#: IPOPT iterations of the whole-horizon polish after a coarse result that already meets every constraint:
#: measured (tune --max-evals 2 --method gradient), the polish's best feasible iterate was its 1st (paper, 1 %
#: below its start) or its 39th (arm7, 0.8 % below), and the 38 iterations between wandered up to 3x the start's
#: peak torque; paper's polish took 3.0 s of the start's 4.8, arm7's 12 s of 17. Was 15; none since issue 43: on
#: the paper's default tune (20 s) a polish iteration costs 2-3 CPU-s, its best was its 1st again (1e-6 below its
#: start) and it wandered to 13 % worse by its 3rd; the whole-horizon run of the result judges it either way
POLISH_ITER = 0
#: IPOPT stops a pass (acceptable point) once the objective moved by less than STALL_CHANGE (a share of the user's
#: design's objective, by which it is normalised) over STALL_ITER consecutive iterations that meet the constraints:
#: a count of iterations, never a timing, so the same scenario gives the same result on any machine; the paper's
#: coarse pass spent 23 of its 36 iterations moving the objective by less than 0.2 % (0.0712 -> 0.0706)
STALL_CHANGE = 1e-3
STALL_ITER = 3
#: the schedule before (issue 43), the bench's baseline: tolerances, polish and the coarse pass's share of the wall
#: time (which made the result depend on the machine's speed), without the stall stop
PREVIOUS = {"tolerance": PREVIOUS_TOLERANCE, "polish_iter": 15, "coarse_wall_share": 0.5, "stall": False}
CURRENT = {"tolerance": TOLERANCE, "polish_iter": POLISH_ITER, "coarse_wall_share": 1.0, "stall": True}
#: the coarse first pass: IPOPT over this fraction of the horizon (and of the grid) first, then over the whole
#: horizon from its result; the transient, where the paper's peak torque and narrowest margins are, is at the start,
#: and a fifth of the horizon costs about a fifth of the sensitivities
COARSE_FRACTION = 0.25


def schedule() -> dict:
    """The IPOPT/CVODES schedule in use: CURRENT, or PREVIOUS when $SYMFUNNEL_TUNE_PATH is 'previous' (the bench
    measures both in one run)."""
    import os
    return PREVIOUS if os.environ.get("SYMFUNNEL_TUNE_PATH", "").strip().lower() == "previous" else CURRENT


def ipopt_available() -> bool:
    """Whether the installed casadi has the IPOPT plugin."""
    try:
        return bool(ca.has_nlpsol("ipopt"))
    except Exception:            # noqa: BLE001 - a broken plugin is the same as none
        return False


def design_values(scenario, vars_, z: ca.SX) -> dict:
    """The tunable keys as expressions of the log-scale coordinates z (each Variable of `synthesis.candidates.variables`)."""
    from ..scenario.tune import TUNABLE
    n = scenario.n
    vals: dict[str, list] = {}
    for i, v in enumerate(vars_):
        x = v.lo * ca.exp(z[i] * math.log(v.hi / v.lo))
        cur = vals.setdefault(v.key, [ca.SX(b) for b in v.base])
        if v.joint is not None:
            cur[v.joint] = x
        else:
            for j, r in enumerate(v.ratio):
                cur[j] = x * r
    out = {}
    for key, entries in vals.items():
        per_joint = TUNABLE[key][0]
        out[key] = ca.vertcat(*entries) if per_joint else entries[0]
        if per_joint and len(entries) == 1 and n > 1:
            out[key] = ca.repmat(entries[0], n, 1)
    return out


def _mapped(layout: dict, zd0: np.ndarray, values: dict) -> ca.SX:
    """The design's numbers (layout of `simulation.closedloop.design_parameters`) with the searched keys' entries
    replaced by their expressions in z (`design_values`), the others at the scenario's values."""
    out = ca.SX(ca.DM(zd0))
    for key, expr in values.items():
        if key not in layout:
            raise ValueError(f"{key} is not one of the design's numbers the closed loop takes as parameters")
        i, shape = layout[key]
        m = int(np.prod(shape)) if shape else 1
        out[i:i + m] = ca.vec(expr) if m > 1 else expr
    return out


def _funnel_order(scenario, values: dict):
    """1 - phi_inf/phi0 per joint (>= 0: the e2 funnel narrows, as verify's funnel.parameters requires) when the
    search moves phi0 or phi_inf, else None."""
    keys = ("funnel.e2.phi0", "funnel.e2.phi_inf")
    if not any(k in values for k in keys):
        return None
    from ..scenario.tune import current_value
    phi0, phi_inf = (values[k] if k in values else ca.DM(current_value(scenario, k)) for k in keys)
    return 1 - phi_inf / phi0


class GradientProblem:
    """The NLP of one scenario's `[tune]`: constraint and objective functions of z with exact Jacobians."""

    def __init__(self, scenario, spec, vars_, *, t_final: float, tau_max=None, sample_values=(),
                 grid_points: int = GRID_POINTS, tolerance=None, compiled: bool = True, progress=None,
                 coarse: float | None = COARSE_FRACTION):
        from ..simulation.closedloop import _design_values, design_parameters, loop_sx
        from ..simulation.compiled import compiled_dae, state_permutation
        from ..design import derive
        self.schedule = schedule()
        tolerance = self.schedule["tolerance"] if tolerance is None else tolerance
        self.sc, self.spec, self.vars = scenario, spec, vars_
        self.d = d = len(vars_)
        self.n = n = scenario.n
        self.T = float(t_final)
        self.K = K = int(grid_points)
        self.tau_max = None if tau_max is None else np.broadcast_to(np.asarray(tau_max, float), (n,)).copy()
        z = ca.SX.sym("z", d)
        values = design_values(scenario, vars_, z)
        order = _funnel_order(scenario, values)
        # The DAE takes all the design's numbers as parameters zd (as the simulated closed loop does), the search
        # coordinates z map into them outside it: every tune of one scenario, whatever its [tune] parameters and
        # bounds, and the coarse pass run on one compiled DAE.
        zd_names, zd0, layout = design_parameters(scenario)
        zd = ca.SX.sym("zd", len(zd_names))
        design = derive(scenario, values=_design_values(layout, zd))
        zmap = ca.Function("tune_zmap", [z], [_mapped(layout, zd0, values)])
        L = loop_sx(scenario, design, float(scenario.simulation.smoothing_width))
        P = ca.vertcat(zd, L["p"])
        self.grid = np.linspace(0.0, self.T, K + 1)
        opts = {"abstol": tolerance[0], "reltol": tolerance[1], "max_num_steps": MAX_STEPS, "linear_solver": "csparse",
                "disable_internal_warnings": True, "show_eval_warnings": False,
                # no second-order correction of the sensitivities' Newton matrix: it needs the DAE's second
                # derivatives and costs ~70 % more per Jacobian, for the same derivatives (tests/test_tune_gradient.py)
                "second_order_correction": False}
        perm, where = state_permutation(n, design.states)
        inv = np.argsort(perm)
        xi, ode = L["x"][list(perm)], L["xdot_p"][list(perm)]
        drop = [(where["x_esn"].start, where["x_esn"].stop)] if "x_esn" in where else None
        dae = compiled_dae("symfunnel_tune", L["t"], xi, P, ode, forward=True, drop=drop, progress=progress) \
            if compiled else None
        #: "compiled" (the DAE, its Newton Jacobian and forward derivative as generated C) or "vm"
        self.code = "compiled" if dae is not None else "vm"
        integ = ca.integrator("tune_loop", "cvodes", dae if dae is not None else
                              {"t": L["t"], "x": xi, "p": P, "ode": ode}, 0.0, list(self.grid[1:]), opts)
        sig = L["signals_p"]
        out = ca.Function("tune_signals", [L["t"], L["x"], P], [sig["tau"], sig["m1"], sig["m2"], sig["e1"]])
        outm = out.map(K + 1)
        # the plants: the nominal one and the uncertainty samples, each (plant parameters, initial state)
        plants = [(L["p0"], L["x0"])]
        if len(sample_values):
            from types import SimpleNamespace

            from ..scenario.uncertainty import run_inputs
            where = {k: i for i, k in enumerate(L["p_names"])}
            for vals in sample_values:
                params, x0 = run_inputs(scenario.campaign, SimpleNamespace(x0=L["x0"], n=n), vals)
                pv = np.array(L["p0"], float)
                for k, v in params.items():
                    pv[where[k]] = v
                plants.append((pv, x0))
        self.nplants = len(plants)
        zM = ca.MX.sym("z", d)
        tgrid = ca.DM(self.grid).T
        cons, taus, ise = [], [], None
        for i, (pv, x0) in enumerate(plants):
            Pm = ca.vertcat(zmap(zM), ca.DM(np.asarray(pv, float)))
            x0v = np.asarray(x0, float)
            xf = integ(x0=ca.DM(x0v[perm]), p=Pm)["xf"]
            X = ca.horzcat(ca.DM(x0v), xf[list(inv), :])
            tau, m1, m2, e1 = outm(tgrid, X, ca.repmat(Pm, 1, K + 1))
            cons += [ca.vec(m1) - spec.margin, ca.vec(m2) - spec.margin]
            if self.tau_max is not None:
                lim = ca.repmat(ca.DM(self.tau_max), 1, K + 1)
                cons += [ca.vec(1 - tau / lim), ca.vec(1 + tau / lim)]
            if i == 0:
                taus = tau
                E = ca.sum1(e1 ** 2)
                ise = ca.sum2(0.5 * (E[:, 1:] + E[:, :-1]) * ca.DM(np.diff(self.grid)).T)
        if order is not None:          # the e2 funnel must narrow: phi0 >= phi_inf (1 - phi_inf/phi0 >= 0)
            cons.append(ca.Function("tune_order", [z], [order])(zM))
        g = ca.vertcat(*cons)
        self.ng = int(g.numel())
        #: constraint values (>= 0 holds) of z on the grid, for every plant
        self.g = ca.Function("tune_g", [zM], [g])
        #: the nominal run's torque on the grid (n x K+1) and ISE
        self.figures = ca.Function("tune_figures", [zM], [taus, ise])
        self._z, self._g, self._tau, self._ise = zM, g, taus, ise
        #: the same problem over the first `coarse` of the horizon, solved first (`solve`), or None
        self.coarse = None
        if coarse is not None and 0 < coarse < 1 and K >= 20:
            self.coarse = GradientProblem(scenario, spec, vars_, t_final=self.T * coarse, tau_max=tau_max,
                                          sample_values=sample_values, grid_points=max(10, int(round(K * coarse))),
                                          tolerance=tolerance, compiled=compiled, progress=progress, coarse=None)

    def jacobian(self) -> ca.Function:
        """dg/dz (CVODES forward sensitivities through CasADi)."""
        return ca.Function("tune_dg", [self._z], [ca.jacobian(self._g, self._z)])

    def solve(self, z0, *, objective: str, ref: float, wall_s: float, max_iter: int = MAX_ITER,
              progress=None) -> dict:
        """IPOPT from z0, first over the coarse horizon (`coarse`), then over the whole one from that result (only a
        polish of at most POLISH_ITER iterations, none when 0, when the result already meets the whole horizon's
        constraints):
        {"z", "status", "success", "iterations", "f", "coarse": the first pass's {"status", "iterations", "z"} or
        None}; limited-memory Hessian."""
        say = progress or (lambda s: None)
        t0 = time.perf_counter()
        first = None
        if self.coarse is not None:
            say(f"coarse pass: IPOPT over the first {self.coarse.T:g} s of the horizon")
            first = self.coarse.solve(z0, objective=objective, ref=ref,
                                      wall_s=self.schedule["coarse_wall_share"] * wall_s, max_iter=max_iter,
                                      progress=progress)
            say(f"coarse pass: {first['status']} after {first['iterations']} iteration(s); now the whole horizon")
            if np.all(np.isfinite(first["z"])):
                z0 = first["z"]
        warm = False
        if first is not None and first["success"] or first is not None and "best feasible" in first["status"]:
            try:                  # the coarse result meets the whole horizon's constraints: only a polish is left
                warm = bool(np.min(np.asarray(self.g(z0), float)) >= 0.0)
            except RuntimeError:
                warm = False
        if warm and self.schedule["polish_iter"] == 0:
            say("coarse pass: its result meets the whole horizon's grid constraints; no polish (POLISH_ITER = 0)")
            return {"z": np.asarray(z0, float), "status": "coarse result, meets the whole horizon's grid constraints",
                    "success": True, "iterations": 0, "f": first["f"],
                    "coarse": {k: first[k] for k in ("status", "iterations", "z")}}
        r = self._solve(z0, objective=objective, ref=ref, wall_s=max(1.0, wall_s - (time.perf_counter() - t0)),
                        max_iter=min(max_iter, self.schedule["polish_iter"]) if warm else max_iter, say=say,
                        warm=warm)
        r["coarse"] = None if first is None else {k: first[k] for k in ("status", "iterations", "z")}
        return r

    def _solve(self, z0, *, objective: str, ref: float, wall_s: float, max_iter: int, say, warm: bool = False) -> dict:
        """One IPOPT run on this problem's horizon. What CasADi and IPOPT print themselves (a failed evaluation dumps
        its arguments, hundreds of lines) is silenced at the file descriptors and summarised in one warning line."""
        from ..core.lifecycle import quiet_c_output
        with quiet_c_output("IPOPT"):
            return self._ipopt(z0, objective=objective, ref=ref, wall_s=wall_s, max_iter=max_iter, say=say, warm=warm)

    def _ipopt(self, z0, *, objective: str, ref: float, wall_s: float, max_iter: int, say, warm: bool = False) -> dict:
        """`_solve`'s IPOPT run; `warm`: z0 is feasible and near a solution, so the barrier starts small (IPOPT's
        default mu_init = 0.1 first pushes the epigraph variable and every slack away from their bounds, which costs
        iterations to undo)."""
        d = self.d
        zM = self._z
        if objective == "peak_torque":
            s = ca.MX.sym("s")
            x = ca.vertcat(zM, s)
            tau = ca.vec(self._tau)
            g = ca.vertcat(self._g, s * ref - tau, s * ref + tau)
            f = s
            tau0 = np.asarray(self.figures(z0)[0], float)      # RuntimeError: the start does not integrate
            s0 = float(np.max(np.abs(tau0))) / ref * 1.01 if np.all(np.isfinite(tau0)) else 2.0
            # the epigraph variable never needs to exceed the start's peak or the limit: keeps IPOPT out of designs
            # whose torque is many times the user's
            top = max(s0, 1.0 if self.tau_max is None else float(np.max(self.tau_max)) / ref)
            x0 = np.concatenate([z0, [min(s0, top)]])
            lbx, ubx = [0.0] * d + [0.0], [1.0] * d + [top]
        else:
            x, g, f = zM, self._g, self._ise / ref
            x0 = np.asarray(z0, float)
            lbx, ubx = [0.0] * d, [1.0] * d
        t0 = time.perf_counter()
        log = ProgressCallback(x.numel(), g.numel(), d, say, t0)
        opts = {"ipopt.hessian_approximation": "limited-memory", "ipopt.max_iter": int(max_iter),
                "ipopt.max_wall_time": max(1.0, float(wall_s)), "ipopt.print_level": 0, "ipopt.sb": "yes",
                "print_time": False, "ipopt.tol": 1e-6, "ipopt.acceptable_tol": 1e-4,
                "ipopt.constr_viol_tol": 1e-6, "iteration_callback": log, "error_on_fail": False}
        if self.schedule["stall"]:        # acceptable once the objective stalls on feasible iterates (STALL_*)
            opts.update({"ipopt.acceptable_tol": 1e10, "ipopt.acceptable_iter": STALL_ITER,
                         "ipopt.acceptable_obj_change_tol": STALL_CHANGE, "ipopt.acceptable_constr_viol_tol": 1e-6})
        if warm:
            opts.update({"ipopt.mu_init": 1e-5, "ipopt.bound_push": 1e-6, "ipopt.bound_frac": 1e-6})
        solver = ca.nlpsol("tune_nlp", "ipopt", {"x": x, "f": f, "g": g}, opts)
        try:
            r = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=0.0, ubg=ca.inf)
        except RuntimeError as exc:
            from ..core.lifecycle import reraise_interrupt
            reraise_interrupt(exc)
            return {"z": np.asarray(z0, float), "status": f"error: {str(exc).splitlines()[-1][:200]}",
                    "success": False, "iterations": log.iterations, "f": math.nan}
        st = solver.stats()
        z = np.clip(np.asarray(r["x"]).ravel()[:d], 0.0, 1.0)
        out = {"z": z, "status": st.get("return_status", "?"), "success": bool(st.get("success", False)),
               "iterations": int(st.get("iter_count", log.iterations)), "f": float(r["f"])}
        if log.best is not None and not (out["success"] and out["f"] <= log.best[0]):
            # IPOPT stopped elsewhere (limit, restoration): its best grid-feasible iterate is the result
            out.update(z=np.clip(log.best[1], 0.0, 1.0), f=log.best[0], status=out["status"] + ", best feasible "
                       f"iterate {log.best[2]}")
        return out


class ProgressCallback(ca.Callback):
    """IPOPT's iteration callback: one progress line per iteration (objective, constraint violation, time)."""

    def __init__(self, nx: int, ng: int, d: int, say, t0: float):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.d, self.say, self.t0 = nx, ng, d, say, t0
        self.iterations = 0
        self.best = None          # (objective, z, iteration) of the best iterate that meets every grid constraint
        self.construct("tune_progress", {})

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        name = ca.nlpsol_out(i)
        if name in ("f",):
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def eval(self, arg):
        g = np.asarray(arg[ca.nlpsol_out().index("g")]).ravel()
        viol = float(np.max(np.maximum(-g, 0.0))) if g.size else 0.0
        f = float(arg[ca.nlpsol_out().index("f")])
        if viol <= 1e-6 and np.isfinite(f) and (self.best is None or f < self.best[0]):
            self.best = (f, np.asarray(arg[ca.nlpsol_out().index("x")]).ravel()[:self.d].copy(), self.iterations)
        self.say(f"ipopt iteration {self.iterations}: objective {f:.5g}, constraint violation {viol:.3g} "
                 f"({time.perf_counter() - self.t0:.1f} s)")
        self.iterations += 1
        return [0]
