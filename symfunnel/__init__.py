"""symfunnel: symbolic design and verification of funnel controllers for robot manipulators.

The Python API (what the CLI is a thin layer over)::

    import symfunnel as sf
    sc = sf.load_scenario("paper")          # or a path to a TOML file
    d = sf.derive(sc)                       # the one symbolic design (CasADi SX)
    vals = sf.evaluate(d, {"t": 0.1, "q": [0.0, 0.1], "dq": [0.0, 0.0]})
    checks = sf.audit(sc, d)
"""

from .errors import CheckFailed, InputError, SymfunnelError

__version__ = "0.1.0"

__all__ = ["InputError", "CheckFailed", "SymfunnelError", "load_scenario", "derive", "evaluate", "audit", "tune"]


def __getattr__(name):  # lazy: keep `import symfunnel` cheap for the CLI's cold start
    if name == "load_scenario":
        from .scenario import load_scenario
        return load_scenario
    if name == "derive":
        from .design import derive
        return derive
    if name == "evaluate":
        from .design import evaluate
        return evaluate
    if name == "audit":
        from .checks.audit import audit
        return audit
    if name == "tune":
        from .tuning import tune
        return tune
    raise AttributeError(name)
