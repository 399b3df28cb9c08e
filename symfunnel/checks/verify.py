"""Verification of a scenario's claims on its simulated closed loop: funnels, Lyapunov decay, bounded signals.

`verify(scenario)` simulates (or takes a given SimResult), evaluates the Lyapunov argument of docs/derivation.md along
the trajectory (`symfunnel.checks.lyapunov`), runs a region-wide falsification over Sobol states inside the funnels,
and returns one `CheckResult` per claim (ids below), each with a margin (positive = holds with room to spare) and
where the worst case sits.

Check ids, in order:

- ``simulation.completed``: the run reached t_final (not a breach, timeout or integrator failure);
- ``funnel.initial_condition``: |e_i(0)| < F_i(0) for both funnels (as in the audit);
- ``funnel.containment.e1.jointJ``, ``funnel.containment.e2.jointJ``: min over t of (F - |e|)/F > 0;
- ``lyapunov.decay.paper``, ``lyapunov.decay.corrected``: V_dot <= -rho V + delta at every trajectory point, rho and
  delta as Theorem 1 prints them / as eq. (8) of docs/derivation.md defines them;
- ``lyapunov.bound.paper``, ``lyapunov.bound.corrected``: V(t) <= V(0) e^{-rho t} + delta/rho (1 - e^{-rho t}) with
  the constant rho = min over the trajectory of rho(t) and delta = max over the trajectory of delta(t);
- ``lyapunov.falsification.paper``, ``lyapunov.falsification.corrected``: the decay inequality at >= 10,000 sampled
  states inside the funnels (falsification, not a proof);
- ``bounded.tau``, ``bounded.w_hat``, ``bounded.x_esn``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..core.io import json_safe
from .audit import CheckResult
from .gate import counts
from .lyapunov import REL_TOL, LyapunovTrajectory, decay_margin, falsify

if TYPE_CHECKING:
    from ..simulation.closedloop import ClosedLoop
    from ..design import Design
    from ..scenario import Scenario
    from ..simulation.result import SimResult

#: how far (relative) the last quarter's peak |tau| may exceed the peak before it and still count as bounded
TAU_GROWTH_ALLOWANCE = 0.1
#: absolute allowance of the bound checks on V, in units of the simulation's absolute state tolerance: the
#: integrator's error (not ||W*||^2) sets how well a simulated V can meet a bound that is ~0 (a perfect model)
V_ABS_ALLOWANCE_PER_ATOL = 100.0


@dataclass
class Verification:
    """Everything `verify` computed: the checks, and the data behind them (for the report)."""

    scenario: Scenario
    design: Design
    closed_loop: ClosedLoop
    result: SimResult
    lyapunov: LyapunovTrajectory | None
    falsification: dict | None
    checks: list[CheckResult]
    timings: dict = field(default_factory=dict)
    certification: object = None        # the certificates (symfunnel.certificates.Certification) shown as checks
    mutation: dict | None = None        # mutation testing (pipeline.run_mutants) when asked for: score, mutants

    @property
    def failed(self) -> list[CheckResult]:
        """The checks that failed (expected or not)."""
        return [c for c in self.checks if c.status == "fail"]

    @property
    def unexpected(self) -> list[CheckResult]:
        """The checks whose outcome is not the declared one: these fail the gate."""
        return [c for c in self.checks if c.unexpected]

    @property
    def status(self) -> str:
        """The gate's verdict: 'pass' when every outcome is as the scenario declares."""
        return "fail" if self.unexpected else "pass"

    def verdicts(self) -> dict:
        """The continuous-time run's verdict and, when verify ran the deployed loop, the sampled run's: {"continuous":
        {"status", "message"}, "sampled": {"status", "message"} | None} (a breach in either is said apart)."""
        out = {"continuous": {"status": self.result.status if self.result is not None else "skip",
                              "message": self.result.message if self.result is not None else ""},
               "sampled": None}
        c = next((c for c in self.checks if c.id == "implementation.containment"), None)
        if c is not None:
            out["sampled"] = {"status": "ok" if c.status == "pass" else "breach", "message": c.detail}
        return out

    def _repr_html_(self) -> str:
        """A notebook table: the gate's verdict and every check."""
        import html
        rows = "".join(f"<tr><td>{html.escape(c.id)}</td><td>{c.status}</td><td>{c.expected}</td>"
                       f"<td>{html.escape(c.detail)}</td></tr>" for c in self.checks)
        score = "" if self.mutation is None else f"; mutation score <b>{self.mutation['score']:.3f}</b>"
        return (f"<p>gate: <b>{self.status}</b>{score}</p><table><tr><th>check</th><th>status</th><th>expected</th>"
                f"<th>detail</th></tr>{rows}</table>")

    @property
    def mutation_score(self) -> float | None:
        """Killed / non-equivalent mutants when mutation testing ran (`verify(mutants=True)`), else None."""
        return None if self.mutation is None else self.mutation["score"]

    def __repr__(self) -> str:
        from .gate import counts_line
        score = "" if self.mutation is None else f", mutation_score={self.mutation['score']:.3f}"
        return (f"Verification(scenario={self.scenario.name!r}, status={self.status!r}, checks={len(self.checks)} "
                f"({counts_line(self.checks)}), unexpected={[c.id for c in self.unexpected]}{score})")

    def to_json(self) -> dict:
        """{"scenario", "status", "checks": [...], "simulation": summary, "lyapunov": {...}, "timings"}."""
        out = {"scenario": self.scenario.name, "status": self.status,
               "unexpected": [c.id for c in self.unexpected],
               "counts": counts(self.checks), "verdicts": self.verdicts(),
               "checks": [json_safe(c.to_json()) for c in self.checks], "timings": self.timings}
        if self.result is not None:
            out["simulation"] = {k: self.result.summary().get(k) for k in ("status", "message", "t_end", "t_final",
                                                                           "points", "wall_time")}
        if self.lyapunov is not None:
            L = self.lyapunov
            out["lyapunov"] = json_safe({"W_star": L.w_star_info, "rho_const": L.rho_const,
                                      "rho_const_lower": L.rho_const_lower, "delta_max": L.delta_max,
                                      "rho_paper_const": L.rho_paper_const, "delta_paper": L.delta_paper_const})
        if self.mutation is not None:
            out["mutation"] = json_safe(self.mutation)
        return out


