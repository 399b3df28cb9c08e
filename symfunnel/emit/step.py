"""The deployed controller's one-period step as a CasADi Function, and the C `Pstep` API wrapped around it.

`step_core(design, tau_max)` is (t, q, dq, x_esn, w_hat, etd) -> (tau, x_esn_next, w_hat_next, margin, qd)
(`step_function(design, rate_hz)` the same with etd fixed at one rate): the reference from the scenario's
expressions, the torque of the design (saturated when tau_max is given), and x_esn, W_hat advanced by one period
h = 1/rate_hz by the exponential Euler method (ETD1):

    x+ = x + phi(lambda_x) * x_esn_dot,  lambda_x = leak / time_constant
    W+ = W + phi(lambda_w) * w_hat_dot,  lambda_w = Gamma * sigma,      phi(l) = (1 - exp(-l h)) / l  (h at l = 0)

which integrates the linear decay parts (-lambda x, -Gamma sigma W) exactly and holds the input-driven parts over
the period, as the zero-order hold holds the measurements. Why: x+ = a x + (1 - a) tanh(.) / leak with
a = exp(-lambda_x h) in (0, 1) is a convex combination, so the reservoir stays in [-1/leak, 1/leak] at every h
(explicit Euler leaves it, and diverges, for h > 2 time_constant / leak); W+ = b W + (1 - b)/sigma Phi (mu2 z2)^T
with b in (0, 1] stays bounded for bounded Phi mu2 z2 at every h. With [adaptation] projection = R the law is
the projected one (family.projection) and the step then scales W+ radially onto the ball ||W||_F <= R (1 + eps)
when it left it, so the deployed W_hat stays in the ball the continuous law keeps, at every h. The period's remaining limit is the loop through
the plant (the e2 funnel's gains), which `symfunnel rate` measures.

Outside a funnel the design's torque is not defined (F - |e| <= 0): the step then evaluates the design at the
state projected onto CLIP times each funnel (identity inside, so tau equals the continuous controller's there) and
reports it through `margin` = 1 - |e| / F per joint (e1 then e2, at the unprojected q, dq; < 0 outside).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..family.projection import outer_radius, radial_clip

__all__ = ["CLIP", "DEFAULT_RATE_HZ", "step_function", "step_core", "etd_factor", "etd_factors", "c_step_files",
           "valid_prefix", "emit_controller_c", "step_settings"]

#: Fraction of a funnel the state is projected onto before evaluating the design outside it.
CLIP = 1.0 - 1e-3
#: Rate baked into the step when neither --rate nor [implementation].rate_hz gives one.
DEFAULT_RATE_HZ = 1000.0


#: names of the C library (glibc's libc and libm, C11 and POSIX) that a prefix + one of the generated names' endings
#: (init, state, reference) would declare a second time: `--prefix set` made the typedef `setstate`
C_LIBRARY_CLASHES = frozenset((
    "aio_init", "cnd_init", "fanotify_init", "inet6_opt_init", "inet6_option_init", "inet6_rth_init", "initstate",
    "inotify_init", "mbsinit", "mtx_init", "posix_spawn_file_actions_init", "posix_spawnattr_init",
    "pthread_attr_getdetachstate", "pthread_attr_init", "pthread_attr_setdetachstate", "pthread_barrier_init",
    "pthread_barrierattr_init", "pthread_cond_init", "pthread_condattr_init", "pthread_mutex_init",
    "pthread_mutexattr_init", "pthread_rwlock_init", "pthread_rwlockattr_init", "pthread_setcancelstate",
    "pthread_spin_init", "sem_init", "setstate", "xdr_reference"))
#: the endings of the generated exported names (the step API's and the contract's functions)
EXPORTED_ENDINGS = ("state", "init", "step", "state_size", "step_core", "funnels", "errors", "alpha2", "alpha2_dot",
                    "controller", "reference")


def valid_prefix(prefix: str) -> bool:
    """True for a prefix that makes valid C identifiers CasADi accepts as function names (a letter first, no '__')
    and declares none of the C library's names (C_LIBRARY_CLASHES)."""
    import re
    return (bool(re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,31}", prefix)) and "__" not in prefix
            and not any(prefix + e in C_LIBRARY_CLASHES for e in EXPORTED_ENDINGS))


def etd_factor(rate: float, h: float) -> float:
    """phi = (1 - exp(-rate h)) / rate, the exponential-Euler weight of a linear decay `rate` over h (h at 0)."""
    if rate == 0.0:
        return h
    return -math.expm1(-rate * h) / rate


