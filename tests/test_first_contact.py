"""First contact: python -m symfunnel, LICENSE and CITATION.cff, a repository that stands alone, a compilable
derive --latex, and simulation failures that say why and what to change."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import pytest

from tests.conftest import REPO

TITLE = "Adaptive Predefined Performance Neural Control for Robotic Manipulators with Unknown Dead Zone"


def test_python_dash_m_symfunnel(tmp_path):
    r = subprocess.run([sys.executable, "-m", "symfunnel", "--version"], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("symfunnel ")
    r = subprocess.run([sys.executable, "-m", "symfunnel", "derive", "nope"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.startswith("symfunnel: error: nope")


def test_license_matches_pyproject_and_citation_cites_the_paper():
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert meta["license"]["text"] == "MIT"
    assert (REPO / "LICENSE").read_text().startswith("MIT License")
    cff = (REPO / "CITATION.cff").read_text()
    assert re.search(r"^cff-version: 1\.2\.0$", cff, re.M) and re.search(r"^license: MIT$", cff, re.M)
    assert re.search(rf"^version: {re.escape(meta['version'])}$", cff, re.M)
    assert f'title: "{TITLE}"' in cff and "type: article" in cff
    assert TITLE in (REPO / "README.md").read_text()


def test_ci_runs_the_readme_test_command():
    """CI runs README's test command character for character, and the test extra holds the plugin its options need."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    block = re.search(r"Tests \(install with the test extra.*?```sh\n(.*?)\n```", readme, re.S)
    assert block, "README shows its test command"
    ci = [ln for ln in (REPO / ".ci" / "run").read_text(encoding="utf-8").splitlines() if "pytest" in ln
          and not ln.lstrip().startswith("#")]
    assert ci == [block.group(1)]
    try:
        import tomllib
    except ModuleNotFoundError:                 # Python 3.10
        import tomli as tomllib
    meta = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    if re.search(r"(^|\s)-n\s", meta["tool"]["pytest"]["ini_options"].get("addopts", "")):
        assert any(d.startswith("pytest-xdist") for d in meta["project"]["optional-dependencies"]["test"])


def _user_files():
    for pattern in ("README.md", "docs/*.md", "derivations/*.toml", "symfunnel/data/*.toml", "CITATION.cff"):
        yield from REPO.glob(pattern)


def test_repository_stands_alone():
    """No user-facing file points at files a user does not have."""
    bad = re.compile(r"\.\./shared|/work/shared|design\.md|paper\.md")
    hits = [f"{p.relative_to(REPO)}:{i}" for p in _user_files()
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if bad.search(line)]
    assert hits == []


def _tex_structure(tex: str) -> None:
    body = [ln for ln in tex.splitlines() if not ln.startswith("%")]
    assert body[0].startswith(r"\documentclass")
    assert tex.count(r"\begin{document}") == 1 and tex.rstrip().endswith(r"\end{document}")
    envs = re.findall(r"\\(begin|end)\{([^}]*)\}", tex)
    stack = []
    for kind, name in envs:
        if kind == "begin":
            stack.append(name)
        else:
            assert stack and stack.pop() == name, name
    assert stack == []
    depth = 0
    for c in re.sub(r"\\[{}]", "", tex):
        depth += {"{": 1, "}": -1}.get(c, 0)
        assert depth >= 0
    assert depth == 0
    # every formula "name = ..." sits inside an equation* environment, every inline $ is paired
    inside = False
    for ln in body:
        if ln == r"\begin{equation*}":
            inside = True
        elif ln == r"\end{equation*}":
            inside = False
        elif re.match(r"^\\?[A-Za-z_{}\\ ]+ = ", ln):
            assert inside, ln
        assert ln.replace(r"\$", "").count("$") % 2 == 0, ln


