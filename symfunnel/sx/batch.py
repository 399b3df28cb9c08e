"""Batched endpoint interval evaluation of an SX tape: many boxes per call, outward rounded, in C or in numpy.

The rules, one per tape operation on arrays of (lo, hi) with their rounding and domain errors, are `batch_rules`;
this module compiles a tape into straight-line calls of them.

`BatchIntervalFunction(f)` runs the tape over arrays of lower and upper bounds, one entry per box, so a branch and
bound evaluates hundreds of boxes in one call (the scalar backends of `sx.interval` pay Python's overhead per
operation and box): by default in the compiled interpreter of `batch_vm` (the same rules in C, one call per batch),
else (`SYMFUNNEL_INTERVAL=numpy`, or no C compiler) compiled once into straight-line numpy code. It is the third,
independent implementation beside codac and arb; `tests/test_interval.py` checks every rule against 200-bit arb
values as for the other two, `tests/test_interval_vm.py` the interpreter against the numpy rules bit for bit.
"""

from __future__ import annotations

import math

import casadi
import numpy as np

from ..core.pycode import compile_source
from .batch_rules import (_FAILING, _INF, _RULES, _SWITCHING, _UNARY, BATCH_OPS, TRANSCENDENTAL_ULPS, _dn, _mulc, _up,
                          rule_name)
from .buffered import Buffered
from .interval import IntervalError, IntervalFunction, read_layout
from .rewrite import kink_quotients
from .tape import BOOKKEEPING, OP_NAMES

__all__ = ["BatchIntervalFunction", "TRANSCENDENTAL_ULPS", "BATCH_OPS"]

