"""A generated CasADi C function, compiled once (cached by `core.ccompile`), loaded and called through ctypes with
fixed argument buffers: the plant steps and plant forces of the sampled loops."""

from __future__ import annotations

import ctypes

import casadi as ca
import numpy as np

_dp = ctypes.POINTER(ctypes.c_double)


class _CFun:
    """A generated CasADi C function with fixed argument buffers: fill .inputs, call, read .outputs (no copies)."""

    def __init__(self, path, name: str, f: ca.Function):
        lib = ctypes.CDLL(str(path))
        self._lib = lib
        self._f = getattr(lib, name)
        self._f.restype = ctypes.c_int
        self.inputs = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.outputs = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._arg = (_dp * max(1, f.sz_arg()))(*[a.ctypes.data_as(_dp) for a in self.inputs])
        self._res = (_dp * max(1, f.sz_res()))(*[a.ctypes.data_as(_dp) for a in self.outputs])
        self._iw = (ctypes.c_int * max(1, f.sz_iw()))()
        self._w = (ctypes.c_double * max(1, f.sz_w()))()

    def __call__(self) -> int:
        return self._f(self._arg, self._res, self._iw, self._w, 0)


def _compiled(f: ca.Function, on_build=None) -> _CFun:
    """Generate C for one function, compile it (cached) and load it."""
    import tempfile
    from pathlib import Path

    from ..core.ccompile import SHARED_FLAGS, compile_cached
    with tempfile.TemporaryDirectory(prefix="symfunnel-plant-") as tmp:
        cg = ca.CodeGenerator(f.name() + ".c", {"with_header": False, "casadi_int": "int"})
        cg.add(f)
        cg.generate(tmp + "/")
        src = Path(tmp, f.name() + ".c").read_text()
    built = compile_cached({f.name() + ".c": src}, [f.name() + ".c"], f"lib{f.name()}.so", SHARED_FLAGS,
                           on_build=on_build)
    return _CFun(built.path, f.name(), f)


def link_step(core: str, api: str, header: tuple[str, str], output: str, on_build=None):
    """Compile (cached) a generated C pair split at the step API: `core` (the CasADi part, which no rate changes)
    to an object once, then `api` with the header (name, text) linked against it into the shared library `output`;
    the `Built` of that library."""
    from ..core.ccompile import SHARED_FLAGS, compile_cached
    obj = compile_cached({"core.c": core}, ["core.c"], "core.o",
                         tuple(f for f in SHARED_FLAGS if f != "-shared") + ("-c",), libs=(), on_build=on_build)
    return compile_cached({"api.c": api, header[0]: header[1], "core.o": obj.path.read_bytes()},
                          ["api.c", "core.o"], output, SHARED_FLAGS, on_build=on_build)
