"""The Python API: one function per CLI command, the same options as keyword arguments, results with `to_json()`
(and `_repr_html_` for notebooks); bad input raises `InputError`, a failed gate `CheckFailed` (with `strict=True`),
a reached `wall_limit=` (seconds, the whole call as for the CLI's --wall-limit) `SimulationError`.

These are what `symfunnel.simulate`, `symfunnel.codegen`, ... are: plain functions (no package of symfunnel has the
name of one of them). A scenario is a built-in name (`"paper"`, `"arm7"`), a path to a TOML file or a `Scenario`.
"""

from __future__ import annotations

import functools
import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from .core import deadline
from .core.errors import CheckFailed, SimulationError
from .design import derive, evaluate
from .pipeline import Run, RunOptions, run_mutants
from .scenario import Scenario, load_scenario

if TYPE_CHECKING:
    from .campaigns.campaign import SweepResult
    from .emit.check import CheckReport
    from .deployed.fmu import FmuExport
    from .synthesis.search import TuneResult

__all__ = ["load_scenario", "derive", "evaluate", "run", "Run", "audit", "simulate", "verify", "certify", "codegen",
           "rate", "report", "sweep", "tune", "init"]


def _scenario(scenario) -> Scenario:
    return scenario if isinstance(scenario, Scenario) else load_scenario(scenario)


def _table(rows: list[tuple[str, ...]], head: tuple[str, ...]) -> str:
    cells = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{cells}</tr>{body}</table>"


class Checks(list):
    """A list of CheckResult with `to_json()` and a notebook table."""

    def to_json(self) -> dict:
        """{"checks": [...]} as `audit --json` prints it."""
        return {"checks": [c.to_json() for c in self]}

    def _repr_html_(self) -> str:
        return _table([(c.id, c.status, c.expected, c.detail) for c in self], ("check", "status", "expected", "detail"))


@dataclass
class CodegenResult:
    """Generated files (name -> text), where they were written, and the cross-check when asked for."""

    scenario: str
    language: str
    files: dict[str, str]
    paths: list[Path] = field(default_factory=list)
    check: CheckReport | None = None

    def __repr__(self) -> str:
        return (f"CodegenResult(scenario={self.scenario!r}, language={self.language!r}, files={list(self.files)}"
                + ("" if self.check is None else f", check passed={self.check.passed}") + ")")

    def to_json(self) -> dict:
        """The shape of `codegen --json`."""
        out = {"scenario": self.scenario, "language": self.language,
               "files": [{"name": k, "bytes": len(v.encode("utf-8"))} for k, v in self.files.items()]}
        if self.check is not None:
            out["check"] = self.check.to_json()
        return out


@dataclass
class ReportResult:
    """Where the report was written."""

    path: Path

    def to_json(self) -> dict:
        """{"path": ...}."""
        return {"path": str(self.path)}

    def _repr_html_(self) -> str:
        return f"<p>report written to <code>{html.escape(str(self.path))}</code></p>"


#: CLI options whose keyword is not the option's name with "-" as "_" (a `--no-x` flag is `x=False`)
OPTION_KEYWORDS = {"rate": "rate_hz", "from": "source"}


def keyword_of(option: str) -> str:
    """The API keyword of a CLI option: `--t-final` -> `t_final`, `--rate` -> `rate_hz`, `--no-jit` -> `jit`."""
    name = option.lstrip("-")
    name = name[3:] if name.startswith("no-") else name
    return OPTION_KEYWORDS.get(name, name.replace("-", "_"))


def _keyword_text(text: str | None) -> str | None:
    """`text` with every CLI option it names (`--t-final`) as the API keyword (`t_final=`)."""
    import re
    if text is None:
        return None
    return re.sub(r"(?<![\w-])--([a-z][a-z0-9-]*)", lambda m: keyword_of(m.group(1)), text)