def etd_factors(scenario, rate_hz: float) -> tuple[float, float]:
    """(phi(lambda_x), phi(lambda_w)) of the exponential Euler update at one period 1/rate_hz."""
    h = 1.0 / float(rate_hz)
    es = scenario.esn
    return etd_factor(es.leak / es.time_constant, h), etd_factor(float(scenario.gamma) * float(scenario.sigma), h)


def step_function(design, rate_hz: float, tau_max=None, name: str = "step") -> ca.Function:
    """One controller period at rate_hz as an SX Function (t, q, dq, x_esn, w_hat) -> step_core's outputs."""
    core = step_core(design, tau_max)
    ins = core.sx_in()[:5]
    etd = ca.DM(list(etd_factors(design.scenario, rate_hz)))
    return ca.Function(name, ins, core.call(ins + [etd]), core.name_in()[:5], core.name_out(),
                       {"cse": True, "allow_duplicate_io_names": True})


def step_states(design) -> tuple[ca.SX, ca.SX]:
    """(x_esn, w_hat) of the step API: the design's own, or a placeholder that stays 0 (one reservoir unit, one
    weight row) for a design without a reservoir or without weights, so the C state struct keeps its layout."""
    s = design.sym
    return (s["x_esn"] if "x_esn" in s else ca.SX.sym("x_esn", 1, 1),
            s["w_hat"] if "w_hat" in s else ca.SX.sym("w_hat", 1, design.n))


def step_initial(design) -> tuple[np.ndarray, np.ndarray]:
    """(x_esn(0), W_hat(0)) of the step API, zeros for a placeholder (see `step_states`)."""
    init = design.variant.initial_states()
    x, w = step_states(design)
    return (np.asarray(init.get("x_esn", np.zeros(x.shape[0])), dtype=float),
            np.asarray(init.get("w_hat", np.zeros(w.shape)), dtype=float))


class Projection:
    """The step's inputs (t, q, dq), its margin and reference outputs, and `project`: design signals with the
    reference substituted and evaluated at the state projected onto CLIP times each funnel (see the module doc)."""

    def __init__(self, design):
        s, S = design.sym, design.signals
        self.t, self.q, self.dq = _, q, dq = s["t"], s["q"], s["dq"]
        self._ref_syms = [s["qd"], s["dqd"], s["ddqd"]]
        self._ref_t = [design.reference_t[k] for k in ("qd", "dqd", "ddqd")]
        F1, F2 = self.ref(S["F1"]), self.ref(S["F2"])
        self.qd = qd = self._ref_t[0]
        e1 = q - qd
        self.q_c = qd + ca.fmin(ca.fmax(e1, -CLIP * F1), CLIP * F1)
        alpha2_c = ca.substitute(self.ref(S["alpha2"]), q, self.q_c)
        e2 = dq - alpha2_c
        self.dq_c = alpha2_c + ca.fmin(ca.fmax(e2, -CLIP * F2), CLIP * F2)
        self.margin = ca.vertcat(1 - ca.fabs(e1) / F1, 1 - ca.fabs(e2) / F2)

    def ref(self, e: ca.SX) -> ca.SX:
        """e with the reference symbols replaced by the scenario's reference in t."""
        return ca.substitute([e], self._ref_syms, self._ref_t)[0]

    def project(self, exprs: list) -> list:
        """Each expression with the reference substituted, at the projected state."""
        outs = [self.ref(e) for e in exprs]
        return ca.substitute(outs, [ca.vertcat(self.q, self.dq)], [ca.vertcat(self.q_c, self.dq_c)])


def projection(design) -> Projection:
    """The step's projection of the state onto the funnels (`Projection`)."""
    return Projection(design)


def step_core(design, tau_max=None, name: str = "step_core") -> ca.Function:
    """(t, q, dq, x_esn, w_hat, etd) -> (tau, x_esn_next, w_hat_next, margin, qd): one period, the rate entering
    only through etd = etd_factors(scenario, rate_hz), so that the compiled core serves every rate."""
    S = design.signals
    P = projection(design)
    etd = ca.SX.sym("etd", 2)
    x_esn, w_hat = step_states(design)
    dots = [S.get(k + "_dot", ca.SX.zeros(*v.shape)) for k, v in (("x_esn", x_esn), ("w_hat", w_hat))]
    tau, xdot, wdot = P.project([S["tau"], *dots])
    if tau_max is not None:
        tm = ca.DM(np.broadcast_to(np.asarray(tau_max, dtype=float), (design.n,)).copy())
        tau = ca.fmin(ca.fmax(tau, -tm), tm)
    x_next = x_esn + etd[0] * xdot
    w_next = w_hat + etd[1] * wdot
    proj = design.parts.get("projection")
    if proj is not None:
        # the projected law keeps ||W_hat|| <= R (1 + eps) in continuous time; one step can cross the layer, so the
        # step scales W_hat radially back onto that ball (family.projection.radial_clip; identity inside)
        w_next = radial_clip(w_next, outer_radius(proj["R"], proj["eps"]))
    return ca.Function(name, [P.t, P.q, P.dq, x_esn, w_hat, etd], [tau, x_next, w_next, P.margin, P.qd],
                       ["t", "q", "dq", "x_esn", "w_hat", "etd"], ["tau", "x_esn_next", "w_hat_next", "margin", "qd"],
                       {"cse": True, "allow_duplicate_io_names": True})


