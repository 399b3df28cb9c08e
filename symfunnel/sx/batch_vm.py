"""The batched interval rules run by one compiled interpreter (csrc/interval_vm.c) instead of numpy calls per
operation: the same rules, the same order of IEEE operations, so +, -, *, /, sqrt and every comparison give the
numpy backend's doubles bit for bit; libm's transcendental functions (not numpy's SIMD ones) are widened by the
same TRANSCENDENTAL_ULPS. A tape of N operations over K boxes costs N numpy calls per rule in the numpy backend
(microseconds each, whatever K) and one C call here.

`SYMFUNNEL_INTERVAL=numpy` selects the numpy backend; without a C compiler it is used anyway, with a warning.
"""

from __future__ import annotations

import ctypes
import os
import warnings
from pathlib import Path

import casadi
import numpy as np

from .batch_rules import _FAILING, _RULES, TRANSCENDENTAL_ULPS, rule_name

#: the interpreter's operations, in the order of interval_vm_ops.h (generated from this tuple)
VM_OPS = ("INPUT", "OUTPUT", "CONST", "ASSIGN", "ADD", "SUB", "MUL", "DIV", "NEG", "TWICE", "FABS", "SQ", "INV",
          "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN", "SINH", "COSH", "TANH", "ATANH", "POW",
          "CONSTPOW", "SIGN", "FLOOR", "CEIL", "FMIN", "FMAX", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR",
          "IF_ELSE_ZERO")
_CODE = {name: i for i, name in enumerate(VM_OPS)}
assert set(VM_OPS[3:]) == set(_RULES), sorted(set(VM_OPS[3:]) ^ set(_RULES))

#: flags of the interpreter's library: ISO C without contraction (no fused multiply-add), no fast-math
VM_FLAGS = ("-std=c99", "-O2", "-ffp-contract=off", "-fno-fast-math", "-fPIC", "-shared")
#: a chunk of boxes keeps its work slots (lower, upper, flag: 17 bytes each) within about this many bytes
CHUNK_BYTES = 1 << 20

_LIB: list = []           # [ctypes function or None], filled on first use


def header() -> str:
    """interval_vm_ops.h: the operation codes of VM_OPS."""
    return "".join(f"#define VM_{name} {i}\n" for i, name in enumerate(VM_OPS)) + \
        f"#define VM_TRANSCENDENTAL_ULPS {int(TRANSCENDENTAL_ULPS)}\n"


def wanted() -> bool:
    """Whether the compiled interpreter is to be used ($SYMFUNNEL_INTERVAL is not 'numpy')."""
    return os.environ.get("SYMFUNNEL_INTERVAL", "c").strip().lower() != "numpy"


def library():
    """The interpreter's `sfi_eval` (compiled once, cached like the other generated C), or None without a working
    C compiler (the numpy backend is used then)."""
    if _LIB:
        return _LIB[0]
    import subprocess

    from ..core.ccompile import compile_cached
    from ..core.errors import InputError
    src = (Path(__file__).parent / "csrc" / "interval_vm.c").read_text(encoding="utf-8")
    try:
        built = compile_cached({"interval_vm.c": src, "interval_vm_ops.h": header()}, ["interval_vm.c"],
                               "libsfs_interval.so", VM_FLAGS)
        lib = ctypes.CDLL(str(built.path))
    except (OSError, RuntimeError, subprocess.SubprocessError, InputError) as exc:
        # no compiler, a failed or timed-out build: the numpy backend computes the same enclosures; other bad
        # input (a malformed $SYMFUNNEL_COMPILE_TIMEOUT) is the user's to fix, as for every other compile
        if isinstance(exc, InputError) and exc.key != "CC":
            raise
        warnings.warn(f"the compiled interval interpreter is not available ({exc}); using the numpy backend",
                      RuntimeWarning, stacklevel=2)
        _LIB.append(None)
        return None
    f = lib.sfi_eval
    vp = ctypes.c_void_p
    f.restype = ctypes.c_int
    f.argtypes = [vp, ctypes.c_int, vp, ctypes.c_int, ctypes.c_int, ctypes.c_int, vp, vp, ctypes.c_long,
                  ctypes.c_int, vp, vp, vp, vp, vp, vp, vp, vp]
    _LIB.append(f)
    return f


