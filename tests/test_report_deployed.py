"""The report's deployed section (issues 41 and 40): the FMU line beside the rate search, checked against the FMU
`symfunnel codegen --lang fmu` writes (its modelDescription.xml read back with zipfile and ElementTree); the rate
bracket (f_sim, f_proven, f_theory) checked against `symfunnel rate --certify --json`; `report --no-deployed` leaving
them out. The report is written once on tests/data/certify_none.toml with a 2 s horizon
and neither code generation nor mutants, its rate bisection ended at its first proven rate (BRACKET_REL_TOL: 30 s
wall with a cold compile cache on a loaded VM, against 46 s for the whole bisection)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import pytest

from tests.conftest import text_once

DATA = Path(__file__).parent / "data"
T_FINAL = 2.0
#: the report's rate bisection on certify_none ends when f_proven / (the highest rate not proven) <= 1 + this
#: (the product's RATE_REL_TOL is 0.1): up to a factor 4.5, so the search ends at its first proven rate, 4x the
#: last unproven one
BRACKET_REL_TOL = 3.5


def _report(scenario: Path, out: Path, **kw) -> str:
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting import build_report
    from symfunnel.scenario import load_scenario
    run = Run(load_scenario(scenario), RunOptions(t_final=T_FINAL, samples=200))
    return build_report(run, out, codegen=False, mutants=False, **kw).read_text(encoding="utf-8")


def _tree(text: str):
    import html5lib
    return html5lib.parse(text, treebuilder="etree", namespaceHTMLElements=False)


def _by_id(tree, ident: str):
    return next((el for el in tree.iter() if el.get("id") == ident), None)


def _classes(el) -> dict:
    """{class: text} of the element's marked children (the FMU line's fields)."""
    return {c.get("class"): "".join(c.itertext()) for c in el.iter() if c.get("class")}


@pytest.fixture(scope="module")
def certify_none_report(tmp_path_factory) -> str:
    """The report on certify_none, written once per session whichever worker runs this module's tests first."""
    # the bracket's wall-clock budget raised from the report's 10 s: on a loaded CI machine 10 s may end it undecided,
    # which the report says honestly but this test (which checks the proven case) cannot use; and its bisection
    # stopped once the proven rate is within BRACKET_REL_TOL of the unproven one: the same deterministic search as
    # the command's, cut after its first proven rate (3 of its 7 attempts, 33k of its 110k boxes), so both ends of
    # the report's bracket are rates the command tried, with the same outcome
    def build() -> str:
        with pytest.MonkeyPatch.context() as mp:
            import symfunnel.certificates.sampled_rate as SR
            import symfunnel.reporting.deployed as D
            mp.setattr(D, "BRACKET_WALL_LIMIT", 120.0)
            mp.setattr(SR, "RATE_REL_TOL", BRACKET_REL_TOL)
            return _report(DATA / "certify_none.toml", tmp_path_factory.mktemp("report") / "certify_none.html")
    return text_once(tmp_path_factory, f"report certify_none t_final={T_FINAL} samples=200 bracket_wall=120 "
                                       f"rel_tol={BRACKET_REL_TOL}", build)


