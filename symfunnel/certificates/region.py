"""The region a certificate holds on, built from the scenario, and the design's own signals written over it.

- Parameters: the plant's quantities in the layout of `plant.equations.plant_parameters`, each a point (its
  scenario value) or, for an `[[uncertainty]]` key, a box: uniform [low, high], normal mean +- 5 std, choice its
  hull. A per-joint quantity drawn once for every joint gets the same box on each joint (a superset).
- Dead-zone slopes: per joint the hull of both branches' slopes d(branch)/du, enclosed by branch and bound over
  u in [b_r, b_r + SLOPE_SPAN] (right) and [b_l - SLOPE_SPAN, b_l] (left) with the breakpoints' and scales' boxes
  (exact for the linear branches of the shipped scenarios: their slope is a constant), and the slopes attained
  there (at actual u) that a refutation is re-checked at.
- Joints (input gain): the box hull of the e1 funnel tube {q_d(t) + e : t in [0, T], |e| <= F1(t)}, from rigorous
  ranges of q_d and F1 over [0, T], intersected with the model's joint limits where it has them (URDF).
- The funnel region R_m (bounds, invariance): t in [0, T], e1 = s1 (1 - m) F1(t), e2 = s2 (1 - m) F2(t) with
  s1, s2 in [-1, 1]^n, so q = q_d(t) + e1 and dq = alpha2(t, q) + e2 follow the funnels. The design's graph is
  rewritten on it (`symfunnel.sx.rewrite`): its nodes e1 = q - q_d and e2 = dq - alpha2 are replaced by their
  region expressions (equal on R_m), so the interval evaluation never subtracts two wide intervals for them.
  Controller states enter as boxes that are not split.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..plant.equations import dead_zone_deviation, plant_acceleration, plant_parameters
from ..sx.branch import rigorous_range
from ..sx.interval import IntervalFunction
from ..sx.rewrite import replace_nodes

#: how far beyond its breakpoint a branch's slope is enclosed (the sampled check's span; exact for linear branches)
SLOPE_SPAN = 10.0


@dataclass
class ParameterBox:
    """The plant's parameter vector p as a box, and the initial state's box."""

    names: list[str]
    nominal: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    uncertain: list[str] = field(default_factory=list)       # the scenario keys that gave a box
    q0: tuple[np.ndarray, np.ndarray] | None = None
    dq0: tuple[np.ndarray, np.ndarray] | None = None

    def describe(self) -> dict:
        """The boxes of the uncertain entries, {name: [lo, hi]}."""
        return {k: [float(a), float(b)] for k, a, b in zip(self.names, self.lo, self.hi) if a < b}


def parameter_box(scenario) -> ParameterBox:
    """The plant's parameters as boxes from `[[uncertainty]]` (points elsewhere)."""
    names, p0 = plant_parameters(scenario)
    lo, hi = p0.copy(), p0.copy()
    n = scenario.n
    q0 = dq0 = None
    keys = []
    camp = scenario.campaign
    for unc in (camp.uncertainties if camp else []):
        a, b = (float(v) for v in unc.extremes())
        keys.append(unc.key)
        if unc.key in ("initial.q", "initial.dq"):
            box = (np.full(n, a), np.full(n, b))
            if unc.key == "initial.q":
                q0 = box
            else:
                dq0 = box
            continue
        cols = [k for k in names if k == unc.key or k.startswith(unc.key + "[")]
        for k in cols:
            j = names.index(k)
            lo[j], hi[j] = a, b
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        j = int(np.argmax(~(np.isfinite(lo) & np.isfinite(hi))))
        raise InputError("gives an unbounded parameter box", file=scenario.file, key=names[j],
                         expected="finite bounds")
    return ParameterBox(names, p0, lo, hi, keys, q0, dq0)


def slope_box(scenario, pbox: ParameterBox, backend: str = "arb") -> tuple[np.ndarray, np.ndarray, bool]:
    """Per joint (lo, hi) of the dead zone's branch slopes, and whether every slope is a constant of u."""
    r = slope_ranges(scenario, pbox, backend)
    return r["lo"], r["hi"], r["constant"]