def encode(tape, in_off, out_off) -> tuple[np.ndarray, np.ndarray]:
    """The tape as the interpreter's program: (code (n, 5) int32, constants); an operation with a domain gets its
    number among those in tape order (the culprit numbering of `batch._compile`)."""
    code = np.empty((len(tape.instructions), 5), dtype=np.int32)
    consts: list[float] = []
    n_failing = 0
    for i, ins in enumerate(tape.instructions):
        op, a, r = ins.op, ins.args, ins.res
        if op == casadi.OP_OUTPUT:
            code[i] = (_CODE["OUTPUT"], a[0], 0, 0, out_off[r[0]] + r[1])
        elif op == casadi.OP_INPUT:
            code[i] = (_CODE["INPUT"], 0, 0, r[0], in_off[a[0]] + a[1])
        elif op == casadi.OP_CONST:
            code[i] = (_CODE["CONST"], 0, 0, r[0], len(consts))
            consts.append(float(ins.constant))
        else:
            name = rule_name(tape, op, _CODE)
            aux = -1
            if name in _FAILING:
                aux, n_failing = n_failing, n_failing + 1
            code[i] = (_CODE[name], a[0], a[1] if len(a) > 1 else a[0], r[0], aux)
    return code, np.asarray(consts if consts else [0.0], dtype=float)


class Program:
    """One tape, encoded for the interpreter: run(LO, HI) -> (Lo, Hi, Bad, switched, culprit) as `batch._compile`'s
    numpy code returns them."""

    def __init__(self, tape, in_off, out_off, fn):
        self.code, self.consts = encode(tape, in_off, out_off)
        self.n_work = max(1, int(tape.n_work))
        self.n_in, self.n_out = int(in_off[-1]), int(out_off[-1])
        self.chunk = int(max(8, min(512, CHUNK_BYTES // (17 * self.n_work))))
        self._fn = fn

    def run(self, LO: np.ndarray, HI: np.ndarray):
        LO = np.ascontiguousarray(LO, dtype=float)        # the C reads rows of n_in doubles: no other layout
        HI = np.ascontiguousarray(HI, dtype=float)
        if LO.ndim != 2 or LO.shape != HI.shape or LO.shape[1] != self.n_in:
            raise ValueError(f"boxes of shape {LO.shape} / {HI.shape}, expected (K, {self.n_in}) both")
        K = LO.shape[0]
        B = max(1, min(self.chunk, K))
        Lo = np.empty((K, self.n_out))
        Hi = np.empty((K, self.n_out))
        Bad = np.empty((K, self.n_out), dtype=np.uint8)
        sw = np.empty(K, dtype=np.uint8)
        culprit = np.empty(K, dtype=np.int64)
        wl = np.empty(self.n_work * B)
        wh = np.empty(self.n_work * B)
        wb = np.empty(self.n_work * B, dtype=np.uint8)
        p = lambda a: a.ctypes.data                     # noqa: E731
        rc = self._fn(p(self.code), len(self.code), p(self.consts), self.n_work, self.n_in, self.n_out, p(LO),
                      p(HI), K, B, p(Lo), p(Hi), p(Bad), p(sw), p(culprit), p(wl), p(wh), p(wb))
        if rc == -1:
            from ..core.errors import SymfunnelError
            raise SymfunnelError("interval evaluation needs the rounding mode round-to-nearest (it was changed and "
                                 "not restored)")
        if rc != 0:
            raise RuntimeError(f"the interval interpreter does not know operation code {-2 - rc}")
        return Lo, Hi, Bad.view(bool), sw.view(bool), culprit
