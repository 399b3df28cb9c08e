"""Bench area `verify`: the mutation score of `verify --mutants` on the built-in scenarios (how much our own
verification catches), with the time it takes."""

from __future__ import annotations

import time

from ._result import result


def run(progress) -> list[dict]:
    """Results verify.mutation_score (paper, arm7: the lower) and verify.mutants_wall_s."""
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
    ]