def slope_ranges(scenario, pbox: ParameterBox, backend: str = "arb") -> dict:
    """Per joint the dead zone's slope hull: rigorous (lo, hi) and the attained (lo_seen, hi_seen) with the u, the
    branch and the scale where each is attained.

    Each branch's derivative d(branch)/du is enclosed over its domain by best-first branch and bound in the
    mean-value form (endpoint-tight for a monotone derivative, never a midpoint-radius inflation of the whole
    domain), times the scale's box with outward rounding. The attained slopes are the derivative's double values
    at actual points u (times a scale endpoint): a refutation is re-checked there, never at a slope the dead zone
    does not have."""
    n = scenario.n
    dz = scenario.plant.dead_zone
    if dz is None:
        one = np.ones(n)
        return {"lo": one, "hi": one.copy(), "lo_seen": one.copy(), "hi_seen": one.copy(), "constant": True,
                "where": [None] * n}
    u, bl, br = ca.SX.sym("u"), ca.SX.sym("b_l"), ca.SX.sym("b_r")
    env = {"u": u, "b_l": bl, "b_r": br}
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    lo_seen, hi_seen = np.full(n, np.inf), np.full(n, -np.inf)
    where: list = [dict() for _ in range(n)]
    constant = True

    def box(key, j):
        i = pbox.names.index(f"{key}[{j + 1}]")
        return pbox.lo[i], pbox.hi[i]
    for side, expr in (("right", dz.right), ("left", dz.left)):
        e = ca.SX(expr.to_casadi(env))
        de = ca.jacobian(e, u)
        constant = constant and not ca.depends_on(de, u)
        f = ca.Function("slope", [u, bl, br], [de], ["u", "b_l", "b_r"], ["d"])
        F = IntervalFunction(f, backend, form="mean_value")
        for j in range(n):
            bl_box, br_box = box("plant.dead_zone.b_l", j), box("plant.dead_zone.b_r", j)
            scale = box(f"plant.dead_zone.{side}_scale", j)
            ub = (br_box[0], br_box[1] + SLOPE_SPAN) if side == "right" else (bl_box[0] - SLOPE_SPAN, bl_box[1])
            rr = rigorous_range(F, {"u": ub, "b_l": bl_box, "b_r": br_box}, tol=1e-9, rel_tol=1e-6,
                                max_boxes=4000)
            a, b = float(rr.lo), float(rr.hi)
            if not (np.isfinite(a) and np.isfinite(b)):
                raise InputError(f"has no finite slope bound for joint {j + 1}", file=scenario.file,
                                 key=f"plant.dead_zone.{side}", expected="a branch with a bounded slope")
            cands = [_product(x, y, -1) for x in (a, b) for y in scale]
            lo[j] = min(lo[j], min(cands))
            cands = [_product(x, y, 1) for x in (a, b) for y in scale]
            hi[j] = max(hi[j], max(cands))
            # attained: the derivative's double value at an actual u, times a scale endpoint
            for val, pt in ((float(rr.lo_seen), rr.argmin), (float(rr.hi_seen), rr.argmax)):
                if not np.isfinite(val):
                    continue
                for sc_ in scale:
                    v = val * float(sc_)
                    info = {"branch": side, "u": float(np.ravel(pt["u"])[0]), "scale": float(sc_), "slope": v}
                    if v < lo_seen[j]:
                        lo_seen[j] = v
                        where[j]["lo"] = info
                    if v > hi_seen[j]:
                        hi_seen[j] = v
                        where[j]["hi"] = info
    return {"lo": lo, "hi": hi, "lo_seen": lo_seen, "hi_seen": hi_seen, "constant": constant, "where": where}


def _product(a: float, b: float, direction: int) -> float:
    """a * b rounded down (direction -1) or up (+1); exact products (e.g. by a scale of 1) are not moved."""
    from fractions import Fraction
    p = a * b
    if Fraction(p) == Fraction(a) * Fraction(b):
        return p
    return float(np.nextafter(p, direction * np.inf))


def scalar_range(f: ca.Function, t_final: float, element: int, tol: float = 1e-9) -> tuple[float, float]:
    """Rigorous (lo, hi) of one entry of f(t) over [0, t_final]."""
    r = rigorous_range(f, {"t": (0.0, float(t_final))}, element=element, tol=tol, rel_tol=1e-9, max_boxes=4000,
                       backend="arb", form="mean_value")
    return r.lo, r.hi


