"""The step API as the rate searches build it: the generated C of `codegen --lang c`, compiled once for every rate.

The shipped step bakes its one period into `static const double <P>etd_[2]`, the exponential-Euler weights
(1 - exp(-lambda h)) / lambda (`emit.step.etd_factors`), so a build per rate meant a compile and link per rate. The
search build is the same text except that line (a writable global instead of a static const; `emit.step.c_step_files`
with rate_hz None), linked once against the shipped core's object; `RateStep` writes the weights of its rate into
that global before it runs. The step core receives the weights through the same pointer argument either way, so the
arithmetic is the shipped step's (the tests compare the two builds' runs bit for bit).
"""

from __future__ import annotations

import ctypes

from .step_lib import MARK, StepLibrary

__all__ = ["RateStep", "search_step", "search_sources"]

#: the last few search builds of this process: ((design, tau_max), path); the design object itself is held, so its
#: id is never reused while the entry lives
_BUILT: list[tuple[tuple, object]] = []


class RateStep(StepLibrary):
    """A StepLibrary of the search build at one rate: writes its weights `etd` into the library before init, step
    and raw (instances of one build share that global; each one sets its own before it runs)."""

    def __init__(self, path, prefix: str, n: int, n_esn: int, n_w: int, etd):
        self.etd = tuple(float(v) for v in etd)
        self._etd = (ctypes.c_double * 2).in_dll(ctypes.CDLL(str(path)), prefix + "etd_")
        super().__init__(path, prefix, n, n_esn, n_w)

    def _set(self) -> None:
        self._etd[0], self._etd[1] = self.etd

    def init(self) -> int:
        """Pinit, after setting this rate's weights."""
        self._set()
        return super().init()

    def raw(self):
        """As StepLibrary.raw, with this rate's weights set."""
        self._set()
        return super().raw()

    def step(self, t: float, q, dq):
        """As StepLibrary.step, with this rate's weights set."""
        self._set()
        return super().step(t, q, dq)


def search_sources(design, tau_max) -> dict[str, str]:
    """{"core.c", "api.c", header name: text, "shipped_api.c"}: the shipped C pair at the scenario's rate split at
    the step API (core.c is the shipped text's, byte for byte) and the search build's api.c and header."""
    from ..emit.files import c_names, generate
    from ..emit.step import c_step_files, step_initial, step_settings
    rate, tau_max = step_settings(design, None, tau_max)
    files = generate(design, "c", rate_hz=rate, tau_max=tau_max)
    base = c_names(files)[0]
    x0, w0 = step_initial(design)
    kw = {"prefix": "symfunnel_", "fprefix": "", "basename": base, "tau_max": tau_max, "x0": x0, "w0": w0}
    src_r, hdr_r = c_step_files(design, rate_hz=rate, **kw)
    src_0, hdr_0 = c_step_files(design, rate_hz=None, **kw)
    text, hdr = files[base + ".c"], files[base + ".h"]
    cut = text.index(MARK)
    # the shipped text is the rate-free part followed by this step API: swap that API, nothing else
    if text[cut:] != src_r[src_r.index(MARK):] or hdr.count(hdr_r) != 1:
        raise AssertionError("the generated C pair does not end with the step API of emit.step.c_step_files")
    return {"core.c": text[:cut], "api.c": src_0[src_0.index(MARK):], base + ".h": hdr.replace(hdr_r, hdr_0),
            "shipped_api.c": text[cut:]}


def search_step(design, rate_hz: float, tau_max, on_build=None) -> RateStep:
    """The search build's step at `rate_hz` (saturated at `tau_max`), compiled once per design and torque limit."""
    import numpy as np

    from ..emit.step import etd_factors, step_states
    from .cfun import link_step
    tm = None if tau_max is None else tuple(np.broadcast_to(np.asarray(tau_max, float), (design.n,)).tolist())
    _BUILT[:] = [e for e in _BUILT if e[1].exists()]         # (a compile cache removed since: built again)
    path = next((p for (d, t), p in _BUILT if d is design and t == tm), None)
    if path is None:
        src = search_sources(design, tau_max)
        hdr = next(k for k in src if k.endswith(".h"))
        path = link_step(src["core.c"], src["api.c"], (hdr, src[hdr]), f"lib{hdr[:-2]}_search.so", on_build).path
        _BUILT.append(((design, tm), path))
        del _BUILT[:-4]
    x_esn, w_hat = step_states(design)
    return RateStep(path, "symfunnel_", design.n, int(x_esn.numel()), int(w_hat.numel()),
                    etd_factors(design.scenario, rate_hz))
