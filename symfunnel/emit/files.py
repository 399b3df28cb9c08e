"""The generated files: `generate` (every file of one language, manifest.json last, deterministic), the C file
names, and `write_output` (atomic)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .c import BASENAME
from .contract import LANGS, contract_functions, initial_trajectory

if TYPE_CHECKING:
    import casadi

    from ..design import Design


def _manifest(design: Design, functions: list[casadi.Function], lang: str, files: dict[str, str]) -> str:
    """manifest.json: generator, files with their sha256, the functions with their inputs, outputs and sizes."""
    import casadi

    from ..core.version import __version__
    from .python import manifest_entry
    from ..sx.tape import count_ops
    entries = []
    for f in functions:
        e = manifest_entry(f)
        e["operations"] = count_ops(f)["operations"]
        entries.append(e)
    info = {
        "generator": f"symfunnel {__version__}",
        "casadi_version": casadi.__version__,
        "scenario": design.scenario.name,
        "language": lang,
        "files": [{"name": k, "bytes": len(v.encode("utf-8")),
                   "sha256": hashlib.sha256(v.encode("utf-8")).hexdigest()} for k, v in files.items()],
        "functions": entries,
    }
    if lang == "c":
        info["c_api"] = {"source": BASENAME + ".c", "header": BASENAME + ".h", "casadi_real": "double",
                         "casadi_int": "int", "memory": "static (no malloc; work in locals)"}
    info["trajectory"] = {"file": "trajectory.txt",
                          "row": "controller inputs in manifest order, matrices column-major"}
    return json.dumps(info, indent=2) + "\n"


def generate(design: Design, lang: str, *, trajectory: dict[str, np.ndarray] | None = None, prefix: str | None = None,
             rate_hz: float | None = None, tau_max=None, structured: bool = True) -> dict[str, str]:
    """Every output file of one language as {name: text}, manifest.json last; byte-identical for the same design.

    `trajectory` (controller inputs over time, see `trajectory_from_run`) is what `trajectory.txt` ships; without
    one (a library build, e.g. the sampled-data loop) it holds the initial state alone. C only: `prefix` starts
    every exported symbol (None: the historical names, see codegen.step), `rate_hz` is the period of the generated
    step (default: [implementation].rate_hz, else step.DEFAULT_RATE_HZ) and `tau_max` its saturation (default:
    [implementation].tau_max). `structured=False` writes the controller and step core as unrolled SX functions
    even where `emit.kernel`'s loops apply (the bench's baseline).
    """
    from .c import support_files, trajectory_text
    from .python import emit_python
    if lang not in LANGS:
        raise ValueError(f"unknown language {lang!r}; expected one of {LANGS}")
    functions = contract_functions(design)
    sc = design.scenario
    traj = trajectory if trajectory is not None else initial_trajectory(design)
    traj_txt = trajectory_text(design.controller(), traj, header=(
        f"symfunnel recorded trajectory for scenario '{sc.name}': one sample per line\n"
        + str(traj.get("source", "supplied by the caller"))))
    if lang == "c":
        from .step import emit_controller_c, step_settings
        rate_hz, tau_max = step_settings(design, rate_hz, tau_max)
        base = c_basename(prefix)
        files = emit_controller_c(design, functions, prefix=prefix, basename=base, rate_hz=rate_hz, tau_max=tau_max,
                                  structured=structured)
        sp = prefix if prefix is not None else "symfunnel_"
        files.update(support_files(traj_txt, {"@BASENAME@": base, "@F@": prefix or "", "@P@": sp,
                                              "@UP@": sp.upper()}))
    else:
        doc = (f"Funnel controller of scenario '{sc.name}' ({sc.title}).\n\n"
               "See manifest.json for the functions, their inputs and outputs.")
        from .c import template
        from .step import python_step_source, renamed, step_core, step_settings
        rate_hz, tau_max = step_settings(design, rate_hz, tau_max)
        extra = [renamed(design.reference, "reference"), step_core(design, tau_max, "step_core")]
        doc += ("\n\nThe deployed controller: reference(t) -> (qd, dqd, ddqd), step_core (one period) and the class "
                "Step (Step().step(t, q, dq) -> (rc, tau), the C step's semantics).")
        files = {BASENAME + ".py": emit_python(functions + extra, module_doc=doc)
                 + python_step_source(design, rate_hz, tau_max),
                 "run_trajectory.py": template("run_trajectory.py"),
                 "trajectory.txt": traj_txt}
    files["manifest.json"] = _manifest(design, functions, lang, files)
    if lang == "python":
        m = json.loads(files["manifest.json"])
        m["python_api"] = {"step": {"class": "Step", "rate_hz": rate_hz,
                                    "tau_max": None if tau_max is None else np.broadcast_to(
                                        np.asarray(tau_max, float), (design.n,)).tolist()},
                           "functions": ["reference", "step_core"]}
        files["manifest.json"] = json.dumps(m, indent=2) + "\n"
    if lang == "c":
        m = json.loads(files["manifest.json"])
        m["c_api"].update({"source": base + ".c", "header": base + ".h", "function_prefix": prefix or "",
                           "step": {"prefix": sp, "rate_hz": rate_hz,
                                    "tau_max": None if tau_max is None else np.broadcast_to(
                                        np.asarray(tau_max, float), (design.n,)).tolist(),
                                    "functions": [sp + "state_size", sp + "init", sp + "step"],
                                    "casadi_functions": [(prefix or "") + "reference",
                                                         (prefix or "") + "step_core"]}})
        files["manifest.json"] = json.dumps(m, indent=2) + "\n"
    return files


def c_basename(prefix: str | None) -> str:
    """Base name of the generated C pair: symfunnel_controller without a prefix, else <prefix>controller."""
    return BASENAME if prefix is None else prefix + "controller"


def c_names(files: dict[str, str]) -> tuple[str, str]:
    """(basename, function prefix) of a generated C file set, from its manifest."""
    api = json.loads(files["manifest.json"]).get("c_api", {})
    return api.get("source", BASENAME + ".c")[:-2], api.get("function_prefix", "")


def _ours(out: Path) -> dict[str, str]:
    """{name: sha256} of the files an earlier `symfunnel codegen` wrote into `out` (its manifest.json), if any."""
    import hashlib
    try:
        m = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
        if not str(m.get("generator", "")).startswith("symfunnel"):
            return {}
        listed = {str(f["name"]): str(f["sha256"]) for f in m.get("files", [])}
        listed["manifest.json"] = hashlib.sha256((out / "manifest.json").read_bytes()).hexdigest()
        return listed
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def foreign_files(files: dict[str, str], out_dir: str | os.PathLike) -> list[str]:
    """The files of `files` that exist in out_dir and were not written there by symfunnel (or changed since)."""
    import hashlib
    out = Path(out_dir)
    if not out.is_dir():
        return []
    ours = _ours(out)
    bad = []
    for name, text in files.items():
        p = out / name
        if not p.exists():
            continue
        try:
            digest = hashlib.sha256(p.read_bytes()).hexdigest()
        except OSError:
            bad.append(name)
            continue
        if digest != ours.get(name) and digest != hashlib.sha256(text.encode("utf-8")).hexdigest():
            bad.append(name)
    return bad


def write_output(files: dict[str, str], out_dir: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Write the files into out_dir atomically: all go to a temporary directory first, then are renamed in.

    Raises InputError when out_dir exists and is not a directory, and (without `force`) when it holds a file of the
    same name that symfunnel did not write (the user's own Makefile or main.c). Other files are left alone.
    """
    from ..core.errors import InputError
    from ..core import lifecycle
    from ..core.io import umask_mode
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a directory", file=str(out), key="--out",
                         expected="a directory (created when missing)")
    foreign = [] if force else foreign_files(files, out)
    if foreign:
        raise InputError(f"holds {foreign[0]}" + (f" and {len(foreign) - 1} more file(s)" if len(foreign) > 1 else "")
                         + " not written by symfunnel codegen (or changed since)", file=str(out / foreign[0]),
                         key="--out", expected="--force to overwrite them, or another directory")
    # The temporary directory lives inside an existing out_dir (it may be a mount point: renames never cross
    # file systems), else beside it so that the whole directory can be renamed into place.
    parent = out.absolute() if out.is_dir() else out.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))
        os.chmod(tmp, umask_mode(directory=True))
        lifecycle.register_temporary(tmp)
    except OSError as exc:
        raise InputError(f"cannot be created ({exc.strerror})", file=str(out), key="--out",
                         expected="a writable directory") from None
    try:
        for name, text in files.items():
            with open(tmp / name, "w", encoding="utf-8", newline="\n") as fh:
                fh.write(text)
        if not out.exists():
            try:
                os.rename(tmp, out)
                return [out / n for n in files]
            except OSError:
                out.mkdir(parents=True, exist_ok=True)
        for name in files:
            os.replace(tmp / name, out / name)
    except OSError as exc:
        raise InputError(f"cannot be written ({exc.strerror or exc})", file=str(out), key="--out",
                         expected="a writable directory") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        lifecycle.unregister_temporary(tmp)
    return [out / n for n in files]

