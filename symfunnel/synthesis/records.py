"""What `symfunnel tune` writes and reads back: the tuned scenario as the user's own TOML (comments kept), the
`[[deviations]]` record of each change, the original design recovered from those records, and the original/tuned
comparison the report shows.
"""

from __future__ import annotations

import copy
import math
import warnings

import numpy as np

from ..scenario.tune import TuneSpec
from .candidates import Candidate, Evaluator

__all__ = ["tuned_toml", "tune_records", "original_document", "compare_designs", "TUNE_REASON"]


def tuned_toml(scenario, tuned: dict, keys: list[str]) -> str:
    """The tuned scenario as TOML: the user's own file edited (tomlkit: comments, order and layout kept), the tuned
    keys set (each keeping its line's comment) and the new `[[deviations]]` entries appended; a scenario without a
    readable file is written whole."""
    import tomlkit
    from ..core.toml_write import dumps
    try:
        doc = tomlkit.parse(scenario.path.read_text(encoding="utf-8"))
    except (OSError, TypeError, AttributeError, tomlkit.exceptions.TOMLKitError):
        return dumps(tuned)
    orig = scenario.raw
    for key in keys:
        *path, leaf = key.split(".")
        new, old = tuned, orig
        for p in path + [leaf]:
            new = new.get(p) if isinstance(new, dict) else None
            old = old.get(p) if isinstance(old, dict) else None
        if new is None or new == old:
            continue
        t = doc
        for p in path:
            if p not in t:
                t[p] = tomlkit.table()
            t = t[p]
        item = tomlkit.item(new)
        prev = t.get(leaf) if hasattr(t, "get") else None
        if prev is not None and hasattr(prev, "trivia") and prev.trivia.comment:
            item.trivia.comment_ws = prev.trivia.comment_ws or "  "
            item.trivia.comment = prev.trivia.comment
        t[leaf] = item
    added = (tuned.get("deviations") or [])[len(orig.get("deviations") or []):]
    if added:
        if "deviations" not in doc:
            doc["deviations"] = tomlkit.aot()
        for d in added:
            doc["deviations"].append(dict(d))
    return tomlkit.dumps(doc)


def _record_deviations(raw: dict, changes: list[dict], spec: TuneSpec, b: Candidate, ev: Evaluator,
                       status: str) -> None:
    """Append a `[[deviations]]` entry per changed key (old -> new, why) to the tuned document."""
    if not changes:
        return
    impl = ev.impl
    what = (f"sampled loop at {impl.rate_hz:g} Hz" + (f", |tau| <= {', '.join(f'{x:g}' for x in impl.tau_max)}"
                                                      if impl.tau_max else "")) if impl else "continuous-time loop"
    unc = f" on the nominal plant and {len(ev.samples)} uncertainty samples" if ev.samples else " on the nominal plant"
    why = (f"symfunnel tune ({status}): both funnels kept with margin >= {spec.margin:g} in the {what}{unc} "
           f"over {ev.T:g} s, objective {spec.objective} = {b.figures.get(spec.objective, math.nan):.6g}")
    devs = raw.setdefault("deviations", [])
    for c in changes:
        # exact (shortest round-trip) numbers, so that `original_document` restores the user's design
        devs.append({"key": c["key"], "paper": "", "value": f"{float(c['before'])!r} -> {float(c['after'])!r}",
                     "reason": why})


TUNE_REASON = "symfunnel tune ("


def tune_records(raw: dict) -> list[dict]:
    """The `[[deviations]]` entries that `symfunnel tune` wrote into a scenario document (key, old, new)."""
    import re
    from ..scenario.tune import TUNABLE
    out = []
    for d in raw.get("deviations", []) or []:
        if not (isinstance(d, dict) and str(d.get("reason", "")).startswith(TUNE_REASON)):
            continue
        m = re.fullmatch(r"\s*(\S+)\s*->\s*(\S+)\s*", str(d.get("value", "")))
        k = re.fullmatch(r"([a-z0-9_.]+)(?:\[(\d+)\])?", str(d.get("key", "")))
        if not (m and k and k.group(1) in TUNABLE):
            continue
        try:
            old, new = float(m.group(1)), float(m.group(2))
        except ValueError:
            continue
        out.append({"key": k.group(1), "joint": int(k.group(2)) - 1 if k.group(2) else None, "before": old,
                    "after": new, "name": d["key"]})
    return out


