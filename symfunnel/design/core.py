"""A derived design: every signal once, as CasADi SX in the design's inputs, and its evaluation at points.

The inputs are t, q, dq, the reference qd, dqd, ddqd and the controller's own states, whose names and shapes the
design variant declares (`Design.states`: x_esn and w_hat for the paper's ESN design); everything downstream
(evaluation, audit, simulation, code, report) reads these expressions and asks the design for its layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..sx.tape import count_ops as tape_ops
from ..core.validate import did_you_mean

if TYPE_CHECKING:
    from ..scenario import Scenario

#: the inputs every design has, before the controller states of its variant
JOINT_INPUTS = ("t", "q", "dq", "qd", "dqd", "ddqd")


@dataclass
class Design:
    """Signals of one scenario's design as SX, with the base symbols they are written in."""

    scenario: Scenario
    variant: object                        # the design variant that derived it (design.backstepping.Backstepping)
    sym: dict[str, ca.SX]
    signals: dict[str, ca.SX]
    reference_t: dict[str, ca.SX]          # qd, dqd, ddqd as SX in t (from the scenario's expressions)
    constants: dict[str, ca.SX]
    mutant: str | None = None              # the seeded error this design carries (verify --mutants), if any
    #: named parts of a signal's derivation a certificate reads (e.g. "projection": the projected law's a, b, k, c)
    parts: dict = field(default_factory=dict, repr=False)
    _functions: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        """Short: the scenario and the signals' names (not their SX expressions)."""
        mutant = "" if self.mutant is None else f", mutant={self.mutant!r}"
        return f"Design(scenario={self.scenario.name!r}, {len(self.signals)} signals{mutant})"

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.scenario.n

    @cached_property
    def states(self) -> list[tuple[str, tuple[int, int]]]:
        """The controller's own states (name, shape), in the order of the state vector."""
        return self.variant.states()

    @cached_property
    def inputs(self) -> tuple[str, ...]:
        """All inputs of the design's signals, in canonical order: joint inputs, then controller states."""
        return JOINT_INPUTS + tuple(name for name, _ in self.states)

    @cached_property
    def signal_info(self) -> dict[str, tuple[str, int]]:
        """name -> (description, funnel level needed) for every derived signal."""
        return {k: v for k, v in self.variant.signal_info().items() if k in self.signals}

    def fingerprint(self) -> str:
        """sha256 of the design's SX graphs (signals, reference, constants, named parts; CasADi's serialisation, every
        constant's bits, where printing rounds to 6 digits): what tells two designs of one scenario apart (one set on
        a Run, or a derive patched in a test), e.g. for the certification cache's key (2-6 ms on paper and arm7)."""
        import hashlib
        h = hashlib.sha256(f"{type(self.variant).__name__}|{self.mutant}".encode())

        def add(tag: str, value) -> None:
            if isinstance(value, dict):
                for k in sorted(value, key=str):
                    add(f"{tag}.{k}", value[k])
            elif isinstance(value, (list, tuple)):
                for i, v in enumerate(value):
                    add(f"{tag}[{i}]", v)
            elif isinstance(value, (ca.SX, ca.DM)):
                h.update(tag.encode() + b"=" + value.serialize().encode())
            elif isinstance(value, (int, float, str, bool, np.ndarray, np.generic)) or value is None:
                h.update(tag.encode() + b"=" + repr(np.asarray(value).tolist()).encode())
            else:
                h.update(tag.encode() + b"=" + type(value).__name__.encode())
        for name in ("signals", "reference_t", "constants", "parts"):
            add(name, getattr(self, name))
        return h.hexdigest()

    @property
    def n_regressor(self) -> int:
        """Length of the approximator's regressor Phi (0 without one)."""
        return self.variant.n_regressor

    @property
    def approximator(self):
        """The approximator part of the design."""
        return self.variant.approximator

    @cached_property
    def _owner(self) -> dict[str, tuple[str, int]]:
        """Scalar symbol name -> (base input, position), for ordering free variables canonically."""
        out = {}
        for k in self.inputs:
            s = ca.vec(self.sym[k])
            for i in range(s.numel()):
                out[s[i].name()] = (k, i)
        return out

    def free_symbols(self, name: str) -> list[str]:
        """Names of the scalar symbols a signal depends on, in canonical order (e.g. ['t', 'q1', 'qd1'])."""
        order = {k: j for j, k in enumerate(self.inputs)}
        names = [v.name() for v in ca.symvar(self.signals[name])]
        return sorted(names, key=lambda s: (order[self._owner[s][0]], self._owner[s][1]))

    def inputs_of(self, name: str) -> list[str]:
        """The base inputs a signal actually depends on, in canonical order."""
        used = {self._owner[s][0] for s in self.free_symbols(name)}
        return [k for k in self.inputs if k in used]

    def function(self, name: str, inputs: list[str] | tuple[str, ...] | None = None,
                 outputs: list[str] | None = None) -> ca.Function:
        """A casadi.Function `name`(inputs) -> outputs (default: the signal `name` of its own inputs)."""
        outputs = outputs or [name]
        if inputs is None:
            deps = set()
            for o in outputs:
                deps |= set(self.inputs_of(o))
            inputs = [k for k in self.inputs if k in deps]
        key = (name, tuple(inputs), tuple(outputs))
        if key not in self._functions:
            self._functions[key] = ca.Function(
                name, [self.sym[k] for k in inputs], [self.signals[o] for o in outputs],
                list(inputs), list(outputs), {"cse": True, "allow_duplicate_io_names": True})
        return self._functions[key]

    def controller(self) -> ca.Function:
        """The controller of the generated-code contract: (t, q, dq, qd, dqd, ddqd, states...) -> (tau, state rates...).

        For the paper's design: (t, q, dq, qd, dqd, ddqd, x_esn, w_hat) -> (tau, x_esn_dot, w_hat_dot).
        """
        return self.function("controller", self.inputs, ["tau"] + [f"{k}_dot" for k, _ in self.states])

    @cached_property
    def reference(self) -> ca.Function:
        """t -> (qd, dqd, ddqd) from the scenario's reference expressions."""
        t = self.sym["t"]
        return ca.Function("reference", [t], [self.reference_t[k] for k in ("qd", "dqd", "ddqd")],
                           ["t"], ["qd", "dqd", "ddqd"])

    def ops(self, name: str) -> int:
        """Size of a signal in operations (tape instructions that compute something)."""
        return count_ops(self.function(name))


