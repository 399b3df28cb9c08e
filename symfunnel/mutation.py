"""Mutation testing of the verifier: each seeded error of the design (`Design.variant.mutants()`) goes through the
same gate as the design itself; a verifier that lets one through has a blind spot.

Cheapest checks first: a mutant the design identity already rejects (no simulation needed) is killed by it; the
others are simulated over a short horizon and run through every check. A mutant counts as killed by the checks
whose outcome is unexpected for it but not for the unmutated design at the same horizon. A mutant is equivalent only
with a proof from the variant (e.g. `drop_G` when G is identically zero); score = killed / (total - equivalent).
"""

from __future__ import annotations

import numpy as np

from .design import derive, variant_of
from .checks.theory import check_identity

#: horizon of the simulated stage of mutation testing (the scenario's own when shorter)
MUTANT_HORIZON = 2.0


def run_mutants(scenario, *, t_final: float | None = None, samples: int = 2000, seed: int = 0,
                progress=None) -> dict:
    """{"mutants": [{"id", "description", "killed", "equivalent", "by", "proof"}], "score", "killed", "total",
    "equivalent", "horizon"} for every mutant of the scenario's design."""
    from .pipeline import Run, RunOptions
    say = progress or (lambda s: None)
    horizon = float(t_final if t_final is not None else min(MUTANT_HORIZON, scenario.simulation.t_final))
    variant = variant_of(scenario)
    baseline = None
    rows = []
    for i, m in enumerate(variant.mutants()):
        say(f"mutant {i + 1}/{len(variant.mutants())}: {m.id}")
        design = derive(scenario, mutant=m.id)
        row = {"id": m.id, "description": m.description, "killed": False, "equivalent": False, "by": [],
               "proof": None}
        proof = variant.equivalent(design, m.id)
        if proof:
            row.update(equivalent=True, proof=proof)
            rows.append(row)
            continue
        ident = check_identity(design, np.random.default_rng([seed, 11]))
        if ident.status == "fail":
            row.update(killed=True, by=[ident.id])
            rows.append(row)
            continue
        if baseline is None:
            say("unmutated design at the same horizon (the reference outcomes)")
            baseline = {c.id: c for c in Run(scenario, RunOptions(t_final=horizon, samples=samples,
                                                                  seed=seed)).verification.checks}
        v = Run(scenario, RunOptions(t_final=horizon, samples=samples, seed=seed, mutant=m.id)).verification
        by = [c.id for c in v.checks if c.unexpected and not (c.id in baseline and baseline[c.id].unexpected)]
        row.update(killed=bool(by), by=by)
        rows.append(row)
    total = len(rows)
    eq = sum(r["equivalent"] for r in rows)
    killed = sum(r["killed"] for r in rows)
    score = killed / (total - eq) if total > eq else 1.0
    return {"scenario": scenario.name, "mutants": rows, "score": score, "killed": killed, "total": total,
            "equivalent": eq, "horizon": horizon}
