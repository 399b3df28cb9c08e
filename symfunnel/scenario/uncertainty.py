"""`[[uncertainty]]` and `[sweep]` scenario sections: what a robustness campaign varies and how it samples it.

Every uncertain key is a quantity of the plant side or of `[initial]` (the controller's model stays nominal;
`plant.mujoco.*` keys exist only in a physics engine and need a sweep on it, `sweep --plant mujoco`). A
campaign's run `i` draws a point u in [0, 1)^d of the design of experiments (Sobol, Latin hypercube or plain
random, seeded) and maps each coordinate through its distribution; u, hence every value of run i, is a pure
function of (seed, i) (and, for a Latin hypercube, of the campaign's size), so any run reproduces alone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core import validate as V
from ..core.errors import InputError

DESIGNS = ("sobol", "lhs", "random")
DISTS = {"uniform": ("low", "high"), "normal": ("mean", "std"), "choice": ("values",)}
MAX_RUNS = 10 ** 7
NORMAL_CLIP = 5.0          # normal draws are the inverse CDF of u clipped to +-5 std (bounded, reproducible)
CONTROLLER_SECTIONS = ("model", "reference", "funnel", "controller", "adaptation", "esn")

# uncertain key -> (per-joint quantity?, lower bound, strict?) ; None: unbounded
_PLANT_KEYS = {
    "plant.mass_scale": (False, 0.0, True),
    "plant.viscous": (True, 0.0, False),
    "plant.coulomb": (True, 0.0, False),
    "plant.disturbance_scale": (True, 0.0, False),
    "plant.dead_zone.b_l": (True, None, None),          # must stay < 0: checked as an upper bound below
    "plant.dead_zone.b_r": (True, 0.0, True),
    "plant.dead_zone.left_scale": (True, 0.0, True),
    "plant.dead_zone.right_scale": (True, 0.0, True),
    "plant.mujoco.mass_scale": (True, 0.0, True),      # engine-only (a sweep on the mujoco plant)
    "plant.mujoco.damping": (True, 0.0, False),
    "plant.mujoco.armature": (True, 0.0, False),
    "initial.q": (True, None, None),
    "initial.dq": (True, None, None),
}


@dataclass
class Uncertainty:
    """One `[[uncertainty]]` table: a scenario key, its distribution and whether each joint draws its own value."""

    key: str
    dist: str
    args: dict
    per_joint: bool
    columns: list[str]               # result columns: [key] or [key[1], ..., key[n]]

    def transform(self, u: np.ndarray) -> np.ndarray:
        """Values of this quantity for design points u in [0, 1) (any shape)."""
        u = np.asarray(u, dtype=float)
        if self.dist == "uniform":
            return self.args["low"] + u * (self.args["high"] - self.args["low"])
        if self.dist == "normal":
            from scipy.stats import norm
            lo, hi = norm.cdf(-NORMAL_CLIP), norm.cdf(NORMAL_CLIP)
            return self.args["mean"] + self.args["std"] * norm.ppf(np.clip(u, lo, hi))
        vals = np.asarray(self.args["values"], dtype=float)
        return vals[np.minimum((u * vals.size).astype(int), vals.size - 1)]

    def extremes(self) -> tuple[float, float]:
        """The smallest and largest value this distribution can give."""
        if self.dist == "uniform":
            return self.args["low"], self.args["high"]
        if self.dist == "normal":
            return (self.args["mean"] - NORMAL_CLIP * self.args["std"],
                    self.args["mean"] + NORMAL_CLIP * self.args["std"])
        return min(self.args["values"]), max(self.args["values"])


@dataclass
class SweepSpec:
    """The `[sweep]` table: how many runs, which design of experiments, its seed and the horizon."""

    runs: int = 100
    design: str = "sobol"
    seed: int = 0
    t_final: float | None = None


@dataclass
class Campaign:
    """A scenario's uncertainties and sweep settings."""

    uncertainties: list[Uncertainty] = field(default_factory=list)
    sweep: SweepSpec = field(default_factory=SweepSpec)

    @property
    def columns(self) -> list[str]:
        """One result column per drawn value, in file order."""
        return [c for u in self.uncertainties for c in u.columns]

    def values(self, run_ids, runs: int | None = None) -> np.ndarray:
        """The drawn values (len(run_ids), len(columns)) of the given runs; a pure function of (seed, run id)."""
        ids = np.asarray(run_ids, dtype=np.int64).reshape(-1)
        U = design_points(self.sweep.design, len(self.columns), self.sweep.seed, ids,
                          self.sweep.runs if runs is None else runs)
        out = np.empty_like(U)
        j = 0
        for unc in self.uncertainties:
            k = len(unc.columns)
            out[:, j:j + k] = unc.transform(U[:, j:j + k])
            j += k
        return out


