"""The shipped scenarios' certificate outcomes, pinned: a proof that silently becomes undecided (or a refutation
that disappears) after a change of the interval machinery, the regions or the budgets fails here. Each row is what
`symfunnel certify SCENARIO` gives at the full budget (measured on the 2-core machine: 7-14 s per scenario)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import certify_once

ROOT = Path(__file__).resolve().parent.parent

PINNED = {
    "paper": {"certify.input_gain": "refuted", "certify.bounds": "proven", "certify.invariance": "refuted",
              "certify.containment": "undecided"},
    "arm7": {"certify.input_gain": "refuted", "certify.bounds": "proven", "certify.invariance": "refuted",
             "certify.containment": "undecided"},
    "tests/data/certify_none.toml": {"certify.input_gain": "proven", "certify.bounds": "proven",
                                     "certify.invariance": "proven", "certify.containment": "proven"},
    "derivations/paper_small_dead_zone.toml": {"certify.input_gain": "proven", "certify.bounds": "proven",
                                               "certify.invariance": "refuted", "certify.containment": "undecided"},
    # the projection member: the funnels proven kept (m1 = 0.9, m2 = 0.002; docs/certify.md)
    "derivations/paper_small_dead_zone_projection.toml": {"certify.input_gain": "proven", "certify.bounds": "proven",
                                                          "certify.invariance": "refuted",
                                                          "certify.containment": "proven"},
    "derivations/ppc_log_rbf.toml": {"certify.input_gain": "proven", "certify.bounds": "undecided",
                                     "certify.invariance": "refuted", "certify.containment": "undecided"},
    "derivations/arm7_mujoco_heavy.toml": {"certify.input_gain": "refuted", "certify.bounds": "proven",
                                           "certify.invariance": "refuted", "certify.containment": "undecided"},
    "derivations/sim_breach.toml": {"certify.input_gain": "refuted", "certify.bounds": "proven",
                                    "certify.invariance": "refuted", "certify.containment": "refuted"},
    "derivations/sim_fast_sine.toml": {"certify.input_gain": "refuted", "certify.bounds": "proven",
                                       "certify.invariance": "refuted", "certify.containment": "undecided"},
    "derivations/sim_offset_cosine.toml": {"certify.input_gain": "refuted", "certify.bounds": "proven",
                                           "certify.invariance": "refuted", "certify.containment": "undecided"},
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PINNED))
def test_shipped_certificate_outcomes_are_pinned(name, tmp_path_factory):
    """`symfunnel certify NAME --json` (conftest's certify_once: the run test_certify reads for paper and
    certify_none, computed once per session)."""
    path = str(ROOT / name) if (ROOT / name).exists() else name
    _, out = certify_once(tmp_path_factory, path)
    got = {c["id"]: c["status"] for c in out["certificates"] if c["id"] in PINNED[name]}
    assert got == PINNED[name], {c["id"]: (c["status"], c["detail"][:200]) for c in out["certificates"]
                                 if c["id"] in PINNED[name] and c["status"] != PINNED[name][c["id"]]}
