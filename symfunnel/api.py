"""The Python API: one function per CLI command, the same options as keyword arguments, results with `to_json()`
(and `_repr_html_` for notebooks); bad input raises `InputError`, a failed gate `CheckFailed` (with `strict=True`),
a reached `wall_limit=` (seconds, the whole call as for the CLI's --wall-limit) `SimulationError`."""

from __future__ import annotations

import functools
import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from .core import deadline
from .core.errors import CheckFailed, SimulationError
from .pipeline import Run, RunOptions, run_mutants
from .scenario import Scenario, load_scenario

if TYPE_CHECKING:
    from .codegen.check import CheckReport


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
        try:
            with deadline.limit(kw.get("wall_limit")):
                return fn(*args, **kw)
        except deadline.WallLimitReached as exc:
            raise SimulationError(f"timeout: {exc}") from None
    return call


def run(scenario, **options) -> Run:
    """The pipeline of a scenario (name, path or Scenario) with RunOptions as keywords; stages computed on use."""
    return Run(_scenario(scenario), RunOptions(**options))


@_bounded
def audit(scenario, design=None, **options) -> Checks:
    """`symfunnel audit`: model properties, funnels and printed claims (with the scenario's expectations)."""
    r = run(scenario, **options)
    if design is not None:
        r.__dict__["design"] = design        # a design the caller derived from this scenario: not derived again
    return Checks(r.audit)


@_bounded
def simulate(scenario, **options):
    """`symfunnel simulate`: the closed-loop SimResult (`summary()`/`to_json()`, `save_npz`)."""
    return run(scenario, **options).simulation


@_bounded
def verify(scenario, *, strict: bool = False, mutants: bool = False, **options):
    """`symfunnel verify`: the Verification (`status`, `checks`, `to_json()`); with `mutants=True` the mutation
    testing result instead; `strict=True` raises CheckFailed when the gate fails."""
    sc = _scenario(scenario)
    if mutants:
        return run_mutants(sc, t_final=options.get("t_final"), samples=min(options.get("samples", 10000), 2000))
    v = Run(sc, RunOptions(**options)).verification
    if strict and v.unexpected:
        raise CheckFailed("verify: unexpected outcomes: " + ", ".join(c.id for c in v.unexpected))
    return v


@_bounded
def codegen(scenario, lang: str = "c", out=None, *, check: bool = False, prefix: str | None = None,
            rate_hz: float | None = None, points: int = 1000, seed: int = 0, **options) -> CodegenResult:
    """`symfunnel codegen`: the generated files (written to `out` when given), cross-checked with `check=True`;
    `strict` semantics: a failed cross-check raises CheckFailed."""
    from .codegen.check import check_output
    from .codegen.files import write_output
    r = run(scenario, **options)
    files = r.code(lang, prefix=prefix, rate_hz=rate_hz)
    res = CodegenResult(r.scenario.name, lang, files)
    if out is not None:
        res.paths = write_output(files, out)
    if check:
        res.check = check_output(r.design, lang, files, points=points, seed=seed)
        if not res.check.passed:
            raise CheckFailed(f"codegen check: worst error {res.check.worst:.3e} above {res.check.threshold:.0e}")
    return res


@_bounded
def report(scenario, out=None, *, codegen: bool = True, mutants: bool = True, deployed: bool = True, figures=None,
           **options) -> ReportResult:
    """`symfunnel report`: writes the HTML report (default reports/<name>.html) and returns its path."""
    from .report import build_report
    return ReportResult(build_report(run(scenario, **options), out, codegen=codegen, mutants=mutants,
                                     deployed=deployed, figures_dir=Path(figures) if figures is not None else None))


def sweep(scenario, **options):
    """`symfunnel sweep`: a robustness campaign (result with `to_json()`, as summary.json)."""
    from .campaigns.campaign import sweep as _sweep
    return _sweep(_scenario(scenario), **options)