def _c_array(values) -> str:
    return ", ".join(repr(float(v)) for v in np.ravel(values)) or "0.0"


def c_step_files(design, *, prefix: str, fprefix: str, basename: str, rate_hz: float | None, tau_max,
                 x0: np.ndarray, w0: np.ndarray) -> tuple[str, str]:
    """(C source, header section) of the Pstep API around the generated `<fprefix>step_core`.

    rate_hz None gives the rate searches' build (`deployed.rate_step`): the same text except that the weights
    `<prefix>etd_` are a writable global the caller sets per rate (not a static const baked at one rate) and the
    rate's places (a comment, `<P>RATE_HZ`, which no code uses) read 0.0, so that one object serves every rate."""
    from .c import template
    n = design.n
    x_esn, w_hat = step_states(design)
    N = int(x_esn.numel())
    nr = int(w_hat.shape[0])
    sub = {
        "@P@": prefix, "@F@": fprefix, "@BASENAME@": basename, "@UP@": prefix.upper(),
        "@N@": str(n), "@NESN@": str(N), "@NREG@": str(nr), "@NW@": str(nr * n),
        "@RESN@": str(int(design.sym["x_esn"].numel()) if "x_esn" in design.sym else 0),
        "@RREG@": str(int(design.sym["w_hat"].shape[0]) if "w_hat" in design.sym else 0),
        "@RATE@": repr(float(rate_hz)) if rate_hz is not None else "0.0", "@SCENARIO@": design.scenario.name,
        "@X0@": _c_array(x0), "@W0@": _c_array(np.asarray(w0).reshape(-1, order="F")),
        "@TAUMAX@": ("no saturation (the scenario sets no tau_max)" if tau_max is None else
                     "saturated at tau_max = [" + ", ".join(f"{v:g}" for v in
                                                             np.broadcast_to(np.asarray(tau_max, float), (n,)))
                     + "] N m"),
        "@CLIP@": repr(CLIP),
        "@ETD@": _c_array(etd_factors(design.scenario, rate_hz) if rate_hz is not None else (0.0, 0.0)),
    }

    def fill(text: str) -> str:
        for k, v in sub.items():
            text = text.replace(k, v)
        return text
    src = fill(template("step.c"))
    if rate_hz is None:
        baked = f"static const double {prefix}etd_[2] = "
        if src.count(baked) != 1:
            raise AssertionError(f"templates/step.c: expected one '{baked}'")
        src = src.replace(baked, f"double {prefix}etd_[2] = ")
    return src, fill(template("step.h"))


#: Unit of every named input/output of the generated functions (revolute joints; prismatic: m for rad).
UNITS = {
    "t": "s", "q": "rad", "dq": "rad/s", "qd": "rad", "dqd": "rad/s", "ddqd": "rad/s^2", "x_esn": "-",
    "w_hat": "rad/s^2 per regressor unit", "F1": "rad", "dF1": "rad/s", "F2": "rad/s", "dF2": "rad/s^2",
    "e1": "rad", "z1": "-", "e2": "rad/s", "z2": "-", "alpha2": "rad/s", "alpha2_dot": "rad/s^2",
    "tau": "N m", "x_esn_dot": "1/s", "w_hat_dot": "rad/s^3 per regressor unit", "x_esn_next": "-",
    "w_hat_next": "rad/s^2 per regressor unit", "margin": "- (1 - |e|/F; e1 rows, then e2 rows)",
    "etd": "s (exponential-Euler weights of x_esn_dot and w_hat_dot over one period)",
}


def renamed(f: ca.Function, name: str) -> ca.Function:
    """The same SX function under another name (CSE on)."""
    if f.name() == name:
        return f
    ins = f.sx_in()
    return ca.Function(name, ins, f.call(ins), f.name_in(), f.name_out(),
                       {"cse": True, "allow_duplicate_io_names": True})


