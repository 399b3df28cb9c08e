"""The FMU checked by a real FMI client (FMPy), which validates it and steps it in the sampled loop against the C step.

FMPy validates the FMU's modelDescription.xml and loads its binary; the FMU, stepped by FMPy, closes the
sampled-data loop of `deployed.loop` in place of the compiled C step.

`check_fmu(path, scenario, design, rate_hz)` runs the loop twice with the same plant step, measurements and
hold: once with the generated C step (`simulate_sampled`, as `simulate --rate`), once with the FMU driven through
FMPy's `FMU2Slave` or `FMU3Slave` (one DoStep(t_k, 1/rate) per sample: the inputs q, dq set before it, tau read
after it), and compares the torque sequences, the states and where each run leaves a funnel. FMPy is needed here only
(`pip install 'symfunnel[fmu]'`); the FMU itself needs nothing but a C compiler.
"""

from __future__ import annotations

import itertools
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import InputError

__all__ = ["FmuCheck", "FmuController", "FmuExport", "check_fmu", "export_fmu", "fmu_options", "load_fmpy",
           "TOLERANCE"]

_COUNTER = itertools.count()

#: the largest relative difference |tau_fmu - tau_c| / max(1, |tau_c|) (and of q, dq) the check accepts
TOLERANCE = 1e-9


def load_fmpy():
    """The fmpy package, or InputError saying how to install it."""
    try:
        import fmpy
        import fmpy.fmi2  # noqa: F401
        import fmpy.validation  # noqa: F401
    except ImportError:
        raise InputError("needs FMPy, which is not installed", key="--check",
                         expected="pip install 'symfunnel[fmu]' (FMPy loads, validates and steps the FMU)") from None
    return fmpy