def _keywords(fn):
    """The API's view of a function shared with the CLI: `rate=` accepted for `rate_hz=`, and an InputError naming a
    CLI option (`--t-final`) raised again naming the keyword (`t_final`)."""
    from .core.errors import InputError

    @functools.wraps(fn)
    def call(*args, **kw):
        if "rate" in kw:
            if "rate_hz" in kw:
                raise InputError("is given with rate_hz", key="rate", expected="one of rate= and rate_hz=")
            kw["rate_hz"] = kw.pop("rate")
        try:
            return fn(*args, **kw)
        except InputError as exc:
            if not (exc.key or "").startswith("--") and "--" not in str(exc):
                raise
            key = keyword_of(exc.key) if (exc.key or "").startswith("--") else exc.key
            raise InputError(_keyword_text(exc.reason), file=exc.file, key=key, expected=_keyword_text(exc.expected),
                             example=exc.example) from None
    return call


def _bounded(fn):
    """The call within its `wall_limit=` keyword (also the Run's), a reached limit raised as SimulationError."""
    @functools.wraps(fn)
    def call(*args, **kw):
        deadline.check_seconds(kw.get("wall_limit"), key="wall_limit", allow_none=True)
        try:
            with deadline.limit(kw.get("wall_limit")):
                return fn(*args, **kw)
        except deadline.WallLimitReached as exc:
            raise SimulationError(f"timeout: {exc}") from None
    return _keywords(call)


@_keywords
def run(scenario, *, t_final: float | None = None, integrator: str | None = None, width: float | None = None,
        wall_limit: float | None = None, jit: bool = True, samples: int = 10000, seed: int = 0,
        mutant: str | None = None, rate_hz: float | None = None, plant: str | None = None) -> Run:
    """The pipeline of a scenario with its stages computed on first use (`run.design`, `run.simulation`, ...);
    every option as in `RunOptions` (None: the scenario's own setting); `plant` as `--plant` (the engine)."""
    from .core.outputs import MAX_SAMPLES, check_count
    from .plant.engines import resolve_engine
    check_count(samples, key="--samples", minimum=1, maximum=MAX_SAMPLES, what="a number of samples")
    check_count(seed, key="--seed", minimum=0, maximum=2**63 - 1, what="a seed")
    sc = _scenario(scenario)
    engine = resolve_engine(sc, plant) if plant is not None else None
    return Run(sc, RunOptions(t_final=t_final, integrator=integrator, width=width, wall_limit=wall_limit, jit=jit,
                              samples=samples, seed=seed, mutant=mutant, rate_hz=rate_hz, engine=engine))


@_bounded
def audit(scenario, design=None, *, strict: bool = False, wall_limit: float | None = None) -> Checks:
    """`symfunnel audit`: model properties, funnels and printed claims (with the scenario's expectations); a
    `design` the caller already derived from this scenario is used instead of deriving it again; `strict=True`
    raises CheckFailed when any check fails (as `--strict` exits 1)."""
    r = run(scenario, wall_limit=wall_limit)
    if design is not None:
        r.__dict__["design"] = design
    out = Checks(r.audit)
    failed = [c.id for c in out if c.status == "fail"]
    if strict and failed:
        raise CheckFailed("audit: failed checks: " + ", ".join(failed))
    return out


def sampled_simulation(sc: Scenario, design, *, rate_hz: float | None = None, t_final: float | None = None,
                       engine: str = "symfunnel", progress=None):
    """The deployed controller's sampled-data run (deployed.loop.simulate_sampled) at `rate_hz`, else at the
    scenario's [implementation] rate, else (a physics engine without a rate) at twice the minimum rate on `engine`;
    SimulationError when no rate up to 1 MHz keeps both funnels there."""
    from .deployed.loop import simulate_sampled
    say = progress or (lambda s: None)
    if rate_hz is None and sc.implementation is None:
        from .deployed.rate import min_rate
        found = min_rate(sc, design, t_final=t_final, progress=say, engine=engine)
        if found["min_rate_hz"] is None:
            raise SimulationError(f"breach: no sample rate up to 1 MHz keeps both funnels on the {engine} plant")
        rate_hz = 2.0 * found["min_rate_hz"]
        say(f"sampled at {rate_hz:.6g} Hz: twice the minimum rate {found['min_rate_hz']:.6g} Hz on the {engine} plant")
    return simulate_sampled(sc, design, rate_hz=rate_hz, t_final=t_final, progress=say, engine=engine)


