"""Why a simulation failed and what to change: the integrator's own error and a hint for the settings used."""

from __future__ import annotations

import re


def error_line(text: str) -> str:
    """The informative last line of a CasADi error (e.g. 'CVode returned "CV_TOO_MUCH_WORK"'), without paths."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    last = lines[-1] if lines else str(text)
    last = re.sub(r"^\S*\.cpp:\d+:\s*", "", last)
    return last.replace(" Consult CVODES documentation.", "").strip().rstrip(".")


def failure_hint(method: str, width: float, sim, dt: float, error: str | None) -> str:
    """'; cause: ...; hint: ...' for a run whose integrator failed part-way."""
    if error:
        cause = error
    else:
        cause = ("no integrator error: one output step gave a non-finite or out-of-funnel state that a finer "
                 "step does not reproduce (the step was too large for the dynamics)")
    if width == 0:
        hint = ("smoothing_width = 0 leaves the friction sign and the dead-zone kinks discontinuous, which the "
                "integrator cannot step across; use a width > 0 such as --width 1e-3 (the usual default)")
    elif method == "rk":
        hint = (f"explicit RK4 with step dt/rk_substeps = {dt / sim.rk_substeps:.3g} s is unstable on the stiff "
                f"adaptation loop; raise simulation.rk_substeps (now {sim.rk_substeps}) tenfold, or use "
                "--integrator cvodes")
    elif method == "collocation":
        hint = ("the implicit Radau stage equations did not converge; raise simulation.rk_substeps (now "
                f"{sim.rk_substeps}) or use --integrator cvodes")
    else:
        hint = (f"CVODES could not meet rtol = {sim.rtol:g}, atol = {sim.atol:g}; loosen simulation.rtol/atol or "
                f"raise simulation.smoothing_width (now {width:g})")
    return f"; cause: {cause}; hint: {hint}"


#: the terms of the torque tau = M (alpha2_dot + dF2/F2 e2 - k2 z2 - mu1 z1 r2/mu2 - W_hat^T Phi) + C dq + G, each
#: with what would shrink it (the specification, the reference and funnel e1, is never the advice)
TERMS = (
    ("alpha2_dot", "M alpha2_dot (the virtual control's rate)",
     "lower controller.k1 (alpha2 moves with k1 times the e1 error)"),
    ("feedforward", "M (dF2/F2) e2 (the e2 funnel's shrinking)", "lower funnel.e2.a (a slower e2 funnel)"),
    ("feedback", "M k2 z2 (the e2 feedback)",
     "raise funnel.e2.phi0 so that e2 starts deeper inside F2 (z2 grows without bound as |e2| nears F2), or lower "
     "controller.k2"),
    ("cross", "M mu1 z1 r2/mu2 (the coupling to the e1 funnel)", "lower controller.k1 or raise funnel.e2.phi_inf"),
    ("estimate", "M W_hat^T Phi (the approximator's estimate)", "lower adaptation.gamma"),
    ("model", "C dq + G (the model's Coriolis and gravity terms)", "a slower reference (the specification)"),
)


def torque_terms(design, t: float, q, dq, x_esn=None, w_hat=None) -> dict | None:
    """The terms of the design's torque (TERMS) per joint at one state, as arrays; None for a design whose torque
    is not of that form (its signals M, v, ddq, ... missing)."""
    import casadi as ca
    import numpy as np
    s, sym = design.signals, design.sym
    need = ("M", "C", "G", "alpha2_dot", "dF2", "F2", "e2", "z2", "mu1", "z1", "r2", "mu2", "v", "ddq", "tau")
    if any(k not in s for k in need):
        return None
    k2 = ca.DM(np.broadcast_to(np.asarray(design.scenario.k2, float), (design.n,)).copy())
    M = s["M"]
    terms = {"alpha2_dot": ca.mtimes(M, s["alpha2_dot"]), "feedforward": ca.mtimes(M, s["dF2"] / s["F2"] * s["e2"]),
             "feedback": ca.mtimes(M, -k2 * s["z2"]), "cross": ca.mtimes(M, -s["mu1"] * s["z1"] * s["r2"] / s["mu2"]),
             "estimate": ca.mtimes(M, -(s["v"] - s["ddq"])), "model": ca.mtimes(s["C"], sym["dq"]) + s["G"],
             "tau": s["tau"], "e2": s["e2"], "F2": s["F2"]}
    ins = list(design.inputs)
    f = ca.Function("torque_terms", [sym[k] for k in ins], list(terms.values()))
    qd, dqd, ddqd = design.reference(t)
    val = {"t": t, "q": q, "dq": dq, "qd": qd, "dqd": dqd, "ddqd": ddqd}
    args = []
    for k in ins:
        shape = sym[k].shape
        v = val.get(k)
        if v is None:
            v = x_esn if k == "x_esn" else w_hat if k == "w_hat" else None
        if v is None:
            args.append(ca.DM(np.zeros(shape)))
            continue
        a = np.asarray(v, float)
        args.append(ca.DM(a if a.shape == shape else a.ravel().reshape(shape, order="F")))
    out = f(*args)
    return {k: np.asarray(o, float).ravel() for k, o in zip(terms, out)}


def breach_hint(design, *, t: float, q, dq, x_esn=None, w_hat=None, funnel: str, joint: int, tau_max=None,
                sampled_rate: float | None = None, scenario_arg: str = "SCENARIO") -> str:
    """What to change after a run left a funnel or saturated, computed from the run at that instant: which term
    dominates the torque of the joint, which parameter would relax it, and the `tune` command to run."""
    import numpy as np
    j = joint - 1
    parts = []
    try:
        T = torque_terms(design, t, q, dq, x_esn, w_hat)
    except Exception:          # noqa: BLE001 - a hint is never worth failing the run's report
        T = None
    if T is not None and np.all(np.isfinite(T["tau"])):
        mags = {k: abs(float(T[k][j])) for k, _, _ in TERMS}
        total = sum(mags.values()) or 1.0
        key = max(mags, key=mags.get)
        label, advice = next((lab, adv) for k, lab, adv in TERMS if k == key)
        tau_j = float(T["tau"][j])
        head = f"at t = {t:.4g} s joint {joint} asks for tau = {tau_j:.4g}"
        lim = None if tau_max is None else float(np.broadcast_to(np.asarray(tau_max, float), (design.n,))[j])
        if lim is not None:
            head += f" (limit {lim:g})"
        ratio = abs(float(T["e2"][j])) / float(T["F2"][j]) if float(T["F2"][j]) > 0 else float("nan")
        parts.append(f"{head}; {label} is {100 * mags[key] / total:.0f} % of it (|e2|/F2 = {ratio:.2f}): {advice}")
    if sampled_rate is not None:
        parts.append(f"if the continuous-time run keeps the funnels, the sampled loop at {sampled_rate:g} Hz is too "
                     f"slow: raise implementation.rate_hz (`symfunnel rate {scenario_arg}` finds the minimum)")
    limit_key = "implementation.tau_max" if design.scenario.implementation is not None else "tune.tau_max"
    parts.append(f"or let `symfunnel tune {scenario_arg} --out tuned.toml` search controller.k1/k2 and funnel.e2 "
                 f"(phi0, phi_inf, a) within {limit_key}")
    return f"{funnel} of joint {joint}: " + "; ".join(parts)


#: a run's status as the human-readable output says it (the JSON keeps the status itself)
STATUS_TEXT = {"initial_outside": "the initial state is outside a funnel", "breach": "left a funnel",
               "timeout": "stopped at the wall-clock limit", "failed": "failed"}


def status_text(status: str) -> str:
    """`status` in words for a line a user reads ('ok' and unknown statuses as they are)."""
    return STATUS_TEXT.get(status, status)


def initial_hint(design, *, funnel: str, joint: int, abs_error: float, scenario_arg: str = "SCENARIO") -> str:
    """What to change when the initial state starts outside a funnel: at t = 0 no gain has acted yet, so only the
    funnel's value at 0 or the initial state can fix it (`tune` never changes funnel e1; it does search e2's)."""
    if funnel == "e1":
        return (f"e1 of joint {joint} starts outside: widen funnel e1 so that F1(0) > {abs_error:.4g} "
                f"(funnel.e1.phi0 for the exponential funnel) or start inside, initial.q[{joint - 1}] nearer the reference's qd(0); no gain "
                "changes |e1(0)|, and `symfunnel tune` does not change funnel e1")
    return (f"e2 of joint {joint} starts outside (e2(0) = dq(0) - alpha2(0)): widen funnel e2 so that F2(0) > "
            f"{abs_error:.4g} (funnel.e2.phi0 for the exponential funnel), or change initial.dq[{joint - 1}]; "
            f"`symfunnel tune {scenario_arg} --out tuned.toml` searches funnel.e2 (phi0, phi_inf, a)")