def _g(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.4g}"


# --- the checks ----------------------------------------------------------------------------------

def check_completed(res) -> CheckResult:
    """simulation.completed: the run reached its final time inside both funnels."""
    t_end = float(res.t[-1]) if res.t.size else 0.0
    tf = res.stats.get("t_final")
    ev = {"status": res.status, "t_end": t_end, "t_final": tf, "wall_time": res.stats.get("wall_time")}
    if res.status == "ok":
        return CheckResult("simulation.completed", "pass", res.message or f"reached t = {t_end:g} s",
                           method="simulation", margin=0.0, where={"t": t_end}, evidence=ev)
    where = {"t": t_end}
    if res.breach:
        where = {"t": res.breach.get("time"), "funnel": res.breach.get("funnel"), "joint": res.breach.get("joint")}
    from ..simulation.hints import status_text
    return CheckResult("simulation.completed", "fail", f"{status_text(res.status)}: {res.message}", method="simulation",
                       margin=(t_end - tf) if tf else None, where=where, evidence=ev)


def check_containment(res, n: int) -> list[CheckResult]:
    """funnel.containment.eK.jointJ: the smallest relative margin (F - |e|)/F over the run, and when."""
    out = []
    s = res.signals
    t = res.t
    b = res.breach or {}
    t_end = float(t[-1]) if t.size else 0.0
    bw = getattr(res, "between", None) or {}
    how = f"simulation ({t.size} output points"
    if bw.get("points"):
        how += (f" and {bw['points']} samples between them, up to {bw['per_output_step']} per output step as dense "
                f"as the integrator's steps, {bw.get('refined_steps', 0)} output steps refined on "
                f"{bw.get('refine_points')} points)")
    else:
        how += ")"
    for key, mk, Fk in (("e1", "m1", "F1"), ("e2", "m2", "F2")):
        for j in range(n):
            cid = f"funnel.containment.{key}.joint{j + 1}"
            breached = b.get("funnel") == key and b.get("joint") == j + 1
            if t.size == 0 and not breached:
                out.append(CheckResult(cid, "skip", "no trajectory", method="simulation"))
                continue
            if t.size:
                m = np.asarray(s[mk])[:, j]
                e = np.asarray(s[key])[:, j]
                F = np.asarray(s[Fk])[:, j]
                with np.errstate(invalid="ignore"):
                    i = int(np.nanargmin(np.where(np.isfinite(m), m, np.inf)))
                mmin, tmin = float(m[i]), float(t[i])
                absm = float(F[i] - abs(e[i]))
                where_ = ""
                mb = (bw.get(f"min_margin_{key}") or [None] * n)[j]
                if mb is not None and mb < mmin:
                    mmin, tmin = float(mb), float(bw[f"t_min_margin_{key}"][j])
                    absm = mmin * float(np.interp(tmin, t, F))
                    where_ = ", between output points"
            if breached:
                mb = float(b.get("margin", 0.0))
                out.append(CheckResult(
                    cid, "fail", f"|{key}| of joint {j + 1} reached F at t = {b['time']:.6g} s: |{key}| = "
                    f"{b['abs_error']:.6g}, F = {b['boundary']:.6g} (relative margin {mb:.3g}); "
                    f"{'initial error outside the funnel' if res.status == 'initial_outside' else 'the run stopped there'}",
                    method="simulation (breach located on a 100x finer grid)", margin=mb,
                    where={"t": b["time"], "joint": j + 1},
                    evidence={"abs_error": b.get("abs_error"), "boundary": b.get("boundary")}))
                continue
            span = f"over [0, {t_end:.6g}] s" + ("" if res.status == "ok" else " (the run stopped early)")
            status = "pass" if mmin > 0 else "fail"
            out.append(CheckResult(
                cid, status, f"|{key}| < F{key[1]} {span}: smallest margin (F - |{key}|)/F = {mmin:.4g} "
                f"(F - |{key}| = {absm:.4g}) at t = {tmin:.4g} s{where_}", method=how,
                margin=mmin, where={"t": tmin, "joint": j + 1}, evidence={"abs_margin": absm}))
    return out


