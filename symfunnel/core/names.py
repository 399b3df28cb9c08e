"""The named signals of the design and the identifier rules of scenario files (ground floor: imports nothing of ours)."""

import re

#: a scenario identifier (coordinate, parameter, claim name)
IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

#: names no coordinate or parameter may take: Python's and C's keywords (the generated code names its variables
#: after them) and the values of the expression language
KEYWORDS = frozenset(__import__("keyword").kwlist) | frozenset(__import__("keyword").softkwlist) | frozenset("""
auto break case char const continue default do double else enum extern float for goto if inline int long register
restrict return short signed sizeof static struct switch typedef union unsigned void volatile while _Bool _Complex
_Imaginary nan inf""".split())

# name -> (description, funnel level needed: 0 none, 1 funnel e1, 2 funnels e1 and e2)
SIGNALS: dict[str, tuple[str, int]] = {
    "qd": ("reference position q_d(t)", 0),
    "dqd": ("reference velocity dq_d/dt", 0),
    "ddqd": ("reference acceleration d2q_d/dt2", 0),
    "M": ("inertia matrix M(q)", 0),
    "C": ("Coriolis/centripetal matrix C(q, dq)", 0),
    "G": ("gravity torque G(q)", 0),
    "F1": ("funnel boundary of e1 (the scenario's F, e.g. phi0*exp(-a*t) + phi_inf)", 0),
    "dF1": ("dF1/dt", 0),
    "F2": ("funnel boundary of e2", 0),
    "dF2": ("dF2/dt", 0),
    "e1": ("tracking error q - q_d", 0),
    "de1": ("de1/dt = dq - dq_d", 0),
    "z1": ("first funnel variable e1/(F1 - |e1|)", 1),
    "zeta1": ("1/(F1 - |e1|)", 1),
    "mu1": ("dz1/de1 = F1*zeta1^2", 1),
    "alpha2": ("virtual control (a function of t, q and the reference only)", 1),
    "alpha2_dot": ("exact time derivative of alpha2 (forward-mode AD)", 1),
    "z1_dot": ("exact time derivative of z1 along the flow", 1),
    "e2": ("second error dq - alpha2", 1),
    "z2": ("second funnel variable e2/(F2 - |e2|)", 2),
    "zeta2": ("1/(F2 - |e2|)", 2),
    "mu2": ("dz2/de2 = F2*zeta2^2", 2),
    "Phi": ("the approximator's regressor (ESN: [x_esn; 1]; RBF: Gaussians of its inputs)", 0),
    "v": ("commanded acceleration of the inner loop", 2),
    "tau": ("commanded joint torque (before the unknown dead zone)", 2),
    "ddq": ("joint acceleration of the nominal model under tau", 2),
    "de2": ("de2/dt = ddq - alpha2_dot along the nominal model", 2),
    "z2_dot": ("exact time derivative of z2 along the nominal model", 2),
    "w_hat_dot": ("adaptive-law right-hand side dW_hat/dt", 2),
    "x_esn_dot": ("echo-state reservoir dynamics dx_esn/dt", 1),
}

# Constants of the design that claims may use besides the signals.
CONSTANTS = ("k1", "k2", "Gamma", "sigma")


def compress_names(names: list[str]) -> str:
    """A readable list of symbol names with long runs shortened: 'x_esn_0..x_esn_49 (50)'."""
    out, groups = [], {}
    for s in names:
        groups.setdefault(s.rstrip("0123456789").rstrip("_"), []).append(s)
    for items in groups.values():
        out.append(f"{items[0]}..{items[-1]} ({len(items)})" if len(items) > 4 else ", ".join(items))
    return ", ".join(out) if out else "(constant)"


#: names a scenario may not give to its own coordinates or parameters
RESERVED = {"t", "u", "pi", "e"} | set(SIGNALS) | set(CONSTANTS) | {"x_esn", "w_hat", "q", "dq"}


#: the outcomes a scenario may declare for a check
EXPECT_STATUSES = ("pass", "fail")

#: ids of the audit's and verify's checks (claims aside: claim.<name>); per-joint ids come from `check_ids`
AUDIT_CHECKS = ("model.M_symmetric", "model.M_positive_definite", "model.skew_symmetry", "model.coriolis_consistent",
                "funnel.parameters", "funnel.initial_condition", "funnel.consistency", "reference.derivatives")
VERIFY_CHECKS = ("simulation.completed", "design.identity.vdot", "lyapunov.rho_positive", "lyapunov.decay",
                 "lyapunov.bound", "lyapunov.falsification", "lyapunov.guarantee", "assumption.input_gain",
                 "bounded.tau", "bounded.w_hat", "bounded.x_esn", "implementation.containment",
                 "implementation.saturation", "plant.engine_agreement")


#: ids of the certificates (`symfunnel certify`; verify shows them as checks)
CERTIFY_CHECKS = ("certify.input_gain", "certify.bounds", "certify.invariance", "certify.containment")
#: certificates computed only when `certify --only` names them (certify.sampled: `rate --certify` gives its bracket)
CERTIFY_ON_DEMAND = ("certify.sampled",)


def check_ids(n: int) -> list[str]:
    """Every non-claim check id for an n-joint scenario (what `[[expect]]` may name)."""
    joints = [f"funnel.containment.{e}.joint{j + 1}" for e in ("e1", "e2") for j in range(n)]
    return list(AUDIT_CHECKS) + list(VERIFY_CHECKS) + list(CERTIFY_CHECKS) + joints


def joint_units(joint_types, n: int) -> list[dict]:
    """Per joint, the units of its position error, velocity error and torque: rad, rad/s, N m for a revolute (or
    unknown) joint; m, m/s, N for a prismatic one."""
    types = list(joint_types or [])
    out = []
    for i in range(n):
        pr = i < len(types) and types[i] == "prismatic"
        out.append({"e1": "m" if pr else "rad", "e2": "m/s" if pr else "rad/s", "tau": "N" if pr else "N m"})
    return out


def unit_label(units: list[dict], key: str) -> str:
    """One unit for a quantity over all joints ('N m'), or both when they differ ('N m | N')."""
    seen = []
    for u in units:
        if u[key] not in seen:
            seen.append(u[key])
    return " | ".join(seen)
