"""`tune --method auto`: IPOPT or the derivative-free search, chosen from the problem's size, never from a timing
(the same scenario and options choose the same method on any machine and under any load).

An IPOPT iteration costs about one forward-sensitivity solve of the closed loop over the horizon: its work is
counted as the nominal run's CVODES steps x the closed loop's states x (d + 1) directions x the plants (nominal and
uncertainty samples), and priced at SECONDS_PER_UNIT, measured on the paper's loop (156 states, 5 parameters, one
plant) on a loaded 2-core VM: 6000 steps over 20 s, one Jacobian of the grid constraints in 4.0-4.8 s (0.44 s over
2 s: 919 steps), i.e. 5-8e-7 s per unit, rounded up. IPOPT is chosen when MIN_IPOPT_ITERATIONS such iterations fit
the search's share of --wall-limit (SEARCH_SHARE x the limit, not the time left: that would be a timing again).
The derivative-free search ends on a count too (DERIVATIVE_FREE_EVALUATIONS by default), for the same reason.
"""

from __future__ import annotations

__all__ = ["SECONDS_PER_UNIT", "MIN_IPOPT_ITERATIONS", "DERIVATIVE_FREE_EVALUATIONS", "gradient_fits"]

#: seconds per unit of forward-sensitivity work (CVODES step x state x direction x plant), rounded up from the paper
SECONDS_PER_UNIT = 1e-6
#: the gradient path is chosen only when this many IPOPT iterations fit the search's share of --wall-limit
MIN_IPOPT_ITERATIONS = 8
#: evaluations of the derivative-free search when --max-evals is not given (the user's design included): what ends
#: it is this count, never a timing, so the same scenario writes the same file on any machine and under any load.
#: Measured on the paper deployed at 1 kHz with |tau| <= 200 N m (5 parameters, 20 s horizon, the scenario of
#: `symfunnel bench --only tune`, `tune.wall_s`) on the 2-core VM at load 4.4-5: 100 evaluations in 109 s, 120 in
#: 146 s (with a second tune running), i.e. about 1 s each under load; 120 leaves the rest of the 192 s search share
#: of the default 240 s limit for a heavier load, and the last 48 s for verify's gate. The search's score of the best
#: design (peak torque over the user's design's): 1.40 after the 9 starts, 1.010 at 100, 1.008 at 120 (0.945 at
#: 250: more evaluations, via --max-evals, keep lowering it slowly).
DERIVATIVE_FREE_EVALUATIONS = 120


def gradient_fits(steps: int | None, states: int, d: int, plants: int, budget: float) -> tuple[bool, str]:
    """(choose IPOPT, why not) for a problem of this size and a search budget of `budget` seconds."""
    if not steps or steps <= 0:
        return False, ("the user's design has no completed continuous-time run to size the sensitivity problem by "
                       "(force it with --method gradient)")
    units = int(steps) * int(states) * (int(d) + 1) * int(plants)
    per = units * SECONDS_PER_UNIT
    need = MIN_IPOPT_ITERATIONS * per
    if need > budget:
        return False, (f"{MIN_IPOPT_ITERATIONS} IPOPT iterations of the sensitivity problem ({steps} CVODES steps x "
                       f"{states} states x {d + 1} directions x {plants} plant(s), about {per:.3g} s each at "
                       f"{SECONDS_PER_UNIT:g} s per unit) would need {need:.3g} s, more than the {budget:.3g} s of "
                       "the search (a size, not a timing: force it with --method gradient)")
    return True, (f"{MIN_IPOPT_ITERATIONS} IPOPT iterations of about {per:.3g} s each ({steps} CVODES steps x "
                  f"{states} states x {d + 1} directions x {plants} plant(s)) fit the {budget:.3g} s of the search")