def check_decay(L: LyapunovTrajectory, which: str, claim=None) -> CheckResult:
    """lyapunov.decay (which = 'corrected': the design's rho, delta) or claim.<name> (which = 'paper': a printed decay
    claim's): V_dot <= -rho V + delta along the trajectory (V_dot exact by AD)."""
    cid = f"claim.{claim.name}" if which == "paper" else "lyapunov.decay"
    label = (f"{claim.source or 'printed'}: rho = {claim.rho.text}, delta = {claim.delta.text} (the printed constants "
             "applied to this design)" if which == "paper" else
             "rho = min(2 k1 min mu1, k2 min mu2, sigma gamma), delta = sigma/2 ||W*||^2 + sum mu2 eps^2/(2 k2) "
             "(docs/derivation.md eq. 8)")
    rhs = L.rhs(which)
    margin, allow = decay_margin(L.V_dot, rhs, L.scale)
    finite = np.isfinite(margin)
    method = f"exact V_dot by AD on the closed-loop graph at {int(finite.sum())} trajectory points"
    if not finite.any():
        return CheckResult(cid, "skip", "no trajectory point inside both funnels", method=method)
    viol = finite & (margin < -allow)
    i = int(np.argmin(np.where(finite, margin, np.inf)))
    rel = float(margin[i] / max(abs(L.V_dot[i]) + abs(rhs[i]), 1e-300))
    ev = {"points": int(finite.sum()), "violations": int(viol.sum()), "V": float(L.V[i]),
          "V_dot": float(L.V_dot[i]), "rhs": float(rhs[i]), "relative_margin": rel,
          "rho": float(L.rho_paper[i] if which == "paper" else L.rho[i]),
          "delta": float(L.delta_paper[i] if which == "paper" else L.delta[i])}
    where = {"t": float(L.t[i])}
    if viol.any():
        tv = L.t[viol]
        return CheckResult(cid, "fail", f"{label}: VIOLATED at {int(viol.sum())} of {int(finite.sum())} points "
                           f"(t in [{tv.min():.4g}, {tv.max():.4g}] s); worst at t = {L.t[i]:.4g} s: V_dot = "
                           f"{_g(L.V_dot[i])} > -rho V + delta = {_g(rhs[i])} by {_g(-margin[i])}",
                           method=method, margin=float(margin[i]), where=where, evidence=ev)
    return CheckResult(cid, "pass", f"{label}: holds at all {int(finite.sum())} points; smallest margin "
                       f"-rho V + delta - V_dot = {_g(margin[i])} at t = {L.t[i]:.4g} s",
                       method=method, margin=float(margin[i]), where=where, evidence=ev)