@_bounded
def simulate(scenario, *, t_final: float | None = None, integrator: str | None = None, width: float | None = None,
             wall_limit: float | None = None, jit: bool = True, rate_hz: float | None = None,
             out: str | Path | None = None, plant: str | None = None, convergence: bool = False, progress=None):
    """`symfunnel simulate`: the closed-loop SimResult (`summary()`, `to_json()`, `save()`); `integrator`
    cvodes | rk | collocation, `width` the smoothing width of the plant's kinks, `jit=False` the CasADi VM; `out`
    writes the trajectory as `--out` does, by its suffix (.npz, .csv, .mat); `convergence=True` adds the
    smoothing-width study. With `rate_hz` (`rate`), the scenario's [implementation] or a `plant` engine other than
    symfunnel (e.g. "mujoco"): the deployed controller's sampled run, a `deployed.loop.SampledResult`, as the CLI."""
    import math

    from .core.errors import InputError
    from .plant.engines import resolve_engine
    if t_final is not None and not (isinstance(t_final, (int, float)) and math.isfinite(t_final) and t_final > 0):
        raise InputError(f"is {t_final!r}", key="t_final", expected="a number > 0")
    if width is not None and not (isinstance(width, (int, float)) and math.isfinite(width) and width >= 0):
        raise InputError(f"is {width!r}", key="width", expected="a number >= 0")
    if rate_hz is not None:
        from .scenario.implementation import check_rate
        check_rate(rate_hz, file=None, key="rate_hz")
    if out is not None:
        from .core.outputs import check_output_file
        from .simulation.export import check_suffix
        check_suffix(str(out), key="out")
        check_output_file(out, key="out")
    sc = _scenario(scenario)
    engine = resolve_engine(sc, plant)
    if rate_hz is not None or sc.implementation is not None or engine != "symfunnel":
        res = sampled_simulation(sc, derive(sc), rate_hz=rate_hz, t_final=t_final, engine=engine, progress=progress)
        if out is not None:
            res.save(out)
        return res
    r = Run(sc, RunOptions(t_final=t_final, integrator=integrator, width=width, wall_limit=wall_limit, jit=jit),
            progress)
    res = r.simulation
    if convergence:
        from .simulation import convergence_study
        res.convergence = convergence_study(sc, r.design, t_final=t_final, integrator=integrator, progress=progress)
    if out is not None:
        res.save(out, r.trajectory_arrays() if res.t.size else None)
    return res


@_bounded
def verify(scenario, *, strict: bool = False, mutants: bool = False, t_final: float | None = None,
           samples: int = 10000, seed: int = 0, rate_hz: float | None = None, integrator: str | None = None,
           width: float | None = None, wall_limit: float | None = None, jit: bool = True, plant: str | None = None):
    """`symfunnel verify`: the Verification (`status`, `checks`, `to_json()`); `mutants=True` adds the mutation
    testing (`v.mutation`: score, killed, every mutant; `v.mutation_score`; "mutation" in `to_json()`) to it;
    `strict=True` raises CheckFailed when the gate fails."""
    sc = _scenario(scenario)
    v = run(sc, t_final=t_final, samples=samples, seed=seed, rate_hz=rate_hz, integrator=integrator, width=width,
            wall_limit=wall_limit, jit=jit, plant=plant).verification
    if mutants:
        v.mutation = run_mutants(sc, t_final=t_final, samples=min(samples, 2000), seed=seed)
    if strict and v.unexpected:
        raise CheckFailed("verify: unexpected outcomes: " + ", ".join(c.id for c in v.unexpected))
    return v