def _doc(functions) -> str:
    lines = ["/* Generated functions (CasADi's C API: NAME(arg, res, iw, w, mem) with NAME_work, NAME_incref, ...).",
             " * Every argument is a dense double array, matrices column-major; shape rows x cols, unit:"]
    for f in functions:
        lines.append(f" *   {f.name()}")
        for kind, n_, name_, size in (("in ", f.n_in(), f.name_in, f.size_in),
                                      ("out", f.n_out(), f.name_out, f.size_out)):
            for i in range(n_):
                r, c = size(i)
                nm = name_(i)
                lines.append(f" *     {kind} {i}: {nm:<11} {r} x {c:<3} [{UNITS.get(nm, '-')}]")
    lines.append(" */")
    return "\n".join(lines) + "\n"


def emit_controller_c(design, contract: list, *, prefix: str | None, basename: str, rate_hz: float,
                      tau_max, structured: bool = True) -> dict[str, str]:
    """{basename.c, basename.h}: the contract functions, reference and step core (CasADi) plus the Pstep API.

    prefix None keeps the historical names (functions unprefixed, helpers named after the basename) and names
    the step API `symfunnel_*`; otherwise every exported symbol starts with prefix. `structured` writes the
    controller and the step core as an SX scalar part plus loops (`emit.kernel`) where the design has that form;
    False keeps each one unrolled SX function (the baseline the bench compares with).
    """
    fprefix = prefix or ""
    sprefix = prefix if prefix is not None else "symfunnel_"
    files, head, body = _rate_free_part(design, contract, prefix, basename, tau_max, structured)
    x0, w0 = step_initial(design)
    src, hdr = c_step_files(design, prefix=sprefix, fprefix=fprefix, basename=basename, rate_hz=rate_hz,
                            tau_max=tau_max, x0=x0, w0=w0)
    guard = basename.upper() + "_H"
    return {basename + ".c": body + src,
            basename + ".h": f"#ifndef {guard}\n#define {guard}\n" + head + hdr + f"\n#endif /* {guard} */\n",
            **files}


#: the rate-free part of the last few emit_controller_c calls (a rate search generates one design at many rates)
_RATE_FREE: list[tuple[tuple, tuple, tuple]] = []


def _rate_free_part(design, contract: list, prefix, basename: str, tau_max, structured: bool):
    """(the other files, the header's text before the step API, the source's before it): everything of the C pair
    that does not depend on the rate, reused while the design, its signals and the contract are the same objects
    (a design whose signals are replaced, as the twin tests do, is generated again)."""
    tm = None if tau_max is None else tuple(np.broadcast_to(np.asarray(tau_max, float), (design.n,)).tolist())
    key = (prefix, basename, tm, bool(structured))
    held = (design, *design.signals.values(), *contract)       # the objects themselves: ids are never reused
    for k, h, value in _RATE_FREE:
        if k == key and len(h) == len(held) and all(a is b for a, b in zip(h, held)):
            files, head, body = value
            return dict(files), head, body
    from .c import emit_c
    from .kernel import controller_kernel, shared_source, step_kernel
    fprefix = prefix or ""
    funcs = [renamed(f, fprefix + f.name()) for f in contract]
    funcs.append(renamed(design.reference, fprefix + "reference"))
    core = step_core(design, tau_max, fprefix + "step_core")
    kernels = []
    if structured:
        kernels = [k for k in [controller_kernel(design, f, f.name(), fprefix) for f in funcs
                               if f.name() == fprefix + "controller"] + [step_kernel(design, tau_max, fprefix, projection(design), core)] if k]
    done = {k.name for k in kernels}
    generated = [f for f in funcs + [core] if f.name() not in done] + [k.scalar for k in kernels]
    files = emit_c(generated, basename, prefix=prefix)
    head = _doc(funcs + [core]) + files.pop(basename + ".h") + "".join(k.header for k in kernels)
    loops = (shared_source(design, fprefix) + "\n".join(k.source for k in kernels)) if kernels else ""
    body = files.pop(basename + ".c") + loops
    _RATE_FREE.append((key, held, (dict(files), head, body)))
    del _RATE_FREE[:-4]
    return files, head, body


def step_settings(design, rate_hz=None, tau_max=None) -> tuple[float, object]:
    """(rate_hz, tau_max) of the generated step: the arguments, else the scenario's [implementation], else defaults."""
    impl = getattr(design.scenario, "implementation", None)
    if rate_hz is None:
        rate_hz = impl.rate_hz if impl is not None else DEFAULT_RATE_HZ
    if tau_max is None and impl is not None:
        tau_max = impl.tau_max
    return float(rate_hz), tau_max