def test_derive_latex_is_a_compilable_document(tmp_path):
    from symfunnel.cli import main
    src = (REPO / "derivations" / "paper_2dof.toml").read_text().replace('name = "paper"', 'name = "a_b.c-d"')
    s = tmp_path / "s.toml"
    s.write_text(src)
    out = tmp_path / "signals.tex"
    assert main(["derive", str(s), "--latex", str(out)]) == 0
    tex = out.read_text()
    _tex_structure(tex)
    assert r"\texttt{a\_b.c-d}" in tex and r"\alpha_2 = " in tex and "\\begin{equation*}\n\\alpha_2 = " in tex
    exe = shutil.which("pdflatex") or shutil.which("latex")
    if exe is None:
        pytest.skip("pdflatex/latex is not installed: the document's structure was checked, not compiled")
    r = subprocess.run([exe, "-interaction=nonstopmode", "-halt-on-error", out.name], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:]
    assert (tmp_path / ("signals.pdf" if "pdf" in exe else "signals.dvi")).stat().st_size > 1000


def test_convergence_rate_is_printed(capsys):
    from symfunnel.commands.simulate import _table
    s = {"scenario": "x", "status": "ok", "message": "", "t_end": 1.0, "t_final": 1.0, "points": 2,
         "min_margin_e1": [0.5], "min_margin_e2": [0.5], "max_abs_e1": [0.1], "max_abs_tau": [1.0],
         "max_abs_tau_applied": [1.0], "rms_esn_error": 0.1, "rms_f_true": 1.0, "integrator": "cvodes",
         "code": "compiled", "smoothing_width": 1e-3, "steps": 1, "rhs_evaluations": 1,
         "jacobian_evaluations": 1, "events": 0, "event_counts": {}, "wall_time": 1.0, "compile_time": 0.1,
         "realtime_factor": 1.0,
         "convergence": {"reference_width": 1e-4, "observed_rates": [0.98],
                         "runs": [{"width": 1e-2, "max_abs_q_diff_vs_smallest": 1e-3},
                                  {"width": 1e-3, "max_abs_q_diff_vs_smallest": 1.05e-4}]}}
    _table(s)
    out = capsys.readouterr().out
    assert re.search(r"observed rate\s+0\.98 \(1 expected", out)
    s["convergence"]["observed_rates"] = []
    _table(s)
    assert "n/a: the differences are zero" in capsys.readouterr().out


def test_rk_failure_gives_cause_and_a_hint_that_works(paper, paper_design):
    from symfunnel.simulation import simulate
    r = simulate(paper, paper_design, t_final=2.0, integrator="rk")
    assert r.status == "failed"
    assert "cause: " in r.message and "hint: " in r.message and "rk_substeps (now 10)" in r.message
    sc = paper.replace(simulation__rk_substeps=100)            # what the hint says
    from symfunnel.design import derive
    assert simulate(sc, derive(sc), t_final=2.0, integrator="rk").status == "ok"


@pytest.mark.slow
def test_zero_width_failure_names_the_integrator_error_and_the_width(paper, paper_design):
    from symfunnel.simulation import simulate
    with pytest.warns(RuntimeWarning, match="smoothing_width = 0"):
        r = simulate(paper, paper_design, t_final=2.0, width=0.0)
    if r.status == "ok":
        pytest.skip("this CVODES build crossed the kinks")
    assert "CV_" in r.message and "--width 1e-3" in r.message


def test_failure_hint_per_setting(paper):
    from symfunnel.simulation.hints import error_line, failure_hint
    casadi_text = ('Error in Function::call for \'sim_1\' [CvodesInterface] at .../function.cpp:514:\n'
                   '.../casadi/interfaces/sundials/cvodes_interface.cpp:403: CVode returned "CV_TOO_MUCH_WORK". '
                   'Consult CVODES documentation.')
    assert error_line(casadi_text) == 'CVode returned "CV_TOO_MUCH_WORK"'
    sim = paper.simulation
    assert "--width 1e-3" in failure_hint("cvodes", 0.0, sim, 0.01, None)
    assert "rtol" in failure_hint("cvodes", 1e-3, sim, 0.01, "x")
    assert "Radau" in failure_hint("collocation", 1e-3, sim, 0.01, None)
    assert f"{0.01 / sim.rk_substeps:.3g} s" in failure_hint("rk", 1e-3, sim, 0.01, None)
