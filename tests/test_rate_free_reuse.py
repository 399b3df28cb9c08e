"""The C pair's rate-free part (everything but the step API's constants) is generated once per design and reused at
other rates (a rate search generates one design at many rates): the files must be byte for byte those of a fresh
generation, and a design whose signals were replaced must be generated again."""

from __future__ import annotations

from pathlib import Path

import pytest

from symfunnel.cli import main
from symfunnel.design import derive
from symfunnel.emit import step
from symfunnel.emit.files import generate
from symfunnel.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent


def _scenario(which, tmp_path):
    if which != "urdf":
        return load_scenario(which)
    s = tmp_path / "robot.toml"
    assert main(["init", "--urdf", str(REPO / "tests" / "data" / "branched.urdf"), "--out", str(s), "-q"]) == 0
    return load_scenario(s)


@pytest.mark.parametrize("which", ["paper", "arm7", "urdf"])
def test_a_rate_after_another_is_byte_for_byte_a_fresh_generation(which, tmp_path):
    d = derive(_scenario(which, tmp_path))
    tm = [150.0] * d.n
    for rate, tau_max, prefix, structured in ((1000.0, None, None, True), (250.0, tm, "ab_", True),
                                              (77.0, tm, None, False)):
        step._RATE_FREE.clear()
        fresh = generate(d, "c", rate_hz=rate, tau_max=tau_max, prefix=prefix, structured=structured)
        step._RATE_FREE.clear()
        generate(d, "c", rate_hz=2.5 * rate, tau_max=tau_max, prefix=prefix, structured=structured)
        reused = generate(d, "c", rate_hz=rate, tau_max=tau_max, prefix=prefix, structured=structured)
        assert list(reused) == list(fresh)                  # the same files in the same order (the manifest's)
        for name in fresh:
            assert reused[name] == fresh[name], (which, rate, prefix, structured, name)
        # the rate is in the step API only, and it is there: another rate gives another file
        other = generate(d, "c", rate_hz=2.5 * rate, tau_max=tau_max, prefix=prefix, structured=structured)
        base = "symfunnel_controller" if prefix is None else prefix + "controller"
        assert other[base + ".c"] != fresh[base + ".c"]


def test_another_torque_limit_prefix_or_replaced_signal_is_generated_again(paper, monkeypatch):
    from symfunnel.emit import c
    calls = []
    real = c.emit_c

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)
    monkeypatch.setattr(c, "emit_c", counting)
    d = derive(paper)
    step._RATE_FREE.clear()
    generate(d, "c", rate_hz=1000.0)
    generate(d, "c", rate_hz=500.0)
    assert len(calls) == 1                                  # reused at the second rate
    generate(d, "c", rate_hz=500.0, tau_max=100.0)
    generate(d, "c", rate_hz=500.0, prefix="x_")
    assert len(calls) == 3                                  # a torque limit and a prefix are part of the key
    d.signals["tau"] = d.signals["tau"] * 2                 # the twin tests' way of breaking a design
    generate(d, "c", rate_hz=500.0)
    assert len(calls) == 4
    assert len(step._RATE_FREE) <= 4                        # a few designs, not every one a tune has seen
