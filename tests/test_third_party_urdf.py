"""A robot description written by someone else (Franka Emika Panda, Apache-2.0) against Pinocchio.

The Panda URDF of example-robot-data has 7 revolute arm joints, two prismatic finger joints (one with a `mimic`
tag), fixed joints, rotated inertial frames and mesh references: none of it written with symfunnel in mind.
"""

from __future__ import annotations

import pathlib

import numpy as np

from symfunnel.model.urdf import build_urdf, movable_joint_names, parse_urdf

from .test_models_links import PinocchioRef, check_skew_and_christoffel, compare_with_pinocchio

PANDA = pathlib.Path(__file__).parent / "data" / "third_party" / "panda.urdf"


def test_panda_matches_pinocchio():
    m = build_urdf({"type": "urdf", "path": PANDA.name}, file="panda.toml", base_dir=PANDA.parent)
    assert m.n == 9
    assert m.joint_types.count("prismatic") == 2
    ref = PinocchioRef(PANDA, movable_joint_names(parse_urdf(PANDA)), [0.0, 0.0, -9.81])
    compare_with_pinocchio(m, ref, states=100, seed=4)
    check_skew_and_christoffel(m, states=30, against_base=False)


def test_panda_with_other_gravity():
    g = [1.0, -2.0, -9.0]
    m = build_urdf({"type": "urdf", "path": PANDA.name, "gravity": g}, file="panda.toml", base_dir=PANDA.parent)
    ref = PinocchioRef(PANDA, movable_joint_names(parse_urdf(PANDA)), g)
    compare_with_pinocchio(m, ref, states=50, seed=5)
    assert np.all(np.isfinite(m.joint_lower[:7]))
