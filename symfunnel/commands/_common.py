"""Helpers every command module shares (progress, JSON output, scenario loading); imports nothing of the CLI."""

from __future__ import annotations

import json
import time


def _progress(quiet: bool):
    """A progress printer on stderr (silent with --quiet or when stderr is not a terminal and CI is unset)."""
    if quiet:
        return lambda s: None
    t0 = time.perf_counter()

    def say(s: str) -> None:
        from ..core.lifecycle import user_stderr
        print(f"[{time.perf_counter() - t0:6.1f}s] {s}", file=user_stderr(), flush=True)
    return say


def _dump(obj) -> str:
    from ..core.io import json_safe
    return json.dumps(json_safe(obj), indent=2, allow_nan=False)


from ..core.outputs import scenario_inputs  # noqa: F401 - the commands' name for it

#: the step of reading the scenario (and importing what reads it), named in the message of a limit reached there
LOADING = "loading the scenario"


def loading():
    """The step LOADING, around a command's imports (casadi, numpy and the stages: a second under load) and its
    reading of the scenario, so that a limit reached there names it, not "working"."""
    from ..core import deadline
    return deadline.step(LOADING)


def _load(args):
    """The command's scenario, read under the step LOADING."""
    with loading():
        from ..scenario import load_scenario
        return load_scenario(args.scenario)


def add_force_option(sp) -> None:
    """`--force`: replace an existing output file that symfunnel did not write (never an input)."""
    sp.add_argument("--force", action="store_true", help="replace an existing output that symfunnel did not write "
                    "(an input is never replaced)")


def add_plant_option(sp) -> None:
    """`--plant ENGINE`: the plant of the deployed controller's sampled loop (overrides `[plant] engine`)."""
    from ..plant.engines import ENGINES
    sp.add_argument("--plant", metavar="ENGINE", help="plant of the sampled-data loop: " + ", ".join(ENGINES.names())
                    + " (default: the scenario's [plant] engine, normally symfunnel)")


def _engine(args, scenario) -> str:
    """The engine of this command (--plant or the scenario's), validated before any work (exit 2 otherwise)."""
    from ..plant.engines import resolve_engine
    return resolve_engine(scenario, getattr(args, "plant", None))