def check_runs(runs: Any, *, file: str | None, key: str) -> int:
    """A campaign size: an integer in 1 .. 10^7."""
    if isinstance(runs, bool) or not isinstance(runs, int):
        raise InputError(f"is {V.a_type(runs)}", file=file, key=key, expected=f"an integer in 1 .. {MAX_RUNS}")
    if not 1 <= runs <= MAX_RUNS:
        raise InputError(f"is {runs}", file=file, key=key, expected=f"an integer in 1 .. {MAX_RUNS}")
    return runs


# --- designs of experiments ------------------------------------------------------------------------------

def design_points(design: str, d: int, seed: int, run_ids, runs: int) -> np.ndarray:
    """Points in [0, 1)^d of runs `run_ids` of a campaign of `runs` runs (d = 0 gives (k, 0))."""
    ids = np.asarray(run_ids, dtype=np.int64).reshape(-1)
    if d == 0:
        return np.zeros((ids.size, 0))
    if design == "random":
        return np.stack([np.random.default_rng([seed, int(i)]).random(d) for i in ids]) if ids.size else \
            np.zeros((0, d))
    if design == "lhs":
        return _lhs(d, seed, runs)[ids]
    if design == "sobol":
        return _sobol(d, seed, ids)
    raise ValueError(f"unknown design {design!r}")


@functools.lru_cache(maxsize=4)
def _lhs(d: int, seed: int, runs: int) -> np.ndarray:
    from scipy.stats import qmc
    return qmc.LatinHypercube(d, seed=seed).random(runs)


def _sobol(d: int, seed: int, ids: np.ndarray) -> np.ndarray:
    """Points `ids` of the scrambled Sobol sequence of (d, seed): contiguous blocks are drawn by fast-forwarding."""
    from ..core.sobol import sobol               # scipy's points without importing scipy.stats
    out = np.empty((ids.size, d))
    if ids.size == 0:
        return out
    order = np.argsort(ids, kind="stable")
    s = ids[order]
    breaks = np.flatnonzero(np.diff(s) != 1) + 1
    for block in np.split(np.arange(s.size), breaks):
        out[order[block]] = sobol(d, block.size, seed, skip=int(s[block[0]]))
    return out


# --- parsing ---------------------------------------------------------------------------------------------

def allowed_keys(n: int, model) -> list[str]:
    """Every key an `[[uncertainty]]` table may name for this scenario."""
    return list(_PLANT_KEYS) + [f"plant.parameters.{k}" for k in model.p_names]


def parse_campaign(raw: dict, *, file: str, n: int, model, plant) -> Campaign | None:
    """The scenario's campaign, or None when it has neither `[[uncertainty]]` nor `[sweep]`."""
    if "uncertainty" not in raw and "sweep" not in raw:
        return None
    items = raw.get("uncertainty", [])
    if not isinstance(items, list):
        raise InputError(f"is {V.a_type(items)}", file=file, key="uncertainty",
                         expected="an array of tables ([[uncertainty]])")
    allowed = allowed_keys(n, model)
    seen: set[str] = set()
    uncs = []
    for i, t in enumerate(items):
        uncs.append(_uncertainty(t, f"uncertainty[{i}]", file, n, allowed, seen))
    _check_dead_zone_range(uncs, plant, n, file)
    return Campaign(uncs, _sweep(raw.get("sweep", {}), file))


