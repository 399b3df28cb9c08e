"""symfunnel: symbolic design and verification of funnel controllers for robot manipulators.

The Python API (what the CLI is a thin layer over)::

    import symfunnel as sf
    sc = sf.load_scenario("paper")          # or a path to a TOML file
    d = sf.derive(sc)                       # the one symbolic design (CasADi SX)
    vals = sf.evaluate(d, {"t": 0.5, "q": [0.15, 0.14], "dq": [-0.15, 0.5]})   # a point inside both funnels
    checks = sf.audit(sc, d)                # one function per command: simulate, verify, codegen, report, sweep
    v = sf.verify("paper", t_final=5.0)     # results have to_json(); verify(..., strict=True) raises CheckFailed
"""

from .core.errors import CheckFailed, InputError, SymfunnelError

__version__ = "0.1.0"

__all__ = ["InputError", "CheckFailed", "SymfunnelError", "load_scenario", "derive", "evaluate", "audit", "simulate",
           "verify", "codegen", "report", "sweep", "tune", "run", "Run"]

_LAZY = {"load_scenario": "scenario", "derive": "design", "evaluate": "design", "Run": "pipeline",
         "audit": "api", "verify": "api", "sweep": "api", "run": "api", "tune": "tuning"}
#: command names that are also module names: the (callable) module is the API function, see _callable.py
_CALLABLE_MODULES = ("simulate", "codegen", "report")


def __getattr__(name):  # lazy: keep `import symfunnel` cheap for the CLI's cold start
    import importlib
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    if name in _CALLABLE_MODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(name)
