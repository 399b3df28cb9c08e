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
