"""report: one self-contained HTML file; parses, has its sections, >= 8 SVG figures, MathML, no network reference,
renders in headless Chromium without console errors; a failing scenario gives a report that shows the failure.

How "no http(s) reference" is decided: the report is parsed with html5lib and every attribute of every element
(HTML, inline SVG and MathML alike) is inspected. Namespace declarations (``xmlns``, ``xmlns:*``) are *names*
(URIs that identify the SVG/MathML/XLink vocabularies), never fetched, so they are exempt; every other attribute value
may not start with http(s) (src, href, xlink:href, srcset, ... included), and no attribute or <style> text may
contain ``url(http...`` or ``@import``. Besides, the raw text with the namespace declarations removed may not contain
"http://" or "https://" at all, and there are no <script>, <link>, <iframe>, <object>, <embed> or <img> elements.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

T_FINAL = 2.0          # shortened horizon for the test; `symfunnel report` itself runs the scenario's 20 s
SAMPLES = 200          # the falsification's sampled states (the report's default is 10000); every section is there
SECTIONS = ["overview", "gate", "findings", "scenario", "model", "derivation", "alpha2-dot", "simulation",
            "verification", "deployed", "codegen", "timings"]


#: the report the module checks: the paper scenario over T_FINAL with every section (codegen, mutants, deployed)
PAPER_REPORT_FULL = (f"report paper t_final={T_FINAL} samples={SAMPLES} codegen mutants deployed + verify json, counts "
                     "line, verdicts")


@pytest.fixture(scope="module")
def report_bundle(tmp_path_factory) -> dict:
    """The paper scenario's report and what `verify --json` says of the same Run (its counts line and each check's
    verdict label), built once per test session (conftest's text_once): xdist hands this module's tests to several
    workers, and each built its own module-scoped report before (15-26 s each)."""
    import json

    from tests.conftest import text_once

    def build() -> str:
        from symfunnel.checks.gate import counts_line, verdict
        from symfunnel.pipeline import Run, RunOptions
        from symfunnel.reporting import build_report
        from symfunnel.scenario import load_scenario
        run = Run(load_scenario("paper"), RunOptions(t_final=T_FINAL, samples=SAMPLES))
        out = tmp_path_factory.mktemp("report") / "paper.html"
        assert build_report(run, out) == out
        v = run.verification
        return json.dumps({"html": out.read_text(encoding="utf-8"), "verify": v.to_json(),
                           "counts_line": counts_line(v.checks), "verdicts": {c.id: verdict(c)[0] for c in v.checks}})
    return json.loads(text_once(tmp_path_factory, PAPER_REPORT_FULL, build))


@pytest.fixture(scope="module")
def report_path(report_bundle, tmp_path_factory):
    """The report's HTML as a file of this worker (Chromium opens it)."""
    out = tmp_path_factory.mktemp("report") / "paper.html"
    out.write_text(report_bundle["html"], encoding="utf-8")
    return out


def test_overview_counts_and_tables_agree_with_verify_json(report_bundle, report_text, tree):
    """Every check of `verify --json` appears exactly once in the report's tables, with the verdict label of its
    status against its declaration; the overview's counts are verify's."""
    js = report_bundle["verify"]
    k = js["counts"]
    warnings = f"{k['warn']} warning" + ("" if k["warn"] == 1 else "s")
    line = f"{k['pass']} passed, {k['fail']} failed ({k['expected_fail']} expected), {warnings}, {k['skip']} skipped"
    assert line == report_bundle["counts_line"]
    gate = next(el for el in tree.iter() if el.get("id") == "gate")
    assert line in "".join(gate.itertext())
    assert js["status"].upper() in "".join(gate.itertext())
    rows = [el for el in tree.iter() if _local(el.tag) == "tr"]
    seen = {}
    for r in rows:
        codes = [el for el in r.iter() if _local(el.tag) == "code"]
        if not codes:
            continue
        first = "".join(codes[0].itertext()).strip()
        if any(first == c["id"] for c in js["checks"]):
            seen.setdefault(first, []).append("".join(r.itertext()))
    for c in js["checks"]:
        assert len(seen.get(c["id"], [])) == 1, (c["id"], len(seen.get(c["id"], [])))
        label = report_bundle["verdicts"][c["id"]]
        assert label in seen[c["id"]][0], (c["id"], label)
    assert "skipped</span>" not in report_text or k["skip"]


@pytest.mark.slow
def test_a_report_of_the_users_own_arm_says_nothing_about_a_paper(tmp_path):
    """`init`'s arm (no source, no claims): no word 'paper', no NaN in a legend, no numpy warning."""
    import warnings

    from symfunnel.cli import main
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting import build_report
    from symfunnel.scenario import load_scenario
    assert main(["init", "--out", str(tmp_path / "arm.toml")]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = build_report(Run(load_scenario(tmp_path / "arm.toml"), RunOptions(t_final=2.0, samples=200)),
                           tmp_path / "arm.html", codegen=False, mutants=False, deployed=False)
    text = out.read_text(encoding="utf-8")
    assert not re.search(r"paper", text, re.I), re.search(r".{60}paper.{60}", text, re.I | re.S).group(0)
    assert not re.search(r"\bnan\b", text)
    assert "Findings" not in text and "None declared" not in text and "None listed" not in text


@pytest.fixture(scope="module")
def report_text(report_bundle):
    return report_bundle["html"]


@pytest.fixture(scope="module")
def tree(report_text):
    import html5lib
    return html5lib.parse(report_text, treebuilder="etree", namespaceHTMLElements=False)


def _local(tag) -> str:
    return tag.split("}", 1)[-1] if isinstance(tag, str) else ""


def test_parses_strictly(report_text):
    import html5lib
    parser = html5lib.HTMLParser(strict=False)
    parser.parse(report_text)
    fatal = [e for e in parser.errors if e[1] not in ("unexpected-end-tag-in-math",)]
    assert not fatal, fatal[:5]
    assert report_text.startswith("<!DOCTYPE html>")


def test_has_its_sections(tree):
    ids = {el.get("id") for el in tree.iter() if el.get("id")}
    for s in SECTIONS:
        assert s in ids, s


def test_at_least_eight_svg_figures_and_mathml(tree):
    svgs = [el for el in tree.iter() if _local(el.tag) == "svg"]
    assert len(svgs) >= 8
    maths = [el for el in tree.iter() if _local(el.tag) == "math"]
    assert len(maths) >= 10
    # the exact alpha2_dot and the printed claims are there as MathML
    sec = next(el for el in tree.iter() if el.get("id") == "derivation")
    assert sum(1 for el in sec.iter() if _local(el.tag) == "math") >= 10


def test_no_network_reference(tree, report_text):
    for el in tree.iter():
        tag = _local(el.tag)
        assert tag not in ("script", "link", "iframe", "object", "embed", "img", "base"), tag
        for k, v in el.attrib.items():
            name = _local(k)
            if k == "xmlns" or k.startswith("xmlns:") or name == "xmlns" or "xmlns" in k:
                continue
            assert not re.match(r"\s*https?:", v, re.I), (tag, k, v)
            assert not re.search(r"url\(\s*['\"]?\s*https?:", v, re.I), (tag, k, v)
        if tag == "style":
            css = el.text or ""
            assert "@import" not in css
            assert not re.search(r"url\(", css)
    stripped = re.sub(r'\sxmlns(:\w+)?="[^"]*"', "", report_text)
    assert "http://" not in stripped and "https://" not in stripped
    from symfunnel.reporting.html import no_network_references
    assert no_network_references(report_text) == []


def test_verification_table_shows_failures_plainly(tree, report_text):
    # the paper's Theorem 1 is falsified on the sampled states: shown as FAIL with its margin and where
    # expected findings about the paper are styled apart from failures of the design
    rows = [el for el in tree.iter() if _local(el.tag) == "tr" and "finding-row" in (el.get("class") or "")]
    text = " ".join("".join(r.itertext()) for r in rows)
    assert "claim.theorem1" in text
    assert "None: every check this design must pass, passes." in report_text
    assert "FINDING (expected)" in text and "FAIL (unexpected)" not in text
    assert "not a proof" in report_text
    assert "W*" in report_text and "not given by the source" in report_text


def test_code_generation_section(tree):
    sec = next(el for el in tree.iter() if el.get("id") == "codegen")
    text = "".join(sec.itertext())
    import importlib.util
    if importlib.util.find_spec("symfunnel.emit") is not None:
        import symfunnel.emit as cg
        if hasattr(cg, "codegen_summary"):
            assert "alpha2_dot" in text and "controller" in text
            return
    assert "not available" in text


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


@pytest.mark.slow
def test_renders_in_headless_chromium_without_console_errors(report_path, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium on this machine (.ci/run installs Debian's `chromium`; apt-get install chromium)")
    shot = tmp_path / "shot.png"
    profile = tempfile.mkdtemp(prefix="symfunnel-chromium-")
    try:
        cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0", f"--screenshot={shot}",
               "--window-size=1200,3000", report_path.resolve().as_uri()]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env={**os.environ, "HOME": profile})
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    log = r.stdout + r.stderr
    console = [ln for ln in log.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert not console, console
    assert shot.exists(), log[-2000:]
    import matplotlib.image as mpimg
    import numpy as np
    img = mpimg.imread(str(shot))[..., :3]
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    nonwhite = np.mean(np.any(img < 0.9, axis=2))
    assert nonwhite > 0.02, f"screenshot looks blank ({nonwhite:.2%} non-white pixels)"
    assert float(img.std()) > 0.05


@pytest.mark.slow
def test_failing_scenario_gives_a_report_that_shows_the_failure(write_scenario, tmp_path, capsys):
    """An initial error outside its funnel: `report` still writes the file, and it shows the failed checks."""
    from symfunnel.cli import main
    from symfunnel.scenario import DATA_DIR
    text = (DATA_DIR / "paper_2dof.toml").read_text(encoding="utf-8").replace("phi0 = 0.4 ", "phi0 = 0.18 ", 1)
    p = write_scenario(text)
    out = tmp_path / "sub" / "bad.html"
    code = main(["report", str(p), "--out", str(out), "--no-codegen", "--no-mutants", "--samples", "1000", "-q"])
    assert code == 0
    assert capsys.readouterr().out.strip() == str(out)
    html = out.read_text(encoding="utf-8")
    assert "funnel.initial_condition" in html and "the initial state is outside a funnel" in html
    assert "initial_outside" not in html                # the status in words, not the JSON's value
    assert re.search(r'id="gate">\s*<p>Gate \(<code>symfunnel verify</code>\): <span class="badge fail">FAIL', html)
    assert "Failures of this design" in html
    assert not list(out.parent.glob(".*.tmp"))            # atomic: no temporary file left behind


def test_default_path(paper):
    from symfunnel.reporting import default_path
    assert default_path(paper) == Path("reports") / "paper.html"


def test_first_contact_details(report_text, tree):
    """Header names the built-in scenario (not its install path); '(see' has its space; raw sympy matrices are
    gone from the details; the figures that reproduce the paper's Figures 6-8 say so; the exact alpha2_dot is laid
    out (lines, named parts) rather than one line cut off at the right."""
    from symfunnel.scenario import DATA_DIR
    header = "".join(next(el for el in tree.iter() if _local(el.tag) == "header").itertext())
    assert "built-in: paper" in header and str(DATA_DIR) not in header
    text = "".join(tree.itertext())
    assert not re.search(r"\S\(see", text)
    assert "Matrix([" not in report_text
    caps = [" ".join("".join(el.itertext()).split()) for el in tree.iter() if _local(el.tag) == "figcaption"]
    for num, title in ((6, "Output tracking"), (7, "Friction compensation"), (8, "Control signals")):
        assert any(f"Reproduces Figure {num} (\u201c{title}\u201d)" in c for c in caps), num
    a2d = next(el for el in tree.iter() if el.get("id") == "alpha2-dot-formula")
    rows = [el for el in a2d.iter() if (el.get("class") or "") == "eqn-rhs"]
    assert len(rows) >= 2


def test_deployed_section_states_the_minimum_rate_and_what_sets_it(tree, report_path):
    """Issue: the report states the minimum rate (every tried rate listed), what changes it (re-computed), and the
    peak torque beside the limits; the figure of margin against rate is there."""
    sec = next(el for el in tree.iter() if el.get("id") == "deployed")
    text = " ".join("".join(sec.itertext()).split())
    import re
    m = re.search(r"minimum rate ([0-9.]+) Hz", text)
    assert m and float(m.group(1)) > 0
    assert "funnel.e2.phi_inf" in text and "controller.k2" in text and "peak |" in text
    assert any(el.get("id") == "fig-margin-rate" for el in sec.iter())
