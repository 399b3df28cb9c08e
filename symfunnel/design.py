"""The one symbolic derivation of the funnel-backstepping design, in CasADi SX (see docs/derivation.md).

Every signal is built once here, as an SX expression in the base symbols
t, q, dq, qd, dqd, ddqd, x_esn, w_hat; everything else (evaluation, audit, simulation, code, report)
reads these expressions and never re-derives them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

from .errors import InputError
from .names import SIGNALS

BASE_INPUTS = ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat")


@dataclass
class Design:
    """Signals of one scenario's design as SX, with the base symbols they are written in."""

    scenario: object
    sym: dict[str, ca.SX]
    signals: dict[str, ca.SX]
    reference_t: dict[str, ca.SX]          # qd, dqd, ddqd as SX in t (from the scenario's expressions)
    esn: object
    constants: dict[str, ca.SX]
    _functions: dict = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.scenario.n

    @cached_property
    def _owner(self) -> dict[str, tuple[str, int]]:
        """Scalar symbol name -> (base input, position), for ordering free variables canonically."""
        out = {}
        for k in BASE_INPUTS:
            s = ca.vec(self.sym[k])
            for i in range(s.numel()):
                out[s[i].name()] = (k, i)
        return out

    def free_symbols(self, name: str) -> list[str]:
        """Names of the scalar symbols a signal depends on, in canonical order (e.g. ['t', 'q1', 'qd1'])."""
        order = {k: j for j, k in enumerate(BASE_INPUTS)}
        names = [v.name() for v in ca.symvar(self.signals[name])]
        return sorted(names, key=lambda s: (order[self._owner[s][0]], self._owner[s][1]))

    def inputs_of(self, name: str) -> list[str]:
        """The base inputs a signal actually depends on, in canonical order."""
        used = {self._owner[s][0] for s in self.free_symbols(name)}
        return [k for k in BASE_INPUTS if k in used]

    def function(self, name: str, inputs: list[str] | tuple[str, ...] | None = None,
                 outputs: list[str] | None = None) -> ca.Function:
        """A casadi.Function `name`(inputs) -> outputs (default: the signal `name` of its own inputs)."""
        outputs = outputs or [name]
        if inputs is None:
            deps = set()
            for o in outputs:
                deps |= set(self.inputs_of(o))
            inputs = [k for k in BASE_INPUTS if k in deps]
        key = (name, tuple(inputs), tuple(outputs))
        if key not in self._functions:
            self._functions[key] = ca.Function(
                name, [self.sym[k] for k in inputs], [self.signals[o] for o in outputs],
                list(inputs), list(outputs), {"cse": True, "allow_duplicate_io_names": True})
        return self._functions[key]

    def controller(self) -> ca.Function:
        """The controller of the generated-code contract: (t, q, dq, qd, dqd, ddqd, x_esn, w_hat) -> (tau, x_esn_dot, w_hat_dot)."""
        return self.function("controller", BASE_INPUTS, ["tau", "x_esn_dot", "w_hat_dot"])

    @cached_property
    def reference(self) -> ca.Function:
        """t -> (qd, dqd, ddqd) from the scenario's reference expressions."""
        t = self.sym["t"]
        return ca.Function("reference", [t], [self.reference_t[k] for k in ("qd", "dqd", "ddqd")],
                           ["t"], ["qd", "dqd", "ddqd"])

    def ops(self, name: str) -> int:
        """Size of a signal in operations (tape instructions that compute something)."""
        return count_ops(self.function(name))


def count_ops(f: ca.Function) -> int:
    """Number of real operations on an SX function's tape (no inputs, outputs, constants or copies)."""
    from .codegen.tape import count_ops as tape_ops
    return tape_ops(f)["operations"]


def _named(prefix: str, n: int) -> ca.SX:
    return ca.vertcat(*[ca.SX.sym(f"{prefix}{i + 1}") for i in range(n)])


