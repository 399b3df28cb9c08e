"""The Python API against the CLI: every command and option has its function and keyword, the same JSON, errors
that name the keyword, the exceptions and nothing internal at the top level, short reprs."""

from __future__ import annotations

import argparse
import inspect
import json
import subprocess
import sys

import numpy as np
import pytest

import symfunnel as sf
from symfunnel.cli import build_parser

#: CLI commands without an API function, and why
CLI_ONLY_COMMANDS = {
    "bench": "measures symfunnel itself (a developer's tool; symfunnel.bench holds its functions)",
}

#: CLI options without a keyword of their own, and why ("*": on every command)
CLI_ONLY_OPTIONS = {
    ("*", "--quiet"): "progress on stderr: the API prints nothing (`progress=` takes a callable where offered)",
    ("*", "--json"): "the output format: every result has to_json(), the same JSON",
    ("derive", "--eval"): "sf.evaluate(design, point) is the API of it",
    ("derive", "--all"): "with --eval: sf.evaluate returns every signal",
    ("derive", "--latex"): "writes the signals as LaTeX: the API's design holds the SX themselves",
    ("derive", "--force"): "with --latex (the file it writes)",
    ("derive", "--wall-limit"): "derive is one symbolic step; the other functions take wall_limit",
}

#: the options whose keyword is not the option's name with "-" as "_" and "--no-x" as x (design.md section 9)
RENAMED = {"--rate": "rate_hz",
           "--from": "source"}         # `from` is a Python keyword


def _keyword(option: str) -> str:
    if option in RENAMED:
        return RENAMED[option]
    name = option[2:]
    return (name[3:] if name.startswith("no-") else name).replace("-", "_")


def _commands():
    p = build_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def test_every_cli_command_and_option_has_its_function_and_keyword():
    missing = []
    commands = _commands()
    assert set(commands) >= {"simulate", "verify", "rate", "certify", "codegen", "report", "sweep", "tune"}
    for name, sp in commands.items():
        if name in CLI_ONLY_COMMANDS:
            continue
        params = inspect.signature(getattr(sf, name)).parameters
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            if not a.option_strings:
                key = a.dest                                # the positional scenario
            else:
                option = max(a.option_strings, key=len)
                if ("*", option) in CLI_ONLY_OPTIONS or (name, option) in CLI_ONLY_OPTIONS:
                    continue
                key = _keyword(option)
            if key not in params:
                missing.append(f"{name} {a.option_strings or a.dest} -> {key}")
    assert not missing, missing


def test_the_top_level_shows_the_api_and_its_exceptions():
    from symfunnel.core import errors
    shown = dir(sf)
    assert {"rate", "simulate", "verify", "certify", "InputError", "CheckFailed", "SimulationError"} <= set(shown)
    sf.rate, sf.simulate                                    # noqa: B018 - loads the subpackages as attributes
    assert not {"core", "api", "design", "simulation", "commands", "cli"} & set(dir(sf))
    assert (sf.InputError, sf.CheckFailed, sf.SimulationError) == (errors.InputError, errors.CheckFailed,
                                                                   errors.SimulationError)
    from symfunnel import SimulationError  # noqa: F401 - importable by name, as README shows


@pytest.mark.parametrize("call,key", [
    (lambda: sf.simulate("paper", t_final=-1.0), "t_final"),
    (lambda: sf.simulate("paper", rate=-5.0), "rate_hz"),
    (lambda: sf.rate("paper", margin=2.0), "margin"),
    (lambda: sf.rate("paper", t_final=0.0), "t_final"),
    (lambda: sf.rate("paper", set_margin=(0.5, 0.5)), "set_margin"),
    (lambda: sf.certify("paper", wall_limit=-1.0), "wall_limit"),
    (lambda: sf.certify("paper", only="nonsense"), "only"),
    (lambda: sf.verify("paper", plant="no-such-engine"), "plant"),
    (lambda: sf.tune("paper", max_evals=0), "max_evals"),
    (lambda: sf.init("s.txt"), "out"),
    (lambda: sf.verify("paper", samples=0), "samples"),            # was a CasADi assertion (a degenerate map)
    (lambda: sf.report("paper", samples=1.5), "samples"),
    (lambda: sf.codegen("paper", points=0, check=True), "points"),
    (lambda: sf.verify("paper", seed=-1), "seed"),
    (lambda: sf.init("s.toml", source="paper", urdf="a.urdf"), "source"),
])
def test_api_errors_name_the_keyword_not_the_cli_option(call, key):
    with pytest.raises(sf.InputError) as e:
        call()
    assert e.value.key == key and f"key '{key}'" in str(e.value)
    assert "--" not in str(e.value)


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "symfunnel", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def test_rate_is_the_cli_json_and_has_a_short_repr():
    r = sf.rate("paper", t_final=0.5, margin=0.05)
    p = _cli("rate", "paper", "--t-final", "0.5", "--json", "-q")
    assert p.returncode == 0, p.stderr
    assert r.to_json() == json.loads(p.stdout)
    assert r.min_rate_hz == json.loads(p.stdout)["min_rate_hz"] > 0
    # the rate found holds and every tried rate below it does not (the bisection's own invariant, from its rows)
    held = [d["rate_hz"] for d in r.to_json()["tried"] if d["holds"]]
    assert min(held) == r.min_rate_hz
    assert all(d["rate_hz"] < r.min_rate_hz for d in r.to_json()["tried"] if not d["holds"])
    assert repr(r).startswith("RateResult(scenario='paper', min_rate_hz=") and len(repr(r)) < 200


