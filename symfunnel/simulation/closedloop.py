"""The closed loop as one ODE x' = f(t, x), assembled from the one symbolic design (no re-derivation).

State x = [q; dq; controller states...] with the controller states in the order the design declares
(`Design.states`; for the paper's ESN design x_esn, then vec(W_hat) column-major, (N+1) x n, so n = 2, N = 50 gives
2 + 2 + 50 + 102 = 156).

Controller (known): tau and the state rates (x_esn_dot, w_hat_dot, ...) are `Design.signals` with the reference
substituted as functions of t (`Design.reference_t`). Plant (unknown to the controller): `plant.equations`, the one
source of the true robot's accelerations that the sampled loop and the certificates use too. Its uncertain
quantities are the symbols p of `xdot_p` / `signals_p`, which `simulate` compiles once and evaluates at any p;
`xdot`, `signals`, `f` and `outputs` are the same loop at this scenario's p.

The nominal model under tau accelerates by ddq_nom = v - W_hat^T Phi (`signals['ddq']`), so the true unknown term
the ESN estimates is f_true = ddq_plant - ddq_nom and its estimate is w_phi = W_hat^T Phi.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..plant.equations import plant_acceleration, plant_parameters
from ..plant.nonlinearities import check_smoothing_width

if TYPE_CHECKING:
    from ..design import Design
    from ..scenario import Scenario

#: logged signals (name -> shape kind): 'n' per joint, 'N' per reservoir unit, '1' scalar
OUTPUT_NAMES = ("qd", "dqd", "ddqd", "tau", "tau_applied", "e1", "F1", "e2", "F2", "z1", "z2", "alpha2",
                "friction", "disturbance", "ddq", "ddq_nom", "f_true", "w_phi", "m1", "m2")


@dataclass
class ClosedLoop:
    """The closed-loop ODE of one scenario: symbolic state, right-hand side and logged signals as casadi Functions."""

    design: Design
    scenario: Scenario
    n: int
    N: int
    width: float
    t: ca.SX                      # time symbol
    x: ca.SX                      # state vector [q; dq; x_esn; vec(w_hat)]
    xdot: ca.SX                   # right-hand side in (t, x)
    f: ca.Function                # f(t, x) -> xdot
    outputs: ca.Function          # outputs(t, x) -> logged signals (OUTPUT_NAMES)
    x0: np.ndarray
    signals: dict = field(default_factory=dict, repr=False)   # name -> SX in (t, x), the outputs' expressions
    plant_parts: dict = field(default_factory=dict, repr=False)
    # the same loop with the plant's uncertain quantities as parameters p (layout: plant_parameters)
    p: ca.SX = field(default=None, repr=False)
    p_names: list = field(default_factory=list, repr=False)
    p0: np.ndarray = field(default=None, repr=False)        # this scenario's values of p
    xdot_p: ca.SX = field(default=None, repr=False)         # right-hand side in (t, x, p)
    signals_p: dict = field(default_factory=dict, repr=False)   # logged signals in (t, x, p)
    # the same loop with the design's numbers (layout: design_parameters, then the smoothing width if > 0) as
    # parameters z too, what is compiled;
    # None where the design handed in is not the scenario's derivation (then its numbers stay folded in)
    z: ca.SX = field(default=None, repr=False)
    z_names: list = field(default_factory=list, repr=False)
    z0: np.ndarray = field(default=None, repr=False)        # this design's values of z
    xdot_pz: ca.SX = field(default=None, repr=False)        # right-hand side in (t, x, p, z)
    signals_pz: dict = field(default_factory=dict, repr=False)  # logged signals in (t, x, p, z)

    @property
    def nx(self) -> int:
        """Number of states."""
        return int(self.x.numel())

    @property
    def slices(self) -> dict[str, slice]:
        """Where q, dq and each controller state sit in the state vector."""
        out = {"q": slice(0, self.n), "dq": slice(self.n, 2 * self.n)}
        i = 2 * self.n
        for name, (r, c) in self.design.states:
            out[name] = slice(i, i + r * c)
            i += r * c
        return out

    def pack(self, q, dq, *states) -> np.ndarray:
        """State vector from its parts, controller states in the design's order (matrices stored column-major)."""
        parts = [np.ravel(q), np.ravel(dq)]
        for (name, shape), v in zip(self.design.states, states):
            parts.append(np.broadcast_to(np.asarray(v, dtype=float).reshape(shape if shape[1] > 1 else -1),
                                         shape if shape[1] > 1 else (shape[0],)).ravel(order="F"))
        return np.concatenate(parts).astype(float)

    def unpack(self, x) -> dict[str, np.ndarray]:
        """Parts of a state vector (n_x,) or of a trajectory (T, n_x); matrix states as (.., rows, cols)."""
        x = np.asarray(x, dtype=float)
        s = self.slices
        out = {k: x[..., s[k]] for k in ("q", "dq")}
        for name, (r, c) in self.design.states:
            v = x[..., s[name]]
            out[name] = v if c == 1 else np.swapaxes(v.reshape(v.shape[:-1] + (c, r)), -1, -2)
        return out

    def rhs(self, t: float, x) -> np.ndarray:
        """xdot at one point, as numbers."""
        return np.asarray(self.f(t, x)).ravel()

    def evaluate_outputs(self, t, X) -> dict[str, np.ndarray]:
        """Logged signals along a trajectory: t (T,), X (T, n_x) -> name -> (T, ...) arrays (time first)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        X = np.atleast_2d(np.asarray(X, dtype=float))
        T = t.size
        if T == 0:
            return {k: np.zeros((0, self.n)) for k in OUTPUT_NAMES}
        fm = self.outputs.map(T)
        vals = fm(t.reshape(1, -1), X.T)
        out = {}
        for k, v in zip(OUTPUT_NAMES, vals):
            out[k] = np.asarray(v).T          # (T, rows)
        return out


#: the design's numbers a compiled closed loop takes as parameters (`design_parameters`): the keys `derive`'s
#: `values` replaces; the funnels' keys only for the exponential shape (an expression funnel keeps its numbers)
DESIGN_KEYS = ("controller.k1", "controller.k2", "adaptation.gamma", "adaptation.sigma",
               "funnel.e1.phi0", "funnel.e1.phi_inf", "funnel.e1.a", "funnel.e2.phi0", "funnel.e2.phi_inf",
               "funnel.e2.a")


def design_parameters(scenario) -> tuple[list[str], np.ndarray, dict]:
    """Names, values and layout (key -> (first index, shape)) of the design's numbers that the compiled closed loop
    takes as parameters z beside the plant's: gains, adaptation rates and exponential funnels' shapes, per joint as
    key[j] (1-based). Designs that differ only in them run on one compiled loop (tune's candidates, a sweep of
    gains, a user's edits), where folding them in as constants compiled each anew."""
    names, vals, layout = [], [], {}
    for key in DESIGN_KEYS:
        if key.startswith("funnel."):
            _, fk, attr = key.split(".")
            shape = scenario.funnels[fk]
            if attr not in getattr(shape, "KEYS", ()) or not hasattr(shape, attr):
                continue
            v = np.asarray(getattr(shape, attr), dtype=float)
        else:
            v = np.asarray({"controller.k1": scenario.k1, "controller.k2": scenario.k2,
                            "adaptation.gamma": scenario.gamma, "adaptation.sigma": scenario.sigma}[key], dtype=float)
        layout[key] = (len(vals), v.shape)
        if v.ndim == 0:
            names.append(key)
        else:
            names.extend(f"{key}[{j + 1}]" for j in range(v.size))
        vals.extend(float(x) for x in v.ravel())
    return names, np.array(vals, dtype=float), layout


def _design_values(layout: dict, z: ca.SX) -> dict:
    """`derive`'s values: each key of `design_parameters` as its entries of z (a column per joint, a scalar)."""
    out = {}
    for key, (i, shape) in layout.items():
        m = int(np.prod(shape)) if shape else 1
        out[key] = z[i] if not shape else z[i:i + m]
    return out


def loop_sx(scenario, design, width: float) -> dict:
    """The closed loop's symbols and expressions before any number is put in: t, x, p (the plant's quantities,
    layout `plant_parameters`), p0 (this scenario's p), xdot_p and the logged signals in (t, x, p), the plant's
    parts, x0. A design derived with symbolic parameter values (`design.derive(values=...)`) leaves them free in
    xdot_p and the signals (how tune differentiates the closed loop with respect to its gains)."""
    d = design
    sym = d.sym
    n = d.n
    t, q, dq = sym["t"], sym["q"], sym["dq"]
    states = [name for name, _ in d.states]
    ref_syms = ca.vertcat(sym["qd"], sym["dqd"], sym["ddqd"])
    ref_t = ca.vertcat(d.reference_t["qd"], d.reference_t["dqd"], d.reference_t["ddqd"])
    S = d.signals
    names = ["tau", *[f"{k}_dot" for k in states], "ddq", "e1", "F1", "e2", "F2", "z1", "z2", "alpha2", "Phi",
             "qd", "dqd", "ddqd"]
    subbed = ca.substitute([S[k] for k in names], [ref_syms], [ref_t])
    sg = dict(zip(names, subbed))
    tau = sg["tau"]
    p_names, p0 = plant_parameters(scenario)
    p = ca.SX.sym("p", len(p_names))
    plant = plant_acceleration(scenario, q, dq, t, tau, width, p=p)
    ddq = plant["ddq"]
    x = ca.vertcat(q, dq, *[ca.vec(sym[k]) for k in states])
    xdot_p = ca.vertcat(dq, ddq, *[ca.vec(sg[f"{k}_dot"]) for k in states])

    w_hat = sym["w_hat"] if "w_hat" in sym else ca.SX(0, n)
    w_phi = ca.mtimes(w_hat.T, sg["Phi"]) if d.n_regressor else ca.SX.zeros(n, 1)
    f_true = ddq - sg["ddq"]
    outs = {
        "qd": sg["qd"], "dqd": sg["dqd"], "ddqd": sg["ddqd"], "tau": tau, "tau_applied": plant["tau_applied"],
        "e1": sg["e1"], "F1": sg["F1"], "e2": sg["e2"], "F2": sg["F2"], "z1": sg["z1"], "z2": sg["z2"],
        "alpha2": sg["alpha2"], "friction": plant["friction"], "disturbance": plant["disturbance"],
        "ddq": ddq, "ddq_nom": sg["ddq"], "f_true": f_true, "w_phi": w_phi,
        "m1": (sg["F1"] - ca.fabs(sg["e1"])) / sg["F1"], "m2": (sg["F2"] - ca.fabs(sg["e2"])) / sg["F2"],
    }
    sc = scenario
    init = d.variant.initial_states()
    x0 = np.concatenate([np.asarray(sc.q0, float), np.asarray(sc.dq0, float),
                         *[np.ravel(init[k], order="F") for k in states]])
    return {"t": t, "x": x, "p": p, "p_names": p_names, "p0": p0, "xdot_p": xdot_p,
            "signals_p": {k: ca.SX(outs[k]) for k in OUTPUT_NAMES}, "plant_p": {k: ca.SX(v) for k, v in plant.items()},
            "x0": x0, "N": sym["x_esn"].numel() if "x_esn" in sym else 0}


def build_closed_loop(scenario, design, *, width=None) -> ClosedLoop:
    """Assemble the closed-loop ODE of a scenario from its design."""
    w = scenario.simulation.smoothing_width if width is None else width
    if not (isinstance(w, (int, float)) and np.isfinite(w) and w >= 0):
        raise InputError(f"is {w!r}", file=scenario.file, key="simulation.smoothing_width",
                         expected="a finite number >= 0")
    w = check_smoothing_width(float(w), scenario.plant, file=scenario.file if width is None else None,
                              key="simulation.smoothing_width" if width is None else "--width")
    L, zg = _loops(scenario, design, w)
    t, x, p, p0, xdot_p, outs_p, parts_p = (L[k] for k in ("t", "x", "p", "p0", "xdot_p", "signals_p", "plant_p"))
    # the nominal loop in (t, x): p replaced by this scenario's values, for every consumer that takes (t, x)
    pk = list(parts_p)
    nom = ca.substitute([xdot_p] + [outs_p[k] for k in OUTPUT_NAMES] + [parts_p[k] for k in pk], [p],
                        [ca.DM(p0)])
    xdot = nom[0]
    outs = dict(zip(OUTPUT_NAMES, nom[1:1 + len(OUTPUT_NAMES)]))
    plant = dict(zip(pk, nom[1 + len(OUTPUT_NAMES):]))
    f = ca.Function("closed_loop", [t, x], [xdot], ["t", "x"], ["xdot"], {"cse": True})
    outputs = ca.Function("closed_loop_outputs", [t, x], [outs[k] for k in OUTPUT_NAMES], ["t", "x"],
                          list(OUTPUT_NAMES), {"cse": True})
    if w == 0.0:
        warnings.warn("smoothing_width = 0: exact sign friction and dead-zone kinks; CVODES may stall on them",
                      RuntimeWarning, stacklevel=2)
    cl = ClosedLoop(design=design, scenario=scenario, n=design.n, N=L["N"], width=w, t=t, x=x, xdot=xdot, f=f,
                    outputs=outputs, x0=L["x0"], signals=outs, plant_parts=plant, p=p, p_names=L["p_names"],
                    p0=p0, xdot_p=xdot_p, signals_p=outs_p)
    if zg is not None:
        cl.z, cl.z_names, cl.z0, cl.xdot_pz, cl.signals_pz = zg
    return cl


#: (plant scenario, width) pairs whose symbolic loops a design keeps (`_loops`), the oldest dropped first
_LOOPS_PER_DESIGN = 4


def _loops(scenario, design, w: float):
    """The loop's expressions (`loop_sx`) and its graph in the design's numbers z (`_design_parameter_graph`) for
    this plant scenario and width, kept on the design: simulating one design again (a bench, a rate search, a
    notebook) rebuilds neither. Their symbols are shared by every ClosedLoop built from them."""
    cache = design._functions.setdefault("closed_loops", {})
    key = (id(scenario), w)
    hit = cache.get(key)
    if hit is not None and hit[0] is scenario:
        return hit[1], hit[2]
    L = loop_sx(scenario, design, w)
    zg = _design_parameter_graph(scenario, design, w, L)
    while len(cache) >= _LOOPS_PER_DESIGN:
        cache.pop(next(iter(cache)))
    cache[key] = (scenario, L, zg)
    return L, zg


def _design_parameter_graph(scenario, design, w: float, L: dict):
    """(z, names, z0, xdot, signals) of the loop `L` with the design's numbers (and a smoothing width > 0) as
    symbols z: the same derivation with z for the numbers (its design from the design's own scenario, its plant
    from `scenario`), in L's t, x, p.
    Kept only if at z0 it gives L's right-hand side at the initial state and at a perturbed one to 1e-10 relative
    (constant folding rounds a few products differently); else None (a design handed in that is not its
    scenario's derivation, e.g. a hand-edited twin, keeps its numbers folded in)."""
    from ..design import derive
    d = design
    names, z0, layout = design_parameters(d.scenario)
    if w > 0:                  # the smoothing width too (0 is the exact, structurally different, kink)
        names, z0 = [*names, "simulation.smoothing_width"], np.append(z0, w)
    if not names:
        return None
    z = ca.SX.sym("z", len(names))
    try:
        Lz = loop_sx(scenario, derive(d.scenario, mutant=d.mutant, values=_design_values(layout, z)),
                     z[len(names) - 1] if w > 0 else w)
    except (TypeError, ValueError, RuntimeError):
        return None
    if Lz["x"].numel() != L["x"].numel() or Lz["p"].numel() != L["p"].numel():
        return None
    exprs = ca.substitute([Lz["xdot_p"], *[Lz["signals_p"][k] for k in OUTPUT_NAMES]], [Lz["t"], Lz["x"], Lz["p"]],
                          [L["t"], L["x"], L["p"]])
    fz = ca.Function("fz", [L["t"], L["x"], L["p"], z], [exprs[0]])
    fp = ca.Function("fp", [L["t"], L["x"], L["p"]], [L["xdot_p"]])
    x0 = np.asarray(L["x0"], dtype=float)
    rng = np.random.default_rng(0)
    for t, x in ((0.0, x0), (0.1, x0 + 1e-2 * rng.standard_normal(x0.shape))):
        a, b = np.asarray(fz(t, x, L["p0"], z0)).ravel(), np.asarray(fp(t, x, L["p0"])).ravel()
        if not np.allclose(a, b, rtol=1e-10, atol=1e-10 * float(np.max(np.abs(b), initial=1.0)), equal_nan=True):
            return None
    return z, names, z0, exprs[0], dict(zip(OUTPUT_NAMES, exprs[1:]))