class FmuController:
    """An FMU (FMI 2.0 or 3.0 Co-Simulation) stepped by FMPy, with the buffers and `raw()` of
    `deployed.loop.StepLibrary`, so that `simulate_sampled(..., controller=FmuController(path))` runs the sampled
    loop with it. `log` collects what the FMU logged: (status, category, message)."""

    def __init__(self, path, *, instance: str | None = None):
        fmpy = load_fmpy()
        self.md = fmpy.read_model_description(str(path))
        self.fmi = self.md.fmiVersion.split(".")[0]
        self._dir = fmpy.extract(str(path))
        vs = {v.name: v for v in self.md.modelVariables}
        self.n = n = sum(1 for name in vs if name.startswith("q["))
        self.vr_in = [vs[f"q[{i + 1}]"].valueReference for i in range(n)] + \
            [vs[f"dq[{i + 1}]"].valueReference for i in range(n)]
        self.vr_tau = [vs[f"tau[{i + 1}]"].valueReference for i in range(n)]
        self.vr_status = [vs["status"].valueReference]
        self.h = float(self.md.defaultExperiment.stepSize)
        instance = instance or f"symfunnel-check-{next(_COUNTER)}"
        self.instance = instance
        self.log: list[tuple[int, str, str]] = []
        ident = self.md.coSimulation.modelIdentifier
        if self.fmi == "3":
            from fmpy.fmi3 import FMU3Slave

            def log3(env, status, category, message):
                self.log.append((int(status), (category or b"").decode("utf-8", "replace"),
                                 (message or b"").decode("utf-8", "replace")))
            self.fmu = FMU3Slave(guid=self.md.guid, unzipDirectory=self._dir, modelIdentifier=ident,
                                 instanceName=instance)
            self.fmu.instantiate(logMessage=log3)
            self._set, self._get, self._get_int = self.fmu.setFloat64, self.fmu.getFloat64, self.fmu.getInt32
        else:
            from fmpy.fmi2 import FMU2Slave
            self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self._dir, modelIdentifier=ident,
                                 instanceName=instance)
            self._callbacks = _collecting_callbacks(instance, self.log)
            self.fmu.instantiate(callbacks=self._callbacks)
            self._set, self._get, self._get_int = self.fmu.setReal, self.fmu.getReal, self.fmu.getInteger
        self.q, self.dq, self.tau = np.zeros(n), np.zeros(n), np.zeros(n)
        self.steps = 0
        self.error: str | None = None
        self._initialized = False

    def init(self) -> int:
        """Reset the FMU to its start values and initialise it (start time 0)."""
        if self._initialized:
            self.fmu.reset()
        if self.fmi == "3":
            self.fmu.enterInitializationMode(startTime=0.0)
        else:
            self.fmu.setupExperiment(startTime=0.0)
            self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self._initialized = True
        self.steps = 0
        return 0

    def set_inputs(self, q, dq) -> None:
        """Set q and dq."""
        self._set(self.vr_in, [float(v) for v in np.concatenate([np.ravel(q), np.ravel(dq)])])

    def outputs(self) -> tuple[int, np.ndarray]:
        """(status, tau) as the FMU holds them now."""
        return int(self._get_int(self.vr_status)[0]), np.array(self._get(self.vr_tau))

    def do_step(self, t: float, h: float) -> None:
        """fmi2DoStep / fmi3DoStep(t, h); FMICallException when the FMU refuses."""
        self.fmu.doStep(t, h)

    def step(self, t: float, q, dq) -> tuple[int, np.ndarray]:
        """One DoStep(t, h) with inputs q, dq: (status output, or -3 when the FMU refused; tau)."""
        from fmpy.fmi1 import FMICallException
        self.set_inputs(q, dq)
        try:
            self.fmu.doStep(t, self.h)
        except FMICallException as exc:
            said = "; ".join(m for st, _, m in self.log[-3:] if st >= 3)
            self.error = f"the FMU refused DoStep at t = {t!r} s: {exc}" + (f" ({said})" if said else "")
            return -3, np.full(self.n, np.nan)
        self.steps += 1
        return self.outputs()

    # FMU state, under one name for both versions
    def get_state(self):
        return self.fmu.getFMUState() if self.fmi == "3" else self.fmu.getFMUstate()

    def set_state(self, state) -> None:
        (self.fmu.setFMUState if self.fmi == "3" else self.fmu.setFMUstate)(state)

    def free_state(self, state) -> None:
        (self.fmu.freeFMUState if self.fmi == "3" else self.fmu.freeFMUstate)(state)

    def serialize(self, state) -> bytes:
        return (self.fmu.serializeFMUState if self.fmi == "3" else self.fmu.serializeFMUstate)(state)

    def deserialize(self, blob: bytes):
        return (self.fmu.deserializeFMUState if self.fmi == "3" else self.fmu.deSerializeFMUstate)(blob)

    def raw(self):
        """(function, None, (q, dq, tau)) as StepLibrary.raw: rc = function(None, t, *buffers)."""
        def stepf(_state, t, q, dq, tau):
            rc, out = self.step(t, q, dq)
            tau[:] = out
            return rc
        return stepf, None, (self.q, self.dq, self.tau)

    def close(self) -> None:
        """Terminate and free the instance, remove the extracted files."""
        try:
            if self._initialized:
                self.fmu.terminate()
        except Exception:          # a failed FMU may refuse to terminate: free it all the same
            pass
        self.fmu.freeInstance()
        _LOGS.pop(self.instance, None)
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


#: the one set of FMI callbacks of this process and the log list of each instance name: FMPy's native logger
#: proxy (which formats the FMU's variadic messages) keeps the last Python logger it was given in a global, so a
#: logger that is freed while that global still points to it crashes the next FMU that logs (found by the tests);
#: one logger, created once and kept, routes the messages instead
_LOGS: dict[str, list] = {}
_CALLBACKS: list = []


def _collecting_callbacks(name: str, log: list):
    """fmi2CallbackFunctions whose logger appends (status, category, message) of instance `name` to `log`
    (messages of other instances are printed as FMPy prints them)."""
    _LOGS[name] = log
    if _CALLBACKS:
        return _CALLBACKS[0]
    from ctypes import byref

    from fmpy import calloc, free
    from fmpy.fmi2 import (fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions,
                           fmi2CallbackLoggerTYPE)
    from fmpy.logging import addLoggerProxy

    def logger(env, instance, status, category, message):
        entry = (int(status), (category or b"").decode("utf-8", "replace"),
                 (message or b"").decode("utf-8", "replace"))
        target = _LOGS.get((instance or b"").decode("utf-8", "replace"))
        if target is None:
            print(f"[{['OK', 'WARNING', 'DISCARD', 'ERROR', 'FATAL', 'PENDING'][min(max(entry[0], 0), 5)]}] "
                  f"{entry[2]}")
        else:
            target.append(entry)
    cb = fmi2CallbackFunctions()
    cb.logger = fmi2CallbackLoggerTYPE(logger)
    cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
    addLoggerProxy(byref(cb))
    _CALLBACKS.append(cb)
    return cb


