"""The audit: model properties and printed claims against the exact derivation, decided by computation.

Each identity is first sampled (a counterexample decides 'fail' outright); where sampling finds no violation,
sympy is asked for a proof on the converted SX (decides 'pass, symbolic'); if sympy cannot decide in time the
sampled verdict stands and says how many points it rests on.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..design import Design
from ..model.base import christoffel_C
from ..sx.proof import sympy_is_zero
from ..design.sampling import eval_mapped, funnel_states, joint_states, point_of
from .result import CheckResult


# --- sympy with a time limit --------------------------------------------------------------------

def _fmt_vec(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.ravel(v)) + "]"


# --- model properties ---------------------------------------------------------------------------

def _model_funcs(design: Design):
    m = design.scenario.model
    Mdot = ca.jtimes(m.M, m.q, m.dq)
    Cchr = christoffel_C(m.M, m.q, m.dq) if m.C_source == "given" else m.C
    return m, Mdot, Cchr


def _identity_check(cid: str, design: Design, X: ca.SX, scale: ca.SX, what: str, rng, *,
                    show: str) -> "CheckResult":
    """Decide whether the model expression X(q, dq, p) vanishes: sampled counterexample, then sympy proof."""
    sc = design.scenario
    m = sc.model
    a = sc.audit
    k = a.samples
    q, dq = joint_states(design, k, rng)
    f = ca.Function("f", [m.q, m.dq, m.p], [ca.mmax(ca.fabs(X)), scale]).map(k)
    P = np.repeat(np.reshape(m.p_values, (-1, 1)), k, axis=1) if m.p.numel() else np.zeros((0, k))
    absx, sc_ = (np.array(v).ravel() for v in f(q, dq, P))
    rel = absx / np.maximum(sc_, 1e-300)
    rel[~np.isfinite(rel)] = np.inf
    j = int(np.argmax(rel))
    where = {"q": q[:, j].tolist(), "dq": dq[:, j].tolist()}
    evidence = {"samples": k, "max_abs": float(absx[j]), "max_rel": float(rel[j])}
    inputs = [m.q, m.dq, m.p] if m.p.numel() else [m.q, m.dq]
    if rel[j] > a.tolerance:
        proven, simp = sympy_is_zero(X, inputs, a.sympy_timeout)
        if proven:       # the sampled value is round-off over a round-off-sized scale: the proof decides
            return CheckResult(cid, "pass", f"{what}: holds identically (sympy proves {show} = 0 for all q, dq"
                               + (" and parameters" if m.p.numel() else "") + f"; the sampled {absx[j]:.3g} "
                               f"(relative {rel[j]:.3g}) is round-off)", method="symbolic", margin=0.0,
                               evidence=evidence)
        if simp is not None:
            import sympy
            evidence["symbolic"] = str(sympy.sstr(simp))
        return CheckResult(cid, "fail", f"{what}: violated; largest violation {absx[j]:.4g} "
                           f"(relative {rel[j]:.3g}) at q = {_fmt_vec(where['q'])}, dq = {_fmt_vec(where['dq'])}"
                           + (f"; symbolically {show} = {evidence['symbolic']}" if "symbolic" in evidence else ""),
                           method=f"sampled ({k} random states)", margin=-float(rel[j]), where=where,
                           evidence=evidence)
    proven, _ = sympy_is_zero(X, inputs, a.sympy_timeout)
    if proven:
        return CheckResult(cid, "pass", f"{what}: holds identically (sympy proves {show} = 0 for all q, dq"
                           + (" and parameters)" if m.p.numel() else ")"), method="symbolic",
                           margin=0.0, evidence=evidence)
    return CheckResult(cid, "pass", f"{what}: holds at {k} random states (largest relative violation "
                       f"{rel[j]:.3g}); sympy could not decide it symbolically", method=f"sampled ({k} random states)",
                       margin=float(a.tolerance - rel[j]), where=where, evidence=evidence)


def check_M_symmetric(design: Design, rng) -> CheckResult:
    """model.M_symmetric: M(q) = M(q)^T."""
    m = design.scenario.model
    X = m.M - m.M.T
    return _identity_check("model.M_symmetric", design, X, ca.mmax(ca.fabs(m.M)), "M(q) symmetric", rng,
                           show="M - M^T")


def check_skew(design: Design, rng) -> CheckResult:
    """model.skew_symmetry (Property 1): N = dM/dt - 2C satisfies N + N^T = 0."""
    m, Mdot, _ = _model_funcs(design)
    N = Mdot - 2 * m.C
    X = N + N.T
    # the matrices' magnitude |M| |dq| bounds what N's round-off is relative to where dM/dt and C vanish
    scale = ca.mmax(ca.fabs(Mdot)) + 2 * ca.mmax(ca.fabs(m.C)) + ca.mmax(ca.fabs(m.M)) * ca.mmax(ca.fabs(m.dq))
    return _identity_check("model.skew_symmetry", design, X, scale,
                           "Property 1 (dM/dt - 2C skew-symmetric)", rng, show="N + N^T with N = dM/dt - 2C")


def check_coriolis(design: Design, rng) -> CheckResult:
    """model.coriolis_consistent: C(q, dq) dq equals the Christoffel-symbol Coriolis vector of M."""
    m, _, Cchr = _model_funcs(design)
    X = ca.mtimes(m.C, m.dq) - ca.mtimes(Cchr, m.dq)
    scale = ca.mmax(ca.fabs(ca.mtimes(Cchr, m.dq))) + ca.mmax(ca.fabs(ca.mtimes(m.C, m.dq)))
    r = _identity_check("model.coriolis_consistent", design, X, scale,
                        f"C dq consistent with M (C {m.C_source})", rng, show="C dq - C_christoffel dq")
    return r


def check_M_pd(design: Design, rng) -> CheckResult:
    """model.M_positive_definite: exact where M is constant, else sampled over the joint range with local refinement."""
    from ..core.neldermead import minimize       # scipy's Nelder-Mead iterates without importing scipy.optimize

    sc = design.scenario
    m = sc.model
    a = sc.audit
    Mn = m.numeric(m.M)
    fM = ca.Function("M", [m.q], [Mn])
    k = a.samples
    q, _ = joint_states(design, k, rng)
    Ms = np.array(fM.map(k)(q)).reshape(m.n, k, m.n).transpose(1, 0, 2)
    Ms = 0.5 * (Ms + Ms.transpose(0, 2, 1))
    eig = np.linalg.eigvalsh(Ms)
    lmin, lmax = eig[:, 0], eig[:, -1]
    lmin = np.where(np.isfinite(lmin), lmin, -np.inf)
    lo, hi = np.array(a.joint_lower), np.array(a.joint_upper)

    def fmin_eig(x):
        x = np.clip(x, lo, hi)
        M = np.array(fM(x))
        val = np.linalg.eigvalsh(0.5 * (M + M.T))[0]
        return val if np.isfinite(val) else -1e300

    best_val, best_q = float(np.min(lmin)), q[:, int(np.argmin(lmin))]
    constant = not ca.depends_on(Mn, m.q)
    if not constant:
        for j in np.argsort(lmin)[:3]:
            res = minimize(fmin_eig, q[:, j], xatol=1e-10, fatol=1e-14, maxiter=400 * m.n)
            if res.fun < best_val:
                best_val, best_q = float(res.fun), np.clip(res.x, lo, hi)
    method = "exact (M is constant)" if constant else f"sampled ({k} states over the joint range) + local refinement"
    proof, found = (None, None) if constant or best_val <= 0 else _pd_by_intervals(Mn, m.q, lo, hi, a.sympy_timeout)
    seen = fmin_eig(found) if found is not None else np.inf
    if seen < best_val:                     # the search saw a smaller eigenvalue there: re-evaluated, it counts
        best_val, best_q = float(seen), np.clip(found, lo, hi)
        method += " + interval branch and bound (its smallest midpoint, re-evaluated)"
    if proof:
        method = ("interval branch and bound over the joint range (outward-rounded enclosures of M's SX, "
                  "preconditioned Gershgorin discs)")
    where = {"q": best_q.tolist()}
    ev = {"min_eigenvalue": best_val, "max_eigenvalue": float(np.max(lmax)), "samples": k,
          "M_a": best_val, "M_b": float(np.max(lmax))}
    if proof:
        ev["lambda_min_lower_bound"] = proof
    if best_val > 0:
        return CheckResult("model.M_positive_definite", "pass",
                           ("M(q) positive definite over the whole joint range (lambda_min >= "
                            f"{proof:.4g}, proven); " if proof else "M(q) positive definite: ") +
                           f"smallest eigenvalue {best_val:.6g} at q = {_fmt_vec(best_q)}; "
                           f"eigenvalues within [{best_val:.4g}, {np.max(lmax):.4g}] (Property 2 bounds)",
                           method=method, margin=best_val, where=where, evidence=ev)
    return CheckResult("model.M_positive_definite", "fail",
                       f"M(q) not positive definite: eigenvalue {best_val:.6g} at q = {_fmt_vec(best_q)}",
                       method=method, margin=best_val, where=where, evidence=ev)


def _pd_by_intervals(Mn: ca.SX, q: ca.SX, lo, hi, timeout: float, max_n: int = 4):
    """(a rigorous lower bound of lambda_min(M(q)) over the joint box or None when not proven within the budget,
    the point where the search saw its smallest eigenvalue or None): interval branch and bound on M's own SX
    (`sx.search`: outward-rounded enclosures, preconditioned Gershgorin discs), so a URDF arm's M needs no symbolic
    determinant (sympy's took its whole 10 s timeout on 4 joints). Above max_n joints the box is too large to prove
    in the audit's time (arm7: undecided after 3 s): not tried."""
    from ..sx.search import prove_positive_definite
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = q.numel()
    if n > max_n or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None, None
    split = np.array([j for j in range(n) if hi[j] > lo[j] and ca.depends_on(Mn, q[j])], dtype=int)
    try:
        r = prove_positive_definite(ca.Function("M", [q], [0.5 * (Mn + Mn.T)]), lo, hi, split, max_boxes=4000,
                                    seconds=min(float(timeout), 3.0), rel_tol=0.05)
    except Exception:  # noqa: BLE001 - an operation without an interval rule just means "not proven"
        return None, None
    proven = r.status == "proven" and r.lower is not None and r.lower > 0
    return (float(r.lower) if proven else None), (None if r.argmin is None else np.asarray(r.argmin, float))


# --- funnels --------------------------------------------------------------------------------------

def _admitting(shape, abs_e: np.ndarray):
    """(the smallest phi0 per joint that would admit |e(0)|, or None without phi0; a hint per joint)."""
    if not hasattr(shape, "phi_inf"):
        return None, lambda i: f"F(0) must exceed {abs_e[i]:.6g} to admit it"
    need = [max(float(abs_e[i]) - shape.phi_inf[i], 0.0) for i in range(len(abs_e))]
    return need, lambda i: f"phi0 > {need[i]:.6g} would admit it"


def funnel_initial(design: Design, funnels=None) -> tuple[bool, str, dict, float]:
    """|e_i(0)| < F_i(0) for e1 then e2, with the smallest phi0 that would admit the initial error."""
    sc = design.scenario
    funnels = funnels or sc.funnels
    n = design.n
    qd, dqd, ddqd = (np.array(v).ravel() for v in design.reference(0.0))
    q0, dq0 = np.array(sc.q0), np.array(sc.dq0)
    e1 = q0 - qd
    F1 = np.array(funnels["e1"].value(0.0))
    ev = {"e1(0)": e1.tolist(), "F1(0)": F1.tolist()}
    margin1 = (F1 - np.abs(e1)) / F1
    bad = [i for i in range(n) if not abs(e1[i]) < F1[i]]
    if bad:
        need, hint = _admitting(funnels["e1"], np.abs(e1))
        if need is not None:
            ev["phi0_needed_e1"] = need
        i = bad[0]
        return False, (f"funnel e1 infeasible at t = 0: joint {i + 1} has |e1(0)| = {abs(e1[i]):.6g} >= "
                       f"F1(0) = {F1[i]:.6g}; {hint(i)}"), ev, float(np.min(margin1))
    a2 = np.array(design.function("alpha2", ["t", "q", "qd", "dqd"])(0.0, q0, qd, dqd)).ravel()
    e2 = dq0 - a2
    F2 = np.array(funnels["e2"].value(0.0))
    ev.update({"alpha2(0)": a2.tolist(), "e2(0)": e2.tolist(), "F2(0)": F2.tolist()})
    margin2 = (F2 - np.abs(e2)) / F2
    bad = [i for i in range(n) if not abs(e2[i]) < F2[i]]
    margin = float(min(np.min(margin1), np.min(margin2)))
    if bad:
        need, hint = _admitting(funnels["e2"], np.abs(e2))
        if need is not None:
            ev["phi0_needed_e2"] = need
        i = bad[0]
        return False, (f"funnel e2 infeasible at t = 0: joint {i + 1} has |e2(0)| = |dq(0) - alpha2(0)| = "
                       f"{abs(e2[i]):.6g} >= F2(0) = {F2[i]:.6g}; {hint(i)}"), ev, margin
    return True, (f"|e1(0)| = {_fmt_vec(np.abs(e1))} < F1(0) = {_fmt_vec(F1)} and |e2(0)| = "
                  f"{_fmt_vec(np.abs(e2))} < F2(0) = {_fmt_vec(F2)}"), ev, margin


def check_funnel_parameters(design: Design) -> CheckResult:
    """funnel.parameters: the conditions stated with eq. 16 (phi0 >= phi_inf > 0) and a >= 0, for exponential
    funnels (a funnel given as an expression has no phi0: its positivity was checked at load)."""
    bad, checked = [], []
    for key, f in design.scenario.funnels.items():
        if not hasattr(f, "phi0"):
            continue
        checked.append(key)
        for i in range(design.n):
            if not f.phi0[i] >= f.phi_inf[i] > 0:
                bad.append(f"{key} joint {i + 1}: phi0 = {f.phi0[i]:g}, phi_inf = {f.phi_inf[i]:g}")
    if not checked:
        return CheckResult("funnel.parameters", "skip", "no funnel has phi0/phi_inf (both are expressions F(t), "
                           "whose positivity on [0, t_final] is checked when the scenario loads)", method="exact")
    if bad:
        return CheckResult("funnel.parameters", "fail", "phi0 >= phi_inf > 0 (eq. 16) violated: " + "; ".join(bad),
                           method="exact")
    return CheckResult("funnel.parameters", "pass", f"phi0 >= phi_inf > 0 for every joint of funnel "
                       f"{' and '.join(checked)} (eq. 16)", method="exact")


def check_funnel_initial(design: Design) -> CheckResult:
    """funnel.initial_condition: every funnel admits the scenario's initial error."""
    ok, text, ev, margin = funnel_initial(design)
    return CheckResult("funnel.initial_condition", "pass" if ok else "fail", text, method="exact",
                       margin=margin, where={"t": 0.0, "q": list(design.scenario.q0), "dq": list(design.scenario.dq0)},
                       evidence=ev)


# --- claims ---------------------------------------------------------------------------------------

def claim_env(design: Design, claim=None) -> dict:
    """Names a claim expression may use, bound to the design's SX (signals, symbols, parameters, constants, and the
    claim's own numbers)."""
    m = design.scenario.model
    env = dict(design.signals)
    env.update({k: design.sym[k] for k in design.inputs})
    env.update({c: m.q[i] for i, c in enumerate(m.coordinates)})
    env.update({"d" + c: m.dq[i] for i, c in enumerate(m.coordinates)})
    env.update({k: float(v) for k, v in zip(m.p_names, m.p_values)})
    env.update(design.constants)
    if claim is not None:
        env.update(claim.parameters)
    return env


def claim_expression(design: Design, claim) -> ca.SX:
    """The printed claim as SX over the base symbols, broadcast to its signal's shape."""
    from ..core.errors import InputError
    target = design.signals[claim.signal]
    e = claim.expression.to_casadi(claim_env(design, claim))
    e = ca.SX(e)
    if e.shape == (1, 1) and target.shape != (1, 1):
        e = ca.repmat(e, *target.shape)
    if e.shape != target.shape:
        raise InputError(f"has shape {e.shape[0]}x{e.shape[1]}", file=design.scenario.file,
                         key=f"claims.{claim.name}.expression",
                         expected=f"the shape of signal {claim.signal}, {target.shape[0]}x{target.shape[1]}")
    return e


def check_claim(design: Design, claim, rng) -> CheckResult:
    """claim.<name>: the printed expression against the exact signal, sampled inside the funnels, then sympy."""
    sc = design.scenario
    cid = f"claim.{claim.name}"
    if claim.kind == "decay":
        return CheckResult(cid, "skip", f"{claim.source or 'printed'} decay claim: needs the ideal weights fitted on a "
                           "simulated run, so `symfunnel verify` evaluates it", method="verify")
    if claim.kind == "inequality":
        return check_inequality(design, claim, rng)
    if claim.kind == "funnel":
        funnels = dict(sc.funnels)
        funnels[claim.funnel] = claim.spec
        ok, text, ev, margin = funnel_initial(design, funnels)
        return CheckResult(cid, "pass" if ok else "fail", f"{claim.source or 'printed'} funnel {claim.funnel}: {text}",
                           method="exact", margin=margin, where={"t": 0.0}, evidence=ev,
                           verdict="proven" if ok else "refuted")
    exact = design.signals[claim.signal]
    printed = claim_expression(design, claim)
    diff = printed - exact
    k_inside = sc.audit.claim_samples
    k_edge = max(50, k_inside // 4)
    k = k_inside + k_edge
    f = ca.Function("claim", [design.sym[x] for x in design.inputs], [exact, printed], list(design.inputs),
                    ["exact", "printed"])
    r, c = exact.shape
    batches = []
    # inside the funnels, and crowding their boundaries (where a printed form may differ only near |e| = F)
    for kk, edge in ((k_inside, False), (k_edge, True)):
        pts_b = funnel_states(design, kk, rng, edge=edge)
        ex_b, pr_b = eval_mapped(f, pts_b, kk)
        batches.append((pts_b, ex_b.reshape(r, kk, c), pr_b.reshape(r, kk, c)))
    pts = {key: np.concatenate([b[0][key] for b in batches], axis=-1) for key in batches[0][0]}
    ex = np.concatenate([b[1] for b in batches], axis=1)
    pr = np.concatenate([b[2] for b in batches], axis=1)
    d = np.abs(pr - ex)
    scale = np.maximum(np.abs(ex), np.abs(pr))
    rel = np.where(d == 0, 0.0, d / np.maximum(scale, 1e-300))
    rel = np.where(np.isfinite(rel), rel, np.inf)
    rel_pt = rel.max(axis=(0, 2))
    j = int(np.argmax(rel_pt))
    where = point_of(pts, j)
    ev = {"samples": k, "max_rel": float(rel_pt[j]), "max_abs": float(np.nanmax(d[:, j, :])),
          "exact_at_worst": ex[:, j, :].ravel().tolist()[:12], "printed_at_worst": pr[:, j, :].ravel().tolist()[:12],
          "fraction_disagreeing": float(np.mean(rel_pt > sc.audit.tolerance))}
    notes = []
    circular = circular_names(design, claim)
    if circular:
        notes.append(f"circular: the printed {claim.signal} uses {', '.join(circular)}, which the derivation defines "
                     f"through {claim.signal} itself, so it is no explicit formula")
        ev["circular_through"] = circular
    dep_exact = {v.name() for v in ca.symvar(exact)}
    dep_printed = {v.name() for v in ca.symvar(printed)}
    extra = sorted(dep_printed - dep_exact, key=lambda s: design._owner.get(s, ("", 0)))
    if extra:
        notes.append(f"the printed form depends on {', '.join(extra[:6])}{'...' if len(extra) > 6 else ''}, "
                     f"which the exact {claim.signal} does not")
        ev["extra_dependencies"] = extra
    if claim.signal == "w_hat_dot":
        leak = _leakage(design, printed, rng)
        ev["leakage_at_e2_zero"] = leak
        if leak["growing_fraction"] > 0:
            notes.append(f"at states with e2 = 0 the printed law makes ||W_hat|| grow at {leak['growing_fraction']:.0%} "
                         f"of {leak['samples']} points (d||W_hat||^2/dt up to {leak['max_rate']:.3g}): "
                         "its sigma term is not a leakage")
    head = f"{claim.source or 'printed'} {claim.signal}"
    if rel_pt[j] > sc.audit.tolerance:
        detail = (f"{head}: NOT equivalent to the exact signal; disagrees at {ev['fraction_disagreeing']:.0%} of "
                  f"{k} points inside the funnels, worst relative difference {rel_pt[j]:.3g} "
                  f"(abs {ev['max_abs']:.4g}) at t = {where['t']:.4g}, q = {_fmt_vec(where['q'])}, "
                  f"dq = {_fmt_vec(where['dq'])}")
        if notes:
            detail += "; " + "; ".join(notes)
        return CheckResult(cid, "fail", detail, method=f"sampled ({k} points inside the funnels)",
                           margin=-float(rel_pt[j]), where=where, evidence=ev, verdict="refuted")
    inputs = [design.sym[x] for x in design.inputs]
    proven, simp = sympy_is_zero(diff, inputs, sc.audit.sympy_timeout)
    if proven:
        return CheckResult(cid, "pass", f"{head}: equivalent to the exact signal (sympy: difference = 0)",
                           method="symbolic", margin=0.0, evidence=ev, verdict="proven")
    refuted = _refute(simp, inputs, design, pts, ex, min(k, 40), sc.audit.sympy_timeout)
    if refuted is not None:
        jj, value, expr = refuted
        where = point_of(pts, jj)
        ev["sympy_difference"] = expr[:200]
        return CheckResult(cid, "fail", f"{head}: NOT equivalent to the exact signal: sympy's difference "
                           f"printed - exact = {expr[:120]} is {value:.3g} at t = {where['t']:.4g}, "
                           f"q = {_fmt_vec(where['q'])} (evaluated to 50 digits; below the sampling tolerance "
                           f"{sc.audit.tolerance:g} but no rounding)", method="symbolic (refuted at a point)",
                           margin=-abs(value), where=where, evidence=ev, verdict="refuted")
    return CheckResult(cid, "warn", f"{head}: not proven: agrees with the exact signal at {k} points inside the "
                       f"funnels and at their boundaries (worst relative difference {rel_pt[j]:.3g}), but sympy "
                       f"could not prove the difference zero, so the claim may fail elsewhere",
                       method=f"sampled ({k} points inside the funnels); not proven",
                       margin=float(sc.audit.tolerance - rel_pt[j]), where=where, evidence=ev, verdict="not proven")


#: a difference sympy evaluates above this, relative to the signal, is no rounding of the 53-bit constants
REFUTE_REL = 1e-13


def _refute(simp, inputs, design, pts, ex, count: int, timeout: float):
    """(sample index, value, text) where sympy's simplified difference is clearly nonzero (50 digits), or None."""
    if simp is None or all(e == 0 for e in simp):
        return None
    import sympy

    from ..sx.proof import _Timeout, time_limit
    from ..sx.tosympy import sx_to_sympy
    names = list(design.inputs)
    nonzero = [(i, e) for i, e in enumerate(simp) if e != 0]
    k = ex.shape[1]
    try:
        with time_limit(min(timeout, 10.0)):
            syms = list(sx_to_sympy(ca.vertcat(*[ca.vec(x) for x in inputs]), inputs))
            for jj in range(count):
                parts = []
                for name in names:        # block jj of each input (casadi's map layout), column-major
                    a = np.asarray(pts[name])
                    c = a.shape[1] // k
                    parts.append(a[:, jj * c:(jj + 1) * c].ravel(order="F"))
                point = np.concatenate(parts)
                subs = {s_: sympy.Float(float(v), 60) for s_, v in zip(syms, point)}
                scale = max(float(np.max(np.abs(ex[:, jj, :]))), 1e-300)
                for _, e in nonzero:
                    val = complex(sympy.N(e.subs(subs), 50))
                    if abs(val) > REFUTE_REL * scale:
                        return jj, abs(val), str(e)
    except (_Timeout, RecursionError, MemoryError, TypeError, ValueError, ZeroDivisionError):
        return None
    return None
    return None


def circular_names(design: Design, claim) -> list[str]:
    """The signals a printed claim names that depend, through the derivation, on the very signal it defines."""
    used = [k for k in sorted(claim.expression.names) if k in design.signals and k != claim.signal]
    if not used:
        return []
    delta = ca.SX.sym("offset_" + claim.signal, *design.signals[claim.signal].shape)
    probe = design.variant.derive(design.mutant, offsets={claim.signal: delta})
    return [k for k in used if ca.depends_on(ca.vec(probe.signals[k]), ca.vec(delta))]


def check_inequality(design: Design, claim, rng) -> CheckResult:
    """claim.<name> of an inequality claim: lhs <= rhs searched for counterexamples inside the funnels, with V and
    V_dot the design's (V_dot exact by AD along the nominal model plus W*^T Phi, eps = 0) and W* random."""
    from ..core.errors import InputError
    sc = design.scenario
    cid = f"claim.{claim.name}"
    n, nr = design.n, design.n_regressor
    Ws = ca.SX.sym("W_star", nr, n)
    f = ca.mtimes(Ws.T, design.signals["Phi"]) if nr else ca.SX.zeros(n, 1)
    lyap = design.variant.lyapunov(design, Ws, ca.SX.zeros(n, 1))
    x, xdot = design.variant.nominal_flow(design, f)
    env = claim_env(design, claim)
    env.update(V=lyap["V"], V_dot=ca.jtimes(lyap["V"], x, xdot), W_star=Ws)
    lhs, rhs = (ca.SX(e.to_casadi(env)) for e in (claim.lhs, claim.rhs))
    for side, e in (("lhs", lhs), ("rhs", rhs)):
        if e.shape != (1, 1):
            raise InputError(f"has shape {e.shape[0]}x{e.shape[1]}", file=sc.file, key=f"claims.{claim.name}.{side}",
                             expected="a scalar (use dot(a, b) for sums over joints)")
    k_inside = max(sc.audit.claim_samples, 1000)
    k = k_inside + k_inside // 4
    # inside the funnels, and a quarter crowding their boundaries
    a_, b_ = funnel_states(design, k_inside, rng), funnel_states(design, k - k_inside, rng, edge=True)
    pts = {key: np.concatenate([a_[key], b_[key]], axis=-1) for key in a_}
    pts["W_star"] = rng.normal(0.0, 1.0, (nr, k * n)) if nr else np.zeros((0, k * n))
    F = ca.Function("ineq", [design.sym[x] for x in design.inputs] + [Ws], [lhs, rhs], list(design.inputs) + ["W_star"],
                    ["lhs", "rhs"])
    L, R = (a.ravel() for a in eval_mapped(F, pts, k))
    gap = L - R
    tol = sc.audit.tolerance * (np.abs(L) + np.abs(R) + 1e-300)
    viol = np.isfinite(gap) & (gap > tol)
    j = int(np.nanargmax(np.where(np.isfinite(gap), gap, -np.inf)))
    where = point_of(pts, j)
    ev = {"samples": k, "violations": int(viol.sum()), "lhs_at_worst": float(L[j]), "rhs_at_worst": float(R[j])}
    head = f"{claim.source or 'printed'}: {claim.lhs.text} <= {claim.rhs.text}"
    method = f"counterexample search at {k} states inside the funnels (random W*, eps = 0; not a proof)"
    if viol.any():
        return CheckResult(cid, "fail", f"{head}: counterexample at {int(viol.sum())} of {k} states; worst at t = "
                           f"{where['t']:.4g}, q = {_fmt_vec(where['q'])}, dq = {_fmt_vec(where['dq'])}: lhs = "
                           f"{L[j]:.4g} > rhs = {R[j]:.4g}", method=method, margin=-float(gap[j]), where=where,
                           evidence=ev, verdict="refuted")
    return CheckResult(cid, "warn", f"{head}: not proven: no counterexample at {k} states inside the funnels and "
                       f"at their boundaries (largest lhs - rhs {gap[j]:.3g}); a search is no proof",
                       method=method, margin=-float(gap[j]), where=where, evidence=ev, verdict="not proven")


def _leakage(design: Design, law: ca.SX, rng, k: int = 200) -> dict:
    """Sign of d||W_hat||^2/dt = 2 tr(W_hat^T law) at random states with e2 = 0 (where sigma-modification alone acts)."""
    pts = funnel_states(design, k, rng, fill=0.9)
    a2 = design.function("alpha2", ["t", "q", "qd", "dqd"]).map(k)
    pts["dq"] = np.array(a2(pts["t"], pts["q"], pts["qd"], pts["dqd"]))
    w = design.sym["w_hat"]
    rate = 2 * ca.trace(ca.mtimes(w.T, law))
    f = ca.Function("rate", [design.sym[x] for x in design.inputs], [rate], list(design.inputs), ["r"])
    (r,) = eval_mapped(f, pts, k)
    r = r.ravel()
    return {"samples": k, "growing_fraction": float(np.mean(r > 0)), "max_rate": float(np.max(r))}


def audit(scenario, design: Design, *, progress=None) -> list[CheckResult]:
    """Run every audit check of a scenario; returns the results in a fixed order."""
    seed = scenario.audit.seed
    say = progress or (lambda s: None)
    results = []
    steps = [
        ("model.M_symmetric", lambda r: check_M_symmetric(design, r)),
        ("model.M_positive_definite", lambda r: check_M_pd(design, r)),
        ("model.skew_symmetry", lambda r: check_skew(design, r)),
        ("model.coriolis_consistent", lambda r: check_coriolis(design, r)),
        ("funnel.parameters", lambda r: check_funnel_parameters(design)),
        ("funnel.initial_condition", lambda r: check_funnel_initial(design)),
    ]
    for i, claim in enumerate(scenario.claims):
        steps.append((f"claim.{claim.name}", lambda r, c=claim: check_claim(design, c, r)))
    from .consistency import check_funnel_consistency, check_reference_derivatives
    horizon = float(scenario.simulation.t_final)
    steps.append(("funnel.consistency", lambda r: check_funnel_consistency(design, horizon)))
    steps.append(("reference.derivatives", lambda r: check_reference_derivatives(design, horizon)))
    for i, (cid, fn) in enumerate(steps):
        say(f"audit {i + 1}/{len(steps)}: {cid}")
        results.append(fn(np.random.default_rng([seed, i])))
    return results
