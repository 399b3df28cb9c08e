"""The deployed section's additions: the FMU of the deployed controller listed beside the C files (built by the
emitter at the section's rate, cached by core.ccompile, never embedded)."""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET

from .text import fmt

__all__ = ["fmu_entry"]


def fmu_entry(run, rate_hz: float | None, fmi: str = "2") -> dict:
    """The FMU `codegen --lang fmu --fmi FMI --rate RATE` would write, described for the report: file name, FMI
    version, size, model identifier, variable count, GUID and a one-line FMPy snippet ({"error": why} when no rate
    or the build fails). The binary is built (cached by its sources) but not embedded."""
    if rate_hz is None:
        return {"error": "no sampled run, so no rate to build the FMU at"}
    from ..emit.fmu import build_fmu, fmu_sources
    t0 = time.perf_counter()
    try:
        src = fmu_sources(run.design, rate_hz, fmi=fmi)
        data = build_fmu(src)
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"error": f"{type(exc).__name__}: {exc}"}
    root = ET.fromstring(src.model_description)
    file = f"{src.identifier}.fmu"
    return {"file": file, "fmi_version": root.get("fmiVersion"), "bytes": len(data), "guid": src.guid,
            "model_identifier": src.identifier, "variables": len(root.find("ModelVariables")),
            "rate": fmt(src.rate_hz), "seconds": time.perf_counter() - t0,
            "command": f"symfunnel codegen {_scenario_arg(run.scenario)} --lang fmu --fmi {fmi} --rate {src.rate_hz:g} "
                       f"--out DIR",
            "snippet": f'import fmpy; res = fmpy.simulate_fmu("{file}", stop_time={10.0 / src.rate_hz:g}, '
                       f'output=["tau[1]", "status"])'}


def _scenario_arg(scenario) -> str:
    """How the command line names the scenario: a built-in's name, else its file."""
    from ..scenario import is_builtin
    return scenario.name if is_builtin(scenario.path) else str(scenario.path)
