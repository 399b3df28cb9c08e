"""`symfunnel bench`: performance figures, each measured side by side with a baseline in the same run.

Each area module (`symfunnel.bench.<area>`) exposes `run(progress) -> list[dict]` returning results of the form
{"id", "value", "unit", "baseline", "baseline_value", "ratio"} (`bench --json`); ratio = baseline time /
symfunnel time, higher is better.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from ._result import result  # noqa: F401 - the areas' result form, also importable from here

#: modules of this package that are tools an area uses, not areas (checker_mutants: `verify`'s checker mutation score)
TOOLS = ("checker_mutants",)
# Every other module of this package is an area: adding a benchmark area is adding one module with `run(progress)`.
AREAS = tuple(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)])
              if not m.name.startswith("_") and m.name not in TOOLS)


def run(areas=None, progress=None) -> list[dict]:
    """Run the benchmarks of the selected areas (default: all that are available)."""
    say = progress or (lambda s: None)
    out = []
    for area in areas or AREAS:
        try:
            mod = importlib.import_module(f"symfunnel.bench.{area}")
        except ModuleNotFoundError as exc:
            if exc.name == f"symfunnel.bench.{area}":
                continue
            raise
        say(f"bench {area}")
        out.extend(mod.run(say))
    return out
