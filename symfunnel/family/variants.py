"""The registry of design variants: the names a scenario may declare in `[design] variant`, so that the scenario
layer validates them without importing the design; the design layer maps each name to its class
(`symfunnel.design.VARIANT_CLASSES`)."""

from __future__ import annotations

from ..core.registry import Registry

VARIANTS = Registry("design variant", "design.variant")
VARIANTS.add("backstepping", "two-step funnel backstepping with an adaptive approximator (the paper's design)",
             "symfunnel.design.backstepping.Backstepping")
