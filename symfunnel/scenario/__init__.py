"""Scenario files (TOML) loaded into validated, typed objects; every error names the file, the key and what was
expected.

By job: `document` (what a validated scenario is: the dataclasses), `load` (a name or path to a `Scenario`),
`sections` (one parser per section of the physical and numerical set-up), `claims` (what the scenario declares
about its source: printed claims, expected outcomes, deviations), and the specs of `[implementation]`, `[tune]` and
`[[uncertainty]]`/`[sweep]`.
"""

from __future__ import annotations

from .claims import INEQUALITY_NAMES, claim_names
from .document import (
                       AuditSpec,
                       Claim,
                       DesignSpec,
                       Deviation,
                       ESNSpec,
                       Expectation,
                       PlantSpec,
                       Scenario,
                       SimulationSpec,
)
from .load import (
                       BUILTIN,
                       DATA_DIR,
                       TOP_KEYS,
                       from_dict,
                       is_builtin,
                       load_scenario,
                       resolve,
)
from .sections import ESN_INPUTS, build_model

__all__ = ["Scenario", "Claim", "Expectation", "PlantSpec", "ESNSpec", "DesignSpec", "SimulationSpec", "AuditSpec",
           "Deviation", "DATA_DIR", "BUILTIN", "TOP_KEYS", "resolve", "is_builtin", "load_scenario", "from_dict",
           "build_model", "claim_names", "INEQUALITY_NAMES", "ESN_INPUTS"]
