"""Certificates: proofs over whole regions by interval branch and bound on the design's own SX graph.

`run_certificates(...)` computes, for one scenario, `certify.input_gain` (sym(M_p^-1 D M) positive definite over
the joint region x the parameter box x the dead-zone slopes), `certify.invariance` (the Lyapunov argument's barrier
closure over a grid of margins) and `certify.bounds` (rigorous enclosures of mu2, tau and eps on the funnel region;
saturation against tau_max), each proven, refuted (with a counterexample the ordinary CasADi Functions reproduce)
or undecided (with what is left). docs/certify.md says what each proves, over which region, and what it does not.
"""

from __future__ import annotations

import time

import numpy as np

from ..core.names import CERTIFY_CHECKS, CERTIFY_ON_DEMAND
from .problem import Budget, Context
from .region import parameter_box
from .result import CHECK_STATUS, Certificate, Certification

__all__ = ["run_certificates", "CERTIFICATES", "DEFAULT_WORK", "Certificate", "Certification", "CHECK_STATUS"]

#: the certificate ids, in the order they are reported
CERTIFICATES = CERTIFY_CHECKS
#: the deterministic work budget of each certificate, in tape operations x boxes (a certificate with a 600-operation
#: tape gets ~80,000 boxes; a wall-clock limit can only stop a search earlier)
DEFAULT_WORK = {"certify.input_gain": 4e7, "certify.bounds": 5e7, "certify.invariance": 5e7,
                "certify.containment": 1.5e8, "certify.sampled": 5e7}     # containment's: sampled_rate.CONTAINMENT_WORK
#: the order they are computed in (bounds uses the set a containment or invariance certificate proves)
_ORDER = ("certify.input_gain", "certify.invariance", "certify.containment", "certify.bounds")


def _sampled(ctx: Context, budget: Budget) -> Certificate:
    """certify.sampled at the scenario's [implementation] (its tau_max; the bisection starts at its rate, else at
    1 kHz), S the set certify.containment proves (computed when not asked for), else the default margins;
    `rate --certify` adds the simulated rate and the C step's run."""
    from .sampled_rate import certify_sampled
    impl = getattr(ctx.scenario, "implementation", None)
    return certify_sampled(ctx, budget, tau_max=impl.tau_max if impl is not None else None,
                           start_hz=impl.rate_hz if impl is not None else None)


def run_certificates(scenario, design, *, t_final: float, W_star=None, w_star_info=None, w_hat_range=None,
                     only=None, wall_limit: float | None = None, work: dict | None = None,
                     progress=None, breach: dict | None = None) -> Certification:
    """Every certificate (or those in `only`) of one scenario; `wall_limit` seconds for all of them together;
    `breach`: the simulated run's funnel breach from the initial state, if it has one (refutes containment)."""
    from .bounds import certify_bounds
    from .containment import certify_containment
    from .input_gain import certify_input_gain
    from .invariance import certify_invariance
    say = progress or (lambda s: None)
    t0 = time.monotonic()
    _regular_on(scenario, float(t_final))
    expiry = None if wall_limit is None else t0 + float(wall_limit)
    wanted = [c for c in _ORDER if only is None or c in only] + [c for c in CERTIFY_ON_DEMAND if only and c in only]
    ctx = Context(scenario, design, float(t_final), parameter_box(scenario),
                  None if W_star is None else np.asarray(W_star, float), w_hat_range,
                  w_star_info=dict(w_star_info or {}), breach=breach)
    budgets = dict(DEFAULT_WORK, **(work or {}))
    fns = {"certify.input_gain": certify_input_gain, "certify.invariance": certify_invariance,
           "certify.bounds": certify_bounds, "certify.containment": certify_containment,
           "certify.sampled": _sampled}
    done = {}
    for i, cid in enumerate(wanted):
        left = len(wanted) - i
        share = None if expiry is None else time.monotonic() + max(0.0, expiry - time.monotonic()) / left
        say(f"{cid}: interval branch and bound")
        if expiry is not None and time.monotonic() >= expiry:
            done[cid] = Certificate(cid, "undecided", "the wall-clock limit was reached before this certificate "
                                    "started", undecided_fraction=1.0)
        else:
            done[cid] = fns[cid](ctx, Budget(float(budgets[cid]), share))
        ctx.results[cid] = done[cid]
        say(f"{cid}: {done[cid].status} ({done[cid].seconds:.1f} s, {done[cid].boxes} boxes)")
    certs = [done[c] for c in CERTIFICATES + CERTIFY_ON_DEMAND if c in done]
    return Certification(scenario.name, certs, seconds=time.monotonic() - t0, wall_limit=wall_limit, context=ctx)


def _regular_on(scenario, t_final: float) -> None:
    """The loader proved q_d in C^2 and F_i > 0 in C^1 over the scenario's own horizon; a longer one (--t-final) is
    proven here before any certificate relies on it (InputError naming the key otherwise)."""
    from ..scenario.regularity import check_funnel_regular, check_reference_regular
    camp = scenario.campaign
    loaded = max(scenario.simulation.t_final, (camp.sweep.t_final or 0.0) if camp is not None else 0.0)
    if t_final <= loaded:
        return
    check_reference_regular(scenario.reference, t_final, file=scenario.file)
    for key, shape in scenario.funnels.items():
        check_funnel_regular(shape, t_final, file=scenario.file,
                             key=f"funnel.{key}" + (".F" if "F" in shape.KEYS else ""))