def _uncertainty(t: Any, p: str, file: str, n: int, allowed: list[str], seen: set) -> Uncertainty:
    V.check_keys(t, ["key", "dist", "per_joint", "low", "high", "mean", "std", "values"], file=file, prefix=p,
                 required=["key", "dist"])
    key = V.get_str(t, "key", file=file, prefix=p)
    section = key.split(".", 1)[0]
    if section in CONTROLLER_SECTIONS:
        alt = "plant." + key.split(".", 1)[1] if key.startswith("model.parameters.") else None
        raise InputError(f"is '{key}', which the controller sees (its model stays nominal; uncertainty is the "
                         f"plant's){'; did you mean ' + repr(alt) + '?' if alt in allowed else ''}", file=file,
                         key=p + ".key", expected="a key of [plant] or [initial]")
    if key not in allowed:
        raise InputError(f"is '{key}', not an uncertain quantity{V.did_you_mean(key, allowed)}", file=file,
                         key=p + ".key", expected="one of " + ", ".join(allowed))
    if key in seen:
        raise InputError(f"'{key}' is given twice", file=file, key=p + ".key", expected="each key once")
    seen.add(key)
    dist = V.get_str(t, "dist", file=file, prefix=p, choices=list(DISTS))
    for k in t:
        if k in ("low", "high", "mean", "std", "values") and k not in DISTS[dist]:
            hint = V.did_you_mean(k, DISTS[dist])
            raise InputError(f"unknown key for dist = '{dist}'{hint}", file=file, key=f"{p}.{k}",
                             expected="one of " + ", ".join(DISTS[dist]))
    per_joint_qty = _PLANT_KEYS.get(key, (False,))[0]
    per_joint = V.get_bool(t, "per_joint", False, file=file, prefix=p)
    if per_joint and not per_joint_qty:
        raise InputError("is true for a quantity with one value", file=file, key=p + ".per_joint",
                         expected="false (or absent)")
    args: dict = {}
    if dist == "uniform":
        args["low"] = V.get_float(t, "low", file=file, prefix=p)
        args["high"] = V.get_float(t, "high", file=file, prefix=p)
        if not args["low"] < args["high"]:
            raise InputError(f"is {args['high']:g} with low = {args['low']:g}", file=file, key=p + ".high",
                             expected="low < high")
    elif dist == "normal":
        args["mean"] = V.get_float(t, "mean", file=file, prefix=p)
        args["std"] = V.get_float(t, "std", file=file, prefix=p, minimum=0, strict_min=True)
    else:
        vals = V.get_list(t, "values", file=file, prefix=p)
        if not vals:
            raise InputError("is empty", file=file, key=p + ".values", expected="at least one number")
        args["values"] = [V.as_float(v, file=file, key=f"{p}.values[{j}]") for j, v in enumerate(vals)]
    cols = [f"{key}[{j + 1}]" for j in range(n)] if per_joint else [key]
    unc = Uncertainty(key, dist, args, per_joint, cols)
    lo, hi = unc.extremes()
    bad = None
    if key == "plant.dead_zone.b_l" and not hi < 0:
        bad = "values < 0 (eq. 2 needs b_l < 0)"
    elif key in _PLANT_KEYS and _PLANT_KEYS[key][1] is not None:
        _, bound, strict = _PLANT_KEYS[key]
        if lo < bound or (strict and lo == bound):
            bad = f"values {'>' if strict else '>='} {bound:g}"
    if bad:
        what = "mean - 5 std" if dist == "normal" else ("low" if dist == "uniform" else "every value")
        raise InputError(f"can give {hi if key.endswith('b_l') else lo:g} ({what})", file=file, key=p,
                         expected=bad)
    return unc