def derive(scenario) -> Design:
    """Build every signal of the design for a scenario, once, as SX (the single source of truth)."""
    from .esn import ESN, ESNConfig

    sc = scenario
    model = sc.model
    n = model.n
    t = ca.SX.sym("t")
    q, dq = model.q, model.dq
    qd, dqd, ddqd = _named("qd", n), _named("dqd", n), _named("ddqd", n)
    es = sc.esn
    try:
        esn = ESN(ESNConfig(size=es.size, leak=es.leak, time_constant=es.time_constant,
                            spectral_radius=es.spectral_radius, input_scaling=es.input_scaling,
                            sparsity=es.sparsity, seed=es.seed, bias=es.bias),
                  n_inputs=n * len(es.inputs))
    except ValueError as exc:
        raise InputError(getattr(exc, "reason", str(exc)), file=sc.file,
                         key="esn." + getattr(exc, "key", "") if getattr(exc, "key", "") else "esn",
                         expected=getattr(exc, "expected", None)) from None
    x_esn = ca.SX.sym("x_esn", es.size)
    w_hat = ca.SX.sym("w_hat", esn.n_regressor, n)
    sym = dict(t=t, q=q, dq=dq, qd=qd, dqd=dqd, ddqd=ddqd, x_esn=x_esn, w_hat=w_hat)

    k1 = ca.DM(sc.k1)
    k2 = ca.DM(sc.k2)
    gamma = ca.DM(sc.gamma)
    sigma = ca.DM(sc.sigma)

    s: dict[str, ca.SX] = {}
    s["qd"], s["dqd"], s["ddqd"] = qd, dqd, ddqd
    s["M"] = model.numeric(model.M)
    s["C"] = model.numeric(model.C)
    s["G"] = model.numeric(model.G)

    for i, key in ((1, "e1"), (2, "e2")):
        f = sc.funnels[key]
        F = ca.DM(f.phi0) * ca.exp(-ca.DM(f.a) * t) + ca.DM(f.phi_inf)
        s[f"F{i}"] = F
        s[f"dF{i}"] = ca.jtimes(F, t, ca.SX(1))

    # Step 1: the outer funnel loop on e1 = q - qd.
    s["e1"] = q - qd
    s["de1"] = dq - dqd
    s["zeta1"] = 1 / (s["F1"] - ca.fabs(s["e1"]))
    s["z1"] = s["e1"] * s["zeta1"]
    s["mu1"] = s["F1"] * s["zeta1"] ** 2
    s["alpha2"] = dqd + s["dF1"] / s["F1"] * s["e1"] - k1 * s["z1"]

    # Exact derivatives along the flow by forward-mode AD: d/dt = d/dt + dq.d/dq + dqd.d/dqd + ddqd.d/ddqd.
    x1 = ca.vertcat(t, q, qd, dqd)
    v1 = ca.vertcat(1, dq, dqd, ddqd)
    s["alpha2_dot"] = ca.jtimes(s["alpha2"], x1, v1)
    s["z1_dot"] = ca.jtimes(s["z1"], x1, v1)

    # Step 2: the inner funnel loop on e2 = dq - alpha2.
    s["e2"] = dq - s["alpha2"]
    s["zeta2"] = 1 / (s["F2"] - ca.fabs(s["e2"]))
    s["z2"] = s["e2"] * s["zeta2"]
    s["mu2"] = s["F2"] * s["zeta2"] ** 2
    s["Phi"] = esn.regressor(x_esn)
    s["v"] = (s["alpha2_dot"] + s["dF2"] / s["F2"] * s["e2"] - k2 * s["z2"]
              - s["mu1"] * s["z1"] / (s["zeta2"] * s["mu2"]))
    s["tau"] = ca.mtimes(s["M"], s["v"] - ca.mtimes(w_hat.T, s["Phi"])) + ca.mtimes(s["C"], dq) + s["G"]
    # The nominal model under tau accelerates by exactly v - W_hat^T Phi (tau is its inverse dynamics).
    s["ddq"] = s["v"] - ca.mtimes(w_hat.T, s["Phi"])
    s["de2"] = s["ddq"] - s["alpha2_dot"]
    x2 = ca.vertcat(t, q, dq, qd, dqd)
    v2 = ca.vertcat(1, dq, s["ddq"], dqd, ddqd)
    s["z2_dot"] = ca.jtimes(s["z2"], x2, v2)
    s["w_hat_dot"] = gamma * (ca.mtimes(s["Phi"], (s["mu2"] * s["z2"]).T) - sigma * w_hat)

    # Echo state network driven by normalised design signals.
    feeds = []
    for name in es.inputs:
        scale = es.scales.get(name, 1.0)
        feeds.append((s[name] if name in s else sym[name]) / scale)
    s["x_esn_dot"] = esn.xdot(x_esn, ca.vertcat(*feeds))

    # Reference as functions of t, from the scenario's expressions; derivatives by AD.
    ref_env = {"t": t}
    qd_t = ca.vertcat(*[e.to_casadi(ref_env) for e in sc.reference])
    dqd_t = ca.jtimes(qd_t, t, ca.SX(1))
    ddqd_t = ca.jtimes(dqd_t, t, ca.SX(1))
    reference_t = {"qd": qd_t, "dqd": dqd_t, "ddqd": ddqd_t}

    constants = {"k1": ca.SX(k1), "k2": ca.SX(k2), "Gamma": ca.SX(gamma), "sigma": ca.SX(sigma)}
    return Design(scenario=sc, sym=sym, signals=s, reference_t=reference_t, esn=esn, constants=constants)


