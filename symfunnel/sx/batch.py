"""Batched endpoint interval evaluation of an SX tape with numpy: many boxes per call, outward rounded.

`BatchIntervalFunction(f)` compiles the tape once into straight-line numpy code over arrays of lower and upper
bounds, one entry per box, so a branch and bound evaluates hundreds of boxes in one call (the scalar backends of
`sx.interval` pay Python's overhead per operation and box). It is the third, independent implementation beside
codac and arb; `tests/test_interval.py` checks every rule against 200-bit arb values as for the other two.

Rounding. Every result is pushed one ulp outward (`numpy.nextafter`) after being computed in round-to-nearest:
IEEE 754 +, -, *, / and sqrt are correctly rounded, so the exact result lies within half an ulp and one ulp outward
encloses it. numpy's exp, log, sin, cos, tan, asin, acos, atan, sinh, cosh, tanh, atanh and pow are not correctly
rounded (libm or SIMD code within a few ulps): their results are widened by TRANSCENDENTAL_ULPS ulps first.
Endpoint arithmetic is exact for wide boxes (no midpoint-radius overestimation: the product of two positive
intervals stays positive), which the branch and bound's first, wide boxes need.

Domain errors (division by an interval containing 0, log of one reaching <= 0, sqrt below 0, atanh outside (-1, 1),
asin/acos outside [-1, 1], tan across a pole, pow outside its domain) and non-finite values mark the box's output
invalid: (-inf, inf). A discontinuous operation (sign, floor, ceil, a comparison, a logic operation, an undecided
if-else) that switches on a box sets its `switched` flag, so the mean-value form is not applied there.
"""

from __future__ import annotations

import math

import casadi
import numpy as np

from ..core.pycode import compile_source
from .buffered import Buffered
from .interval import IntervalError, IntervalFunction, read_layout
from .tape import OP_NAMES

__all__ = ["BatchIntervalFunction", "TRANSCENDENTAL_ULPS", "BATCH_OPS"]

#: ulps by which results of numpy's (not correctly rounded) transcendental functions are widened
TRANSCENDENTAL_ULPS = 8
_REL = TRANSCENDENTAL_ULPS * 2.0 ** -52
_INF = np.inf
_PI_LO = math.pi                     # the double nearest pi is below pi
_PI_HI = math.nextafter(math.pi, 4)


def _dn(x):
    return np.nextafter(x, -_INF)


def _up(x):
    return np.nextafter(x, _INF)


def _wdn(x):
    """Down, widened for a transcendental function's error."""
    return np.nextafter(x - np.abs(x) * _REL, -_INF)


def _wup(x):
    return np.nextafter(x + np.abs(x) * _REL, _INF)


def _bad_of(*arrays):
    out = np.zeros(np.shape(arrays[0]), dtype=bool)
    for a in arrays:
        out |= ~np.isfinite(a)
    return out


# --- rules: each takes (lo, hi) pairs and returns (lo, hi, bad) or (lo, hi, bad, switched) ------------------

def ADD(al, ah, bl, bh):
    return _dn(al + bl), _up(ah + bh), None


def SUB(al, ah, bl, bh):
    return _dn(al - bh), _up(ah - bl), None


def MUL(al, ah, bl, bh):
    p1, p2, p3, p4 = al * bl, al * bh, ah * bl, ah * bh
    lo = np.minimum(np.minimum(p1, p2), np.minimum(p3, p4))
    hi = np.maximum(np.maximum(p1, p2), np.maximum(p3, p4))
    return _dn(lo), _up(hi), None


def _mulc(al, ah, c):
    """MUL with a constant factor c (bl = bh = c): of its four products two pairs are equal, so two are enough;
    the same values bit for bit, NaN and infinities included (np.minimum(p, p) is p)."""
    p, q = al * c, ah * c
    return _dn(np.minimum(p, q)), _up(np.maximum(p, q))


def DIV(al, ah, bl, bh):
    bad = (bl <= 0) & (bh >= 0)
    bl = np.where(bad, 1.0, bl)
    bh = np.where(bad, 1.0, bh)
    q1, q2, q3, q4 = al / bl, al / bh, ah / bl, ah / bh
    lo = np.minimum(np.minimum(q1, q2), np.minimum(q3, q4))
    hi = np.maximum(np.maximum(q1, q2), np.maximum(q3, q4))
    return _dn(lo), _up(hi), bad


def NEG(al, ah):
    return -ah, -al, None


def TWICE(al, ah):
    return 2.0 * al, 2.0 * ah, None