def check_bound(L: LyapunovTrajectory, which: str = "corrected") -> CheckResult:
    """lyapunov.bound: V(t) <= V(0) e^{-rho t} + delta/rho (1 - e^{-rho t}) with constant rho, delta."""
    cid = "lyapunov.bound"
    B = L.bound_paper if which == "paper" else L.bound
    rho = L.rho_paper_const if which == "paper" else L.rho_const
    delta = L.delta_paper_const if which == "paper" else L.delta_max
    what = (f"rho = {_g(rho)} (min over the trajectory of the paper's rho(t)), delta = {_g(delta)}"
            if which == "paper" else
            f"rho = {_g(rho)} (min over the trajectory of rho(t); the constant lower bound min(2k1/F1(0), "
            f"k2/F2(0), sigma gamma) is {_g(L.rho_const_lower)}), delta = {_g(delta)} (max over the trajectory)")
    ok = np.isfinite(B) & np.isfinite(L.V)
    ok[0] = False                      # B(0) = V(0): equality by construction
    method = f"integrated bound at {int(ok.sum())} trajectory points"
    if not ok.any():
        return CheckResult(cid, "skip", "no trajectory points inside both funnels after t = 0", method=method)
    margin = B - L.V
    abs_allow = V_ABS_ALLOWANCE_PER_ATOL * float(L.extra.get("atol", 1e-8))
    allow = REL_TOL * np.abs(B) + abs_allow
    viol = ok & (margin < -allow)
    i = int(np.argmin(np.where(ok, margin, np.inf)))
    ev = {"rho": rho, "delta": delta, "V0": float(L.V[0]), "ultimate": delta / rho if rho > 0 else None,
          "V_at_worst": float(L.V[i]), "bound_at_worst": float(B[i]),
          "relative_margin": float(margin[i] / max(abs(B[i]), 1e-300))}
    if viol.any():
        return CheckResult(cid, "fail", f"V(t) <= V(0) e^(-rho t) + delta/rho (1 - e^(-rho t)) with {what}: VIOLATED "
                           f"at {int(viol.sum())} points; worst at t = {L.t[i]:.4g} s: V = {_g(L.V[i])} > bound "
                           f"{_g(B[i])} by {_g(-margin[i])}", method=method, margin=float(margin[i]),
                           where={"t": float(L.t[i])}, evidence=ev)
    return CheckResult(cid, "pass", f"V(t) <= V(0) e^(-rho t) + delta/rho (1 - e^(-rho t)) with {what}: holds; "
                       f"smallest margin {_g(margin[i])} (relative {ev['relative_margin']:.3g}) at t = {L.t[i]:.4g} s",
                       method=method, margin=float(margin[i]), where={"t": float(L.t[i])}, evidence=ev)


def check_falsification(fz: dict, which: str, claim=None) -> CheckResult:
    """lyapunov.falsification (or, for a printed decay claim, claim.<name>.falsification's part of claim.<name>):
    the decay inequality at sampled states inside the funnels."""
    cid = f"claim.{claim.name}" if which == "paper" else "lyapunov.falsification"
    r = fz[which]
    method = (f"falsification (sampled), not a proof: {fz['samples']} scrambled-Sobol states inside both funnels "
              f"(|e| <= {fz['fill']:g} F, t in [{fz['t_range'][0]:g}, {fz['t_range'][1]:g}], x_esn in its invariant "
              f"box, W_hat within +-{fz['w_scale']:.3g})")
    ev = {k: v for k, v in r.items() if k != "where"}
    w = r["where"]
    if not r["evaluated"]:          # every sampled state overflowed: nothing says the inequality holds
        return CheckResult(cid, "fail", f"V_dot <= -rho V + delta ({which}): not finite at any of the "
                           f"{fz['samples']} sampled states inside the funnels (the design's numbers overflow "
                           "floating point)", method=method, evidence=ev)
    at = f"t = {w['t']:.4g}, q = [{', '.join(f'{v:.4g}' for v in w['q'])}], dq = [{', '.join(f'{v:.4g}' for v in w['dq'])}]"
    if r["violations"]:
        return CheckResult(cid, "fail", f"V_dot <= -rho V + delta ({which}) violated at {r['violations']} of "
                           f"{r['evaluated']} sampled states ({r['fraction']:.1%}); worst at {at}: V_dot = "
                           f"{_g(r['V_dot'])} > {_g(r['rhs'])}", method=method, margin=r["worst_margin"], where=w,
                           evidence=ev)
    return CheckResult(cid, "pass", f"V_dot <= -rho V + delta ({which}): no counterexample at {r['evaluated']} "
                       f"sampled states; smallest margin {_g(r['worst_margin'])} at {at}", method=method,
                       margin=r["worst_margin"], where=w, evidence=ev)


