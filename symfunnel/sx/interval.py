"""Outward-rounded interval evaluation of an SX casadi.Function's instruction tape, with two independent backends.

`IntervalFunction(f, backend="codac" | "arb")` compiles the tape of `f` once into straight-line Python that calls
one rule per instruction: codac 2 `Interval`s (outward-rounded interval arithmetic) or python-flint `arb` balls
(midpoint-radius arithmetic with rigorous error radii). Neither backend uses the other's results.

The rules of both arithmetics (one per tape operation, with their domain errors and outward rounding) are in
`interval_rules`; this module compiles a tape into calls of them and evaluates it on boxes.

What an enclosure means: for every point x of the input box, the exact real value of the tape's expression at x
lies in [lo, hi] (and so does CasADi's double result, for ops that IEEE rounds correctly).

`eval_point` is CasADi's own double evaluation of the function (what branch and bound tests midpoints with).
Compiled functions keep the previous box's intervals (rebuilding only the inputs that changed), so one
IntervalFunction is not to be shared between threads.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import casadi
import numpy as np

from ..core.errors import SymfunnelError
from ..core.pycode import compile_source
from .interval_rules import BACKENDS, DISCONTINUOUS, RULE_OPS, UNARY, Backend, get_backend
from .tape import OP_NAMES, Tape, as_sx_function, read_tape

__all__ = ["IntervalError", "IntervalFunction", "Enclosure", "BACKENDS", "get_backend", "RULE_OPS"]

_INF = math.inf


class IntervalError(SymfunnelError):
    """An SX function the interval evaluator cannot take: an operation without an interval rule, or free symbols."""


class Enclosure(NamedTuple):
    """Rigorous bounds of one output in its dense shape; entries that are not enclosures are (-inf, +inf)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """Where the bounds are a real (finite) enclosure, i.e. no domain error and no overflow."""
        return np.isfinite(self.lo) & np.isfinite(self.hi)

    @property
    def all_valid(self) -> bool:
        """Whether every entry is a finite enclosure."""
        return bool(np.all(self.valid))

    def contains(self, value) -> np.ndarray:
        """Elementwise lo <= value <= hi."""
        v = np.asarray(value, dtype=float).reshape(self.lo.shape)
        return (self.lo <= v) & (v <= self.hi)


# --- compiling a tape -------------------------------------------------------------------------------------------

def _compile(tape: Tape, be: Backend, in_off: list[int], out_off: list[int]) -> Callable:
    """Straight-line Python for the tape: run(x, ctx) -> tuple of backend values, one per output nonzero."""
    name = tape.function.name()
    ns: dict[str, Any] = {}
    lines = ["def run(x, ctx):"]
    n_out = out_off[-1]
    outs = [None] * n_out
    consts: dict[float, str] = {}
    O = casadi  # noqa: E741
    for ins in tape.instructions:
        op, a, r = ins.op, ins.args, ins.res
        if op == O.OP_INPUT:
            lines.append(f"    w{r[0]} = x[{in_off[a[0]] + a[1]}]")
        elif op == O.OP_OUTPUT:
            k = out_off[r[0]] + r[1]
            lines.append(f"    o{k} = w{a[0]}")
            outs[k] = f"o{k}"
        elif op == O.OP_CONST:
            c = float(ins.constant)
            key = math.copysign(1.0, c) if c == 0 else c   # keep -0.0 apart from 0.0 (1/-0 differs)
            cname = consts.get(key)
            if cname is None:
                cname = consts[key] = f"C{len(consts)}"
                ns[cname] = be.point(c)
            lines.append(f"    w{r[0]} = {cname}")
        elif op == O.OP_PARAMETER:
            raise IntervalError(f"function {name!r} has free SX variables; interval evaluation needs every symbol "
                                "as an input")
        else:
            opname = OP_NAMES.get(op, f"<{op}>")
            rule = be.rules.get(opname)
            if rule is None:
                raise IntervalError(f"no interval rule for OP_{opname} in function {name!r}")
            ns.setdefault(opname, rule)
            n_args = 1 if opname in UNARY else 2
            args = ", ".join(f"w{j}" for j in a[:n_args])
            if opname in DISCONTINUOUS:
                args += ", ctx"
            lines.append(f"    w{r[0]} = {opname}({args})")
    zero = "ZERO__"
    ns[zero] = be.point(0.0)
    lines.append("    return (" + "".join(f"{o or zero}, " for o in outs) + ")")
    code = compile_source("\n".join(lines), f"<interval tape of {name} ({be.name})>")
    exec(code, ns)
    return ns["run"]