@dataclass
class CertifyResult:
    """The certificates of one scenario (`symfunnel certify`): `certificates`, the gate's `status`, `to_json()`."""

    scenario: Scenario
    certification: object

    @property
    def certificates(self) -> list:
        """The Certificate objects, in the contract's order."""
        return self.certification.certificates

    @property
    def status(self) -> str:
        """'pass' when every certificate's outcome is the one the scenario declares (pass unless [[expect]])."""
        return self.certification.status(self.scenario)

    @property
    def unexpected(self) -> list[str]:
        """Ids of the certificates whose outcome is not the declared one."""
        return [c.id for c in self.certification.checks(self.scenario) if c.unexpected]

    def __repr__(self) -> str:
        return (f"CertifyResult(scenario={self.scenario.name!r}, status={self.status!r}, "
                f"certificates={ {c.id: c.status for c in self.certificates} })")

    def to_json(self) -> dict:
        """`certify --json`: {"scenario", "status", "certificates": [...]}."""
        return self.certification.to_json(self.scenario)

    def _repr_html_(self) -> str:
        return _table([(c.id, c.status, f"{c.seconds:.1f} s", c.detail) for c in self.certificates],
                      ("certificate", "status", "time", "detail"))


def certify_ids(only) -> tuple[str, ...] | None:
    """Certificate ids from `only` (full ids or their last part, e.g. 'input_gain'); InputError for others."""
    from .core.errors import InputError
    from .core.names import CERTIFY_CHECKS, CERTIFY_ON_DEMAND
    known = CERTIFY_CHECKS + CERTIFY_ON_DEMAND
    if only is None:
        return None
    out = []
    for k in ([only] if isinstance(only, str) else list(only)):
        cid = k if str(k).startswith("certify.") else f"certify.{k}"
        if cid not in known:
            raise InputError(f"is '{k}'", key="--only", expected="one of " + ", ".join(known))
        out.append(cid)
    return tuple(out)


@_keywords
def certify(scenario, *, only=None, wall_limit: float | None = None, t_final: float | None = None,
            strict: bool = False, progress=None) -> CertifyResult:
    """`symfunnel certify`: proofs over regions by interval branch and bound on the design's own graph
    (certify.input_gain, certify.bounds, certify.invariance; `only` a subset); `wall_limit` seconds end the
    searches with `undecided` (the fraction left), never with a wrong verdict; `strict=True` raises CheckFailed when
    an outcome is not the declared one."""
    import math
    from .core.errors import InputError
    if wall_limit is not None and not (isinstance(wall_limit, (int, float)) and math.isfinite(wall_limit)
                                       and wall_limit > 0):
        raise InputError(f"is {wall_limit!r}", key="--wall-limit", expected="a number of seconds > 0")
    sc = _scenario(scenario)
    r = Run(sc, RunOptions(t_final=t_final, certify_only=certify_ids(only), certify_wall_limit=wall_limit,
                           wall_limit=wall_limit, certify_work=1.0), progress)
    res = CertifyResult(sc, r.certification)
    if strict and res.unexpected:
        raise CheckFailed("certify: unexpected outcomes: " + ", ".join(res.unexpected))
    return res