@dataclass
class FmuCheck:
    """The result of `check_fmu`."""

    problems: list[str]                 # FMPy's validation of the modelDescription (empty: none)
    rate_hz: float
    samples: int                        # controller periods both runs stepped
    samples_reference: int
    max_abs_tau: float                  # max |tau_fmu - tau_c| over samples and joints
    max_rel_tau: float                  # max |tau_fmu - tau_c| / max(1, |tau_c|)
    max_rel_state: float                # the same for q, dq at the samples
    status: str                         # the FMU loop's: ok | breach | failed
    status_reference: str               # the C step loop's
    breach: dict | None
    breach_reference: dict | None
    error: str | None = None
    wall: dict = field(default_factory=dict)

    @property
    def same_breach(self) -> bool:
        """Both runs leave the funnels at the same time, funnel and joint (or neither does)."""
        def key(b):
            return None if b is None else (b["time"], b["funnel"], b["joint"])
        return key(self.breach) == key(self.breach_reference)

    @property
    def passed(self) -> bool:
        return (not self.problems and self.error is None and self.samples == self.samples_reference
                and self.status == self.status_reference and self.same_breach
                and self.max_rel_tau <= TOLERANCE and self.max_rel_state <= TOLERANCE)

    def to_json(self) -> dict:
        return {"passed": self.passed, "validation_problems": list(self.problems), "rate_hz": self.rate_hz,
                "samples": self.samples, "samples_reference": self.samples_reference,
                "max_abs_tau_difference": self.max_abs_tau, "max_rel_tau_difference": self.max_rel_tau,
                "max_rel_state_difference": self.max_rel_state, "tolerance": TOLERANCE,
                "status": self.status, "status_reference": self.status_reference,
                "breach": self.breach, "breach_reference": self.breach_reference, "same_breach": self.same_breach,
                "error": self.error, "wall_s": self.wall}


