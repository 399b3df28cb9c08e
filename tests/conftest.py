"""Shared fixtures: the paper scenario and its design, and a helper that writes scenario variants."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Compiled artefacts of a test run go to a private cache, never to the user's.
os.environ.setdefault("SYMFUNNEL_CACHE", str(Path(__file__).parent.parent / ".pytest_cache" / "symfunnel"))

REPO = Path(__file__).resolve().parent.parent
PAPER = REPO / "derivations" / "paper_2dof.toml"


@pytest.fixture(scope="session")
def paper():
    """The built-in paper scenario."""
    from symfunnel.scenario import load_scenario
    return load_scenario("paper")


@pytest.fixture(scope="session")
def paper_design(paper):
    """The paper scenario's design (derived once per session)."""
    from symfunnel.design import derive
    return derive(paper)


MINIMAL_2LINK = """
[model]
type = "matrices"
coordinates = ["q1", "q2"]
[model.parameters]
a = 3.0
b = 1.0
c = 0.8
[model.matrices]
M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["b + c*cos(q2)", "b"]]
{C}
[reference]
q = ["0.3*sin(t)", "0.2*cos(t)"]
[initial]
q = [0.0, 0.2]
dq = [0.3, 0.0]
"""


@pytest.fixture
def write_scenario(tmp_path):
    """Write a scenario text to a file in tmp_path and return its path."""
    def write(text: str, name: str = "s.toml") -> Path:
        p = tmp_path / name
        p.write_text(text, encoding="utf-8")
        return p
    return write