def _compile(tape, in_off, out_off):
    """Straight-line numpy code: run(LO, HI) -> (L, H, bad, switched, culprit) with arrays (K,) per value, and the
    flat inputs each failing instruction depends on (culprit k: the first instruction with a domain error on box k,
    whose inputs are `deps[culprit]`; -1 for none).

    Two facts known before running shorten the code (and CPython's compile of it) without changing a bit of what
    it computes: which values may carry a domain-error flag at all (only those downstream of an operation with a
    domain, `_FAILING`, or of a non-finite constant; the flags of the others are None and are not written), and
    which factors of a product are constants (`_mulc`, the same four products with two of them equal)."""
    name = tape.function.name()
    lines = ["def run(LO, HI):", "    K = LO.shape[0]", "    sw = np.zeros(K, dtype=bool)",
             "    culprit = np.full(K, -1)"]
    n_failing = 0                           # failing instructions so far: the next one's culprit number
    flagged: dict[int, bool] = {}           # work slot -> its flag b<slot> may be an array (else it is None)
    const: dict[int, float] = {}            # work slot -> the constant it holds
    outs = [None] * out_off[-1]
    ns = {"np": np, "_mulc": _mulc}

    def flags(slots):
        return [f"b{j}" for j in slots if flagged.get(j)]

    # slots carry a mask of "value computed under a certainly-false if-else condition": such a branch's domain
    # errors do not count (CasADi evaluates both branches and multiplies the dead one by 0)
    for ins in tape.instructions:
        op, a, r = ins.op, ins.args, ins.res
        if op == casadi.OP_OUTPUT:
            k = out_off[r[0]] + r[1]
            lines.append(f"    L{k} = l{a[0]}; H{k} = h{a[0]}")
            outs[k] = bool(flagged.get(a[0]))              # whether the output has a flag to copy
            if outs[k]:
                lines.append(f"    B{k} = b{a[0]}")
            continue
        w = r[0]
        const.pop(w, None)
        if op == casadi.OP_INPUT:
            j = in_off[a[0]] + a[1]
            flagged[w] = False
            lines.append(f"    l{w} = LO[:, {j}]; h{w} = HI[:, {j}]")
        elif op == casadi.OP_CONST:
            c = float(ins.constant)
            flagged[w] = not math.isfinite(c)
            if math.isfinite(c):
                const[w] = c
                lines.append(f"    l{w} = h{w} = {c!r}")
            else:
                lines.append(f"    l{w} = h{w} = np.float64({str(c)!r}); b{w} = np.ones(K, dtype=bool)")  # 'inf'/'nan'
        else:
            opname = rule_name(tape, op, _RULES)
            ns[opname] = _RULES[opname]
            args = [a[0]] if opname in _UNARY else [a[0], a[1]]
            argtxt = ", ".join(f"l{j}, h{j}" for j in args)
            fl = flags(args)
            if opname == "IF_ELSE_ZERO":
                c, x = args
                lines.append(f"    l{w}, h{w}, _, s_, dead = IF_ELSE_ZERO({argtxt}); sw |= s_")
                # the condition's errors count; the branch's only where the condition is not certainly false
                if fl:
                    bx = f"(b{x} & ~dead)" if flagged.get(x) else "None"
                    bc = f"b{c}" if flagged.get(c) else "None"
                    lines.append(f"    b{w} = _orb({bc}, {bx})")
                is_flagged = bool(fl)
            elif opname in _SWITCHING:
                lines.append(f"    l{w}, h{w}, _, s_ = {opname}({argtxt}); sw |= s_")
                is_flagged = bool(fl)
                if fl:
                    lines.append(f"    b{w} = _orb({', '.join(fl)})")
            elif opname in _FAILING:
                lines.append(f"    l{w}, h{w}, e_ = {opname}({argtxt})")
                lines.append(f"    if e_ is not None: culprit = np.where((culprit < 0) & e_, {n_failing}, culprit)")
                n_failing += 1
                lines.append(f"    b{w} = _orb({', '.join(fl + ['e_'])})")
                is_flagged = True
            else:
                if opname == "MUL" and (args[0] in const or args[1] in const) \
                        and not (args[0] in const and args[1] in const):
                    x, c = (args[1], const[args[0]]) if args[0] in const else (args[0], const[args[1]])
                    lines.append(f"    l{w}, h{w} = _mulc(l{x}, h{x}, {c!r})")
                else:
                    lines.append(f"    l{w}, h{w}, _ = {opname}({argtxt})")
                is_flagged = bool(fl)
                if fl:
                    lines.append(f"    b{w} = {fl[0]}" if len(fl) == 1 else f"    b{w} = _orb({', '.join(fl)})")
            flagged[w] = is_flagged
    ns["_orb"] = _orb
    n = out_off[-1]
    lines.append("    Lo = np.empty((K, %d)); Hi = np.empty((K, %d)); Bad = np.zeros((K, %d), dtype=bool)" % (n, n, n))
    for k in range(n):
        if outs[k] is None:
            lines.append(f"    Lo[:, {k}] = 0.0; Hi[:, {k}] = 0.0")
        else:
            lines.append(f"    Lo[:, {k}] = L{k}; Hi[:, {k}] = H{k}")
            if outs[k]:
                lines.append(f"    if B{k} is not None: Bad[:, {k}] = B{k}")
    lines.append("    return Lo, Hi, Bad, sw, culprit")
    code = compile_source("\n".join(lines), f"<batch interval tape of {name}>")
    exec(code, ns)
    return ns["run"], _culprit_deps(tape, in_off)


def _culprit_deps(tape, in_off) -> list[int]:
    """`_compile`'s second result alone: per operation with a domain (in tape order), the bitmask of the flat
    inputs it depends on."""
    dep: dict[int, int] = {}
    deps: list[int] = []
    for ins in tape.instructions:
        op, a, r = ins.op, ins.args, ins.res
        if op == casadi.OP_OUTPUT:
            continue
        if op == casadi.OP_INPUT:
            dep[r[0]] = 1 << (in_off[a[0]] + a[1])
        elif op == casadi.OP_CONST:
            dep[r[0]] = 0
        else:
            mask = 0
            for j in a[:1] if OP_NAMES.get(op) in _UNARY else a[:2]:
                mask |= dep.get(j, 0)
            if OP_NAMES.get(op) in _FAILING:
                deps.append(mask)
            dep[r[0]] = mask
    return deps


#: the largest map eval_points builds (a power of two, as its other sizes are)
POINTS_PER_MAP = 8192



def _orb(*flags):
    out = None
    for f in flags:
        if f is None:
            continue
        out = f if out is None else (out | f)
    return out


