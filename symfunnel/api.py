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
    from .simulation.result import SimResult
    from .synthesis.search import TuneResult

__all__ = ["load_scenario", "derive", "evaluate", "run", "Run", "audit", "simulate", "verify", "certify", "codegen",
           "report", "sweep", "tune"]


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
    return call


def run(scenario, *, t_final: float | None = None, integrator: str | None = None, width: float | None = None,
        wall_limit: float | None = None, jit: bool = True, samples: int = 10000, seed: int = 0,
        mutant: str | None = None, rate_hz: float | None = None, plant: str | None = None) -> Run:
    """The pipeline of a scenario with its stages computed on first use (`run.design`, `run.simulation`, ...);
    every option as in `RunOptions` (None: the scenario's own setting); `plant` as `--plant` (the engine)."""
    from .plant.engines import resolve_engine
    sc = _scenario(scenario)
    engine = resolve_engine(sc, plant) if plant is not None else None
    return Run(sc, RunOptions(t_final=t_final, integrator=integrator, width=width, wall_limit=wall_limit, jit=jit,
                              samples=samples, seed=seed, mutant=mutant, rate_hz=rate_hz, engine=engine))


@_bounded
def audit(scenario, design=None, *, wall_limit: float | None = None) -> Checks:
    """`symfunnel audit`: model properties, funnels and printed claims (with the scenario's expectations); a
    `design` the caller already derived from this scenario is used instead of deriving it again."""
    r = run(scenario, wall_limit=wall_limit)
    if design is not None:
        r.__dict__["design"] = design
    return Checks(r.audit)


@_bounded
def simulate(scenario, *, t_final: float | None = None, integrator: str | None = None, width: float | None = None,
             wall_limit: float | None = None, jit: bool = True, rate_hz: float | None = None,
             out: str | Path | None = None) -> SimResult:
    """`symfunnel simulate`: the closed-loop SimResult (`summary()`, `to_json()`, `save()`); `integrator`
    cvodes | rk | collocation, `width` the smoothing width of the plant's kinks, `jit=False` the CasADi VM; `out`
    writes the trajectory as `--out` does, by its suffix (.npz, .csv, .mat)."""
    if out is not None:
        from .core.outputs import check_output_file
        from .simulation.export import check_suffix
        check_suffix(str(out), key="out")
        check_output_file(out, key="out")
    r = run(scenario, t_final=t_final, integrator=integrator, width=width, wall_limit=wall_limit, jit=jit,
            rate_hz=rate_hz)
    res = r.simulation
    if out is not None:
        res.save(out, r.trajectory_arrays() if res.t.size else None)
    return res


@_bounded
def verify(scenario, *, strict: bool = False, mutants: bool = False, t_final: float | None = None,
           samples: int = 10000, seed: int = 0, rate_hz: float | None = None, integrator: str | None = None,
           width: float | None = None, wall_limit: float | None = None, jit: bool = True, plant: str | None = None):
    """`symfunnel verify`: the Verification (`status`, `checks`, `to_json()`); with `mutants=True` the mutation
    testing result instead; `strict=True` raises CheckFailed when the gate fails."""
    sc = _scenario(scenario)
    if mutants:
        return run_mutants(sc, t_final=t_final, samples=min(samples, 2000))
    v = run(sc, t_final=t_final, samples=samples, seed=seed, rate_hz=rate_hz, integrator=integrator, width=width,
            wall_limit=wall_limit, jit=jit, plant=plant).verification
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
    from .emit.check import check_output
    from .emit.files import write_output
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


@_bounded
def report(scenario, out=None, *, codegen: bool = True, mutants: bool = True, deployed: bool = True, figures=None,
           t_final: float | None = None, samples: int = 10000, seed: int = 0, rate_hz: float | None = None,
           wall_limit: float | None = None, plant: str | None = None) -> ReportResult:
    """`symfunnel report`: writes the HTML report (default reports/<name>.html) and returns its path; `figures`
    a directory for every figure as PNG and PDF; `codegen`, `mutants`, `deployed` include those sections."""
    from .reporting import build_report
    r = run(scenario, t_final=t_final, samples=samples, seed=seed, rate_hz=rate_hz, wall_limit=wall_limit, plant=plant)
    return ReportResult(build_report(r, out, codegen=codegen, mutants=mutants, deployed=deployed,
                                     figures_dir=Path(figures) if figures is not None else None))


def sweep(scenario, *, runs: int | None = None, workers: int | None = None, scheduler: str | None = None, out=None,
          resume: bool = False, progress=None, chunk_size: int | None = None, plant: str | None = None) -> SweepResult:
    """`symfunnel sweep`: a robustness campaign over the scenario's `[[uncertainty]]` (result with `to_json()`, as
    summary.json); `scheduler` the address of a dask cluster, else `workers` local processes; `plant` as `--plant`."""
    from .campaigns.campaign import sweep as _sweep
    from .plant.engines import resolve_engine
    sc = _scenario(scenario)
    return _sweep(sc, runs=runs, workers=workers, scheduler=scheduler, out=out, resume=resume,
                  progress=progress, chunk_size=chunk_size, engine=resolve_engine(sc, plant))


def tune(scenario, *, wall_limit: float = 240.0, t_final: float | None = None, progress=None,
         max_evaluations: int | None = None, gate: bool = True, method: str = "auto") -> TuneResult:
    """`symfunnel tune`: search the scenario's `[tune]` parameters for a design that keeps the funnels within the
    limits (never the reference or the e1 funnel) in `wall_limit` seconds and at most `max_evaluations`
    evaluations; `method` "auto" | "gradient" | "derivative-free"; `gate=False` skips verify's gate on the
    result; `result.tuned_text` is the scenario's file with the tuned gains (4 significant digits)."""
    from .synthesis.search import tune as _tune
    return _tune(_scenario(scenario), wall_limit=wall_limit, t_final=t_final, progress=progress,
                 max_evaluations=max_evaluations, gate=gate, method=method)
