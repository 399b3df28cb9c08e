"""The one orchestrator: a `Run` carries a scenario through the pipeline, computing each stage once, on demand.

    scenario -> design -> closed loop -> simulation -> Lyapunov argument (W* fitted once) -> verification
                      \\-> audit                                       \\-> code (C, Python)

Every command, the report and the Python API go through a Run; no stage below rebuilds a stage above (they take
what they need as arguments), so a report derives, compiles, simulates and fits W* exactly once.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from .core import deadline
from .checks import theory as _theory
from .design import derive, variant_of
from .scenario import Scenario, load_scenario

if TYPE_CHECKING:
    from .checks.audit import CheckResult
    from .checks.lyapunov import LyapunovTrajectory
    from .checks.verify import Verification
    from .simulation.closedloop import ClosedLoop
    from .design import Design
    from .simulation.result import SimResult


@dataclass
class RunOptions:
    """Settings a command may override for the stages of one run (None: the scenario's own)."""

    t_final: float | None = None
    integrator: str | None = None
    width: float | None = None
    wall_limit: float | None = None
    jit: bool = True
    samples: int = 10000            # falsification states of verify
    seed: int = 0
    mutant: str | None = None       # derive the design with this seeded error (verify --mutants)
    rate_hz: float | None = None    # verify the sampled-data controller at this rate (overrides [implementation])
    engine: str | None = None       # the plant of the sampled loop (overrides [plant] engine)
    certify: bool = True            # verify includes the certificates (mutation testing leaves them out)
    certify_only: tuple[str, ...] | None = None   # which certificates (None: all)
    certify_wall_limit: float | None = None       # seconds for the certificates' searches (None: no limit)
    certify_work: float = 0.1       # share of the certificates' full work budget (verify: a tenth; certify: all)


@dataclass
class Run:
    """One scenario through the pipeline; each stage is a cached property computed on first use."""

    scenario: Scenario
    options: RunOptions = field(default_factory=RunOptions)
    progress: Callable[[str], None] | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @classmethod
    def load(cls, name_or_path=None, **options) -> Run:
        """A Run of a built-in scenario name or a TOML path, with option overrides as keywords."""
        progress = options.pop("progress", None)
        return cls(load_scenario(name_or_path), RunOptions(**options), progress)

    def _say(self, msg: str) -> None:
        if self.progress:
            self.progress(msg)

    def _timed(self, name: str, fn, what: str | None = None):
        t0 = time.perf_counter()
        with deadline.step(what or name):
            out = fn()
        self.timings[name] = time.perf_counter() - t0
        return out

    def _bounded(self, name: str, fn, what: str):
        """A stage of getting the trajectory (derive, build, compile, integrate): all of them within the Run's
        wall-clock limit (RunOptions.wall_limit, else the scenario's [simulation] wall_limit), counted over the time
        spent inside them (a Run kept and used again later starts from what its earlier stages used, not from the
        clock); integration stops gracefully at it, the others raise deadline.WallLimitReached."""
        budget = self.__dict__.setdefault("_budget", {"spent": 0.0, "depth": 0})
        seconds = self.wall_limit
        if budget["depth"] == 0:             # a stage inside another runs under the outer one's deadline
            now = time.monotonic()
            budget["entered"] = now
            budget["expiry"] = now + seconds - budget["spent"] if seconds else float("inf")
            budget["started"] = now - budget["spent"]
        budget["depth"] += 1
        try:
            with deadline.until(budget["expiry"], seconds, budget["started"]):
                return self._timed(name, fn, what)
        finally:
            budget["depth"] -= 1
            if budget["depth"] == 0:
                budget["spent"] += time.monotonic() - budget["entered"]

    @property
    def wall_limit(self) -> float | None:
        """The seconds the stages of getting the trajectory may take together (None or 0: no limit)."""
        return self.options.wall_limit if self.options.wall_limit is not None else self.scenario.simulation.wall_limit

    @property
    def t_final(self) -> float:
        """The horizon of this run."""
        return float(self.options.t_final if self.options.t_final is not None else self.scenario.simulation.t_final)

    # --- stages ---------------------------------------------------------------------------------------

    @cached_property
    def design(self) -> Design:
        """The design, derived once (with the run's mutant, if any)."""
        from .design import derive
        self._say("deriving the design" + (f" (mutant {self.options.mutant})" if self.options.mutant else ""))
        return self._bounded("derive", lambda: derive(self.scenario, mutant=self.options.mutant), "deriving the design")

    @cached_property
    def closed_loop(self) -> ClosedLoop:
        """The closed-loop ODE of plant and controller."""
        from .simulation.closedloop import build_closed_loop
        self._say("building the closed loop")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            design = self.design
            return self._bounded("closed_loop", lambda: build_closed_loop(self.scenario, design,
                                                                          width=self.options.width),
                                 "building the closed loop")

    @cached_property
    def simulation(self) -> SimResult:
        """The simulated closed loop (SimResult)."""
        from .simulation import simulate
        o = self.options
        self._say("simulating the closed loop")
        design, cl = self.design, self.closed_loop
        res = self._bounded("simulate", lambda: simulate(
            self.scenario, design, t_final=o.t_final, integrator=o.integrator, width=o.width,
            progress=self.progress, wall_limit=o.wall_limit, closed_loop=cl, jit=o.jit),
            "compiling and integrating the closed loop")
        from .simulation.hints import status_text
        self._say(f"simulation: {status_text(res.status)} ({res.message})")
        return res

    @cached_property
    def lyapunov(self) -> LyapunovTrajectory | None:
        """The Lyapunov argument along the simulated trajectory (W* fitted once), or None without a trajectory."""
        from .checks.lyapunov import along_trajectory
        from .checks.verify import decay_claim
        res = self.simulation
        if not res.t.size:
            return None
        self._say("Lyapunov function and its exact derivative along the trajectory (AD)")
        return self._timed("lyapunov", lambda: along_trajectory(self.closed_loop, res.t, res.x, res.signals["f_true"],
                                                                claim=decay_claim(self.scenario)),
                           "evaluating the Lyapunov function along the trajectory")

    @cached_property
    def audit(self) -> list[CheckResult]:
        """The audit's checks (model, funnels, printed claims)."""
        from .checks.audit import audit
        from .checks.gate import apply_expectations
        return apply_expectations(self.scenario, self._timed(
            "audit", lambda: audit(self.scenario, self.design, progress=self.progress), "auditing the model and claims"))

    @cached_property
    def verification(self) -> Verification:
        """Every verify check on the simulated closed loop, the certificates' included (unless options.certify is
        off), with the scenario's expectations applied to all of them."""
        from .checks.gate import apply_expectations
        from .checks.verify import verify
        o = self.options
        v = self._timed("verify", lambda: verify(
            self.scenario, self.design, self.closed_loop, self.simulation, self.lyapunov, self.audit,
            t_final=self.t_final, samples=o.samples, seed=o.seed, progress=self.progress, rate_hz=o.rate_hz,
            engine=o.engine),
            "running verify's checks")
        if o.certify:
            v.certification = self.certification
            v.checks.extend(v.certification.checks(self.scenario))
            apply_expectations(self.scenario, v.checks)
        return v

    @cached_property
    def certification(self):
        """The certificates (`symfunnel certify`): interval proofs over the scenario's regions, with W* and the
        W_hat range of the simulated run where the design has adaptive weights; cached in-process by the
        scenario's content and the horizon (the same input gives the same certificates)."""
        from .certificates import run_certificates
        o = self.options
        design = self.design
        W = info = wr = None
        only = o.certify_only
        if design.n_regressor and (only is None or set(only) & {"certify.bounds", "certify.invariance",
                                                                           "certify.sampled"}):
            res = self.simulation
            L = self.lyapunov
            if L is not None and res.status != "timeout":
                W, info = L.W_star, L.w_star_info
                wh = self.closed_loop.unpack(res.x).get("w_hat")
                if wh is not None and len(wh):
                    wr = (np.min(wh, axis=0), np.max(wh, axis=0))
        breach = None
        if only is None or "certify.containment" in only:      # a real breach from x0 refutes containment
            res = self.simulation
            if res.status in ("breach", "initial_outside"):
                b = res.breach or {}
                breach = {"t": float(b.get("time", res.t[-1] if len(res.t) else 0.0)),
                          "q": np.asarray(res.signals["q"][-1]).tolist() if len(res.t) else None,
                          "dq": np.asarray(res.signals["dq"][-1]).tolist() if len(res.t) else None,
                          **{k: b[k] for k in ("funnel", "joint", "abs_error", "boundary") if k in b},
                          "message": res.message}
        key = _certification_key(self.scenario, self.t_final, only, o.mutant, o.certify_work, design=design)
        if o.certify_wall_limit is None and key in _CERTIFICATIONS:
            return _CERTIFICATIONS[key]
        wall = o.certify_wall_limit
        budget, seconds = self.__dict__.get("_budget"), self.wall_limit
        if wall is not None and budget is not None and seconds:     # what deriving and simulating left of it
            wall = max(0.0, min(wall, seconds - budget["spent"]))
        self._say("certificates: interval branch and bound on the design's graph")
        cert = self._timed("certify", lambda: run_certificates(
            self.scenario, design, t_final=self.t_final, W_star=W, w_star_info=info, w_hat_range=wr, only=only,
            wall_limit=wall, work=scaled_work(o.certify_work), progress=self.progress, breach=breach),
            "proving the certificates")
        if o.certify_wall_limit is None:
            _CERTIFICATIONS[key] = cert
            while len(_CERTIFICATIONS) > 8:
                _CERTIFICATIONS.pop(next(iter(_CERTIFICATIONS)))
        return cert

    @cached_property
    def mutation(self) -> dict:
        """`verify --mutants`: the design's seeded errors through the same gate (`run_mutants`; the list is the
        design variant's `mutants()`, e.g. `design.backstepping.MUTANTS`)."""
        return self._timed("mutants", lambda: run_mutants(self.scenario, samples=min(self.options.samples, 2000),
                                                          seed=self.options.seed, progress=self.progress),
                           "testing the verifier on the design's mutants")

    @cached_property
    def implementation(self) -> dict:
        """The deployed controller: minimum sample rate, the design help (which parameter sets it), the sampled run
        at the scenario's rate (twice the minimum without [implementation]) and its peak torque beside the limits."""
        from .deployed.summary import implementation_report
        return self._timed("implementation", lambda: implementation_report(
            self.scenario, self.design, t_final=self.t_final, progress=self.progress),
            "checking the deployed controller")

    @cached_property
    def engine_comparison(self) -> dict | None:
        """The deployed controller on symfunnel's plant and on the run's physics engine side by side (None on
        symfunnel's plant only, or without a rate to compare at): at the deployed section's rate, reusing its run."""
        engine = self.options.engine or self.scenario.plant.engine
        if engine == "symfunnel":
            return None
        from .deployed.compare import engine_comparison
        data = self.implementation
        res = (data.get("run") or {}).get("result")
        if res is None:
            return None
        return self._timed("engine_comparison", lambda: engine_comparison(
            self.scenario, self.design, rate_hz=res.rate_hz, engine=engine, t_final=self.t_final, symfunnel_run=res,
            symfunnel_min_rate=data["min_rate"], progress=self.progress), f"the deployed controller on {engine}")

    def trajectory_arrays(self) -> dict[str, np.ndarray]:
        """The simulated trajectory with V (from the one Lyapunov stage) and W*, for `simulate --out`."""
        res = self.simulation
        data = {"t": res.t, **{k: np.asarray(v) for k, v in res.signals.items()}}
        L = self.lyapunov
        if L is not None:
            data["V"] = L.V
            data["W_star"] = L.W_star
        return data

    @cached_property
    def code_trajectory(self) -> dict[str, np.ndarray]:
        """Controller inputs at 50 samples of the simulated run's first 2 s (for the generated main programs)."""
        from .emit.contract import trajectory_from_run
        return trajectory_from_run(self.design, self.closed_loop, self.simulation)

    def code(self, lang: str, *, prefix: str | None = None, rate_hz: float | None = None) -> dict[str, str]:
        """The generated files of one language ({name: text}), generated once per language and C options."""
        cache = self.__dict__.setdefault("_code", {})
        key = (lang, prefix, rate_hz)
        if key not in cache:
            from .emit.files import generate
            cache[key] = generate(self.design, lang, trajectory=self.code_trajectory, prefix=prefix, rate_hz=rate_hz)
        return cache[key]


#: certifications computed in this process, by scenario content, horizon and selection (deterministic results)
_CERTIFICATIONS: dict = {}


def scaled_work(share: float) -> dict:
    """Each certificate's work budget times `share` (verify's gate runs them at a tenth of `certify`'s budget, so a
    verify on a new scenario stays interactive; a search cut short says `undecided`, never a wrong verdict)."""
    from .certificates import DEFAULT_WORK
    return {k: float(v) * float(share) for k, v in DEFAULT_WORK.items()}


def _certification_key(scenario, t_final: float, only, mutant=None, work: float = 1.0, design=None) -> str:
    """The in-process certification cache's key: the scenario's content, the horizon, the certificates and their
    budget, and the design's own graph (`Design.fingerprint`) where a design is given."""
    import hashlib
    import json
    # the files the scenario reads (a URDF: {path: sha256}) are part of it: an edited robot is another scenario
    text = json.dumps([str(scenario.path), scenario.raw, getattr(scenario, "inputs", {}), float(t_final),
                       sorted(only) if only else None, mutant, float(work),
                       None if design is None else design.fingerprint()],
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


# --- mutation testing of the verifier ---------------------------------------------------------------------
# Each seeded error of the design (`Design.variant.mutants()`) goes through the same gate as the design itself; a
# verifier that lets one through has a blind spot. Cheapest checks first: a mutant the design identity already
# rejects (no simulation needed) is killed by it; the others are simulated over a short horizon and run through every
# check. A mutant counts as killed by the checks whose outcome is unexpected for it but not for the unmutated design
# at the same horizon. A mutant is equivalent only with a proof from the variant (e.g. `drop_G` when G is identically
# zero); score = killed / (total - equivalent).

#: horizon of the simulated stage of mutation testing (the scenario's own when shorter)
MUTANT_HORIZON = 2.0
#: a mutant's identity check judges these first states of its 2000 first (`check_identity(failure_first=...)`):
#: only whether it fails is read, and a seeded error fails it at nearly every state (arm7: 16 mutants, 0.3 s each)
MUTANT_IDENTITY_FIRST = 200


def check_identity(design, rng):
    """design.identity.vdot as mutation testing runs it: the same status as `checks.theory.check_identity`, a failure
    found among the first MUTANT_IDENTITY_FIRST states ending it (`failure_first`)."""
    return _theory.check_identity(design, rng, failure_first=MUTANT_IDENTITY_FIRST)


def run_mutants(scenario, *, t_final: float | None = None, samples: int = 2000, seed: int = 0,
                progress=None) -> dict:
    """{"mutants": [{"id", "description", "killed", "equivalent", "by", "proof"}], "score", "killed", "total",
    "equivalent", "horizon"} for every mutant of the scenario's design."""
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
            baseline = {c.id: c for c in Run(scenario, RunOptions(t_final=horizon, samples=samples, seed=seed,
                                                                  certify=False)).verification.checks}
        v = Run(scenario, RunOptions(t_final=horizon, samples=samples, seed=seed, mutant=m.id,
                                     certify=False)).verification
        by = [c.id for c in v.checks if c.unexpected and not (c.id in baseline and baseline[c.id].unexpected)]
        row.update(killed=bool(by), by=by)
        rows.append(row)
    total = len(rows)
    eq = sum(r["equivalent"] for r in rows)
    killed = sum(r["killed"] for r in rows)
    score = killed / (total - eq) if total > eq else 1.0
    return {"scenario": scenario.name, "mutants": rows, "score": score, "killed": killed, "total": total,
            "equivalent": eq, "horizon": horizon}