def check_bounded(res, design, L: LyapunovTrajectory | None) -> list[CheckResult]:
    """bounded.tau, bounded.w_hat, bounded.x_esn over the simulated horizon."""
    s = res.signals
    t = res.t
    out = []
    if t.size == 0:
        return [CheckResult(f"bounded.{k}", "skip", "no trajectory", method="simulation")
                for k in ("tau", "w_hat", "x_esn")]
    # tau: finite, and not growing at the end of the horizon (its unit per joint: N m, or N for a prismatic one)
    from ..core.names import joint_units
    n_tau = np.asarray(s["tau"]).reshape(len(t), -1).shape[1]
    tu = [u["tau"] for u in joint_units(getattr(res, "joint_types", None), n_tau)]
    tau = np.asarray(s["tau"])
    fin = bool(np.isfinite(tau).all())
    a = np.abs(tau)
    i, j = np.unravel_index(int(np.nanargmax(np.where(np.isfinite(a), a, -1))), a.shape)
    peak, t_peak = float(a[i, j]), float(t[i])
    q = max(1, int(0.75 * len(t)))
    h = min(max(0, int(0.5 * len(t))), q - 1)
    early = float(np.nanmax(a[:q])) if q else float("nan")
    late = float(np.nanmax(a[q:])) if q < len(t) else early
    before = float(np.nanmax(a[h:q]))          # the third quarter: the window just before the last
    # the peaks between output points (simulation.between) count where they fall
    bw = getattr(res, "between", None) or {}
    t_split = float(t[q]) if q < len(t) else np.inf
    for jj, (v, tv) in enumerate(zip(bw.get("max_abs_tau") or [], bw.get("t_max_abs_tau") or [])):
        if v is None:
            continue
        if v > peak:
            peak, t_peak, j = float(v), float(tv), jj
        if tv >= t_split:
            late = max(late, float(v))
        else:
            early = max(early, float(v))
            if h < len(t) and tv >= float(t[h]):
                before = max(before, float(v))
    grow = late / max(early, 1e-300) - 1
    rising = late / max(before, 1e-300) - 1
    method = ("finite horizon: finite everywhere, and the peak |tau| over the last quarter of the run at most "
              f"{1 + TAU_GROWTH_ALLOWANCE:g} x the peak before it (no growth at the end); a last quarter above "
              f"{1 + TAU_GROWTH_ALLOWANCE:g} x the third quarter's peak is a warning: a finite horizon shows no bound "
              "on what still grows at its end")
    ok = fin and grow <= TAU_GROWTH_ALLOWANCE
    status = "pass" if ok else "fail"
    note = "" if fin else "; NON-FINITE values"
    if ok and rising > TAU_GROWTH_ALLOWANCE:
        status = "warn"
        note = (f"; still growing at the horizon's end (last-quarter peak {rising + 1:.3g} x the third quarter's "
                f"{_g(before)}): bounded over this horizon only, not shown bounded beyond it")
    out.append(CheckResult("bounded.tau", status,
                           f"max |tau| = {_g(peak)} {tu[j]} at t = {t_peak:.4g} s, joint {j + 1}; last-quarter "
                           f"peak {_g(late)} vs earlier peak {_g(early)} "
                           f"({tu[0] if len(set(tu)) == 1 else ' | '.join(dict.fromkeys(tu))})" + note,
                           method=method, margin=float(TAU_GROWTH_ALLOWANCE - grow) if fin else None,
                           where={"t": t_peak, "joint": int(j + 1)},
                           evidence={"max_abs": peak, "late_peak": late, "early_peak": early,
                                     "third_quarter_peak": before}))
    if "w_hat" not in s:
        return out + [CheckResult(f"bounded.{k}", "skip", "this design has no such state (no approximator)",
                                  method="design layout") for k in ("w_hat", "x_esn")]
    # W_hat: finite and within the bound the corrected Lyapunov argument implies
    W = np.asarray(s["w_hat"]).reshape(len(t), -1)
    nrm = np.linalg.norm(W, axis=1)
    fin = bool(np.isfinite(W).all())
    i = int(np.nanargmax(np.where(np.isfinite(nrm), nrm, -1)))
    if L is not None and np.isfinite(L.bound).any():
        abs_allow = V_ABS_ALLOWANCE_PER_ATOL * float(L.extra.get("atol", 1e-8))
        lim = np.linalg.norm(L.W_star) + np.sqrt(2 * float(res.gamma) * (np.maximum(L.bound, 0) + abs_allow))
        ok_pts = np.isfinite(lim)
        marg = np.where(ok_pts, lim - nrm, np.inf)
        k = int(np.argmin(marg))
        ok = fin and bool(np.all(marg >= -REL_TOL * np.abs(np.where(ok_pts, lim, 0))))
        out.append(CheckResult(
            "bounded.w_hat", "pass" if ok else "fail",
            f"max ||W_hat||_F = {_g(nrm[i])} at t = {t[i]:.4g} s; within ||W*|| + sqrt(2 gamma B(t)) (B the "
            f"corrected integrated bound) with smallest margin {_g(marg[k])} at t = {t[k]:.4g} s; "
            f"||W_hat(t_end)|| = {_g(nrm[-1])}" + ("" if fin else "; NON-FINITE values"),
            method="finite horizon: ||W_hat(t)||_F <= ||W*||_F + sqrt(2 gamma B(t)), implied by V >= ||W~||^2/(2 gamma)",
            margin=float(marg[k]), where={"t": float(t[k])},
            evidence={"max_norm": float(nrm[i]), "final_norm": float(nrm[-1]), "W_star_norm": float(np.linalg.norm(L.W_star))}))
    else:
        out.append(CheckResult("bounded.w_hat", "pass" if fin else "fail",
                               f"max ||W_hat||_F = {_g(nrm[i])} at t = {t[i]:.4g} s (no Lyapunov bound available)",
                               method="finite horizon: finite everywhere", where={"t": float(t[i])},
                               evidence={"max_norm": float(nrm[i])}))
    if "x_esn" not in s:
        return out + [CheckResult("bounded.x_esn", "skip", "this design has no reservoir", method="design layout")]
    # x_esn: the reservoir's invariant box |x| <= 1/leak
    x = np.asarray(s["x_esn"]).reshape(len(t), -1)
    box = 1.0 / float(design.scenario.esn.leak)
    ax = np.abs(x)
    i, j = np.unravel_index(int(np.nanargmax(np.where(np.isfinite(ax), ax, np.inf))), ax.shape)
    fin = bool(np.isfinite(x).all())
    inside0 = bool(np.all(np.abs(x[0]) <= box))
    ok = fin and float(ax[i, j]) <= box * (1 + 1e-9)
    out.append(CheckResult("bounded.x_esn", "pass" if ok else "fail",
                           f"max |x_esn| = {_g(ax[i, j])} (unit {j + 1}, t = {t[i]:.4g} s) against the invariant box "
                           f"|x| <= 1/leak = {_g(box)}" + ("" if inside0 else " (x_esn(0) starts outside the box)"),
                           method="finite horizon: |x_esn,i| <= 1/leak (tanh reservoir, see symfunnel/family/esn.py)",
                           margin=float(box - ax[i, j]), where={"t": float(t[i]), "unit": int(j + 1)},
                           evidence={"max_abs": float(ax[i, j]), "box": box}))
    return out


