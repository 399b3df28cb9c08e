"""The design layer: a scenario's controller derived once as CasADi SX by its design variant.

`derive(scenario)` picks the variant the scenario declares (`[design]`; the paper's two-step funnel backstepping by
default) and returns a `Design`; `derive(scenario, mutant=ID)` the same design with one seeded error (for
`verify --mutants`).
"""

from __future__ import annotations

from ..family.variants import VARIANTS
from .backstepping import MUTANTS, Backstepping, Mutant
from .core import JOINT_INPUTS, Design, count_ops, evaluate, funnel_level, point_inputs

__all__ = ["Design", "derive", "evaluate", "point_inputs", "funnel_level", "count_ops", "variant_of",
           "JOINT_INPUTS", "VARIANTS", "VARIANT_CLASSES", "MUTANTS", "Mutant"]


#: the class of each name in the variant registry (`family.variants.VARIANTS`; a test checks they match)
VARIANT_CLASSES = {"backstepping": Backstepping}


def variant_of(scenario):
    """The design variant object a scenario declares."""
    VARIANTS.get(scenario.design.variant, file=scenario.file, key="design.variant")
    return VARIANT_CLASSES[scenario.design.variant](scenario)


def derive(scenario, *, mutant: str | None = None, values: dict | None = None) -> Design:
    """Build every signal of the scenario's design, once, as SX (the single source of truth); `values` replaces
    tunable design parameters by expressions (see `Backstepping.derive`)."""
    return variant_of(scenario).derive(mutant, values=values)