def original_document(raw: dict, n: int) -> dict | None:
    """The scenario document before `symfunnel tune` (its records undone, old values back), or None when the
    document carries no tune record. A shared per-joint key gets back old/new times each joint's value (tune kept
    the joints' ratios)."""
    recs = tune_records(raw)
    if not recs:
        return None
    from ..scenario.tune import TUNABLE
    doc = copy.deepcopy(raw)
    for r in reversed(recs):           # the last change first: a key tuned twice returns to its first value
        *path, leaf = r["key"].split(".")
        t = doc
        for p in path:
            t = t.setdefault(p, {})
        cur = t.get(leaf)
        if not TUNABLE[r["key"]][0]:
            t[leaf] = r["before"]
        elif r["joint"] is not None:
            vals = list(cur) if isinstance(cur, list) else [cur] * n
            vals[r["joint"]] = r["before"]
            t[leaf] = vals
        else:
            scale = r["before"] / r["after"]
            t[leaf] = [v * scale for v in cur] if isinstance(cur, list) else cur * scale
    doc["deviations"] = [d for d in doc.get("deviations", [])
                         if not str(d.get("reason", "")).startswith(TUNE_REASON)]
    if not doc["deviations"]:
        del doc["deviations"]
    return doc


def compare_designs(tuned, *, tuned_run=None, t_final: float | None = None, sweep_runs: int | None = None,
                    progress=None) -> dict | None:
    """Original (from tune's `[[deviations]]` records) against tuned, side by side: peak |tau|, min margins e1/e2
    of the continuous-time run, the minimum sample rate (with `[implementation]`) and the breach probability of a
    campaign of the scenario's `[[uncertainty]]` (`sweep_runs` runs, default tune's `runs`). None without records.
    """
    import tempfile
    say = progress or (lambda s: None)
    orig_raw = original_document(tuned.raw, tuned.n)
    if orig_raw is None:
        return None
    from ..scenario import from_dict
    original = from_dict(orig_raw, file=tuned.file, base_dir=tuned.path.parent, default_name=tuned.name)
    spec = tuned.tune or TuneSpec()
    sides = {}
    for label, sc in (("original", original), ("tuned", tuned)):
        from ..pipeline import Run, RunOptions
        say(f"tuning comparison: the {label} design")
        run = tuned_run if label == "tuned" and tuned_run is not None else Run(sc, RunOptions(t_final=t_final))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = run.simulation
        s = sim.signals
        tau = np.abs(np.asarray(s["tau"]))
        side = {"scenario": sc, "simulation": sim, "status": sim.status,
                "peak_torque": float(np.max(tau)) if tau.size else None,
                "min_margin_e1": float(np.min(s["m1"])) if np.size(s["m1"]) else None,
                "min_margin_e2": float(np.min(s["m2"])) if np.size(s["m2"]) else None}
        if sc.implementation is not None:
            from ..deployed.rate import min_rate
            r = min_rate(sc, run.design, margin=spec.margin, t_final=t_final, rel_tol=0.1,
                         start=sc.implementation.rate_hz)
            side["min_rate_hz"] = r["min_rate_hz"]
        if sc.campaign is not None and sc.campaign.uncertainties:
            from ..campaigns.campaign import sweep
            runs = sweep_runs or spec.runs
            with tempfile.TemporaryDirectory(prefix="symfunnel-tune-cmp-") as tmp:
                summ = sweep(sc, runs=runs, workers=1, out=tmp).summary
            side["breach_probability"] = summ["breach_probability"]
            side["breach_ci95"] = summ["ci95"]
            side["runs"] = runs
        sides[label] = side
    return {"original": sides["original"], "tuned": sides["tuned"], "changes": tune_records(tuned.raw)}