Box = Any   # (lo, hi) pair of arrays of the input's shape, or one array of shape (..., 2)


def read_layout(obj, function: casadi.Function):
    """The tape of an SX Function, with its inputs' and outputs' names, shapes, nonzeros and offsets set on `obj`
    (shared by the interval evaluators); IntervalError when it has free symbols."""
    tape = read_tape(function)
    if tape.free:
        raise IntervalError(f"function {function.name()!r} has free SX variables "
                            f"({', '.join(v.name() for v in tape.free)}); interval evaluation needs every symbol "
                            "as an input")
    obj.name = function.name()
    obj.in_names, obj.out_names = tape.in_names, tape.out_names
    obj.in_sx_shapes, obj.out_sx_shapes = tape.in_shapes, tape.out_shapes
    obj.in_nz, obj.out_nz = tape.in_nz, tape.out_nz
    obj.in_off = [0, *np.cumsum([len(nz) for nz in tape.in_nz]).tolist()]
    obj.out_off = [0, *np.cumsum([len(nz) for nz in tape.out_nz]).tolist()]
    return tape


class IntervalFunction:
    """Interval extension of an SX casadi.Function, compiled once from its tape, on one backend.

    `form="natural"` evaluates every instruction on intervals. `form="mean_value"` also encloses
    f(X) in f(m) + J(X) (X - m) with m the box midpoint and J CasADi's AD Jacobian (itself interval-evaluated), and
    returns the intersection with the natural enclosure: it pays off on narrow boxes, where its overestimation
    shrinks with the square of the width against linearly for the natural form (the dependency effect), and it is
    skipped on boxes where a discontinuous operation (sign, a comparison, an undecided if-else, floor) switches,
    where the mean-value theorem does not hold.

    Usage::

        F = IntervalFunction(d.function("tau"), backend="codac")
        lo, hi = F.eval([(t_lo, t_hi), (q_lo, q_hi), ...])[0]      # rigorous bounds of tau over the box
        F.eval_point([t, q, ...])                                  # the same function in double (CasADi)
    """

    def __init__(self, f: casadi.Function, backend: str = "codac", form: str = "natural"):
        if form not in ("natural", "mean_value"):
            raise ValueError(f"unknown form {form!r} (expected 'natural' or 'mean_value')")
        self.function = as_sx_function(f)
        self.backend = get_backend(backend)
        self.form = form
        tape = read_layout(self, self.function)
        self._run = _compile(tape, self.backend, self.in_off, self.out_off)
        self._jac: tuple[IntervalFunction, list[tuple[int, int]]] | None = None
        self._last: tuple | None = None
        if form == "mean_value":
            self._jac = self._jacobian()

    # --- shapes ----------------------------------------------------------------------------------------------
    @staticmethod
    def _np_shape(shape: tuple[int, int]) -> tuple[int, ...]:
        return (shape[0],) if shape[1] == 1 else shape

    @property
    def in_shapes(self) -> list[tuple[int, ...]]:
        """Numpy shape of each input: (n,) for a column vector (scalars (1,)), (r, c) for a matrix."""
        return [self._np_shape(s) for s in self.in_sx_shapes]

    @property
    def out_shapes(self) -> list[tuple[int, ...]]:
        """Numpy shape of each output, the same convention as `in_shapes`."""
        return [self._np_shape(s) for s in self.out_sx_shapes]

    @property
    def n_in_nz(self) -> int:
        """Number of scalar input nonzeros (the flat layout of `eval_flat`)."""
        return self.in_off[-1]

    @property
    def n_out_nz(self) -> int:
        """Number of scalar output nonzeros."""
        return self.out_off[-1]

    def _input_nz(self, i: int, value) -> np.ndarray:
        """The nonzeros (column-major structural order) of input i given as a scalar, vector or matrix."""
        r, c = self.in_sx_shapes[i]
        a = np.asarray(value, dtype=float)
        if a.shape == (r, c) or (c == 1 and a.size == r) or (r == 1 and a.size == c):
            flat = a.reshape((r, c), order="F" if a.shape != (r, c) else "C").ravel(order="F")
            return flat[list(self.in_nz[i])]
        if a.size == 1:
            return np.full(len(self.in_nz[i]), float(a.reshape(())))
        raise ValueError(f"input {i} ({self.in_names[i]!r}) of {self.name!r} is {r}x{c}; got shape {a.shape}")

    def _ordered(self, values) -> list:
        if isinstance(values, Mapping):
            missing = [k for k in self.in_names if k not in values]
            if missing:
                raise ValueError(f"{self.name!r} needs inputs {', '.join(missing)}")
            return [values[k] for k in self.in_names]
        values = list(values)
        if len(values) != len(self.in_names):
            raise ValueError(f"{self.name!r} has {len(self.in_names)} inputs ({', '.join(self.in_names)}); "
                             f"got {len(values)}")
        return values

    def flatten_box(self, boxes) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) flat vectors over all input nonzeros from per-input boxes (sequence in input order, or dict)."""
        los, his = [], []
        for i, b in enumerate(self._ordered(boxes)):
            if isinstance(b, tuple) and len(b) == 2:
                lo, hi = b
            else:
                a = np.asarray(b, dtype=float)
                if a.shape[-1:] != (2,):
                    raise ValueError(f"box of input {self.in_names[i]!r}: give (lo, hi) or an array of shape (..., 2)")
                lo, hi = a[..., 0], a[..., 1]
            los.append(self._input_nz(i, lo))
            his.append(self._input_nz(i, hi))
        lo = np.concatenate(los) if los else np.zeros(0)
        hi = np.concatenate(his) if his else np.zeros(0)
        if np.isnan(lo).any() or np.isnan(hi).any():
            raise ValueError(f"box of {self.name!r} has NaN bounds")
        if (lo > hi).any():
            j = int(np.argmax(lo > hi))
            raise ValueError(f"box of {self.name!r} has lo > hi at flat input {j} ({lo[j]} > {hi[j]})")
        return lo, hi

    def flatten_point(self, values) -> np.ndarray:
        """The flat vector over all input nonzeros of one point (sequence in input order, or dict)."""
        parts = [self._input_nz(i, v) for i, v in enumerate(self._ordered(values))]
        return np.concatenate(parts) if parts else np.zeros(0)

    def unflatten_point(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Per-input arrays (dense, numpy shapes of `in_shapes`) from a flat nonzero vector."""
        out = {}
        for i, name in enumerate(self.in_names):
            r, c = self.in_sx_shapes[i]
            dense = np.zeros(r * c)
            dense[list(self.in_nz[i])] = x[self.in_off[i]:self.in_off[i + 1]]
            out[name] = dense.reshape((r, c), order="F").reshape(self._np_shape((r, c)))
        return out

    def _dense_outputs(self, lo: np.ndarray, hi: np.ndarray) -> list[Enclosure]:
        out = []
        for k, (r, c) in enumerate(self.out_sx_shapes):
            L, H = np.zeros(r * c), np.zeros(r * c)
            nz = list(self.out_nz[k])
            L[nz] = lo[self.out_off[k]:self.out_off[k + 1]]
            H[nz] = hi[self.out_off[k]:self.out_off[k + 1]]
            shape = self._np_shape((r, c))
            out.append(Enclosure(L.reshape((r, c), order="F").reshape(shape),
                                 H.reshape((r, c), order="F").reshape(shape)))
        return out

    # --- evaluation ------------------------------------------------------------------------------------------
    def eval(self, boxes) -> list[Enclosure]:
        """Rigorous enclosures of every output over the box (one box per input: (lo, hi) or an (..., 2) array)."""
        lo, hi = self.flatten_box(boxes)
        return self._dense_outputs(*self.eval_flat(lo, hi))

    def eval_flat(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Enclosures of the output nonzeros (flat, output after output) over a box given by flat nonzero bounds."""
        be = self.backend
        ctx: list = []
        with be.mode():
            vals = self._run(self._inputs(lo, hi), ctx)
            bounds = be.bounds
            L = np.empty(len(vals))
            H = np.empty(len(vals))
            for k, v in enumerate(vals):
                L[k], H[k] = bounds(v)
            if self._jac is not None and not ctx:
                L, H = self._mean_value(lo, hi, L, H)
        return L, H

    def _inputs(self, lo: np.ndarray, hi: np.ndarray) -> list:
        """Backend intervals of the flat box, rebuilding only the entries that differ from the previous call's box
        (branch and bound changes one variable from box to box, and making an interval costs about an operation)."""
        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        make = self.backend.interval
        last = self._last
        if last is not None and last[0].shape == lo.shape:
            changed = np.flatnonzero((last[0] != lo) | (last[1] != hi)).tolist()
            xs = list(last[2])
            for j in changed:
                xs[j] = make(float(lo[j]), float(hi[j]))
        else:
            xs = [make(a, b) for a, b in zip(lo.tolist(), hi.tolist())]
        self._last = (lo.copy(), hi.copy(), xs)
        return xs

    def eval_values(self, lo: np.ndarray, hi: np.ndarray) -> tuple[tuple, bool]:
        """The backend's raw values of the output nonzeros over a flat box, and whether no discontinuity switched."""
        ctx: list = []
        with self.backend.mode():
            vals = self._run(self._inputs(lo, hi), ctx)
        return vals, not ctx

    def eval_point(self, values) -> list[np.ndarray]:
        """The outputs in double at one point, by the CasADi Function itself (the midpoint test of branch and bound)."""
        res = self.function(*[np.asarray(v, dtype=float) for v in self._ordered(values)])
        res = [res] if self.function.n_out() == 1 else list(res)
        return [np.asarray(casadi.DM(v).full(), dtype=float).reshape(s) for v, s in zip(res, self.out_shapes)]

    def eval_point_flat(self, x: np.ndarray) -> np.ndarray:
        """The output nonzeros in double at a flat input point (CasADi's double evaluation)."""
        args = []
        for i, (r, c) in enumerate(self.in_sx_shapes):
            args.append(casadi.DM(casadi.Sparsity(self.function.sparsity_in(i)), x[self.in_off[i]:self.in_off[i + 1]]))
        res = self.function.call(args)
        return np.concatenate([np.asarray(casadi.DM(v).nonzeros(), dtype=float) for v in res]) if res else np.zeros(0)

    # --- the mean-value form ---------------------------------------------------------------------------------
    def _jacobian(self) -> tuple[IntervalFunction, list[tuple[int, int]]]:
        f = self.function
        xin = f.sx_in()
        outs = f.call(xin)
        y = casadi.vertcat(casadi.SX(0, 1), *[casadi.SX(o).nz[:] for o in outs])
        x = casadi.vertcat(casadi.SX(0, 1), *[v.nz[:] for v in xin])
        J = casadi.jacobian(y, x)
        rows, cols = J.sparsity().get_triplet()
        jf = casadi.Function(f.name() + "_jac", xin, [J], {"cse": True})
        jif = IntervalFunction(jf, backend=self.backend.name, form="natural")
        # the jacobian's output nonzeros are column-major: entry k is (rows[k], cols[k])
        return jif, list(zip(rows, cols))

    def _mean_value(self, lo, hi, L, H):
        jf, entries = self._jac
        be = self.backend
        mid = np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
        fm = self._run([be.point(v) for v in mid.tolist()], [])
        J, _ = jf.eval_values(lo, hi)
        make = be.interval
        sub = be.rules["SUB"]
        mul = be.rules["MUL"]
        add = be.rules["ADD"]
        wide = {j for j in range(len(lo)) if lo[j] < hi[j]}
        dx = {j: sub(make(lo[j], hi[j]), be.point(mid[j])) for j in wide}
        acc = list(fm)
        for k, (i, j) in enumerate(entries):
            if j in wide:
                acc[i] = add(acc[i], mul(J[k], dx[j]))
        for i, v in enumerate(acc):
            a, b = be.bounds(v)
            # only a valid natural enclosure is tightened: a domain error stays an error
            if a > -_INF and L[i] > -_INF:
                L[i], H[i] = max(L[i], a), min(H[i], b)
                if L[i] > H[i]:
                    raise IntervalError(f"{self.name!r}: the mean-value and natural enclosures of output nonzero "
                                        f"{i} are disjoint ({a}, {b}) -- an interval rule is wrong")
        return L, H

    def __repr__(self) -> str:
        return (f"IntervalFunction({self.name!r}, backend={self.backend.name!r}, form={self.form!r}, "
                f"inputs={list(self.in_names)}, outputs={list(self.out_names)})")