def _abs(al, ah):
    pos = al >= 0
    neg = ah <= 0
    lo = np.where(pos, al, np.where(neg, -ah, 0.0))
    hi = np.where(pos, ah, np.where(neg, -al, np.maximum(-al, ah)))
    return lo, hi


def FABS(al, ah):
    lo, hi = _abs(al, ah)
    return lo, hi, None


def SQ(al, ah):
    lo, hi = _abs(al, ah)
    return np.maximum(_dn(lo * lo), 0.0), _up(hi * hi), None


def INV(al, ah):
    bad = (al <= 0) & (ah >= 0)
    al = np.where(bad, 1.0, al)
    ah = np.where(bad, 1.0, ah)
    return _dn(1.0 / ah), _up(1.0 / al), bad


def EXP(al, ah):
    return np.maximum(_wdn(np.exp(al)), 0.0), _wup(np.exp(ah)), None


def LOG(al, ah):
    bad = al <= 0
    al = np.where(bad, 1.0, al)
    ah = np.where(bad, 1.0, ah)
    return _wdn(np.log(al)), _wup(np.log(ah)), bad


def SQRT(al, ah):
    bad = al < 0
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return np.maximum(_dn(np.sqrt(al)), 0.0), _up(np.sqrt(ah)), bad


def _contains_point(al, ah, phase, period):
    """Whether some phase + k period (k integer) may lie in [al, ah] (conservative: the interval is widened)."""
    tol = 1e-12 * np.maximum(1.0, np.maximum(np.abs(al), np.abs(ah)))
    k_lo = np.ceil((al - tol - phase) / period)
    k_hi = np.floor((ah + tol - phase) / period)
    return k_lo <= k_hi


def _periodic(fn, al, ah, max_phase, min_phase):
    """sin or cos on intervals: values at the ends, +1 / -1 where a maximum / minimum lies inside."""
    wide = ~(ah - al < 6.0) | ~(np.abs(al) < 1e15) | ~(np.abs(ah) < 1e15)
    a = np.where(wide, 0.0, al)
    b = np.where(wide, 0.0, ah)
    fa, fb = fn(a), fn(b)
    lo = np.minimum(fa, fb)
    hi = np.maximum(fa, fb)
    two_pi = 2.0 * math.pi
    hi = np.where(_contains_point(a, b, max_phase, two_pi), 1.0, _wup(hi))
    lo = np.where(_contains_point(a, b, min_phase, two_pi), -1.0, _wdn(lo))
    lo = np.where(wide, -1.0, np.maximum(lo, -1.0))
    hi = np.where(wide, 1.0, np.minimum(hi, 1.0))
    return lo, hi


def SIN(al, ah):
    lo, hi = _periodic(np.sin, al, ah, 0.5 * math.pi, -0.5 * math.pi)
    return lo, hi, None


def COS(al, ah):
    lo, hi = _periodic(np.cos, al, ah, 0.0, math.pi)
    return lo, hi, None


def TAN(al, ah):
    bad = ~(ah - al < 3.0) | _contains_point(al, ah, 0.5 * math.pi, math.pi) | ~(np.abs(al) < 1e15) \
        | ~(np.abs(ah) < 1e15)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.tan(al)), _wup(np.tan(ah)), bad


def ASIN(al, ah):
    bad = (al < -1) | (ah > 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.arcsin(al)), _wup(np.arcsin(ah)), bad