def python_step_source(design, rate_hz: float, tau_max) -> str:
    """Source of the numpy module's `Step` class (appended after the generated `reference` and `step_core`): the C
    `Pstep` API's semantics in Python (same initial state, the same exponential-Euler weights of one period
    1/rate_hz, saturation inside step_core, return code 0 inside both funnels, 1 outside, -2 non-finite input, -3
    non-finite output), so the deployed loop can be prototyped without a compiler."""
    sc = design.scenario
    x0, w0 = step_initial(design)
    x_esn, w_hat = step_states(design)
    lam_x = sc.esn.leak / sc.esn.time_constant
    lam_w = float(sc.gamma) * float(sc.sigma)
    tm = ("None" if tau_max is None else
          "[" + ", ".join(repr(float(v)) for v in np.broadcast_to(np.asarray(tau_max, float), (design.n,))) + "]")
    return f'''

#: the step's defaults: the rate its period is baked at in the C step, the torque limit (None: no saturation)
RATE_HZ = {float(rate_hz)!r}
TAU_MAX = {tm}
N_JOINTS = {design.n}
X_ESN0 = np.array([{_c_array(x0)}]).reshape({tuple(int(d) for d in x_esn.shape)!r})
W_HAT0 = np.array([{_c_array(np.asarray(w0).reshape(-1, order="F"))}]).reshape({tuple(int(d) for d in w_hat.shape)!r}, order="F")
_LAMBDA = ({lam_x!r}, {lam_w!r})       # linear decay rates of x_esn (leak/time constant) and W_hat (gamma sigma)


def _etd(rate, h):
    """(1 - exp(-rate h)) / rate, the exponential-Euler weight of a linear decay over h (h at rate 0)."""
    return h if rate == 0.0 else -np.expm1(-rate * h) / rate


class Step:
    """The deployed controller's one period, as the generated C step (`Pinit`, `Pstep`): call `step(t, q, dq)`
    once per period 1/rate_hz; it returns (rc, tau) with rc 0 inside both funnels, 1 outside (tau still finite),
    -2 for a non-finite input, -3 for a non-finite result (the state is then left unchanged). The state is
    x_esn, w_hat, margin (1 - |e|/F: e1 rows then e2 rows), qd, t and steps, as the C struct's. The rate only sets
    the exponential-Euler weights (the C step bakes RATE_HZ); the torque limit is step_core's (TAU_MAX)."""

    def __init__(self, rate_hz=RATE_HZ):
        rate_hz = float(rate_hz)
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a number > 0, got {{rate_hz!r}}")
        self.rate_hz = rate_hz
        self.etd = np.array([_etd(_LAMBDA[0], 1.0 / rate_hz), _etd(_LAMBDA[1], 1.0 / rate_hz)])
        self.init()

    def init(self):
        """The scenario's initial controller state (Pinit); returns 0."""
        self.x_esn = X_ESN0.copy()
        self.w_hat = W_HAT0.copy()
        self.margin = np.ones(2 * N_JOINTS)
        self.qd = np.zeros(N_JOINTS)
        self.t = 0.0
        self.steps = 0
        return 0

    def step(self, t, q, dq):
        """One period at time t [s] from the measured q, dq: (rc, tau) as Pstep."""
        q = np.asarray(q, dtype=float).reshape(N_JOINTS)
        dq = np.asarray(dq, dtype=float).reshape(N_JOINTS)
        if not (np.isfinite(t) and np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
            return -2, np.full(N_JOINTS, np.nan)
        tau, x_next, w_next, margin, qd = step_core(t, q, dq, self.x_esn, self.w_hat, self.etd)
        tau, x_next, w_next = (np.asarray(a, dtype=float) for a in (tau, x_next, w_next))
        if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(x_next)) and np.all(np.isfinite(w_next))):
            return -3, np.full(N_JOINTS, np.nan)
        margin = np.asarray(margin, dtype=float).reshape(-1)
        rc = 0 if np.all(margin > 0.0) else 1
        self.x_esn = x_next.reshape(self.x_esn.shape)
        self.w_hat = w_next.reshape(self.w_hat.shape)
        self.margin = margin
        self.qd = np.asarray(qd, dtype=float).reshape(-1)
        self.t = float(t)
        self.steps += 1
        return rc, tau.reshape(-1)


#: the name the C API uses for it
step = Step
'''