@_bounded
def codegen(scenario, lang: str = "c", out=None, *, check: bool = False, prefix: str | None = None,
            rate_hz: float | None = None, points: int = 1000, seed: int = 0, t_final: float | None = None,
            wall_limit: float | None = None, force: bool = False, fmi: str | None = None) -> CodegenResult | FmuExport:
    """`symfunnel codegen`: the generated files (written to `out` when given; `force` as `--force`), cross-checked
    with `check=True` (a failed cross-check raises CheckFailed); `prefix` and `rate_hz` as `--prefix`, `--rate`.
    `lang="fmu"` (with `rate_hz`, `out`; `fmi` as `--fmi`) writes `out/<name>.fmu` and returns
    `deployed.fmu.FmuExport` (its `check` the FMPy check; a failed one raises CheckFailed after writing)."""
    from .core.errors import InputError
    from .core.outputs import MAX_POINTS, check_count
    from .emit.check import check_output
    from .emit.files import write_output
    check_count(points, key="--points", minimum=1000, maximum=MAX_POINTS, what="a number of check points")
    check_count(seed, key="--seed", minimum=0, maximum=2**63 - 1, what="a seed")
    if lang == "fmu":
        from .deployed.fmu import export_fmu, fmu_options
        fmi = fmu_options(fmi, rate_hz, prefix, check=check, keys=("fmi", "rate_hz", "prefix", "check"))
        if out is None:
            raise InputError("is missing", key="out", expected="a directory for <name>.fmu with lang='fmu'")
        r = run(scenario, t_final=t_final, wall_limit=wall_limit)
        res = export_fmu(r.scenario, r.design, out, rate_hz, fmi=fmi, check=check, force=force)
        if res.check is not None and not res.check.passed:
            raise CheckFailed(f"codegen --lang fmu check failed: {res.check.to_json()}")
        return res
    if fmi is not None:
        raise InputError(f"is given with lang={lang!r}", key="fmi", expected="lang='fmu'")
    r = run(scenario, t_final=t_final, wall_limit=wall_limit)
    files = r.code(lang, prefix=prefix, rate_hz=rate_hz)
    res = CodegenResult(r.scenario.name, lang, files)
    if out is not None:
        res.paths = write_output(files, out, force=force)
    if check:
        res.check = check_output(r.design, lang, files, points=points, seed=seed)
        if not res.check.passed:
            raise CheckFailed(f"codegen check: worst error {res.check.worst:.3e} above {res.check.threshold:.0e}")
    return res


@dataclass
class RateResult:
    """The deployed controller's minimum sample rate (`symfunnel rate`): `min_rate_hz` (None: none up to 1 MHz),
    every tried rate, and with `certify=True` the proven rate and the theory's bound; `to_json()` is `rate --json`."""

    scenario: str
    data: dict

    @property
    def min_rate_hz(self) -> float | None:
        """The simulated minimum rate in Hz (None when no rate up to 1 MHz keeps both funnels with the margin)."""
        return self.data["min_rate_hz"]

    @property
    def proven_rate_hz(self) -> float | None:
        """The proven rate (certify.sampled) in Hz; None when undecided or not asked for (`certify=False`)."""
        return self.data.get("proven_rate_hz")

    def to_json(self) -> dict:
        """The JSON `rate --json` prints."""
        from .core.io import json_safe
        return json_safe(self.data)

    def __repr__(self) -> str:
        proven = f", proven_rate_hz={self.proven_rate_hz:.6g}" if self.proven_rate_hz is not None else ""
        found = "None" if self.min_rate_hz is None else f"{self.min_rate_hz:.6g}"
        return (f"RateResult(scenario={self.scenario!r}, min_rate_hz={found}{proven}, "
                f"engine={self.data.get('engine')!r}, {len(self.data['tried'])} rates tried)")

    def _repr_html_(self) -> str:
        return _table([(f"{d['rate_hz']:.6g} Hz", d["status"], "holds" if d["holds"] else "does not hold")
                       for d in self.data["tried"]], ("rate", "status", "margin"))