def funnel_sup(design, key: str, t_final: float) -> np.ndarray:
    """Rigorous upper bounds of F_key(t) per joint over [0, t_final]."""
    f = design.function(key, ["t"])
    return np.array([scalar_range(f, t_final, j)[1] for j in range(design.n)])


def joint_box(design, t_final: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """(lo, hi) per joint: the hull of the e1 funnel tube over [0, T], intersected with the model's joint limits."""
    sc = design.scenario
    n = design.n
    t = design.sym["t"]
    qd = ca.Function("qd", [t], [design.reference_t["qd"]], ["t"], ["qd"])
    F1 = funnel_sup(design, "F1", t_final)
    lo, hi = np.empty(n), np.empty(n)
    for j in range(n):
        a, b = scalar_range(qd, t_final, j)
        lo[j], hi[j] = float(np.nextafter(a - F1[j], -np.inf)), float(np.nextafter(b + F1[j], np.inf))
    info = {"tube": [lo.tolist(), hi.tolist()], "limits": None}
    m = sc.model
    if m.joint_lower is not None and m.joint_upper is not None:
        jl = np.where(np.isfinite(m.joint_lower), m.joint_lower, -np.inf)
        ju = np.where(np.isfinite(m.joint_upper), m.joint_upper, np.inf)
        info["limits"] = [jl.tolist(), ju.tolist()]
        lo, hi = np.maximum(lo, jl), np.minimum(hi, ju)
        if np.any(lo > hi):
            j = int(np.argmax(lo > hi))
            raise InputError(f"keeps joint {j + 1}'s funnel tube outside the joint limits", file=sc.file,
                             key="reference.q", expected="a reference whose e1 funnel meets the joint limits")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        j = int(np.argmax(~(np.isfinite(lo) & np.isfinite(hi))))
        raise InputError(f"gives no bounded range for joint {j + 1}", file=sc.file, key="funnel.e1",
                         expected="a bounded funnel (or joint limits)")
    return lo, hi, info


# --- the input gain ----------------------------------------------------------------------------------------

def input_gain_function(design) -> ca.Function:
    """(q, p, d) -> sym(M_p(q, p)^-1 diag(d) M(q)): the effective input gain of the plant under the design's torque
    (M the controller's model, M_p the plant's inertia with parameters p, d the dead-zone slopes), as SX."""
    from ..sx.linalg import ldl_solve
    sc = design.scenario
    n = design.n
    q, dq, t = design.sym["q"], design.sym["dq"], design.sym["t"]
    names, _ = plant_parameters(sc)
    p = ca.SX.sym("p", len(names))
    d = ca.SX.sym("d", n)
    Mp = plant_acceleration(sc, q, dq, t, ca.SX.sym("tau", n), 0.0, p=p)["M"]
    DM = ca.mtimes(ca.diag(d), design.signals["M"])
    G = ca.horzcat(*[ldl_solve(Mp, DM[:, j]) for j in range(n)])
    S = 0.5 * (G + G.T)
    return ca.Function("input_gain", [q, p, d], [S], ["q", "p", "d"], ["S"], {"cse": True})


def inertia_functions(design) -> tuple[ca.Function, ca.Function]:
    """The ordinary CasADi Functions M(q) of the controller's model and M_p(q, p) of the plant (for re-checks)."""
    sc = design.scenario
    q, dq, t = design.sym["q"], design.sym["dq"], design.sym["t"]
    names, _ = plant_parameters(sc)
    p = ca.SX.sym("p", len(names))
    Mp = plant_acceleration(sc, q, dq, t, ca.SX.sym("tau", design.n), 0.0, p=p)["M"]
    return ca.Function("M", [q], [design.signals["M"]]), ca.Function("M_p", [q, p], [Mp])


# --- the funnel region -------------------------------------------------------------------------------------

REGION_INPUTS = ("t", "s1", "s2", "m", "p")


@functools.lru_cache(maxsize=8)
def homogeneity_proven(transform_name: str) -> tuple[str, ...]:
    """The outputs k of a registered transformation for which sympy proves build(s F, F)[k] = F^deg build(s, 1)[k]
    (F > 0, s real) with the degrees the transformation declares (`HOMOGENEITY`); empty if it declares none."""
    import sympy

    from ..family.transforms import TRANSFORMS
    from ..sx.proof import _Timeout, simplify, time_limit
    from ..sx.tosympy import sx_to_sympy
    T = TRANSFORMS.get(transform_name)()
    degrees = getattr(T, "HOMOGENEITY", {})
    s, F = ca.SX.sym("s"), ca.SX.sym("F")
    S, FF = sympy.Symbol("s", real=True), sympy.Symbol("F", positive=True)
    a, b = T.build(s * F, F), T.build(s, ca.SX(1))
    out = []
    for k, deg in degrees.items():
        if k not in a:
            continue
        try:
            with time_limit(10.0):
                e = sx_to_sympy(a[k] - F ** deg * b[k], [s, F], [[S], [FF]])[0]
                if simplify(e) == 0:
                    out.append(k)
        except (_Timeout, RecursionError, NotImplementedError):
            continue
    return tuple(out)


def region_signals(design, exprs: dict[str, ca.SX]):
    """The expressions (in the design's symbols, the plant's p and the controller states) written over the funnel
    region: returns (region inputs [t, s1, s2, m], outputs, output names, controller-state symbols, rewritten nodes).

    The rewriting replaces, in the design's own graph (its AD-derived signals included), e_i by s_i' F_i with
    s_i' = s_i (1 - m); the operations F_i - e_i, F_i + e_i, F_i - |e_i| and e_i / F_i by F_i (1 - s_i'),
    F_i (1 + s_i'), F_i (1 - |s_i'|) and s_i'; and each transformation output the transformation declares
    homogeneous (and sympy proves so) by its value at the normalised error: z_i = z(s_i'), mu_i = mu(s_i')/F_i,
    r_i = F_i r(s_i'), ... -- all equal on R_m, and free of the F - |e| cancellation that interval arithmetic
    cannot see.
    """
    d = design
    n = d.n
    sym = d.sym
    S = d.signals
    t = sym["t"]
    s1, s2, m = ca.SX.sym("s1", n), ca.SX.sym("s2", n), ca.SX.sym("m")
    names = list(exprs)
    T = d.variant.transform
    proven = homogeneity_proven(T.name)
    degrees = getattr(T, "HOMOGENEITY", {})
    nodes, values, tags, rewritten = [], [], [], []
    sn = {}
    for i, si in ((1, s1), (2, s2)):
        sn[i] = si * (1 - m)
        F = S[f"F{i}"]
        for j in range(n):
            nodes += [S[f"e{i}"][j], F[j]]
            values += [sn[i][j] * F[j], F[j]]
            tags += [{("e", i, j)}, {("F", i, j)}]
        rewritten.append(f"e{i}")
        unit = T.build(sn[i], ca.SX.ones(n))
        for k in proven:
            name = f"{k}{i}"
            if name in S:
                for j in range(n):
                    nodes.append(S[name][j])
                    values.append(unit[k][j] * F[j] ** degrees[k])
                    tags.append(set())
                rewritten.append(name)
    Fs = {i: S[f"F{i}"] for i in (1, 2)}

    def find(tagset, kind):
        return [(x[1], x[2]) for x in (tagset or ()) if x[0] == kind]

    def rule(op, at, av):
        if op == "FABS":
            for i, j in find(at[0], "e"):
                return Fs[i][j] * ca.fabs(sn[i][j]), {("abs", i, j)}
        if op in ("SUB", "ADD") and len(at) == 2:
            for i, j in find(at[0], "F"):
                if (i, j) in find(at[1], "e"):
                    return Fs[i][j] * (1 - sn[i][j] if op == "SUB" else 1 + sn[i][j]), None
                if op == "SUB" and (i, j) in find(at[1], "abs"):
                    return Fs[i][j] * (1 - ca.fabs(sn[i][j])), None
            if op == "ADD":
                for i, j in find(at[1], "F"):
                    if (i, j) in find(at[0], "e"):
                        return Fs[i][j] * (1 + sn[i][j]), None
        if op == "DIV" and len(at) == 2:
            for i, j in find(at[0], "e"):
                if (i, j) in find(at[1], "F"):
                    return sn[i][j], None
        return None
    out = replace_nodes([exprs[k] for k in names] + [S["alpha2"]], ca.vertcat(*nodes), ca.vertcat(*values),
                        tags=[frozenset(x) for x in tags], rule=rule)
    alpha2 = out.pop()
    ref = [sym["qd"], sym["dqd"], sym["ddqd"]]
    ref_t = [d.reference_t["qd"], d.reference_t["dqd"], d.reference_t["ddqd"]]
    q = ref_t[0] + s1 * (1 - m) * S["F1"]
    a2 = ca.substitute([alpha2], [sym["q"], *ref], [q, *ref_t])[0]
    dq = a2 + s2 * (1 - m) * S["F2"]
    outs = ca.substitute(out, [sym["q"], sym["dq"], *ref], [q, dq, *ref_t])
    state_syms = [sym[k] for k, _ in d.states]
    return [t, s1, s2, m], outs, names, state_syms, rewritten


def structurally_zero(e: ca.SX) -> bool:
    """Whether every entry of e is 0 once CasADi's common-subexpression elimination has merged identical nodes
    (x - x of the same node is 0): a graph identity, no numbers involved."""
    if e.nnz() == 0:
        return True
    return bool(replace_nodes([e], ca.SX(0, 1), ca.SX(0, 1))[0].is_zero())


#: f_true's bracket with D(tau) - tau in the form where tau enters once (`plant.equations.dead_zone_deviation`)
DEAD_ZONE_DEVIATION = True


def true_unknown(design, p: ca.SX, width: float = 0.0, solve=None) -> dict[str, ca.SX]:
    """f_true = ddq_plant - ddq_nominal in the design's symbols and the plant's p (exact nonlinearities at width 0):
    what the plant adds to the nominal model under the design's torque, and the applied torque.

    Written directly, f_true = M_p^-1 (D(tau) - C_p dq - G_p - friction - d) - ddq_nom subtracts two large, nearly
    equal terms (tau contains M ddq_nom), which interval arithmetic cannot cancel. When the design's torque is, by a
    graph identity (`structurally_zero`), the nominal model's inverse dynamics tau = M ddq_nom + C dq + G, the
    same function is
        f_true = M_p^-1 ((D(tau) - tau) + (M - M_p) ddq_nom + (C - C_p) dq + (G - G_p) - friction - d),
    whose terms are small where the plant is close to the model (exactly 0 where it equals it); otherwise (a mutant
    design, another variant) the direct form is used. `form` says which. `solve`: another form of M_p^-1 rhs than
    LDL^T (`face_forms.solver_form`: the adjugate for two joints, a pivot order or a preconditioner for more).
    """
    from ..sx.linalg import ldl_solve
    sc = design.scenario
    S = design.signals
    q, dq = design.sym["q"], design.sym["dq"]
    pl = plant_acceleration(sc, q, dq, design.sym["t"], S["tau"], width, p=p)
    resid = S["tau"] - (ca.mtimes(S["M"], S["ddq"]) + ca.mtimes(S["C"], dq) + S["G"])
    if structurally_zero(resid):
        # D(tau) - tau in the form where tau enters once (`dead_zone_deviation`), at width 0
        dev = dead_zone_deviation(sc, S["tau"], p) if DEAD_ZONE_DEVIATION and width == 0 else None
        rhs = ((pl["tau_applied"] - S["tau"] if dev is None else dev) + ca.mtimes(S["M"] - pl["M"], S["ddq"])
               + ca.mtimes(S["C"] - pl["C"], dq) + (S["G"] - pl["G"]) - pl["friction"] - pl["disturbance"])
        f = ca.solve(pl["M"], rhs) if design.n == 1 else (solve or ldl_solve)(pl["M"], rhs)
        return {"f_true": f, "tau_applied": pl["tau_applied"], "form": "inverse dynamics"}
    return {"f_true": pl["ddq"] - S["ddq"], "tau_applied": pl["tau_applied"], "form": "direct"}