def test_fmu_line_describes_the_fmu_codegen_writes(certify_none_report, tmp_path):
    """Issue 41 item 3: the deployed section lists the FMU (name, FMI version, size, identifier, variables, GUID,
    the FMPy line); each field equals the FMU `codegen --lang fmu` writes at the section's rate."""
    tree = _tree(certify_none_report)
    sec = _by_id(tree, "deployed")
    line = _by_id(sec, "deployed-fmu")
    assert line is not None, "the deployed section has no FMU line"
    f = _classes(line)
    text = " ".join("".join(line.itertext()).split())
    rate = float(re.search(r"at ([0-9.e+-]+) Hz", text).group(1))
    # the section's sampled run is at that rate
    assert re.search(rf"At {re.escape(format(rate, 'g'))} Hz", " ".join("".join(sec.itertext()).split()))
    out = tmp_path / "fmu"
    p = subprocess.run([sys.executable, "-m", "symfunnel", "codegen", str(DATA / "certify_none.toml"), "--lang",
                        "fmu", "--rate", repr(rate), "--out", str(out), "--json"], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    written = out / json.loads(p.stdout)["file"]
    with zipfile.ZipFile(written) as zf:
        md = ET.fromstring(zf.read("modelDescription.xml"))
        assert any(n.startswith("binaries/") and n.endswith(".so") for n in zf.namelist())
    assert f["fmu-file"] == written.name
    assert f["fmu-fmi"] == md.get("fmiVersion") == "2.0"
    assert int(f["fmu-bytes"]) == written.stat().st_size
    assert f["fmu-id"] == md.find("CoSimulation").get("modelIdentifier")
    assert f["fmu-guid"] == md.get("guid")
    assert int(f["fmu-vars"]) == len(md.findall("ModelVariables/ScalarVariable")) > 0
    assert f'fmpy.simulate_fmu("{written.name}"' in f["fmu-snippet"]
    assert "binaries" not in certify_none_report and "PK\x03\x04" not in certify_none_report   # not embedded


def test_no_deployed_leaves_the_fmu_out(tmp_path):
    """`report --no-deployed` skips the deployed section, the FMU line and the rate bracket with it."""
    text = _report(DATA / "certify_none.toml", tmp_path / "r.html", deployed=False)
    tree = _tree(text)
    assert _by_id(tree, "deployed") is None and _by_id(tree, "deployed-fmu") is None
    assert _by_id(tree, "deployed-bracket") is None and _by_id(tree, "fig-rate-bracket") is None


def _cli_bracket(scenario: str) -> dict:
    """`symfunnel rate SCENARIO --certify --json --t-final T`, run on its own (no wall limit)."""
    p = subprocess.run([sys.executable, "-m", "symfunnel", "rate", scenario, "--certify", "--json", "--t-final",
                        repr(T_FINAL), "-q"], capture_output=True, text=True, timeout=600)
    assert p.returncode in (0, 1), p.stderr
    return json.loads(p.stdout)


def _bracket(text: str) -> tuple[dict, str, str]:
    """The bracket line's fields, its text and the bracket figure's SVG text."""
    tree = _tree(text)
    sec = _by_id(tree, "deployed")
    line = _by_id(sec, "deployed-bracket")
    assert line is not None, "the deployed section has no rate bracket"
    fig = _by_id(sec, "fig-rate-bracket")
    svg = " ".join("".join(fig.itertext()).split()) if fig is not None else ""
    return _classes(line), " ".join("".join(line.itertext()).split()), svg


def _same(shown: str, value) -> bool:
    """The report's 6-digit rate against the command's number."""
    return value is not None and shown == f"{value:.6g}"


@pytest.mark.slow
def test_bracket_on_certify_none_is_proven_and_agrees_with_rate_certify(certify_none_report, certify_none_rate):
    """Issue 40: the deployed section shows f_sim, f_proven, f_theory (one figure, log axis) and what is proven on
    which set; each number against `rate --certify --json` run independently. The report's proof has a 10 s budget,
    so its f_proven is a rate the command's (deterministic) bisection also proved, at or above the command's."""
    f, text, svg = _bracket(certify_none_report)
    args = certify_none_rate.args                    # the command on this scenario over this module's horizon
    assert Path(args[4]).resolve() == (DATA / "certify_none.toml").resolve()
    assert args[args.index("--t-final") + 1] == repr(T_FINAL)
    assert certify_none_rate.returncode in (0, 1), certify_none_rate.stderr
    cli = json.loads(certify_none_rate.stdout)       # `rate --certify` run on its own (conftest: once per session)
    assert cli["certificate"]["status"] == "proven"
    assert f["rate-status"] == "proven"
    assert _same(f["rate-sim"], cli["min_rate_hz"])
    assert _same(f["rate-theory"], cli["theory_rate_hz"])
    proven = float(f["rate-proven"])
    cli_proven = [t["rate_hz"] for t in cli["certificate"]["tried"] if t["proven"]]
    assert any(f"{p:.6g}" == f["rate-proven"] for p in cli_proven), (f["rate-proven"], cli_proven)
    # the bracket's lower end ("not proven at ... Hz") is a rate the command tried and did not prove either
    below = re.search(r"not proven at ([0-9.e+-]+) Hz", text).group(1)
    assert any(f"{t['rate_hz']:.6g}" == below for t in cli["certificate"]["tried"] if not t["proven"]), below
    assert float(below) < proven
    assert proven >= float(f"{cli['proven_rate_hz']:.6g}")
    assert proven >= cli["min_rate_hz"]                     # a proven rate below the simulated one is a bug
    assert "on the set S" in text or "any state of the set S" in text
    assert "(1 \u2212 0.5) F1" in text and "returns to S" in text
    for label in ("f_sim", "f_proven", "f_theory"):       # the three marks in the figure's legend
        assert label in svg, label
    assert f"{proven:.6g} Hz" in svg


@pytest.mark.slow
def test_bracket_on_paper_is_undecided_and_shows_f_sim_and_f_theory(paper_report_2s):
    """On paper no rate is proven over S (undecided: S's floor, or a point of S failing at every rate): the figure
    shows f_sim and f_theory only and the text says why; both numbers equal the command's. The report is
    conftest's PAPER_REPORT_2S (this module's horizon and samples; test_report_layout measures the same one)."""
    text = paper_report_2s
    f, line, svg = _bracket(text)
    cli = _cli_bracket("paper")
    assert cli["certificate"]["status"] == "undecided" and cli["proven_rate_hz"] is None
    assert f["rate-status"] == "undecided" and f["rate-proven"] == "-"
    assert _same(f["rate-sim"], cli["min_rate_hz"])
    assert _same(f["rate-theory"], cli["theory_rate_hz"])
    # why: a point of S that fails a check at every rate, or S's floor (a state of S that leaves it within a period)
    assert "No rate is proven" in line and ("fails the check" in line or "leaves S after" in line)
    assert "f_sim" in svg and "f_theory" in svg and "f_proven" not in svg
