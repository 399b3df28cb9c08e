"""symfunnel: symbolic design and verification of funnel controllers for robot manipulators.

The Python API (what the CLI is a thin layer over; `symfunnel.api` holds it)::

    import symfunnel as sf
    sc = sf.load_scenario("paper")          # or a path to a TOML file
    d = sf.derive(sc)                       # the one symbolic design (CasADi SX)
    vals = sf.evaluate(d, {"t": 0.5, "q": [0.15, 0.14], "dq": [-0.15, 0.5]})   # a point inside both funnels
    checks = sf.audit(sc, d)                # one function per command: simulate, verify, codegen, report, sweep
    v = sf.verify("paper", t_final=5.0)     # results have to_json(); verify(..., strict=True) raises CheckFailed
    r = sf.rate("paper", margin=0.05)       # the deployed controller's minimum sample rate (certify=True: proven)

Every CLI option is a keyword of the same name (`--t-final` -> `t_final`; `--rate` -> `rate_hz`, `rate` too); bad
input raises `InputError` naming the keyword, a failed gate `CheckFailed`, a run that cannot go on `SimulationError`.
"""

from .core.errors import CheckFailed, InputError, SimulationError, SymfunnelError
from .core.version import __version__

#: the commands, as plain functions of `symfunnel.api` (imported on first use: `import symfunnel` stays cheap)
_API = ("load_scenario", "derive", "evaluate", "audit", "simulate", "verify", "certify", "codegen", "rate", "report",
        "sweep", "tune", "init", "run", "Run")

__all__ = ["InputError", "CheckFailed", "SimulationError", "SymfunnelError", "__version__", *_API]


def __getattr__(name):
    if name in _API:
        from . import api
        return getattr(api, name)
    raise AttributeError(f"module 'symfunnel' has no attribute {name!r}")


def __dir__():
    """The API (`__all__`), not the subpackages (`core`, `design`, ...) that importing it loads as attributes."""
    return sorted(__all__)