class BatchIntervalFunction(IntervalFunction):
    """Endpoint interval extension of an SX casadi.Function over many boxes at once (numpy, outward rounded).

    `eval_batch(LO, HI)` takes (K, n_in_nz) bounds and returns (L, H, switched) of shape (K, n_out_nz), (K,):
    invalid entries (a domain error, a non-finite value) are (-inf, inf). The single-box methods of
    IntervalFunction (`eval`, `eval_flat`) work on a batch of one, so it plugs into `sx.branch` as well.
    """

    def __init__(self, f: casadi.Function):
        # the layout of IntervalFunction (names, shapes, nonzeros, offsets) without its scalar backends
        from .tape import as_sx_function
        self.function = as_sx_function(f)
        tape = read_layout(self, self.function)
        self.backend = None
        self.form = "natural"
        from . import batch_vm
        fn = batch_vm.library() if batch_vm.wanted() else None
        if fn is not None:          # the compiled interpreter: the same rules, no Python per operation
            self._run, self._deps = batch_vm.Program(tape, self.in_off, self.out_off, fn).run, _culprit_deps(tape,
                                                                                                       self.in_off)
        else:
            self._run, self._deps = _compile(tape, self.in_off, self.out_off)
        #: the tape's real operations, `tape.count_ops(f)["operations"]`, counted from the tape read here (a
        #: certificate's budget needs it; reading every instruction of the function again cost as much)
        self.operations = sum(1 for ins in tape.instructions if ins.op not in BOOKKEEPING)
        self._jac = None
        self._last = None
        self._map: dict[int, Buffered] = {}

    def eval_batch(self, LO: np.ndarray, HI: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(L, H, switched) over K boxes given as (K, n_in_nz) arrays of lower and upper bounds."""
        L, H, sw, _ = self.eval_batch_culprit(LO, HI)
        return L, H, sw

    def eval_batch_culprit(self, LO: np.ndarray, HI: np.ndarray):
        """(L, H, switched, culprit): culprit[k] is the first failing instruction on box k (-1: none); its flat
        inputs are `culprit_inputs(culprit[k])` -- the variables worth splitting to get rid of the failure."""
        LO = np.ascontiguousarray(LO, dtype=float).reshape(-1, self.n_in_nz)
        HI = np.ascontiguousarray(HI, dtype=float).reshape(-1, self.n_in_nz)
        with np.errstate(all="ignore"):
            L, H, bad, sw, culprit = self._run(LO, HI)
            bad = bad | ~np.isfinite(L) | ~np.isfinite(H)
        L = np.where(bad, -_INF, L)
        H = np.where(bad, _INF, H)
        return L, H, sw, culprit

    def culprit_inputs(self, k: int) -> np.ndarray:
        """The flat input indices failing instruction number k depends on."""
        mask = self._deps[k]
        return np.array([j for j in range(self.n_in_nz) if mask >> j & 1], dtype=int)

    def eval_flat(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Enclosures of the output nonzeros over one flat box."""
        L, H, _ = self.eval_batch(np.asarray(lo, float)[None, :], np.asarray(hi, float)[None, :])
        return L[0], H[0]

    def eval_values(self, lo, hi):
        """Not available: this backend has no interval objects to hand out (use eval_batch)."""
        raise NotImplementedError("BatchIntervalFunction evaluates bounds only (eval_batch)")

    def eval_points(self, X: np.ndarray) -> np.ndarray:
        """CasADi's double values of the output nonzeros at K flat points (K, n_in_nz) -> (K, n_out_nz); more than
        POINTS_PER_MAP points go through one map of that size, chunk by chunk (building map(K) costs time linear
        in K, about as much as evaluating it; each point's value is its own either way)."""
        X = np.asarray(X, float).reshape(-1, self.n_in_nz)
        K0 = X.shape[0]
        if K0 > POINTS_PER_MAP:
            return np.concatenate([self.eval_points(X[s:s + POINTS_PER_MAP]) for s in range(0, K0, POINTS_PER_MAP)])
        K = 1 << max(0, (K0 - 1).bit_length())          # a few map sizes only (building one costs more than a call)
        if K > K0:
            X = np.concatenate([X, np.repeat(X[-1:], K - K0, axis=0)])
        if K not in self._map:
            self._map[K] = Buffered(self.function.map(K))
        b = self._map[K]
        # the map's inputs and outputs are its K copies' nonzeros one copy after the other, which are the rows of
        # X and of the result: numpy buffers, no dense DM of every input and output
        for a, (i0, i1) in zip(b.args, zip(self.in_off[:-1], self.in_off[1:])):
            a.reshape(K, i1 - i0)[:] = X[:, i0:i1]
        b.evaluate()
        cols = [r.reshape(K, -1) for r in b.res]
        return (np.concatenate(cols, axis=1) if cols else np.zeros((K, 0)))[:K0]

    def __repr__(self) -> str:
        return f"BatchIntervalFunction({self.name!r}, inputs={list(self.in_names)}, outputs={list(self.out_names)})"


class BatchCenteredForm:
    """The mean-value (centered) form in the inputs `wrt`, batched: f(W, U) in f(w_m, U) + J_w(W, U) (W - w_m) with
    w_m the midpoint of W and J_w = df/dw by CasADi's AD of the same graph, intersected with the natural enclosure,
    on boxes where no discontinuous operation switches (the mean-value theorem needs f continuous in w there) and
    the natural enclosure is valid (which shows f defined on the box). Its overestimation shrinks with the square of
    the box width (the natural form's only linearly). Also returns max |J_w| per output and w-variable, with which
    the branch and bound splits by sensitivity."""

    def __init__(self, f: casadi.Function, wrt, order: int = 1, prune: bool = False):
        """`order` 2: the Jacobian J_w is itself enclosed by this form (J_w(W, U) in J_w(w_m, U) + H(W, U) (W - w_m),
        H = dJ_w/dw by AD of the same graph, intersected with J_w's natural enclosure), so the spread |J_w| r is
        |J_w(w_m)| r plus a term of second order in r: where the natural J_w suffers dependency (a large product
        whose change over the box is small), the enclosure shrinks with r^2 instead of staying at the natural
        J_w's width. `prune` (implied by order 2): the Jacobian's tape has only the columns of the w-variables the
        outputs depend on structurally (the others are exact zeros), so an input of many unused entries costs
        nothing in it, nor in the Hessian."""
        self.natural = BatchIntervalFunction(f)
        self.order = int(order)
        F = self.natural
        f = F.function
        unknown = [k for k in wrt if k not in F.in_names]
        if unknown:
            raise ValueError(f"{f.name()!r} has no input {', '.join(unknown)}")
        self.wrt = [k for k in F.in_names if k in wrt]
        xin = f.sx_in()
        outs = f.call(xin)
        y = casadi.vertcat(casadi.SX(0, 1), *[casadi.SX(o).nz[:] for o in outs])
        w = casadi.vertcat(casadi.SX(0, 1), *[xin[F.in_names.index(k)].nz[:] for k in self.wrt])
        self.n_out = F.n_out_nz
        self.w_flat = (np.concatenate([np.arange(F.in_off[F.in_names.index(k)], F.in_off[F.in_names.index(k) + 1])
                                       for k in self.wrt]).astype(int) if self.wrt else np.zeros(0, int))
        cols = np.arange(self.w_flat.size)
        if prune or self.order >= 2:
            colind = np.asarray(casadi.jacobian(y, w).sparsity().colind())
            cols = np.flatnonzero(colind[1:] > colind[:-1])
            w = w[[int(c) for c in cols]] if cols.size else casadi.SX(0, 1)
        # fmax/fmin's derivative quotients written so that their enclosure stays finite across a kink
        J = casadi.densify(kink_quotients([casadi.jacobian(y, w)])[0])
        jf = casadi.Function(f.name() + "_dw", xin, [casadi.vec(J)], list(F.in_names), ["J"],
                             {"cse": True, "allow_duplicate_io_names": True})
        jac = BatchCenteredForm(jf, self.wrt, self.order - 1, prune=True) if self.order >= 2 \
            else BatchIntervalFunction(jf)
        self.jac = jac if cols.size == self.w_flat.size else _Columns(jac, cols, self.w_flat.size, self.n_out)
        #: refine(LO, HI, L, H, JL, JH) -> (JL, JH): a hook that narrows entries of the Jacobian's enclosure
        #: (K, n_w, n_out) given the outputs' enclosure (L, H) on the box (e.g. `certificates.regressor_jacobian`);
        #: it must return a valid enclosure of df/dw on the box, which the form then uses `refine_passes` times
        self.refine = None
        self.refine_passes = 1

    def __getattr__(self, name):
        if name == "natural":
            raise AttributeError(name)
        return getattr(self.natural, name)

    def eval_batch(self, LO: np.ndarray, HI: np.ndarray, with_jacobian: bool = False):
        """(L, H, switched[, Jabs (K, n_out, n_w)]) over K boxes; `self.last_culprit` is the natural tape's
        culprit array of the call (see BatchIntervalFunction.eval_batch_culprit)."""
        F = self.natural
        LO = np.asarray(LO, float).reshape(-1, F.n_in_nz)
        HI = np.asarray(HI, float).reshape(-1, F.n_in_nz)
        L, H, sw, self.last_culprit = F.eval_batch_culprit(LO, HI)
        nw = self.w_flat.size
        K = LO.shape[0]
        if nw == 0:
            return (L, H, sw, np.zeros((K, self.n_out, 0))) if with_jacobian else (L, H, sw)
        JL, JH, _ = self.jac.eval_batch(LO, HI)
        JL, JH = JL.reshape(K, nw, self.n_out), JH.reshape(K, nw, self.n_out)      # column-major
        wl, wh = LO[:, self.w_flat], HI[:, self.w_flat]
        wm = np.where(wl == wh, wl, 0.5 * wl + 0.5 * wh)
        r = np.maximum(_up(wh - wm), _up(wm - wl))          # |w - w_m| <= r on the box, rounded up
        MLO, MHI = LO.copy(), HI.copy()
        MLO[:, self.w_flat] = wm
        MHI[:, self.w_flat] = wm
        CL, CH, _ = F.eval_batch(MLO, MHI)
        L2, H2 = L, H
        for k in range(1 + (self.refine_passes if self.refine is not None else 0)):
            if k:
                # another valid enclosure of some Jacobian entries, given the outputs' enclosure on the box
                JL, JH = self.refine(LO, HI, L2, H2, JL, JH)
            Jabs = np.maximum(np.abs(JL), np.abs(JH)).transpose(0, 2, 1)
            with np.errstate(all="ignore"):
                spread = np.einsum("kij,kj->ki", Jabs, r)
                spread = _up(spread * (1.0 + 4.0 * nw * 2.0 ** -52))      # the sum's rounding, outward
                ML, MH = _dn(CL - spread), _up(CH + spread)
            ok = (~sw)[:, None] & np.isfinite(L) & np.isfinite(H) & np.isfinite(ML) & np.isfinite(MH)
            L2 = np.where(ok, np.maximum(L2, ML), L2)
            H2 = np.where(ok, np.minimum(H2, MH), H2)
            if np.any(L2 > H2):
                raise IntervalError(f"{F.name!r}: the centered and natural enclosures are disjoint -- a rule is "
                                    "wrong")
        if with_jacobian:
            return L2, H2, sw, Jabs
        return L2, H2, sw

    def eval_flat(self, lo, hi):
        """Enclosures over one flat box."""
        L, H, _ = self.eval_batch(np.asarray(lo, float)[None, :], np.asarray(hi, float)[None, :])
        return L[0], H[0]


class _Columns:
    """A Jacobian evaluator of some columns only (the w-variables the outputs depend on), read as the full Jacobian
    (column-major, the other columns exact zeros); every other attribute is the inner evaluator's."""

    def __init__(self, inner, cols: np.ndarray, nw: int, n_out: int):
        self.inner, self.cols, self.nw, self.n_out = inner, cols, nw, n_out

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def eval_batch(self, LO, HI):
        L, H, sw = self.inner.eval_batch(LO, HI)[:3]
        K = L.shape[0]
        out = []
        for A in (L, H):
            full = np.zeros((K, self.nw, self.n_out))
            full[:, self.cols, :] = A.reshape(K, self.cols.size, self.n_out)
            out.append(full.reshape(K, -1))
        return out[0], out[1], sw
