"""Closed-loop simulation with CasADi integrators, funnel-breach detection, a wall-clock limit and compiled code.

How a run works (docs/simulation.md has the long version):

* The closed loop (`symfunnel.simulation.closedloop`) is one SX graph x' = f(t, x). For the integrator its states are permuted
  to [vec(W_hat); x_esn; q; dq], which lets the sparse LU of CVODES' Newton matrix stay sparse (the rows of ddq are
  dense, so they go last); the public state order stays [q; dq; x_esn; vec(W_hat)].
* The right-hand side, its sparse Jacobian and the logged signals are generated as C (`casadi.CodeGenerator`),
  compiled once with the system C compiler and cached in $SYMFUNNEL_CACHE (default ~/.cache/symfunnel) under the
  sha256 of the generated source, then loaded with `casadi.external`; without a compiler the CasADi VM is used.
  The integrators and the logged signals (one serial map per chunk) are evaluated on numpy buffers
  (`sx.buffered.Buffered`): no numpy -> DM -> numpy conversion per chunk.
* Time is integrated in chunks of the output grid (growing 1, 5, 25, 100, 500 points: reproducible), with
  a parameter for the chunk's start time, so one integrator object serves every chunk. After each chunk the funnel
  margins m_i = (F_i - |e_i|)/F_i and finiteness are checked on the grid; a breach (or an integrator failure) is
  then located on a 100x finer grid within the output step, and the trajectory up to it is kept.
* Non-smooth plant terms (Coulomb friction's sign, the dead zone's kinks) are smoothed with the scenario's
  `simulation.smoothing_width` w (plant/nonlinearities.py: sign_w(x) = x/sqrt(x^2 + w^2), ramp_w); w = 0 keeps them exact and
  warns. `convergence_study` measures the effect of w. The controller's own |e| terms are the design, not smoothed:
  z = e/(F - |e|) is C^1 and the resulting right-hand side is Lipschitz, which BDF handles.

Modules, by job: `compiled` (the closed loop as compiled C or on the VM, cached), `runner` (one integrator call
over a relative grid, with statistics), `run` (`simulate`: the chunked run loop and the wall-clock limit), `breach`
(locating a breach or failure), `result` (`SimResult`), `convergence` (`convergence_study`).
"""

from __future__ import annotations

from .compiled import Compiled, compile_closed_loop
from .convergence import convergence_study
from .result import SimResult
from .run import simulate

__all__ = ["Compiled", "SimResult", "compile_closed_loop", "convergence_study", "simulate"]
