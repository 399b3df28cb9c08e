"""A gate a user's own design can pass (issue 45, item 3): one fact, one severity.

- the unedited `symfunnel init` scenario (and one from `init --urdf` on a third-party robot) passes `verify`;
- a refuted `certify.invariance` (the Lyapunov level-set argument is vacuous) is a warning unless the scenario
  declares it; declared as required (`status = "pass"`) it fails the gate;
- `certify.bounds` says on which set it holds (`region.kind`), and on a stand-in region it is never a PASS;
- the report opens with Guarantees (proven / refuted / open).
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

import pytest

from symfunnel.certificates.result import Certificate, Certification
from symfunnel.checks.audit import CheckResult
from symfunnel.cli import main
from symfunnel.reporting.certify import guarantees

ROOT = Path(__file__).resolve().parent.parent
PANDA = ROOT / "tests" / "data" / "third_party" / "panda.urdf"


def _verify(capsys, path):
    code = main(["verify", str(path), "--json", "-q"])
    return code, json.loads(capsys.readouterr().out)


def test_the_init_scenario_passes_verify_as_written(tmp_path, capsys):
    out = tmp_path / "mine.toml"
    assert main(["init", "--out", str(out), "-q"]) == 0
    capsys.readouterr()
    text = out.read_text()
    assert "[[expect]]" in text and "symfunnel verify" in text        # the template says how to declare a finding
    code, res = _verify(capsys, out)
    by = {c["id"]: c for c in res["checks"]}
    assert code == 0 and res["status"] == "pass", [c["id"] for c in res["checks"] if c["status"] == "fail"]
    # the vacuous level-set argument is a finding about that argument (as lyapunov.guarantee): warn, not fail
    assert by["certify.invariance"]["status"] == "warn"
    # the bounds of the stand-in region R_0.05 are information, never a PASS
    bounds = by["certify.bounds"]
    assert bounds["status"] == "warn" and bounds["evidence"]["region"]["kind"] == "stand_in"


def test_declaring_the_level_set_argument_required_makes_its_refutation_fail(tmp_path, capsys):
    out = tmp_path / "mine.toml"
    assert main(["init", "--out", str(out), "-q"]) == 0
    out.write_text(out.read_text() + '\n[[expect]]\ncheck = "certify.invariance"\nstatus = "pass"\n'
                   'reason = "this design must close the Lyapunov argument"\n')
    capsys.readouterr()
    assert main(["certify", str(out), "--only", "invariance", "--json", "-q"]) == 1
    res = json.loads(capsys.readouterr().out)
    (inv,) = res["certificates"]
    assert inv["status"] == "refuted" and inv["check"] == "fail" and res["unexpected"] == ["certify.invariance"]
    # the same certificate undeclared: a warning, the gate passes
    out.write_text(out.read_text().split("\n[[expect]]\ncheck = \"certify.invariance\"")[0])
    assert main(["certify", str(out), "--only", "invariance", "--json", "-q"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["certificates"][0]["check"] == "warn" and res["status"] == "pass"


def _cert(cid, status, **kw):
    return Certificate(cid, status, f"{cid} {status}", **kw)


def test_guarantees_sort_each_fact_once():
    certs = [_cert("certify.input_gain", "proven", lower=0.5),
             _cert("certify.bounds", "proven", region={"kind": "stand_in"}, lower=1.0, upper=2.0),
             _cert("certify.invariance", "refuted"),
             _cert("certify.containment", "undecided")]
    cert = Certification("x", certs)
    checks = {c.id: c for c in cert.checks()}
    assert [checks[c].status for c in ("certify.input_gain", "certify.bounds", "certify.invariance",
                                       "certify.containment")] == ["pass", "warn", "warn", "warn"]
    breach = CheckResult("funnel.containment.e1.joint1", "fail", "breach at t = 1")
    g = guarantees(cert, checks, list(checks.values()) + [breach])
    assert len(g["proven"]) == 1 and "certify.input_gain" in str(g["proven"][0]["head"])
    # one line each, the whole detail in a collapsed block
    assert len(g["refuted"]) == 1 and "breach at t = 1" in str(g["refuted"][0]["head"]) + str(g["refuted"][0]["detail"])
    assert len(g["open"]) == 3
    # on the set a certificate proves the loop stays in, the bound is a guarantee
    certs[1] = _cert("certify.bounds", "proven", region={"kind": "proven_invariant"}, lower=1.0, upper=2.0)
    cert = Certification("x", certs)
    checks = {c.id: c for c in cert.checks()}
    assert checks["certify.bounds"].status == "pass"
    g = guarantees(cert, checks, list(checks.values()))
    assert any("max |tau| <= 2" in html.unescape(str(p["head"])) for p in g["proven"])


@pytest.mark.slow(first=True)          # the suite's longest test: started first (tests/conftest.py, module_order)
def test_a_third_party_urdf_from_init_passes_verify_and_its_report_opens_with_guarantees(tmp_path, capsys):
    """Panda (example-robot-data, Apache-2.0) through `init --urdf`: verify passes as written.

    One Run serves both, as in `symfunnel verify` (its `.verification`, exit 1 exactly when `unexpected`) and
    `symfunnel report` (`build_report` of it): the 8-joint verification is computed once, not once per command.
    The report leaves out its deployed section (`--no-deployed`): the guarantees are read from the certificates and
    verify's checks only (reporting.certify.guarantees), and the deployed section's rate search, rate sensitivity
    and rate bracket on 8 joints were half of this test's time (52 of 106 s; test_report_deployed checks them)."""
    import shutil

    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting import build_report
    from symfunnel.scenario import load_scenario
    src = tmp_path / "panda.urdf"
    shutil.copy(PANDA, src)
    out = tmp_path / "panda.toml"
    assert main(["init", "--urdf", str(src), "--out", str(out), "-q"]) == 0
    capsys.readouterr()
    run = Run(load_scenario(out), RunOptions(samples=10000))     # verify's and report's defaults
    v = run.verification
    res = v.to_json()
    assert not v.unexpected and res["status"] == "pass", [c["id"] for c in res["checks"] if c["status"] == "fail"]
    html = tmp_path / "panda.html"
    assert build_report(run, html, deployed=False) == html
    text = html.read_text()
    assert text.index('id="guarantees"') < text.index('id="overview"')
    section = re.sub("<[^>]+>", "", text[text.index('id="guarantees"'):text.index('id="overview"')])
    assert "Proven" in section and "Refuted" in section and "Open" in section
