"""Robot models: M(q), C(q, dq), G(q) as SX, from typed matrices or from link data (planar, DH, URDF).

`MODEL_TYPES` is the registry of `[model] type`: each entry builds a model from the validated table.
"""

from __future__ import annotations

from ..core.registry import Registry

MODEL_TYPES = Registry("model type", "model.type")


@MODEL_TYPES.register("matrices", "M, C (optional: Christoffel symbols of M) and G typed as expressions")
def _matrices(table, *, file, base_dir):
    from .matrices import build_matrices
    return build_matrices(table, file=file)


@MODEL_TYPES.register("planar", "a planar serial chain of links (lengths, masses, centres of mass, inertias)")
def _planar(table, *, file, base_dir):
    from .links import build_planar
    return build_planar(table, file=file)


@MODEL_TYPES.register("dh", "a Denavit-Hartenberg table (standard or modified) with link inertias")
def _dh(table, *, file, base_dir):
    from .links import build_dh
    return build_dh(table, file=file)


@MODEL_TYPES.register("urdf", "a URDF file: its movable joints in depth-first order, inertias from the file")
def _urdf(table, *, file, base_dir):
    from .urdf import build_urdf
    return build_urdf(table, file=file, base_dir=base_dir)