def rate_search(sc: Scenario, *, margin: float = 0.05, t_final: float | None = None, plant: str | None = None,
                certify: bool = False, set_margin=None, wall_limit: float | None = None, progress=None) -> dict:
    """The dict of `rate --json` (what `rate` and the CLI share): the simulated search (deployed.rate.min_rate) and
    with `certify` the proven bracket; errors name the CLI's options (the API's `_keywords` renames them)."""
    import math
    import time

    from .core.errors import InputError
    from .deployed.rate import min_rate
    from .plant.engines import resolve_engine
    started = time.monotonic()
    if not (isinstance(margin, (int, float)) and math.isfinite(margin) and 0 <= margin < 1):
        raise InputError(f"is {margin!r}", key="--margin", expected="a number in [0, 1)")
    if t_final is not None and not (isinstance(t_final, (int, float)) and math.isfinite(t_final) and t_final > 0):
        raise InputError(f"is {t_final!r}", key="--t-final", expected="a number > 0")
    if set_margin is not None and not certify:
        raise InputError("is given without --certify", key="--set-margin", expected="--certify with it")
    if set_margin is not None and (len(set_margin) != 2 or not all(
            isinstance(v, (int, float)) and math.isfinite(v) and 1e-3 <= v < 1 for v in set_margin)):
        raise InputError(f"is {list(set_margin)!r}", key="--set-margin", expected="two margins E1 E2 in [0.001, 1)")
    engine = resolve_engine(sc, plant)
    say = progress or (lambda s: None)
    r = Run(sc, RunOptions(t_final=t_final), progress=say)      # W_hat's box (certify) from this horizon
    out = min_rate(sc, r.design, margin=margin, t_final=t_final, progress=say, engine=engine)
    if certify:
        # the proof gets half of what the simulated search left of the wall limit, and ends undecided
        left = None if wall_limit is None else max(0.0, 0.5 * (wall_limit - (time.monotonic() - started)))
        out.update(_certified_rate(sc, r, out, t_final=t_final, margin=margin, set_margin=set_margin,
                                   wall_limit=left, progress=say))
    return out


def _certified_rate(sc, run, r: dict, *, t_final, margin, set_margin, wall_limit, progress) -> dict:
    """certify.sampled beside the simulated search: the contract's keys (docs/certify.md)."""
    from .certificates.sampled_rate import sampled_bracket, simulated_w_hat_range
    design = run.design
    # W_hat's box: the simulated run's range (widened by the certificate), as the report's bracket takes it
    wr = simulated_w_hat_range(design, run.closed_loop, run.simulation) if design.n_regressor else None
    T = t_final if t_final is not None else sc.simulation.t_final
    return sampled_bracket(sc, design, t_final=T, margin=margin, set_margin=tuple(set_margin) if set_margin else None,
                           f_sim=r["min_rate_hz"], w_hat_range=wr, wall_limit=wall_limit, progress=progress)


@_bounded
def rate(scenario, *, margin: float = 0.05, t_final: float | None = None, plant: str | None = None,
         certify: bool = False, set_margin=None, wall_limit: float | None = None, progress=None) -> RateResult:
    """`symfunnel rate`: the lowest sample rate of the deployed C controller whose sampled loop keeps both funnels
    with `margin` after the transient (bisection on a log scale, every tried rate listed); `certify=True` adds the
    proven rate (certify.sampled, `set_margin` as `--set-margin`) and the sampled-data theory's bound."""
    sc = _scenario(scenario)
    return RateResult(sc.name, rate_search(sc, margin=margin, t_final=t_final, plant=plant, certify=certify,
                                           set_margin=set_margin, wall_limit=wall_limit, progress=progress))


