"""A casadi.Function evaluated on preallocated numpy buffers (Function.buffer): for the simulation's chunks and
the interval search's mapped point evaluations, where converting numpy -> DM -> numpy per call costs more than
the evaluation."""

from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["Buffered"]


class Buffered:
    """A casadi.Function evaluated on preallocated numpy buffers: no numpy -> DM -> numpy conversion per call.

    `args` and `res` hold each input's and output's nonzeros (column-major); calling it with full arrays needs
    every input and output dense (`supports`), writing into `args` and calling `evaluate` works for any sparsity.
    The outputs are overwritten by the next evaluation; callers copy what they keep.
    """

    def __init__(self, f: ca.Function, *, stats: bool = False):
        self.f = f
        self.with_stats = stats
        self.stats: dict = {}        # of the last evaluation (with stats=True)
        self._counted: dict = {}     # CasADi's n_call_* counters of this buffer's memory so far
        self.buffer, self._eval = f.buffer()
        self.args = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.res = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        for i, a in enumerate(self.args):
            self.buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self.buffer.set_res(i, memoryview(r))

    @staticmethod
    def supports(f: ca.Function) -> bool:
        """Whether every input and output of f is dense (the buffers hold nonzeros only)."""
        return (all(f.sparsity_in(i).is_dense() for i in range(f.n_in()))
                and all(f.sparsity_out(i).is_dense() for i in range(f.n_out())))

    def __call__(self, *args) -> int:
        """Evaluate on `args` (arrays in the inputs' column-major order); the outputs are then in `self.res`."""
        for a, v in zip(self.args, args):
            a[:] = np.ravel(v, order="F")
        return self.evaluate()

    def evaluate(self) -> int:
        """Evaluate on the values already in `self.args`; CasADi's return code."""
        try:
            self._eval()
        finally:
            if self.with_stats:
                self._count()
        return self.buffer.ret()

    def _count(self) -> None:
        # A buffer keeps one memory object, whose n_call_* counters add up over evaluations (a plain call starts
        # from zero): report the difference, as a plain call would.
        st = dict(self.buffer.stats())
        for k, v in st.items():
            if k.startswith("n_call_") and isinstance(v, (int, float)):
                st[k] = v - self._counted.get(k, 0)
                self._counted[k] = v
        self.stats = st
