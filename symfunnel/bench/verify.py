"""Bench area `verify`: the mutation score of `verify --mutants` on the built-in scenarios (how much our own
verification catches of a wrong design), with the time it takes, and the checker mutation score (how much the test
suite catches of a wrong checker: `symfunnel.bench.checker_mutants`)."""

from __future__ import annotations

import time

from ._result import result


def checker_score(progress) -> list[dict]:
    """verify.checker_mutation_score: seeded errors in the checking code against the tests that cover them
    (resumable: a repeated bench keeps the outcomes whose mutant and tests are unchanged); [] without a source
    checkout or without pytest-cov (the `test` extra), saying why."""
    import importlib.util

    from . import checker_mutants as cm
    if not (cm.repo_root() / "tests").is_dir() or importlib.util.find_spec("pytest_cov") is None:
        progress("verify: checker mutation score skipped (needs a source checkout with the test extra: pytest-cov)")
        return []
    t0 = time.perf_counter()
    out = cm.run(progress=progress)
    wall = time.perf_counter() - t0
    return [result("verify.checker_mutation_score", out["score"], "fraction", None, None, None,
                   mutants=out["mutants"], killed=out["killed"], equivalent=out["equivalent"],
                   survived=out["survived"], classes=out["classes"], target=0.9,
                   meets_target=bool(out["score"] >= 0.9), wall_s=wall)]


def run(progress) -> list[dict]:
    """Results verify.mutation_score (paper, arm7: the lower), verify.mutants_wall_s and
    verify.checker_mutation_score."""
    from ..pipeline import run_mutants
    from ..scenario import load_scenario
    scores, walls, rows = {}, {}, {}
    for name in ("paper", "arm7"):
        progress(f"verify: mutation testing on {name}")
        t0 = time.perf_counter()
        out = run_mutants(load_scenario(name))
        walls[name] = time.perf_counter() - t0
        scores[name] = out["score"]
        rows[name] = {"killed": out["killed"], "total": out["total"], "equivalent": out["equivalent"],
                      "survived": [m["id"] for m in out["mutants"] if not m["killed"] and not m["equivalent"]]}
    worst = min(scores, key=scores.get)
    return [
        result("verify.mutation_score", scores[worst], "fraction", None, None, None, target=0.9,
               meets_target=bool(scores[worst] >= 0.9), per_scenario=scores, details=rows),
        result("verify.mutants_wall_s", sum(walls.values()), "s", None, None, None, per_scenario=walls),
    ] + checker_score(progress)
