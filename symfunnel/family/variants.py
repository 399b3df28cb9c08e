"""The registry of design variants: names the scenario may declare in `[design] variant`, each resolved lazily to the
class in `symfunnel.design` that derives it (so the scenario layer validates names without importing the design)."""

from __future__ import annotations

import importlib

from ..core.registry import Registry

VARIANTS = Registry("design variant", "design.variant")
VARIANTS.add("backstepping", "two-step funnel backstepping with an adaptive approximator (the paper's design)",
             "symfunnel.design.backstepping:Backstepping")


def resolve(name: str, *, file: str | None = None):
    """The class of a registered variant."""
    module, attr = VARIANTS.get(name, file=file, key="design.variant").split(":")
    return getattr(importlib.import_module(module), attr)
