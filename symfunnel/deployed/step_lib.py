"""The compiled step API of generated C (`<P>state_size`, `<P>init`, `<P>step`) called through ctypes: the
controller of the sampled-data loops (`deployed.loop`), compiled from the files `codegen --lang c` writes."""

from __future__ import annotations

import ctypes

import numpy as np

__all__ = ["MARK", "StepLibrary", "step_library"]

_dp = ctypes.POINTER(ctypes.c_double)
#: First line of the step API's part of a generated .c file (templates/step.c).
MARK = "/* ---- The deployed controller (see"


class StepLibrary:
    """The compiled step API (`<P>state_size`, `<P>init`, `<P>step`) of generated C, called through ctypes."""

    def __init__(self, path, prefix: str, n: int, n_esn: int, n_w: int):
        self.lib = ctypes.CDLL(str(path))
        self.n, self.n_esn, self.n_w = n, n_esn, n_w
        self._size = getattr(self.lib, prefix + "state_size")
        self._init = getattr(self.lib, prefix + "init")
        self._step = getattr(self.lib, prefix + "step")
        self._size.restype = ctypes.c_int
        self._init.restype = ctypes.c_int
        self._step.restype = ctypes.c_int
        self._step.argtypes = [ctypes.c_void_p, ctypes.c_double, _dp, _dp, _dp]
        self.state = np.zeros((self._size() + 7) // 8)            # doubles first: aligned storage
        self._state_p = self.state.ctypes.data
        self.q, self.dq, self.tau = np.zeros(n), np.zeros(n), np.zeros(n)
        self._ptrs = tuple(a.ctypes.data_as(_dp) for a in (self.q, self.dq, self.tau))
        self.init()

    def init(self) -> int:
        """Pinit: the scenario's initial controller state."""
        return self._init(ctypes.c_void_p(self._state_p))

    @property
    def x_esn(self) -> np.ndarray:
        """A view of the state's reservoir (writable)."""
        return self.state[:self.n_esn]

    @property
    def w_hat(self) -> np.ndarray:
        """A view of the state's weights, column-major (writable)."""
        return self.state[self.n_esn:self.n_esn + self.n_w]

    @property
    def margin(self) -> np.ndarray:
        """The margins of the last step: e1 then e2 per joint."""
        o = self.n_esn + self.n_w
        return self.state[o:o + 2 * self.n]

    def raw(self):
        """(function, state pointer, (q, dq, tau) pointers): rc = function(state, t, *pointers) on the buffers."""
        return self._step, self._state_p, self._ptrs

    def step(self, t: float, q, dq) -> tuple[int, np.ndarray]:
        """Pstep at (t, q, dq): (return code, tau)."""
        self.q[:] = q
        self.dq[:] = dq
        rc = self._step(self._state_p, t, *self._ptrs)
        return rc, self.tau.copy()


def step_library(design, files: dict[str, str], on_build=None) -> StepLibrary:
    """Compile (cached) the generated C pair of `files` as a shared library and wrap its step API."""
    import json

    from ..emit.files import c_names
    from .cfun import link_step
    base = c_names(files)[0]
    api = json.loads(files["manifest.json"])["c_api"]["step"]
    # The file's CasADi part does not depend on the rate (only the step API's constants after MARK do): compile
    # it once to an object, then link the rest, so a rate search compiles the big part once.
    text = files[base + ".c"]
    cut = text.index(MARK)
    built = link_step(text[:cut], text[cut:], (base + ".h", files[base + ".h"]), f"lib{base}_step.so", on_build)
    from ..emit.step import step_states
    x_esn, w_hat = step_states(design)        # the design's, or the placeholders the step API keeps at 0
    return StepLibrary(built.path, api["prefix"], design.n, int(x_esn.numel()), int(w_hat.numel()))