@_bounded
def report(scenario, out=None, *, codegen: bool = True, mutants: bool = True, deployed: bool = True, figures=None,
           t_final: float | None = None, samples: int = 10000, seed: int = 0, rate_hz: float | None = None,
           wall_limit: float | None = None, plant: str | None = None, force: bool = False,
           sweep: str | Path | None = None) -> ReportResult:
    """`symfunnel report`: writes the HTML report (default reports/<name>.html) and returns its path; `figures`
    a directory for every figure as PNG and PDF; `codegen`, `mutants`, `deployed` include those sections; `force`
    replaces an output symfunnel did not write; `sweep` a campaign's directory: its sweep page instead (refused
    for another scenario's campaign)."""
    from .reporting import build_report, default_path
    if sweep is not None:
        from .reporting.sweep import write_sweep_page
        name = _scenario(scenario).name if scenario is not None else None
        return ReportResult(Path(write_sweep_page(sweep, out, scenario_name=name)))
    sc = _scenario(scenario)
    from .core.outputs import check_replaceable, scenario_inputs
    check_replaceable(out if out is not None else default_path(sc), key="out", inputs=scenario_inputs(sc), force=force)
    r = run(sc, t_final=t_final, samples=samples, seed=seed, rate_hz=rate_hz, wall_limit=wall_limit, plant=plant)
    return ReportResult(build_report(r, out, codegen=codegen, mutants=mutants, deployed=deployed,
                                     figures_dir=Path(figures) if figures is not None else None))


@_keywords
def sweep(scenario, *, runs: int | None = None, workers: int | None = None, scheduler: str | None = None, out=None,
          resume: bool = False, progress=None, chunk_size: int | None = None, plant: str | None = None) -> SweepResult:
    """`symfunnel sweep`: a robustness campaign over the scenario's `[[uncertainty]]` (result with `to_json()`, as
    summary.json); `scheduler` the address of a dask cluster, else `workers` local processes; `plant` as `--plant`."""
    from .campaigns.campaign import sweep as _sweep
    from .plant.engines import resolve_engine
    sc = _scenario(scenario)
    return _sweep(sc, runs=runs, workers=workers, scheduler=scheduler, out=out, resume=resume,
                  progress=progress, chunk_size=chunk_size, engine=resolve_engine(sc, plant))


@_keywords
def tune(scenario, *, wall_limit: float = 240.0, t_final: float | None = None, progress=None,
         max_evals: int | None = None, gate: bool = True, method: str = "auto", out=None,
         max_evaluations: int | None = None) -> TuneResult:
    """`symfunnel tune`: search the scenario's `[tune]` parameters for a design that keeps the funnels within the
    limits (never the reference or the e1 funnel) in `wall_limit` seconds and at most `max_evals` evaluations
    (`max_evaluations` an older name of it); `method` "auto" | "gradient" | "derivative-free"; `gate=False` skips
    verify's gate on the result; `result.tuned_text` is the scenario's file with the tuned gains (4 significant
    digits), written to `out` when given (as `--out`)."""
    from .core.errors import InputError
    from .synthesis.search import tune as _tune
    if max_evals is not None and max_evaluations is not None:
        raise InputError("is given with max_evaluations", key="max_evals", expected="one of the two")
    max_evals = max_evals if max_evals is not None else max_evaluations
    if max_evals is not None and not (isinstance(max_evals, int) and max_evals >= 1):
        raise InputError(f"is {max_evals!r}", key="max_evals", expected="an integer >= 1")
    sc = _scenario(scenario)
    if out is not None:
        from .core.outputs import check_not_input, check_output_file, scenario_inputs
        check_output_file(out, key="out")
        check_not_input(out, scenario_inputs(sc), key="out")
    res = _tune(sc, wall_limit=wall_limit, t_final=t_final, progress=progress, max_evaluations=max_evals, gate=gate,
                method=method)
    if out is not None:
        from .core.io import atomic_write
        from .core.toml_write import dumps
        atomic_write(out, res.tuned_text or dumps(res.tuned_raw))
    return res


@_keywords
def init(out, *, urdf: str | Path | None = None, source: str | Path | None = None, joints=None,
         force: bool = False) -> Path:
    """`symfunnel init`: write a commented starting scenario to `out` (.toml) and return its path: a 2-link planar
    arm, the movable joints of `urdf` (`joints` a subset, names), or a copy of `source` (`--from`: a built-in name or
    a file); an existing `out` is replaced only with `force=True`."""
    from .design.starting import write_starting
    return write_starting(out, urdf=None if urdf is None else str(urdf),
                          source=None if source is None else str(source), joints=joints, force=force)