def _check_dead_zone_range(uncs: list[Uncertainty], plant, n: int, file: str) -> None:
    """The dead zone's branches must stay continuous and increasing at the extreme breakpoints the campaign draws."""
    by = {u.key: u for u in uncs}
    if plant.dead_zone is None:
        for k in by:
            if k.startswith("plant.dead_zone."):
                raise InputError("the scenario's plant has no dead zone", file=file, key="uncertainty",
                                 expected=f"a [plant.dead_zone] table to vary {k}")
        return
    if "plant.dead_zone.b_l" not in by and "plant.dead_zone.b_r" not in by:
        return
    from ..plant.nonlinearities import DeadZoneSpec
    from ..plant.nonlinearities import check_dead_zone_spec as _check_dead_zone
    dz = plant.dead_zone
    for pick in (0, 1):
        b = {}
        for k, nominal in (("b_l", dz.b_l), ("b_r", dz.b_r)):
            u = by.get(f"plant.dead_zone.{k}")
            b[k] = [u.extremes()[pick]] * n if u else list(nominal)
        try:
            _check_dead_zone(DeadZoneSpec(b["b_l"], b["b_r"], dz.left, dz.right), n, file)
        except InputError as exc:
            raise InputError(f"at the campaign's extreme breakpoints: {exc.reason}", file=file,
                             key=exc.key, expected=exc.expected) from None


def _sweep(t: Any, file: str) -> SweepSpec:
    p = "sweep"
    V.check_keys(t, ["runs", "design", "seed", "t_final"], file=file, prefix=p)
    d = SweepSpec()
    runs = check_runs(t.get("runs", d.runs), file=file, key="sweep.runs")
    design = V.get_str(t, "design", d.design, file=file, prefix=p, choices=list(DESIGNS))
    seed = V.get_int(t, "seed", d.seed, file=file, prefix=p, minimum=0, maximum=2 ** 63 - 1)
    tf = V.get_float(t, "t_final", None, file=file, prefix=p, minimum=0, strict_min=True, maximum=1e6) \
        if "t_final" in t else None
    return SweepSpec(runs, design, seed, tf)


# --- applying a run's values -----------------------------------------------------------------------------

def run_inputs(campaign: Campaign, cl, values: np.ndarray) -> tuple[dict, np.ndarray]:
    """Plant parameters (names of `plant.equations.plant_parameters`) and initial state of one run's drawn values."""
    params: dict = {}
    x0 = cl.x0.copy()
    n = cl.n
    j = 0
    for unc in campaign.uncertainties:
        k = len(unc.columns)
        v = np.broadcast_to(values[j:j + k], (n,)) if _PLANT_KEYS.get(unc.key, (False,))[0] else values[j:j + k]
        j += k
        if unc.key in ("initial.q", "initial.dq"):
            off = 0 if unc.key == "initial.q" else n
            x0[off:off + n] = v
        elif _PLANT_KEYS.get(unc.key, (False,))[0]:
            params.update({f"{unc.key}[{i + 1}]": float(v[i]) for i in range(n)})
        else:
            params[unc.key] = float(v[0])
    return params, x0


def scenario_edits(campaign: Campaign, n: int, values: np.ndarray) -> dict[str, Any]:
    """Dotted scenario key -> value (a number, or a list per joint) that reproduce one run's drawn values."""
    out: dict[str, Any] = {}
    j = 0
    for unc in campaign.uncertainties:
        k = len(unc.columns)
        v = [float(x) for x in values[j:j + k]]
        j += k
        per_joint_qty = _PLANT_KEYS.get(unc.key, (False,))[0]
        out[unc.key] = (v if unc.per_joint else v * n) if per_joint_qty else v[0]
    return out