def ACOS(al, ah):
    bad = (al < -1) | (ah > 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return np.maximum(_wdn(np.arccos(ah)), 0.0), _wup(np.arccos(al)), bad


def ATAN(al, ah):
    return _wdn(np.arctan(al)), _wup(np.arctan(ah)), None


def SINH(al, ah):
    return _wdn(np.sinh(al)), _wup(np.sinh(ah)), None


def COSH(al, ah):
    lo, hi = _abs(al, ah)
    return np.maximum(_wdn(np.cosh(lo)), 1.0), _wup(np.cosh(hi)), None


def TANH(al, ah):
    return np.maximum(_wdn(np.tanh(al)), -1.0), np.minimum(_wup(np.tanh(ah)), 1.0), None


def ATANH(al, ah):
    bad = (al <= -1) | (ah >= 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.arctanh(al)), _wup(np.arctanh(ah)), bad


def _ipow(al, ah, n):
    """x^n for an integer n >= 1 (monotone for odd n; in |x| for even n), before widening."""
    if n % 2:
        return np.power(al, n), np.power(ah, n)
    lo, hi = _abs(al, ah)
    return np.power(lo, n), np.power(hi, n)


def POW(al, ah, bl, bh):
    shape = np.broadcast(al, bl).shape
    lo = np.full(shape, -_INF)
    hi = np.full(shape, _INF)
    bad = np.ones(shape, dtype=bool)
    al, ah, bl, bh = (np.broadcast_to(v, shape) for v in (al, ah, bl, bh))
    point = (bl == bh) & (np.floor(bl) == bl) & (np.abs(bl) < 1024)
    for n in np.unique(bl[point]) if point.any() else []:
        sel = point & (bl == n)
        a, b = al[sel], ah[sel]
        k = int(abs(n))
        if k == 0:
            lo[sel], hi[sel], bad[sel] = 1.0, 1.0, False
            continue
        pl, ph = _ipow(a, b, k)
        if n < 0:
            z = (a <= 0) & (b >= 0)
            pl, ph = np.where(z, 1.0, pl), np.where(z, 1.0, ph)
            # 1/x^k: x^k has one sign on the box (0 excluded)
            ql, qh = 1.0 / ph, 1.0 / pl
            pl, ph = np.minimum(ql, qh), np.maximum(ql, qh)
            bad[sel] = z
        else:
            bad[sel] = False
        lo[sel], hi[sel] = _wdn(pl), _wup(ph)
    real = ~point
    ok = real & ((al > 0) | ((al >= 0) & (bl > 0)))
    if ok.any():
        a, b, c, d = al[ok], ah[ok], bl[ok], bh[ok]
        corners = [np.power(x, y) for x in (a, b) for y in (c, d)]
        lo[ok] = np.maximum(_wdn(np.minimum.reduce(corners)), 0.0)
        hi[ok] = _wup(np.maximum.reduce(corners))
        bad[ok] = False
    return lo, hi, bad


CONSTPOW = POW


def SIGN(al, ah):
    lo, hi = np.sign(al), np.sign(ah)
    return lo, hi, None, lo != hi


def FLOOR(al, ah):
    lo, hi = np.floor(al), np.floor(ah)
    return lo, hi, None, lo != hi


def CEIL(al, ah):
    lo, hi = np.ceil(al), np.ceil(ah)
    return lo, hi, None, lo != hi


def FMIN(al, ah, bl, bh):
    return np.minimum(al, bl), np.minimum(ah, bh), None


def FMAX(al, ah, bl, bh):
    return np.maximum(al, bl), np.maximum(ah, bh), None


def _decided(true, false):
    lo = np.where(true, 1.0, 0.0)
    hi = np.where(false, 0.0, 1.0)
    return lo, hi, None, ~(true | false)


def LT(al, ah, bl, bh):
    return _decided(ah < bl, al >= bh)


def LE(al, ah, bl, bh):
    return _decided(ah <= bl, al > bh)


def EQ(al, ah, bl, bh):
    return _decided((al == ah) & (bl == bh) & (al == bl), (ah < bl) | (bh < al))


def NE(al, ah, bl, bh):
    return _decided((ah < bl) | (bh < al), (al == ah) & (bl == bh) & (al == bl))


def _truth(al, ah):
    """(certainly nonzero, certainly zero)."""
    return (al > 0) | (ah < 0), (al == 0) & (ah == 0)


def NOT(al, ah):
    t, f = _truth(al, ah)
    return _decided(f, t)


def AND(al, ah, bl, bh):
    ta, fa = _truth(al, ah)
    tb, fb = _truth(bl, bh)
    return _decided(ta & tb, fa | fb)


def OR(al, ah, bl, bh):
    ta, fa = _truth(al, ah)
    tb, fb = _truth(bl, bh)
    return _decided(ta | tb, fa & fb)


def IF_ELSE_ZERO(cl, ch, xl, xh):
    t, f = _truth(cl, ch)
    lo = np.where(f, 0.0, np.where(t, xl, np.minimum(xl, 0.0)))
    hi = np.where(f, 0.0, np.where(t, xh, np.maximum(xh, 0.0)))
    # a certainly false condition masks its branch (also a domain error there, as CasADi's double evaluation does)
    return lo, hi, None, ~(t | f), f


def ASSIGN(al, ah):
    return al, ah, None


_RULES = {name: fn for name, fn in globals().items() if name.isupper() and callable(fn)
          and name not in ("TRANSCENDENTAL_ULPS",)}
_UNARY = frozenset(("ASSIGN", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN",
                    "ACOS", "ATAN", "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL", "NOT"))
_SWITCHING = frozenset(("SIGN", "FLOOR", "CEIL", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR", "IF_ELSE_ZERO"))
#: the tape operations this backend has a rule for (the same set as codac's and arb's)
BATCH_OPS = frozenset(_RULES)


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
    dep: dict[int, int] = {}                # work slot -> bitmask of the flat inputs it depends on
    deps: list[int] = []                    # per failing instruction (in culprit numbering), its inputs' bitmask
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
            dep[w] = 1 << j
            flagged[w] = False
            lines.append(f"    l{w} = LO[:, {j}]; h{w} = HI[:, {j}]")
        elif op == casadi.OP_CONST:
            dep[w] = 0
            c = float(ins.constant)
            flagged[w] = not math.isfinite(c)
            if math.isfinite(c):
                const[w] = c
                lines.append(f"    l{w} = h{w} = {c!r}")
            else:
                lines.append(f"    l{w} = h{w} = np.float64({str(c)!r}); b{w} = np.ones(K, dtype=bool)")  # 'inf'/'nan'
        elif op == casadi.OP_PARAMETER:
            raise IntervalError(f"function {name!r} has free SX variables; interval evaluation needs every symbol "
                                "as an input")
        else:
            opname = OP_NAMES.get(op, f"<{op}>")
            if opname not in _RULES:
                raise IntervalError(f"no interval rule for OP_{opname} in function {name!r}")
            ns[opname] = _RULES[opname]
            args = [a[0]] if opname in _UNARY else [a[0], a[1]]
            mask = 0
            for j in args:
                mask |= dep.get(j, 0)
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
                lines.append(f"    if e_ is not None: culprit = np.where((culprit < 0) & e_, {len(deps)}, culprit)")
                deps.append(mask)
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
            dep[w] = mask
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
    return ns["run"], deps


#: the largest map eval_points builds (a power of two, as its other sizes are)
POINTS_PER_MAP = 8192

_FAILING = frozenset(("DIV", "INV", "LOG", "SQRT", "TAN", "ASIN", "ACOS", "ATANH", "POW", "CONSTPOW"))


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
        self._run, self._deps = _compile(tape, self.in_off, self.out_off)
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

    def __init__(self, f: casadi.Function, wrt):
        self.natural = BatchIntervalFunction(f)
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
        J = casadi.densify(casadi.jacobian(y, w))
        self.jac = BatchIntervalFunction(casadi.Function(f.name() + "_dw", xin, [casadi.vec(J)], list(F.in_names),
                                                         ["J"], {"cse": True, "allow_duplicate_io_names": True}))
        self.n_out = F.n_out_nz
        self.w_flat = (np.concatenate([np.arange(F.in_off[F.in_names.index(k)], F.in_off[F.in_names.index(k) + 1])
                                       for k in self.wrt]).astype(int) if self.wrt else np.zeros(0, int))

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
        Jabs = np.maximum(np.abs(JL), np.abs(JH)).reshape(K, nw, self.n_out).transpose(0, 2, 1)   # column-major
        wl, wh = LO[:, self.w_flat], HI[:, self.w_flat]
        wm = np.where(wl == wh, wl, 0.5 * wl + 0.5 * wh)
        r = np.maximum(_up(wh - wm), _up(wm - wl))          # |w - w_m| <= r on the box, rounded up
        MLO, MHI = LO.copy(), HI.copy()
        MLO[:, self.w_flat] = wm
        MHI[:, self.w_flat] = wm
        CL, CH, _ = F.eval_batch(MLO, MHI)
        with np.errstate(all="ignore"):
            spread = np.einsum("kij,kj->ki", Jabs, r)
            spread = _up(spread * (1.0 + 4.0 * nw * 2.0 ** -52))      # the sum's rounding, outward
            ML, MH = _dn(CL - spread), _up(CH + spread)
        ok = (~sw)[:, None] & np.isfinite(L) & np.isfinite(H) & np.isfinite(ML) & np.isfinite(MH)
        L2 = np.where(ok, np.maximum(L, ML), L)
        H2 = np.where(ok, np.minimum(H, MH), H)
        if np.any(L2 > H2):
            raise IntervalError(f"{F.name!r}: the centered and natural enclosures are disjoint -- a rule is wrong")
        if with_jacobian:
            return L2, H2, sw, Jabs
        return L2, H2, sw

    def eval_flat(self, lo, hi):
        """Enclosures over one flat box."""
        L, H, _ = self.eval_batch(np.asarray(lo, float)[None, :], np.asarray(hi, float)[None, :])
        return L[0], H[0]