# --- the driver ----------------------------------------------------------------------------------

def decay_claim(scenario):
    """The scenario's printed decay claim (a theorem's rho and delta), if it declares one."""
    return next((c for c in scenario.claims if c.kind == "decay"), None)


def check_decay_claim(L: LyapunovTrajectory | None, fz: dict | None, claim) -> CheckResult:
    """claim.<name> of a decay claim: fails when the printed inequality is violated along the run or at a sampled
    state (both evaluated with the design's exact V_dot)."""
    if L is None:
        return CheckResult(f"claim.{claim.name}", "skip", "no trajectory to evaluate on", method="simulation")
    along = check_decay(L, "paper", claim)
    if along.status == "fail":
        along.verdict = "refuted"
        return along
    if along.status == "skip":
        return along
    if fz is not None:
        sampled = check_falsification(fz, "paper", claim)
        if sampled.status == "fail":
            sampled.detail = along.detail + "; but " + sampled.detail
            sampled.verdict = "refuted"
            return sampled
    # agreement at samples is no proof: the claim is neither proven nor refuted (warn, never pass)
    n = int(along.evidence.get("points", 0)) + (int(fz["paper"]["evaluated"]) if fz is not None else 0)
    along.status, along.verdict = "warn", "not proven"
    along.detail = (f"not proven: held at {n} samples ({along.evidence.get('points', 0)} trajectory points"
                    + (f", {fz['paper']['evaluated']} sampled states" if fz is not None else "")
                    + f"), no proof; {along.detail}")
    return along