def count_ops(f: ca.Function) -> int:
    """Number of real operations on an SX function's tape (no inputs, outputs, constants or copies)."""
    return tape_ops(f)["operations"]


# --- evaluation ---------------------------------------------------------------------------------

def _as_array(value, shape, what: str, file: str | None, scalar_ok: bool = False) -> np.ndarray:
    from ..core.inputs import number_array
    return number_array(value, tuple(shape), file=file, key=what, scalar_ok=scalar_ok)


def point_inputs(design: Design, point: dict, *, file: str | None = None, key: str = "") -> dict:
    """Input values of one point {t, q, dq[, controller states]} with the reference taken from the scenario."""
    n = design.n
    states = dict(design.states)
    if not isinstance(point, dict):
        raise InputError("is not an object", file=file, key=key or "(point)",
                         expected='{"t": ..., "q": [...], "dq": [...]}')
    allowed = ["t", "q", "dq", *states]
    for k in point:
        if k not in allowed:
            raise InputError(f"unknown key{did_you_mean(k, allowed)}", file=file, key=(key + "." if key else "") + k,
                             expected="one of " + ", ".join(allowed))
    for k in ("t", "q", "dq"):
        if k not in point:
            raise InputError("is missing", file=file, key=(key + "." if key else "") + k, expected="a value")
    pre = (key + ".") if key else ""
    t = float(_as_array(point["t"], (1,), pre + "t", file)[0])
    out = dict(t=t, q=_as_array(point["q"], (n,), pre + "q", file), dq=_as_array(point["dq"], (n,), pre + "dq", file))
    for name, shape in states.items():
        matrix = shape[1] > 1
        shape = shape if matrix else (shape[0],)
        out[name] = _as_array(point.get(name, 0.0 if matrix else [0.0] * shape[0]), shape, pre + name, file,
                              scalar_ok=matrix)
    out["qd"], out["dqd"], out["ddqd"] = (np.array(v).ravel() for v in design.reference(t))
    return out


def funnel_level(design: Design, inp: dict) -> tuple[int, list[str]]:
    """How many funnels the point is inside (0, 1 or 2), with a message for the first one it is not."""
    F = design.function("funnel_signals", design.inputs, ["e1", "F1", "e2", "F2"])
    e1, F1, e2, F2 = (np.array(v).ravel() for v in F(*[inp[k] for k in design.inputs]))
    bad1 = [i for i in range(design.n) if not abs(e1[i]) < F1[i]]
    if bad1:
        i = bad1[0]
        return 0, [f"point outside funnel e1 at joint {i + 1}: |e1| = {abs(e1[i]):.6g} >= F1 = {F1[i]:.6g}"]
    bad2 = [i for i in range(design.n) if not abs(e2[i]) < F2[i]]
    if bad2:
        i = bad2[0]
        return 1, [f"point outside funnel e2 at joint {i + 1}: |e2| = {abs(e2[i]):.6g} >= F2 = {F2[i]:.6g}"]
    return 2, []


def evaluate(design: Design, point: dict, *, file: str | None = None, key: str = "",
             warn=None) -> dict:
    """Every model matrix and design signal at one point; signals needing a funnel the point is outside are None."""
    inp = point_inputs(design, point, file=file, key=key)
    level, msgs = funnel_level(design, inp)
    for m in msgs:
        if warn is not None:
            warn(m)
        else:
            import warnings
            warnings.warn(m, stacklevel=2)
    info = design.signal_info
    names = list(info)
    f = design.function("all_signals", design.inputs, names)
    vals = f(*[inp[k] for k in design.inputs])
    out = {}
    for k, v in zip(names, vals):
        if info[k][1] > level:
            out[k] = None
            continue
        a = np.array(v)
        out[k] = a.ravel().tolist() if a.shape[1] == 1 else a.tolist()
    return out
