"""Scenario files: clear errors naming file, key and expectation (exit 2); fuzzed files never crash."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from symfunnel.core.errors import InputError
from symfunnel.scenario import load_scenario

from .conftest import MINIMAL_2LINK, PAPER, REPO


def _err(write_scenario, text):
    p = write_scenario(text)
    with pytest.raises(InputError) as ei:
        load_scenario(p)
    return str(ei.value), p


def test_builtin_is_the_derivations_file():
    from symfunnel.scenario import DATA_DIR
    assert (DATA_DIR / "paper_2dof.toml").read_bytes() == PAPER.read_bytes()


def test_unknown_key_has_did_you_mean(write_scenario):
    msg, p = _err(write_scenario, MINIMAL_2LINK.format(C="") + "\n[controler]\nk1 = 2\n")
    assert str(p) in msg and "controler" in msg and "did you mean 'controller'" in msg


def test_nested_unknown_key(write_scenario):
    msg, _ = _err(write_scenario, MINIMAL_2LINK.format(C="") + "\n[funnel.e1]\nphi_0 = 0.2\n")
    assert "funnel.e1.phi_0" in msg and "phi0" in msg


@pytest.mark.parametrize("edit, key", [
    (("[initial]\nq = [0.0, 0.2]", "[initial]\nq = [0.0, 0.2, 0.1]"), "initial.q"),
    (("[initial]\nq = [0.0, 0.2]", "[initial]\nq = \"zero\""), "initial.q"),
    (('q = ["0.3*sin(t)", "0.2*cos(t)"]', 'q = ["0.3*sin(t)", "0.2*cos(x)"]'), "reference.q[1]"),
    (('q = ["0.3*sin(t)", "0.2*cos(t)"]', 'q = ["0.3*sin(t)", "__import__(\'os\')"]'), "reference.q[1]"),
    (("a = 3.0", "a = \"three\""), "model.parameters.a"),
    (('M = [["a + 2*c*cos(q2)"', 'M = [["a + 2*c*cos(q2)*dq1"'), "model.matrices.M[0][0]"),
    (('type = "matrices"', 'type = "matrix"'), "model.type"),
])
def test_errors_name_the_key(write_scenario, edit, key):
    text = MINIMAL_2LINK.format(C="").replace(*edit)
    msg, p = _err(write_scenario, text)
    assert key in msg and str(p) in msg and "expected" in msg


def test_missing_required_section(write_scenario):
    text = MINIMAL_2LINK.format(C="").replace("[reference]", "[references]")
    msg, _ = _err(write_scenario, text)
    assert "references" in msg


def test_bad_sections_values(write_scenario):
    base = MINIMAL_2LINK.format(C="")
    for extra, key in [("\n[esn]\nspectral_radius = 1.2\n", "esn.spectral_radius"),
                       ("\n[plant.dead_zone]\nb_l = 0.5\nb_r = 1.0\n", "plant.dead_zone.b_l"),
                       ("\n[plant.dead_zone]\nb_l = -1\nb_r = 1.0\nright = \"u\"\n", "plant.dead_zone.right"),
                       ("\n[plant.dead_zone]\nb_l = -1\nb_r = 1.0\nleft = \"-(u - b_l)\"\n", "plant.dead_zone.left"),
                       ("\n[simulation]\nintegrator = \"cvode\"\n", "simulation.integrator"),
                       ("\n[controller]\nk1 = -1\n", "controller.k1"),
                       ("\n[[claims]]\nname = \"x\"\nsignal = \"alpha3\"\nexpression = \"1\"\n", "claims[0].signal"),
                       ("\n[[claims]]\nname = \"x\"\nsignal = \"alpha2\"\nexpression = \"foo\"\n",
                        "claims[0].expression")]:
        msg, _ = _err(write_scenario, base + extra)
        assert key in msg, (key, msg)


def test_not_toml_and_missing_file(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text("[model\n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_scenario(p)
    with pytest.raises(InputError, match="no such file"):
        load_scenario(tmp_path / "nope.toml")
    p.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match="UTF-8"):
        load_scenario(p)


def test_cli_bad_input_is_one_line_and_exit_2(write_scenario):
    p = write_scenario(MINIMAL_2LINK.format(C="") + "\n[controler]\n")
    r = subprocess.run([sys.executable, "-m", "symfunnel.cli", "derive", str(p)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert str(p) in r.stderr and "controller" in r.stderr


# --- fuzzing --------------------------------------------------------------------------------------

def _mutations():
    """Scenario documents derived from valid ones by deleting keys, swapping types and inserting junk."""
    import tomllib
    docs = [tomllib.loads(PAPER.read_text()), tomllib.loads(MINIMAL_2LINK.format(C=""))]
    junk = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20),
                     st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=30),
                     st.lists(st.text(max_size=8), max_size=4), st.lists(st.floats(), max_size=4),
                     st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
                     st.sampled_from(["sin(", "q1**99999", "__import__('os')", "1e400", "t/0", "", "q9",
                                      "().__class__", "lambda: 0", "9**9**9", "abs(abs(abs(q1)))"]))
    return st.tuples(st.sampled_from(docs), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 2), junk),
                                                     min_size=1, max_size=4))


def _apply(doc, edits):
    import copy
    doc = copy.deepcopy(doc)
    for idx, kind, value in edits:
        # walk to a random table
        node = doc
        path = []
        while True:
            tables = [k for k, v in node.items() if isinstance(v, dict)]
            if not tables or idx % 3 == 0:
                break
            k = tables[idx % len(tables)]
            path.append(k)
            node = node[k]
            idx //= 3
        keys = list(node)
        if kind == 0 and keys:
            del node[keys[idx % len(keys)]]
        elif kind == 1 and keys:
            node[keys[idx % len(keys)]] = value
        else:
            node[f"k{idx % 7}"] = value
    return doc


def _toml_dump(doc) -> str | None:
    """A small TOML writer for fuzzed documents (None if the value cannot be written as TOML)."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int):
            return str(v)
        if isinstance(v, float):
            if v != v:
                return "nan"
            if v in (float("inf"), float("-inf")):
                return "inf" if v > 0 else "-inf"
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            parts = [val(x) for x in v]
            return None if any(p is None for p in parts) else "[" + ", ".join(parts) + "]"
        if isinstance(v, dict):
            parts = [f"{json.dumps(k)} = {val(x)}" for k, x in v.items()]
            return None if any(p.endswith("None") for p in parts) else "{" + ", ".join(parts) + "}"
        return None
    lines = []
    for k, v in doc.items():
        s = val(v)
        if s is None:
            return None
        lines.append(f"{json.dumps(k)} = {s}")
    return "\n".join(lines) + "\n"


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(_mutations())
def test_fuzzed_scenarios_only_raise_input_error(tmp_path_factory, case):
    doc, edits = case
    text = _toml_dump(_apply(doc, edits))
    if text is None:
        return
    p = tmp_path_factory.mktemp("fz") / "f.toml"
    p.write_text(text, encoding="utf-8")
    try:
        sc = load_scenario(p)
    except InputError:
        return
    from symfunnel.design import derive
    try:
        derive(sc)
    except InputError:
        pass


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_only_raise_input_error(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("fb") / "b.toml"
    p.write_bytes(data)
    try:
        load_scenario(p)
    except InputError:
        pass


def test_hostile_expression_in_file_is_rejected_without_running(write_scenario, tmp_path):
    marker = tmp_path / "pwned"
    payload = f"__import__('os').system('touch {marker}')"
    text = MINIMAL_2LINK.format(C="").replace('"0.2*cos(t)"', json.dumps(payload))
    with pytest.raises(InputError):
        load_scenario(write_scenario(text))
    assert not marker.exists()


def test_repo_scenarios_load():
    for p in sorted((REPO / "derivations").glob("*.toml")):
        load_scenario(p)