def verify(scenario, design, closed_loop, result, lyapunov: LyapunovTrajectory | None, audit_checks=(), *,
           t_final: float, samples: int = 10000, seed: int = 0, progress=None,
           rate_hz: float | None = None, engine: str | None = None) -> Verification:
    """Every check on the stages computed by the pipeline (`symfunnel.pipeline.Run`), the audit's included, with the
    scenario's expectations applied; never raises for a failed claim."""
    from . import theory
    from .gate import apply_expectations
    say = progress or (lambda s: None)
    timings = {}
    cl = closed_loop
    L = lyapunov
    claim = decay_claim(scenario)
    checks = list(audit_checks)
    checks += [c for c in [check_completed(result)] + check_containment(result, design.n)]
    t0 = time.perf_counter()
    say("design identity: V_dot along the nominal model + symbolic unknowns (AD)")
    checks.append(theory.check_identity(design, np.random.default_rng([seed, 11]), closed_loop=cl, result=result))
    timings["identity"] = time.perf_counter() - t0
    checks.append(theory.check_rho_positive(design, t_final))
    fz = None
    if L is not None:
        checks.append(check_decay(L, "corrected"))
        checks.append(check_bound(L))
        t0 = time.perf_counter()
        say(f"falsification over {samples} Sobol states inside the funnels")
        fz = falsify(cl, L.W_star, samples=samples, seed=seed, t_range=(0.0, float(t_final)), claim=claim)
        timings["falsification"] = time.perf_counter() - t0
        checks.append(check_falsification(fz, "corrected"))
    else:
        for cid in ("lyapunov.decay", "lyapunov.bound", "lyapunov.falsification"):
            checks.append(CheckResult(cid, "skip", "no trajectory to evaluate on", method="simulation"))
    checks.append(theory.check_guarantee(design, L))
    say("assumption: input gain M_p^-1 D M over the dead-zone slopes")
    checks.append(theory.check_input_gain(design, np.random.default_rng([seed, 13])))
    if claim is not None:
        checks = [c for c in checks if c.id != f"claim.{claim.name}"]
        checks.append(check_decay_claim(L, fz, claim))
    checks += check_bounded(result, design, L)
    from .limits import check_limits                         # the URDF's position and velocity limits
    checks += check_limits(scenario, design, result, t_final)
    engine = engine or getattr(scenario.plant, "engine", "symfunnel")
    if engine != "symfunnel":                                # the engine is the same robot before it is the plant
        from .engine import check_engine_agreement
        checks.append(check_engine_agreement(scenario, seed=seed, progress=say))
    from .implementation import implementation_checks       # [implementation] or --rate: the deployed controller
    checks += implementation_checks(scenario, design, rate_hz=rate_hz, t_final=t_final, progress=say, engine=engine)
    apply_expectations(scenario, checks)
    return Verification(scenario=scenario, design=design, closed_loop=cl, result=result, lyapunov=L,
                        falsification=fz, checks=checks, timings=timings)
