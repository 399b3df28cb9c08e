"""The registered parts a scenario selects by name: funnel shapes, error transformations, approximators (the ESN
among them), design variants and integrators.

Each kind has one registry (`FUNNEL_SHAPES`, `TRANSFORMS`, `APPROXIMATORS`); adding a part is adding one registered
class to the kind's module. These modules sit below the scenario (which validates against the registries) and the
design (which builds from them): they import only casadi, numpy and the ground floor.
"""
