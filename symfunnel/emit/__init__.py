"""Generated code for the controller: C (CasADi's CodeGenerator) and numpy-only Python (from the SX tape).

Both languages get the same functions, in the same order, all built with `Design.function` from the one SX graph
(CSE on), and described in `manifest.json` (docs/exports.md, "Controller code"):

==============  ======================================  ===========================================
function        inputs                                  outputs
==============  ======================================  ===========================================
funnels         t                                       F1, dF1, F2, dF2
errors          t, q, dq, qd, dqd                       e1, z1, e2, z2
alpha2          t, q, qd, dqd                           alpha2
alpha2_dot      t, q, dq, qd, dqd, ddqd                 alpha2_dot
controller      t, q, dq, qd, dqd, ddqd, x_esn, w_hat   tau, x_esn_dot, w_hat_dot
==============  ======================================  ===========================================

API::

    files = generate(design, "c", trajectory=traj)   # {file name: text}, manifest.json included; deterministic
    write_output(files, "ctl")               # atomic: a failure never leaves half-written files
    report = check_output(design, "c", files, points=1000)   # compile (cached) / import, compare with CasADi
    summary = codegen_summary(design, traj)   # both languages: files, sizes, op counts, checks (no timings)

Notes
-----
The recorded trajectory shipped with the code (`trajectory.txt`, 50 samples over the first 2 s) comes from the
pipeline's one simulation of the scenario (`trajectory_from_run`; `symfunnel.pipeline.Run.code` passes it).
Timing the generated code is `symfunnel bench`'s job (`symfunnel.bench._timing`), not code generation's.

Modules, by job: `contract` (the functions and the trajectory they ship), `files` (generate, manifest, names,
atomic writing), `check` (cross-checks against CasADi, main.c, the report's summary); the emitters `c`, `python`,
`step` (the deployed step), and `build` (the compile cache).
"""

from __future__ import annotations

from .c import BASENAME
from .check import check_output, codegen_summary, main_program
from .contract import CONTRACT, LANGS, contract_functions, initial_trajectory, trajectory_from_run
from .files import c_basename, c_names, generate, write_output

__all__ = ["CONTRACT", "BASENAME", "LANGS", "contract_functions", "initial_trajectory", "trajectory_from_run",
           "generate", "write_output", "c_basename", "c_names", "check_output", "main_program", "codegen_summary"]
