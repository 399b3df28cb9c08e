"""`symfunnel.simulate`: the simulation stage's public names (implemented in `symfunnel.simulation`), and, called,
the API function `symfunnel.simulate(...)`."""

from __future__ import annotations

from .simulation import Compiled, SimResult, compile_closed_loop, convergence_study, simulate

__all__ = ["Compiled", "SimResult", "compile_closed_loop", "convergence_study", "simulate"]

from ._callable import make_callable  # noqa: E402 - after the module body: calling this module is the API function

make_callable(__name__, "simulate")
