"""The checker mutation tool itself (symfunnel.bench.checker_mutants), on a tiny repository: a mutant of a check
that one test kills, one that survives every covering test, an equivalent one, and edits that no longer apply."""

from __future__ import annotations

import json

import pytest

from symfunnel.bench import AREAS
from symfunnel.bench.checker_mutants import (CLASSES, MUTANTS, CheckerMutant, MutantError, apply, mutated_lines,
                                             repo_root, run)

CHECK = '''SCALE = 1.0


def inside(e, F):
    """The funnel is open: |e| = F is outside."""
    return abs(e) < SCALE * F


def describe(e, F):
    return "inside" if inside(e, F) else "outside"
'''

TESTS = '''from pkg.check import describe, inside


def test_inside_pins_the_boundary():
    assert inside(0.5, 1.0) and not inside(1.0, 1.0)


def test_describe_runs():
    assert describe(0.5, 1.0)
'''


def _repo(tmp_path):
    root = tmp_path / "repo"
    (root / "pkg").mkdir(parents=True)
    (root / "tests").mkdir()
    (root / "pkg" / "__init__.py").write_text("")
    (root / "pkg" / "check.py").write_text(CHECK)
    (root / "tests" / "__init__.py").write_text("")
    (root / "tests" / "test_check.py").write_text(TESTS)
    return root


def test_a_kill_under_xdist_is_named_by_its_test(tmp_path):
    """With -n in the repository's addopts, pytest -x ends a run with a failure as "interrupted" (exit 2): the
    kill is still the failing test's (from the junit file), not "the mutant breaks collection"."""
    root = _repo(tmp_path)
    (root / "pyproject.toml").write_text('[tool.pytest.ini_options]\naddopts = "-n 2"\n')
    mutants = (CheckerMutant("non_strict", "pkg/check.py", "abs(e) < SCALE * F", "abs(e) <= SCALE * F",
                             "comparison", "|e| = F inside"),)
    out = run(root=root, state=tmp_path / "state", mutants=mutants, package="pkg", marker=None, workers=1)
    row = out["rows"][0]
    assert row["status"] == "killed" and row["note"] == ""
    assert row["by"] == "tests/test_check.py::test_inside_pins_the_boundary"


def test_one_killed_one_survived_one_equivalent_and_resumed(tmp_path):
    root = _repo(tmp_path)
    mutants = (
        CheckerMutant("non_strict", "pkg/check.py", "abs(e) < SCALE * F", "abs(e) <= SCALE * F", "comparison",
                      "|e| = F inside"),
        CheckerMutant("scale", "pkg/check.py", "SCALE = 1.0", "SCALE = 1.001", "constant",
                      "a module-level constant: runs at import, selects the tests of its module"),
        CheckerMutant("wording", "pkg/check.py", '"inside" if', '"in" if', "constant", "another word"),
        CheckerMutant("docstring", "pkg/check.py", "The funnel is open", "The funnel is closed", "constant",
                      "a docstring", equivalent="a docstring is not executed by any check"),
    )
    lines = []
    out = run(root=root, state=tmp_path / "state", mutants=mutants, package="pkg", marker=None, workers=1,
              progress=lines.append)
    rows = {r["id"]: r for r in out["rows"]}
    assert rows["non_strict"]["status"] == "killed"
    assert rows["non_strict"]["by"] == "tests/test_check.py::test_inside_pins_the_boundary"
    assert rows["non_strict"]["tests"] == 2            # both tests cover the line (describe calls inside)
    assert rows["wording"]["status"] == "survived" and rows["wording"]["tests"] == 1
    assert rows["docstring"]["status"] == "equivalent"
    assert rows["scale"]["status"] == "killed" and rows["scale"]["tests"] == 2
    assert out["score"] == 2 / 3 and out["killed"] == 2 and out["survived"] == ["wording"]
    assert out["equivalent"] == [{"id": "docstring", "argument": "a docstring is not executed by any check"}]
    assert any("baseline" in s for s in lines)
    # a second run keeps every outcome (nothing changed) and runs no baseline again
    again = []
    out2 = run(root=root, state=tmp_path / "state", mutants=mutants, package="pkg", marker=None, workers=1,
               progress=again.append)
    assert [r["status"] for r in out2["rows"]] == [r["status"] for r in out["rows"]]
    assert not any("baseline" in s for s in again) and sum("kept" in s for s in again) == 3
    # a new test that pins the wording: only its file is measured again, and it kills the survivor
    (root / "tests" / "test_words.py").write_text("from pkg.check import describe\n\n\ndef test_word():\n"
                                                  "    assert describe(0.5, 1.0) == 'inside'\n")
    third = []
    out3 = run(root=root, state=tmp_path / "state", mutants=mutants, package="pkg", marker=None, workers=1,
               progress=third.append)
    assert any("baseline run under coverage of 1 test files" in s for s in third)
    assert {r["id"]: r["status"] for r in out3["rows"]}["wording"] == "killed" and out3["score"] == 1.0
    # only a subset
    assert [r["id"] for r in run(root=root, state=tmp_path / "state", mutants=mutants, package="pkg", marker=None,
                                 workers=1, only=["wording"])["rows"]] == ["wording"]


def test_an_edit_that_no_longer_matches_exactly_once_fails_loudly(tmp_path):
    root = _repo(tmp_path)
    gone = CheckerMutant("gone", "pkg/check.py", "abs(e) > SCALE * F", "abs(e) >= F", "comparison", "not in the file")
    twice = CheckerMutant("twice", "pkg/check.py", "inside", "in", "constant", "occurs several times")
    for m in (gone, twice):
        with pytest.raises(MutantError, match="exactly once"):
            run(root=root, state=tmp_path / "state", mutants=(m,), package="pkg", marker=None, workers=1)
    with pytest.raises(MutantError, match="unknown mutant"):
        run(root=root, state=tmp_path / "state", mutants=(gone,), package="pkg", only=["nope"], workers=1)


def test_the_projects_mutants_apply_and_cover_every_class():
    root = repo_root()
    assert len(MUTANTS) >= 30 and len({m.id for m in MUTANTS}) == len(MUTANTS)
    assert {m.kind for m in MUTANTS} == set(CLASSES)
    for m in MUTANTS:
        text = (root / m.file).read_text(encoding="utf-8")
        assert apply(text, m) != text, m.id
        assert mutated_lines(text, m), m.id
        assert not m.equivalent or len(m.equivalent) > 80, m.id      # an argument, not a label
    files = {m.file for m in MUTANTS}
    for part in ("checks/verify.py", "checks/theory.py", "checks/audit.py", "checks/lyapunov.py",
                 "design/backstepping.py", "deployed/loop.py", "emit/step.py", "deployed/rate.py",
                 "campaigns/campaign.py"):
        assert f"symfunnel/{part}" in files, part


def test_the_tool_is_no_bench_area_and_lists_its_mutants(capsys):
    from symfunnel.bench.checker_mutants import main
    assert "checker_mutants" not in AREAS and "verify" in AREAS
    assert main(["--list"]) == 0
    out = capsys.readouterr().out
    assert len(out.strip().splitlines()) == len(MUTANTS) and "[equivalent]" in out
    json.dumps([m.__dict__ for m in MUTANTS])