# --- evaluation ---------------------------------------------------------------------------------

def _as_array(value, shape, what: str, file: str | None, scalar_ok: bool = False) -> np.ndarray:
    from .inputs import number_array
    return number_array(value, tuple(shape), file=file, key=what, scalar_ok=scalar_ok)


def point_inputs(design: Design, point: dict, *, file: str | None = None, key: str = "") -> dict:
    """Base-input values of one point {t, q, dq[, x_esn, w_hat]} with the reference taken from the scenario."""
    n = design.n
    if not isinstance(point, dict):
        raise InputError("is not an object", file=file, key=key or "(point)",
                         expected='{"t": ..., "q": [...], "dq": [...]}')
    allowed = ["t", "q", "dq", "x_esn", "w_hat"]
    from .validate import did_you_mean
    for k in point:
        if k not in allowed:
            raise InputError(f"unknown key{did_you_mean(k, allowed)}", file=file, key=(key + "." if key else "") + k,
                             expected="one of " + ", ".join(allowed))
    for k in ("t", "q", "dq"):
        if k not in point:
            raise InputError("is missing", file=file, key=(key + "." if key else "") + k, expected="a value")
    pre = (key + ".") if key else ""
    t = float(_as_array(point["t"], (1,), pre + "t", file)[0])
    q = _as_array(point["q"], (n,), pre + "q", file)
    dq = _as_array(point["dq"], (n,), pre + "dq", file)
    N = design.sym["x_esn"].numel()
    x = _as_array(point.get("x_esn", [0.0] * N), (N,), pre + "x_esn", file)
    wshape = design.sym["w_hat"].shape
    w = _as_array(point.get("w_hat", 0.0), wshape, pre + "w_hat", file, scalar_ok=True)
    qd, dqd, ddqd = (np.array(v).ravel() for v in design.reference(t))
    return dict(t=t, q=q, dq=dq, qd=qd, dqd=dqd, ddqd=ddqd, x_esn=x, w_hat=w)


def funnel_level(design: Design, inp: dict) -> tuple[int, list[str]]:
    """How many funnels the point is inside (0, 1 or 2), with a message for the first one it is not."""
    F = design.function("funnel_signals", BASE_INPUTS, ["e1", "F1", "e2", "F2"])
    e1, F1, e2, F2 = (np.array(v).ravel() for v in F(*[inp[k] for k in BASE_INPUTS]))
    bad1 = [i for i in range(design.n) if not abs(e1[i]) < F1[i]]
    if bad1:
        i = bad1[0]
        return 0, [f"point outside funnel e1 at joint {i + 1}: |e1| = {abs(e1[i]):.6g} >= F1 = {F1[i]:.6g}"]
    bad2 = [i for i in range(design.n) if not abs(e2[i]) < F2[i]]
    if bad2:
        i = bad2[0]
        return 1, [f"point outside funnel e2 at joint {i + 1}: |e2| = {abs(e2[i]):.6g} >= F2 = {F2[i]:.6g}"]
    return 2, []


def evaluate(design: Design, point: dict, *, file: str | None = None, key: str = "",
             warn=None) -> dict:
    """Every model matrix and design signal at one point; signals needing a funnel the point is outside are None."""
    inp = point_inputs(design, point, file=file, key=key)
    level, msgs = funnel_level(design, inp)
    for m in msgs:
        if warn is not None:
            warn(m)
        else:
            import warnings
            warnings.warn(m, stacklevel=2)
    names = [k for k in SIGNALS if k in design.signals] + ["x_esn_dot"]
    f = design.function("all_signals", BASE_INPUTS, names)
    vals = f(*[inp[k] for k in BASE_INPUTS])
    out = {}
    for k, v in zip(names, vals):
        need = SIGNALS.get(k, ("", 2))[1]
        if need > level:
            out[k] = None
            continue
        a = np.array(v)
        out[k] = a.ravel().tolist() if a.shape[1] == 1 else a.tolist()
    return out
