"""The funnel-backstepping design variant (the paper's, generalised): its signals, state layout, Lyapunov function,
target V_dot form, rho/delta and mutants, over any error transformation and approximator of `symfunnel.family`.

With z = T(e, F) of a transformation (dz/dt = mu (de/dt - dF/F e), r = e/z) and f the unknown term of the
acceleration, f = W*^T Phi + eps:

    alpha2 = dqd + (dF1/F1) e1 - k1 z1
    v      = alpha2_dot + (dF2/F2) e2 - k2 z2 - mu1 z1 r2 / mu2
    tau    = M (v - W_hat^T Phi) + C dq + G
    W_hat' = Gamma (Phi (mu2 z2)^T - sigma W_hat)
    V      = 1/2 z1^T z1 + 1/2 z2^T z2 + 1/(2 Gamma) ||W* - W_hat||_F^2

and along the nominal model plus f the design's *target form* of V_dot holds exactly (docs/derivation.md):

    V_dot = -sum k1 mu1 z1^2 - sum k2 mu2 z2^2 + (mu2 z2)^T eps + sigma tr(W~^T W_hat),    W~ = W* - W_hat.

Every mutant of `MUTANTS` is a one-term change of this derivation, so a verifier that accepts one has a blind spot.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..family.approximators import APPROXIMATORS
from ..family.projection import project
from ..family.transforms import TRANSFORMS
from ..sx.linalg import ldl_solve


@dataclass(frozen=True)
class Mutant:
    """A seeded error of the derivation: an id and what it changes."""

    id: str
    description: str
    needs_weights: bool = False          # only for designs with an approximator
    needs_projection: bool = False       # only for designs whose law is projected onto a ball
    transform: str | None = None         # only for this transformation


MUTANTS = (
    Mutant("drop_cross_term", "v without the coupling term -mu1 z1 r2/mu2"),
    Mutant("flip_cross_term", "v with +mu1 z1 r2/mu2 (the coupling term's sign)"),
    Mutant("drop_dF1_term", "alpha2 without (dF1/F1) e1"),
    Mutant("drop_dF2_term", "v without (dF2/F2) e2"),
    Mutant("flip_k1", "alpha2 with +k1 z1"),
    Mutant("flip_k2", "v with +k2 z2"),
    Mutant("drop_M_in_tau", "tau = (v - W_hat^T Phi) + C dq + G (no inertia)"),
    Mutant("drop_C_dq", "tau without C dq"),
    Mutant("drop_G", "tau without G"),
    Mutant("zero_alpha2_dot", "v without alpha2_dot (the derivative the paper handles loosely)"),
    Mutant("half_alpha2_dot", "v with alpha2_dot/2"),
    Mutant("drop_estimate_in_tau", "tau without -M W_hat^T Phi", needs_weights=True),
    Mutant("flip_adaptation", "W_hat' = Gamma(-Phi (mu2 z2)^T - sigma W_hat)", needs_weights=True),
    Mutant("zeta_for_mu_in_adaptation", "adaptation driven by zeta2 z2 instead of mu2 z2", needs_weights=True,
           transform="funnel"),
    Mutant("z_for_mu_in_adaptation", "adaptation driven by z2 instead of mu2 z2", needs_weights=True),
    Mutant("flip_sigma", "W_hat' = Gamma(Phi (mu2 z2)^T + sigma W_hat)", needs_weights=True),
    Mutant("flip_projection", "W_hat' = Y + c W_hat (the projection's correction pushes outwards)",
           needs_weights=True, needs_projection=True),
    Mutant("drop_projection_test", "the projection's correction without the boundary test max(<W_hat, Y>, 0): "
           "applied where Y already points inwards", needs_weights=True, needs_projection=True),
)


class _Signals(dict):
    """The signal table under construction: a signal with an offset gets it added where it is defined."""

    def __init__(self, offsets: dict[str, ca.SX]):
        super().__init__()
        self.offsets = offsets

    def __setitem__(self, name: str, value) -> None:
        super().__setitem__(name, value + self.offsets[name] if name in self.offsets else value)


def _named(prefix: str, n: int) -> ca.SX:
    return ca.vertcat(*[ca.SX.sym(f"{prefix}{i + 1}") for i in range(n)])


def _check_projection(scenario, n_regressor: int) -> tuple[float, float] | None:
    """(R, eps) of [adaptation] projection, validated against the design: it needs adaptive weights, and W_hat(0)
    inside the ball ||W_hat||_F <= R (InputError naming the key otherwise); None without a projection."""
    R = scenario.projection
    if R is None:
        return None
    if not n_regressor:
        raise InputError("is set but the design has no adaptive weights (no approximator)", file=scenario.file,
                         key="adaptation.projection", expected="no projection, or an approximator")
    w0 = abs(float(scenario.w_hat0)) * float(np.sqrt(n_regressor * scenario.n))
    if not w0 <= R:
        raise InputError(f"= {R:g} leaves W_hat(0) outside the ball: ||W_hat(0)||_F = {w0:.6g} (w_hat0 in each of "
                         f"{n_regressor} x {scenario.n} entries)", file=scenario.file, key="adaptation.projection",
                         expected=f"a radius >= {w0:.6g}, or a smaller w_hat0")
    return float(R), float(scenario.projection_layer)


class Backstepping:
    """The paper's two-step backstepping over a transformation and an approximator."""

    name = "backstepping"

    def __init__(self, scenario):
        self.scenario = scenario
        self.transform = TRANSFORMS.get(scenario.design.transform, file=scenario.file, key="design.transform")()
        self.approximator = APPROXIMATORS.get(scenario.design.approximator, file=scenario.file,
                                              key="approximator.type")(scenario)
        self.projection = _check_projection(scenario, self.approximator.n_regressor)

    # --- layout -------------------------------------------------------------------------------------

    @property
    def n_regressor(self) -> int:
        """Length of Phi (0 without an approximator)."""
        return self.approximator.n_regressor

    def states(self) -> list[tuple[str, tuple[int, int]]]:
        """The controller's own states, in order: the approximator's, then the weight estimate W_hat."""
        out = list(self.approximator.states())
        if self.n_regressor:
            out.append(("w_hat", (self.n_regressor, self.scenario.n)))
        return out

    def initial_states(self) -> dict[str, np.ndarray]:
        """Initial values of the controller states (W_hat filled with the scenario's w_hat0)."""
        sc = self.scenario
        out = dict(self.approximator.initial(sc))
        if self.n_regressor:
            out["w_hat"] = np.full((self.n_regressor, sc.n), float(sc.w_hat0))
        return out

    def mutants(self) -> list[Mutant]:
        """The mutants that apply to this combination of transformation and approximator."""
        return [m for m in MUTANTS if (not m.needs_weights or self.n_regressor)
                and (not m.needs_projection or self.projection is not None)
                and (m.transform is None or m.transform == self.transform.name)]

    def equivalent(self, design, mutant: str) -> str | None:
        """A proof that a mutant cannot change the controller on this scenario, or None."""
        if mutant == "drop_G" and design.signals["G"].is_zero():
            return "G is identically zero for this model (its SX is structurally zero), so tau is unchanged"
        if mutant == "drop_C_dq" and design.signals["C"].is_zero():
            return "C is structurally zero for this model, so tau is unchanged"
        return None

    # --- signals ------------------------------------------------------------------------------------

    def derive(self, mutant: str | None = None, offsets: dict[str, ca.SX] | None = None,
               values: dict[str, ca.SX] | None = None):
        """Every signal of the design as SX, with `mutant` (an id of `mutants()`) applied when given.

        `offsets` adds a symbol to a signal where it is defined, so every signal computed from it depends on that
        symbol: how the audit finds what depends on a signal through the derivation (circular printed claims).
        `values` replaces design parameters (keys of `scenario.tune.TUNABLE`: controller.k1/k2, adaptation.gamma/sigma,
        funnel.e2.phi0/phi_inf/a, and funnel.e1's too) by expressions, e.g. symbols, so that tune can differentiate
        the closed loop with respect to them and one compiled closed loop serves every value of them.
        """
        from .core import Design
        sc = self.scenario
        model = sc.model
        n = model.n
        if mutant is not None and mutant not in {m.id for m in self.mutants()}:
            raise ValueError(f"unknown mutant {mutant!r} of this design")
        mut = mutant or ""
        t = ca.SX.sym("t")
        q, dq = model.q, model.dq
        qd, dqd, ddqd = _named("qd", n), _named("dqd", n), _named("ddqd", n)
        sym = dict(t=t, q=q, dq=dq, qd=qd, dqd=dqd, ddqd=ddqd)
        for name, shape in self.states():
            sym[name] = ca.SX.sym(name, *shape)
        nr = self.n_regressor
        w_hat = sym["w_hat"] if nr else ca.SX(0, n)
        parts: dict = {}

        val = values or {}
        k1, k2 = val.get("controller.k1", ca.DM(sc.k1)), val.get("controller.k2", ca.DM(sc.k2))
        gamma, sigma = val.get("adaptation.gamma", ca.DM(sc.gamma)), val.get("adaptation.sigma", ca.DM(sc.sigma))
        shapes = {key: {k.rsplit(".", 1)[1]: v for k, v in val.items() if k.startswith(f"funnel.{key}.")}
                  for key in ("e1", "e2")}
        s = _Signals(offsets or {})
        s.update(qd=qd, dqd=dqd, ddqd=ddqd)
        s["M"] = model.numeric(model.M)
        s["C"] = model.numeric(model.C)
        s["G"] = model.numeric(model.G)
        for i, key in ((1, "e1"), (2, "e2")):
            F = sc.funnels[key].sx(t, **shapes[key])
            s[f"F{i}"] = F
            s[f"dF{i}"] = ca.jtimes(F, t, ca.SX(1))

        # Step 1: the outer loop on e1 = q - qd.
        s["e1"] = q - qd
        s["de1"] = dq - dqd
        T1 = self.transform.build(s["e1"], s["F1"])
        s["z1"], s["mu1"], s["r1"] = T1["z"], T1["mu"], T1["r"]
        for k in self.transform.extra_signals:
            s[f"{k}1"] = T1[k]
        feed_forward = 0 if mut == "drop_dF1_term" else s["dF1"] / s["F1"] * s["e1"]
        k1_sign = -1 if mut == "flip_k1" else 1
        s["alpha2"] = dqd + feed_forward - k1_sign * k1 * s["z1"]

        # Exact derivatives along the flow by forward-mode AD: d/dt + dq.d/dq + dqd.d/dqd + ddqd.d/ddqd.
        x1, v1 = ca.vertcat(t, q, qd, dqd), ca.vertcat(1, dq, dqd, ddqd)
        s["alpha2_dot"] = ca.jtimes(s["alpha2"], x1, v1)
        s["z1_dot"] = ca.jtimes(s["z1"], x1, v1)

        # Step 2: the inner loop on e2 = dq - alpha2.
        s["e2"] = dq - s["alpha2"]
        T2 = self.transform.build(s["e2"], s["F2"])
        s["z2"], s["mu2"], s["r2"] = T2["z"], T2["mu"], T2["r"]
        for k in self.transform.extra_signals:
            s[f"{k}2"] = T2[k]
        s["Phi"] = self.approximator.regressor(sym)
        a2dot = {"zero_alpha2_dot": 0, "half_alpha2_dot": 0.5 * s["alpha2_dot"]}.get(mut, s["alpha2_dot"])
        ff2 = 0 if mut == "drop_dF2_term" else s["dF2"] / s["F2"] * s["e2"]
        k2_sign = -1 if mut == "flip_k2" else 1
        cross = {"drop_cross_term": 0, "flip_cross_term": -1}.get(mut, 1) * s["mu1"] * s["z1"] * s["r2"] / s["mu2"]
        s["v"] = a2dot + ff2 - k2_sign * k2 * s["z2"] - cross
        estimate = ca.mtimes(w_hat.T, s["Phi"]) if nr else ca.SX.zeros(n, 1)
        inner = s["v"] - (0 if mut == "drop_estimate_in_tau" else estimate)
        s["tau"] = ((inner if mut == "drop_M_in_tau" else ca.mtimes(s["M"], inner))
                    + (0 if mut == "drop_C_dq" else ca.mtimes(s["C"], dq))
                    + (0 if mut == "drop_G" else s["G"]))
        # The nominal model under the unmutated tau accelerates by exactly v - W_hat^T Phi (inverse dynamics).
        s["ddq"] = s["v"] - estimate
        s["de2"] = s["ddq"] - s["alpha2_dot"]
        x2, v2 = ca.vertcat(t, q, dq, qd, dqd), ca.vertcat(1, dq, s["ddq"], dqd, ddqd)
        s["z2_dot"] = ca.jtimes(s["z2"], x2, v2)
        if nr:
            drive = {"zeta_for_mu_in_adaptation": s.get("zeta2", s["mu2"]) * s["z2"],
                     "z_for_mu_in_adaptation": s["z2"]}.get(mut, s["mu2"] * s["z2"])
            learn = -1 if mut == "flip_adaptation" else 1
            leak = -1 if mut == "flip_sigma" else 1
            raw = gamma * (learn * ca.mtimes(s["Phi"], drive.T) - leak * sigma * w_hat)
            if self.projection is None:
                s["w_hat_dot"] = raw
            else:
                P = project(w_hat, raw, *self.projection)
                if mut == "drop_projection_test":
                    P["c"] = P["a"] * P["k"]
                s["w_hat_dot"] = raw + P["c"] * w_hat if mut == "flip_projection" else raw - P["c"] * w_hat
                parts["projection"] = {**P, "w_dot": s["w_hat_dot"], "R": self.projection[0],
                                       "eps": self.projection[1]}
        for name, rate in self.approximator.dynamics(sym, s).items():
            s[f"{name}_dot"] = rate

        # Reference as functions of t, from the scenario's expressions; derivatives by AD.
        qd_t = ca.vertcat(*[e.to_casadi({"t": t}) for e in sc.reference])
        dqd_t = ca.jtimes(qd_t, t, ca.SX(1))
        ddqd_t = ca.jtimes(dqd_t, t, ca.SX(1))
        constants = {"k1": ca.SX(k1), "k2": ca.SX(k2), "Gamma": ca.SX(gamma), "sigma": ca.SX(sigma)}
        return Design(scenario=sc, variant=self, sym=sym, signals=dict(s),
                      reference_t={"qd": qd_t, "dqd": dqd_t, "ddqd": ddqd_t}, constants=constants,
                      mutant=mutant, parts=parts)

    def signal_info(self) -> dict[str, tuple[str, int]]:
        """name -> (description, funnel level needed: 0 none, 1 funnel e1, 2 both) of every signal derived."""
        from ..core.names import SIGNALS
        out = {k: v for k, v in SIGNALS.items() if k not in ("zeta1", "zeta2", "Phi", "w_hat_dot", "x_esn_dot")}
        out["r1"] = ("e1/z1 (finite at e1 = 0)", 1)
        out["r2"] = ("e2/z2 (finite at e2 = 0), the coupling term's factor", 2)
        for k, what in self.transform.extra_signals.items():
            out[f"{k}1"] = (what.replace("e", "e1").replace("F", "F1"), 1)
            out[f"{k}2"] = (what.replace("e", "e2").replace("F", "F2"), 2)
        if self.n_regressor:
            out["Phi"] = SIGNALS["Phi"]
            out["w_hat_dot"] = SIGNALS["w_hat_dot"]
        for name, _ in self.approximator.states():
            out[f"{name}_dot"] = (f"approximator state dynamics d{name}/dt", 1)
        return out

    # --- the Lyapunov argument ----------------------------------------------------------------------

    def lyapunov(self, design, W_star: ca.SX | ca.DM, eps: ca.SX) -> dict[str, ca.SX]:
        """V, its target derivative and the rho/delta of V_dot <= -rho V + delta, in the design's symbols.

        W_star (n_regressor x n) and eps (n x 1) may be symbols (the identity check) or numbers (along a trajectory).
        """
        s = design.signals
        sc = self.scenario
        k1, k2 = ca.DM(sc.k1), ca.DM(sc.k2)
        gamma, sigma = float(sc.gamma), float(sc.sigma)
        V_z = 0.5 * ca.sumsqr(s["z1"]) + 0.5 * ca.sumsqr(s["z2"])
        target = -ca.sum1(k1 * s["mu1"] * s["z1"] ** 2) - ca.sum1(k2 * s["mu2"] * s["z2"] ** 2) \
            + ca.dot(s["mu2"] * s["z2"], eps)
        rho = ca.fmin(ca.mmin(2 * k1 * s["mu1"]), ca.mmin(k2 * s["mu2"]))
        delta = ca.sum1(s["mu2"] * eps ** 2 / (2 * k2))
        if self.n_regressor:
            w_hat = design.sym["w_hat"]
            Wt = W_star - w_hat
            V_w = ca.sumsqr(Wt) / (2 * gamma)
            target = target + sigma * ca.trace(ca.mtimes(Wt.T, w_hat))
            rho = ca.fmin(rho, sigma * gamma)
            delta = delta + sigma / 2 * ca.sumsqr(W_star)
            w_term = sigma * ca.fabs(ca.trace(ca.mtimes(Wt.T, w_hat)))
            if self.projection is not None:
                # the projection's correction -c W_hat adds (c / Gamma) tr(W~^T W_hat) to V_dot (<= 0 for
                # ||W*|| <= R); c from the operator applied to the law written here, not the design's node
                Y = gamma * (ca.mtimes(s["Phi"], (s["mu2"] * s["z2"]).T) - sigma * w_hat)
                proj = ca.trace(ca.mtimes(Wt.T, w_hat)) * project(w_hat, Y, *self.projection)["c"] / gamma
                target = target + proj
                w_term = w_term + ca.fabs(proj)
        else:
            V_w, w_term = ca.SX(0), ca.SX(0)
        scale = (ca.sum1(k1 * s["mu1"] * s["z1"] ** 2) + ca.sum1(k2 * s["mu2"] * s["z2"] ** 2)
                 + ca.fabs(ca.dot(s["mu2"] * s["z2"], eps)) + w_term)
        return {"V": V_z + V_w, "V_z": V_z, "V_w": V_w, "target": target, "rho": rho, "delta": delta,
                "scale": scale}

    def target_text(self) -> str:
        """The target form of V_dot, as text for check details."""
        out = "-sum k1 mu1 z1^2 - sum k2 mu2 z2^2 + (mu2 z2)^T eps"
        out += " + sigma tr(W~^T W_hat)" if self.n_regressor else ""
        return out + (" + (c/Gamma) tr(W~^T W_hat) (projection, c >= 0)" if self.projection is not None else "")

    def rho_text(self) -> str:
        """The constant lower bound of rho, as text."""
        return "min(2 k1/sup F1, k2/sup F2" + (", sigma Gamma)" if self.n_regressor else ")")

    def rho_lower(self, F1_sup: np.ndarray, F2_sup: np.ndarray) -> float:
        """A constant lower bound of rho: mu_i >= h'(0)/F_i >= 1/sup F_i for both transformations."""
        sc = self.scenario
        out = min(float(np.min(2 * np.asarray(sc.k1) / F1_sup)), float(np.min(np.asarray(sc.k2) / F2_sup)))
        if self.n_regressor:
            out = min(out, float(sc.sigma * sc.gamma))
        return out

    def nominal_flow(self, design, f: ca.SX) -> tuple[ca.SX, ca.SX]:
        """(x, xdot) of the design's variables along the nominal model plus an unknown acceleration term f.

        The plant is M ddq + C dq + G = tau + M f, so ddq = M^{-1}(tau - C dq - G) + f; the reference moves along
        (dqd, ddqd); the controller states along their own laws. V is a function of these variables only.
        """
        s, sym = design.signals, design.sym
        n = design.n
        rhs = s["tau"] - ca.mtimes(s["C"], sym["dq"]) - s["G"]
        ddq = (ca.solve(s["M"], rhs) if n == 1 else ldl_solve(s["M"], rhs)) + f
        xs = [sym["t"], sym["q"], sym["dq"], sym["qd"], sym["dqd"]]
        vs = [ca.SX(1), sym["dq"], ddq, sym["dqd"], sym["ddqd"]]
        for name, _ in self.states():
            xs.append(ca.vec(sym[name]))
            vs.append(ca.vec(s[f"{name}_dot"]))
        return ca.vertcat(*xs), ca.vertcat(*vs)