def _rel(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(max |a - b|, max |a - b| / max(1, |b|)) over the finite common part; inf when a non-finite value differs."""
    if a.shape != b.shape:
        k = min(a.shape[0], b.shape[0])
        a, b = a[:k], b[:k]
    if a.size == 0:
        return 0.0, 0.0
    same_nan = np.isnan(a) & np.isnan(b)
    d = np.where(same_nan, 0.0, np.abs(a - b))
    if not np.all(np.isfinite(d)):
        return math.inf, math.inf
    return float(d.max()), float((d / np.maximum(1.0, np.abs(b))).max())


def check_fmu(path, scenario, design, rate_hz: float, *, t_final: float | None = None, progress=None) -> FmuCheck:
    """Validate the FMU with FMPy and run the sampled loop with it and with the C step (see the module doc), both on
    symfunnel's plant whatever the scenario's `[plant] engine` (the check is about the controller)."""
    import time

    from .loop import simulate_sampled
    fmpy = load_fmpy()
    problems = list(fmpy.validation.validate_fmu(str(path)))
    t0 = time.perf_counter()
    try:
        ref = simulate_sampled(scenario, design, rate_hz=rate_hz, t_final=t_final, progress=progress,
                               engine="symfunnel")
        ref_error = None
    except KeyError as exc:
        # deployed.loop.step_library reads design.sym["x_esn"] / ["w_hat"], which a design without an echo state
        # network does not have: the reference loop cannot run (the FMU can: it sizes its state by step_states)
        ref, ref_error = None, (f"the C step's own sampled loop does not run for this design (deployed.loop: "
                                f"KeyError {exc}); nothing to compare the FMU with")
    t1 = time.perf_counter()
    with FmuController(path) as ctl:
        if abs(ctl.h * rate_hz - 1.0) > 1e-12:
            problems.append(f"DefaultExperiment stepSize {ctl.h!r} is not 1/{rate_hz:g} s")
        run = simulate_sampled(scenario, design, rate_hz=rate_hz, t_final=t_final, controller=ctl,
                               progress=progress, engine="symfunnel")
        error = ctl.error
    t2 = time.perf_counter()
    if ref is None:
        return FmuCheck(problems, float(rate_hz), int(run.tau.shape[0]), 0, math.inf, math.inf, math.inf,
                        run.status, "failed", run.breach, None, ref_error, {"fmu_loop": t2 - t1})
    abs_tau, rel_tau = _rel(run.tau, ref.tau)
    _, rel_q = _rel(run.q, ref.q)
    _, rel_dq = _rel(run.dq, ref.dq)
    return FmuCheck(problems, float(rate_hz), int(run.tau.shape[0]), int(ref.tau.shape[0]), abs_tau, rel_tau,
                    max(rel_q, rel_dq), run.status, ref.status, run.breach, ref.breach, error,
                    {"c_step_loop": t1 - t0, "fmu_loop": t2 - t1})


@dataclass
class FmuExport:
    """What `export_fmu` wrote: the .fmu's path and bytes, its sources, and the check when asked for."""

    path: Path
    data: bytes
    sources: object                     # emit.fmu.FmuSources
    check: FmuCheck | None = None

    def to_json(self, scenario: str, out) -> dict:
        """The shape of `codegen --lang fmu --json`."""
        src = self.sources
        d = {"scenario": scenario, "language": "fmu", "fmi_version": f"{src.fmi}.0", "kind": "CoSimulation",
             "out": str(out), "file": self.path.name, "bytes": len(self.data), "guid": src.guid,
             "model_identifier": src.identifier, "rate_hz": src.rate_hz, "sources": list(src.sources)}
        if self.check is not None:
            d["check"] = self.check.to_json()
        return d


def fmu_options(fmi, rate_hz, prefix=None, *, check: bool = False, keys=("--fmi", "--rate", "--prefix", "--check")) \
        -> str:
    """The FMI version of `--lang fmu` options ("2" or "3"), or InputError naming the option that is wrong: another
    version, a missing rate, a prefix, --check without FMPy. Checked before any work."""
    from ..emit.fmu import FMI_VERSIONS
    fmi = "2" if fmi is None else str(fmi).strip()
    fmi = {"2.0": "2", "3.0": "3"}.get(fmi, fmi)
    if fmi not in FMI_VERSIONS:
        raise InputError(f"is '{fmi}'", key=keys[0], expected="2 (FMI 2.0, the default) or 3 (FMI 3.0)")
    if rate_hz is None:
        raise InputError("is missing", key=keys[1],
                         expected="the controller's sample rate in Hz with --lang fmu (one DoStep period = 1/HZ)")
    from ..scenario.implementation import check_rate
    check_rate(rate_hz, file=None, key=keys[1])
    if prefix is not None:
        raise InputError("is given with --lang fmu", key=keys[2],
                         expected="no prefix: the FMU's symbols are the FMI functions, named by the standard")
    if check:
        load_fmpy()
    return fmi


def export_fmu(scenario, design, out, rate_hz: float, *, fmi: str = "2", check: bool = False, force: bool = False,
               progress=None) -> FmuExport:
    """Build `out/<id>.fmu` (emit.fmu), check it with FMPy when asked (`check_fmu`, on a private copy before
    anything is written), and write it atomically. An existing file of that name is replaced only when symfunnel
    wrote it or with `force` (InputError otherwise, before any work); the result is written even when the check
    fails (to read), and `FmuExport.check.passed` says so."""
    import tempfile

    from ..core.io import atomic_write
    from ..core.lifecycle import committing
    from ..emit.fmu import build_fmu, fmu_sources, model_identifier, written_by_symfunnel
    target = Path(out) / f"{model_identifier(scenario.name)}.fmu"
    if Path(out).exists() and not Path(out).is_dir():
        raise InputError("exists and is not a directory", file=str(out), key="--out",
                         expected="a directory (created when missing)")
    if target.is_dir() or (target.exists() and not target.is_file()):
        raise InputError("exists and is not a regular file", file=str(target), key="--out",
                         expected="a directory without a directory or device of that name")
    if target.exists() and not force and not written_by_symfunnel(target):
        raise InputError("holds a file not written by symfunnel codegen", file=str(target), key="--out",
                         expected="--force to overwrite it, or another directory")
    src = fmu_sources(design, rate_hz, fmi=fmi)
    data = build_fmu(src, on_build=progress)
    report = None
    if check:
        with tempfile.TemporaryDirectory(prefix="symfunnel-fmu-") as tmp:
            path = Path(tmp) / target.name
            path.write_bytes(data)
            report = check_fmu(path, scenario, design, src.rate_hz, progress=progress)
    with committing(0 if report is None or report.passed else 1):
        atomic_write(target, data)
    return FmuExport(target, data, src, report)
