"""A typed-in inertia matrix is refused at load (exit 2, naming model.matrices.M) unless it is symmetric and
positive definite at the initial state and on samples of the joint range."""

from __future__ import annotations

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.core.errors import InputError
from symfunnel.scenario import load_scenario
from tests.conftest import MINIMAL_2LINK

GOOD = 'M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["b + c*cos(q2)", "b"]]'


def variant(write_scenario, M: str, extra: str = ""):
    text = MINIMAL_2LINK.format(C="").replace(GOOD, M) + extra
    assert M in text
    return write_scenario(text)


def test_the_good_model_and_an_equal_rewriting_load(write_scenario):
    load_scenario(variant(write_scenario, GOOD))
    # M[1][0] written differently: CasADi sees two expressions, sympy proves them equal
    load_scenario(variant(write_scenario, 'M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["c*cos(q2) + b", "b"]]'))
    load_scenario(variant(write_scenario, 'M = [["2", "cos(q1)^2 + sin(q1)^2"], ["1", "2"]]'))


@pytest.mark.parametrize("M, needle", [
    ('M = [["-(a + 2*c*cos(q2))", "-(b + c*cos(q2))"], ["-(b + c*cos(q2))", "-b"]]',
     "not positive definite at the initial state"),
    ('M = [["1", "2"], ["2", "1"]]', "eigenvalues [-1, 3]"),
    ('M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["b + 2*c*cos(q2)", "b"]]', "not symmetric"),
    ('M = [["1", "0"], ["0", "cos(q1)"]]', "at a sampled configuration"),     # PD at q0 only
    ('M = [["a + 2*c*cos(q2)", "b + c*cos(q2)"], ["b + c*cos(q2) + 1e-14", "b"]]', "sympy"),  # below round-off
])
def test_bad_inertia_matrices_exit_2(write_scenario, capsys, M, needle):
    p = variant(write_scenario, M)
    with pytest.raises(InputError) as ei:
        load_scenario(p)
    assert ei.value.key == "model.matrices.M" and needle in str(ei.value), str(ei.value)
    assert main(["simulate", str(p), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.matrices.M" in err[0]


def test_the_eigenvalues_reported_are_the_matrix_eigenvalues(write_scenario):
    M = np.array([[1.0, 2.5], [2.5, 0.5]])
    p = variant(write_scenario, 'M = [["1", "2.5"], ["2.5", "0.5"]]')
    lam = np.linalg.eigvalsh(M)
    with pytest.raises(InputError, match=f"eigenvalues \\[{lam[0]:.4g}, {lam[1]:.4g}\\]"):
        load_scenario(p)


def test_a_narrower_joint_range_admits_a_locally_valid_model(write_scenario):
    p = variant(write_scenario, 'M = [["1", "0"], ["0", "cos(q1)"]]', '\n[audit]\njoint_range = [-1.0, 1.0]\n')
    assert load_scenario(p).model.kind == "matrices"