def test_simulate_takes_the_rate_alias_and_the_plant():
    """`rate=` is `rate_hz=`; `plant="mujoco"` runs the deployed loop on MuJoCo, the same run as the CLI's."""
    from symfunnel.deployed.loop import simulate_sampled
    a = sf.simulate("paper", t_final=0.1, rate=2000.0)
    b = simulate_sampled(sf.load_scenario("paper"), sf.derive(sf.load_scenario("paper")), rate_hz=2000.0,
                         t_final=0.1)
    assert a.rate_hz == 2000.0 and np.array_equal(a.q, b.q)
    with pytest.raises(sf.InputError, match="rate_hz"):
        sf.simulate("paper", rate=1.0, rate_hz=2.0)
    m = sf.simulate("arm7", plant="mujoco", rate_hz=3512.5, t_final=0.05)
    assert m.stats["engine"] == "mujoco" and m.status == "ok"
    p = _cli("simulate", "arm7", "--plant", "mujoco", "--rate", "3512.5", "--t-final", "0.05", "--json", "-q")
    assert p.returncode == 0, p.stderr
    cli = json.loads(p.stdout)
    api = json.loads(json.dumps(m.summary(), default=float))
    assert np.allclose(cli["min_margin_e1"], api["min_margin_e1"], rtol=0, atol=1e-12)
    assert cli["max_abs_tau"] == pytest.approx(api["max_abs_tau"], abs=1e-9)


def test_reprs_are_short():
    sc = sf.load_scenario("paper")
    d = sf.derive(sc)
    objs = [sc, d, sf.simulate(sc, t_final=0.2), sf.simulate(sc, t_final=0.05, rate_hz=2000.0),
            sf.codegen(sc, "python")]
    for o in objs:
        text = repr(o)
        assert len(text) < 300 and "SX" not in text and "array(" not in text and "\n" not in text, text
    assert repr(sc) == f"Scenario('paper', file={str(sc.path)!r}, 2 joints, t_final={sc.simulation.t_final:g} s)"
    assert repr(objs[2]).startswith("SimResult(scenario='paper', status='ok', t_end=0.2 s,")


@pytest.mark.slow
def test_verify_with_mutants_is_a_verification_with_the_score():
    v = sf.verify("paper", t_final=0.5, samples=200, mutants=True)
    m = v.mutation
    assert type(v).__name__ == "Verification" and v.status == "pass"
    killed = sum(r["killed"] for r in m["mutants"])
    equivalent = sum(r["equivalent"] for r in m["mutants"])
    assert v.mutation_score == pytest.approx(killed / (len(m["mutants"]) - equivalent))
    assert v.to_json()["mutation"]["score"] == v.mutation_score
    assert f"mutation_score={v.mutation_score:.3f}" in repr(v)


def test_rate_with_certify_gives_the_cli_bracket(tmp_path_factory):
    """`certify=True` is `rate --certify`: the same keys and the same proven rate (sampled_1dof, proven in ~1 s);
    only the certificate's own wall time differs between the two runs. The command's run is test_sampled_certificate's
    `bracket` (cli_once: the same command line runs once per session)."""
    from tests.conftest import SAMPLED_1DOF_RATE, cli_once
    r = sf.rate(SAMPLED_1DOF_RATE[1], certify=True, wall_limit=60)
    p = cli_once(tmp_path_factory, *SAMPLED_1DOF_RATE)
    assert p.returncode == 0, p.stderr
    cli, api = json.loads(p.stdout), r.to_json()
    assert set(api) == set(cli) >= {"min_rate_hz", "proven_rate_hz", "theory_rate_hz", "ratio", "certificate"}
    assert set(api["certificate"]) == set(cli["certificate"]) and api["certificate"]["id"] == "certify.sampled"
    assert api["certificate"]["status"] == cli["certificate"]["status"] == "proven"
    assert api["proven_rate_hz"] == cli["proven_rate_hz"] == r.proven_rate_hz >= r.min_rate_hz
    assert api["tried"] == cli["tried"]
    assert f"proven_rate_hz={r.proven_rate_hz:.6g}" in repr(r)


def test_init_writes_what_the_cli_writes(tmp_path):
    from symfunnel.cli import main
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    p = sf.init(tmp_path / "a" / "arm.toml")
    assert main(["init", "--out", str(tmp_path / "b" / "arm.toml"), "-q"]) == 0
    assert p == tmp_path / "a" / "arm.toml"
    assert p.read_text().replace(str(tmp_path / "a"), "D") == \
        (tmp_path / "b" / "arm.toml").read_text().replace(str(tmp_path / "b"), "D")
    sc = sf.load_scenario(p)
    assert sc.n == 2 and repr(sc).startswith("Scenario('arm'")
    with pytest.raises(sf.InputError, match="key 'out'.*exists.*force"):
        sf.init(p)
    assert sf.init(p, force=True) == p
    with pytest.raises(sf.InputError, match="key 'joints': is given without urdf"):
        sf.init(tmp_path / "j.toml", joints="a,b")
