"""The integrators a simulation may use, one registered options builder each (CasADi plugin name = registry name).

Each builder maps (simulation settings, output step h of this chunk, the run's output step, points K) to the
plugin's options; `symfunnel.simulation` builds `casadi.integrator(name, plugin, dae, 0, grid, options)` from it.
"""

from __future__ import annotations

import math

from ..core.registry import Registry

INTEGRATORS = Registry("integrator", "simulation.integrator")

#: CVODES steps allowed between two output points
MAX_STEPS_PER_OUTPUT = 20000


@INTEGRATORS.register("cvodes", "SUNDIALS CVODES, variable-order BDF with error control (default; stiff loops)")
def cvodes_options(sim, h: float, h_run: float, K: int) -> dict:
    """Tolerances and step limit of the scenario, sparse direct linear solver."""
    opts = {"abstol": sim.atol, "reltol": sim.rtol, "max_num_steps": MAX_STEPS_PER_OUTPUT,
            "linear_solver": "csparse", "disable_internal_warnings": True}
    if getattr(sim, "max_step", 0.0) > 0:
        opts["max_step_size"] = float(sim.max_step)
    return opts


def _substeps(sim, h: float, h_run: float, K: int, per: int = 1) -> int:
    # CasADi's fixed-step integrators spread number_of_finite_elements over the whole output grid (at least one
    # step per interval), so it is the total: substeps per output interval times K
    return max(1, int(math.ceil(sim.rk_substeps * h / h_run)) // per) * K


@INTEGRATORS.register("rk", "explicit fixed-step Runge-Kutta 4, `rk_substeps` steps per output step (non-stiff)")
def rk_options(sim, h: float, h_run: float, K: int) -> dict:
    """Fixed steps."""
    return {"number_of_finite_elements": _substeps(sim, h, h_run, K)}


@INTEGRATORS.register("collocation", "implicit Radau collocation (order 3), fixed steps, Newton per step")
def collocation_options(sim, h: float, h_run: float, K: int) -> dict:
    """Fixed steps, half as many as rk (each is implicit and of higher order)."""
    return {"number_of_finite_elements": _substeps(sim, h, h_run, K, per=2), "interpolation_order": 3,
            "collocation_scheme": "radau",
            # the design's |e| makes the stage equations kinked where e crosses 0, so Newton may stall there for a
            # step: accept its last iterate then (NaN is still caught)
            "rootfinder_options": {"max_iter": 30, "error_on_fail": False}}
