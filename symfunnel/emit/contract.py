"""The code-generation contract: which functions the generated code has (`CONTRACT`, built from the design's one
graph by `contract_functions`) and the controller-input trajectory it ships (`trajectory.txt`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import casadi

    from ..simulation.closedloop import ClosedLoop
    from ..design import Design
    from ..simulation.result import SimResult

#: (name, inputs, outputs) of every generated function, in manifest order.
CONTRACT: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("funnels", ("t",), ("F1", "dF1", "F2", "dF2")),
    ("errors", ("t", "q", "dq", "qd", "dqd"), ("e1", "z1", "e2", "z2")),
    ("alpha2", ("t", "q", "qd", "dqd"), ("alpha2",)),
    ("alpha2_dot", ("t", "q", "dq", "qd", "dqd", "ddqd"), ("alpha2_dot",)),
    ("controller", ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"), ("tau", "x_esn_dot", "w_hat_dot")),
)

LANGS = ("c", "python")


def contract_functions(design: Design) -> list[casadi.Function]:
    """The casadi.Functions of the contract, in manifest order, from the design's one graph."""
    out = []
    for name, inputs, outputs in CONTRACT:
        f = design.controller() if name == "controller" else design.function(name, list(inputs), list(outputs))
        out.append(f)
    return out


def initial_trajectory(design: Design) -> dict[str, np.ndarray]:
    """The controller inputs at t = 0 from the scenario's initial state: one sample, no simulation."""
    sc = design.scenario
    init = design.variant.initial_states()
    qd, dqd, ddqd = (np.array(v).reshape(-1, 1, 1) for v in design.reference(0.0))
    col = lambda a: np.asarray(a, dtype=float).reshape(-1, 1, 1)  # noqa: E731
    out = {"t": np.zeros((1, 1, 1)), "q": col(sc.q0), "dq": col(sc.dq0), "qd": qd, "dqd": dqd, "ddqd": ddqd}
    for name, (r, c) in design.states:
        out[name] = np.asarray(init[name], dtype=float).reshape(r, c, 1, order="F")
    out["source"] = f"the initial state of scenario '{sc.name}' (t = 0; no recorded run)"
    return out


def trajectory_from_run(design: Design, closed_loop: ClosedLoop, result: SimResult, samples: int = 50,
                        span: float = 2.0) -> dict[str, np.ndarray]:
    """Controller inputs at `samples` times of a simulated run's first `span` seconds, as (r, c, k) arrays.

    Also holds "source", a one-line description. The samples are interpolated linearly from the simulation's
    output grid (the simulation stage of the pipeline: no second simulator here); a run that stopped at t = 0
    gives its initial state alone.
    """
    t_sim = np.asarray(result.t, dtype=float)
    if t_sim.size >= 2:
        t = np.linspace(t_sim[0], min(t_sim[-1], t_sim[0] + span), samples)
        X = np.stack([np.interp(t, t_sim, result.x[:, j]) for j in range(closed_loop.nx)], axis=1)
    else:
        t = np.zeros(1)
        X = (result.x[:1] if t_sim.size else closed_loop.x0[None, :]).astype(float)
    k = t.size
    parts = closed_loop.unpack(X)
    qd, dqd, ddqd = (np.array(v) for v in design.reference.map(k)(t[None, :]))
    col = lambda a: np.asarray(a, dtype=float)[:, None, :]  # noqa: E731
    out = {"t": t[None, None, :], "q": col(parts["q"].T), "dq": col(parts["dq"].T), "qd": col(qd),
           "dqd": col(dqd), "ddqd": col(ddqd)}
    for name, (r, c) in design.states:
        v = parts[name]                                    # (k, r) or (k, r, c)
        out[name] = np.moveaxis(v.reshape(k, r, c), 0, -1)
    out["source"] = (f"the simulated closed loop of scenario '{design.scenario.name}' (plant with its unknowns), "
                     f"{k} samples over t = {t[0]:g}..{t[-1]:g} s")
    return out



def trajectory_inputs(design: Design, text: str) -> dict[str, np.ndarray]:
    """Parse trajectory.txt back into (r, c, k) arrays of the controller's inputs."""
    data = np.loadtxt(text.splitlines(), comments="#", ndmin=2).T
    ctl = design.controller()
    out, row = {}, 0
    for i in range(ctl.n_in()):
        r, c = ctl.size1_in(i), ctl.size2_in(i)
        out[ctl.name_in(i)] = data[row:row + r * c].reshape(r, c, -1, order="F")
        row += r * c
    return out

