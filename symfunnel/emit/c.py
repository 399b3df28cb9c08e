"""C code through CasADi's CodeGenerator: one .c and one .h with CasADi's C API, static memory only.

The functions come from the one SX graph (`Design.function`, CSE on). CasADi writes the code; this module only
adds `(void)` casts for the parameters a generated function does not use (CasADi's signatures always take
arg, res, iw, w, mem), so that the file compiles with `gcc -std=c99 -Wall -Wextra -Werror -pedantic`, and
refuses output that would allocate memory. Beside the code go an example `main.c` that runs the controller
over a recorded trajectory, a timing loop `bench.c`, a `Makefile` and that trajectory (`trajectory.txt`).
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import casadi
import numpy as np

__all__ = ["BASENAME", "CODEGEN_OPTIONS", "STRICT_CFLAGS", "emit_c", "support_files", "trajectory_text",
           "parse_trajectory_output"]

#: Base name of the generated pair: symfunnel_controller.c / symfunnel_controller.h.
BASENAME = "symfunnel_controller"

#: casadi.CodeGenerator options: a header with the API, double/int types, no memory struct (no casadi/mem.h),
#: work in local variables (avoid_stack False keeps them in registers), plain C, no CasADi main/mex entry points.
CODEGEN_OPTIONS = {
    "with_header": True,
    "with_mem": False,
    "casadi_real": "double",
    "casadi_int": "int",
    "avoid_stack": False,
    "main": False,
    "mex": False,
    "cpp": False,
    "verbose": False,
}

#: The flags the generated C must compile warning-free with (docs/exports.md, "Controller code").
STRICT_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")

_ALLOC = re.compile(r"\b(malloc|calloc|realloc|free|alloca)\s*\(")
_DEF = re.compile(r"^(?:static |CASADI_SYMBOL_EXPORT )*[A-Za-z_][\w ]*?\b\w+\(([^()]*)\) \{$")
_TEMPLATES = ("main.c", "bench.c", "Makefile")


def _silence_unused(code: str) -> str:
    """Insert `(void)name;` for each parameter a function definition never uses (CasADi signatures are fixed)."""
    lines = code.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        out.append(line)
        m = _DEF.match(line)
        if m and m.group(1).strip() not in ("", "void"):
            names = [p.strip().split()[-1].lstrip("*") for p in m.group(1).split(",")]
            j = i + 1
            while j < len(lines) and lines[j] != "}":
                j += 1
            body = "\n".join(lines[i + 1:j])
            unused = [n for n in names if not re.search(rf"\b{re.escape(n)}\b", body)]
            if unused:
                out.append("  " + " ".join(f"(void){n};" for n in unused))
        i += 1
    return "\n".join(out)


def emit_c(functions: Sequence[casadi.Function], basename: str = BASENAME,
           prefix: str | None = None) -> dict[str, str]:
    """Return {basename.c: text, basename.h: text} for the functions, in order; deterministic.

    `prefix` (CasADi's CodeGenerator option) names CasADi's own helpers (`<prefix>_fabs`, ...); without it they
    are named after the basename. Raises ValueError when the generated code would allocate memory.
    """
    functions = list(functions)
    names = [f.name() for f in functions]
    if len(set(names)) != len(names):
        raise ValueError(f"function names must be unique, got {names}")
    opts = dict(CODEGEN_OPTIONS)
    if prefix:
        opts["prefix"] = prefix
    cg = casadi.CodeGenerator(basename + ".c", opts)
    for f in functions:
        cg.add(f)
    with tempfile.TemporaryDirectory(prefix="symfunnel-cg-") as tmp:
        cg.generate(str(tmp) + "/")
        c_text = (Path(tmp) / (basename + ".c")).read_text(encoding="utf-8")
        h_text = (Path(tmp) / (basename + ".h")).read_text(encoding="utf-8")
    c_text = _silence_unused(c_text)
    bad = _ALLOC.search(c_text)
    if bad:
        raise ValueError(f"generated C calls {bad.group(1)}(); the controller must use static memory only")
    return {basename + ".c": c_text, basename + ".h": h_text}


def template(name: str) -> str:
    """Text of a packaged template (main.c, bench.c, Makefile)."""
    return resources.files("symfunnel.emit").joinpath("templates", name).read_text(encoding="utf-8")


def support_files(trajectory: str, subs: dict[str, str] | None = None) -> dict[str, str]:
    """main.c, bench.c, Makefile and trajectory.txt for the generated pair (placeholders @X@ filled from subs)."""
    subs = subs or {"@BASENAME@": BASENAME, "@F@": "", "@P@": "symfunnel_", "@UP@": "SYMFUNNEL_"}
    out = {}
    for name in _TEMPLATES:
        text = template(name)
        for k, v in subs.items():
            text = text.replace(k, v)
        out[name] = text
    out["trajectory.txt"] = trajectory
    return out


def _fmt(x: float) -> str:
    """Shortest repr that round-trips a double (deterministic, exact)."""
    return repr(float(x))


def trajectory_text(controller: casadi.Function, rows: dict[str, np.ndarray], *, header: str = "") -> str:
    """One line per sample: every controller input in manifest order, each matrix column-major.

    `rows` maps each input name of `controller` to an array with the sample index last: (r, c, k), or (r, k)
    for a column vector. Lines starting with '#' are comments (main.c skips them).
    """
    names = [controller.name_in(i) for i in range(controller.n_in())]
    k = None
    cols = []
    for i, name in enumerate(names):
        a = np.asarray(rows[name], dtype=float)
        r, c = controller.size1_in(i), controller.size2_in(i)
        if a.ndim == 2:
            a = a.reshape(r, c, a.shape[-1])
        if a.shape[:2] != (r, c):
            raise ValueError(f"trajectory input {name}: expected ({r}, {c}, k), got {a.shape}")
        k = a.shape[2] if k is None else k
        if a.shape[2] != k:
            raise ValueError(f"trajectory input {name}: {a.shape[2]} samples, expected {k}")
        cols.append(a.reshape(r * c, k, order="F"))
    data = np.vstack(cols)                                  # (total, k)
    lines = [f"# {line}" if line else "#" for line in header.strip().splitlines()]
    lines.append("# columns: " + " ".join(
        f"{n}[{controller.size1_in(i)}x{controller.size2_in(i)}]" for i, n in enumerate(names))
        + " (matrices column-major)")
    for j in range(data.shape[1]):
        lines.append(" ".join(_fmt(v) for v in data[:, j]))
    return "\n".join(lines) + "\n"


def parse_trajectory_output(text: str) -> np.ndarray:
    """The rows main.c prints (t then tau) as a (k, 1 + n) array."""
    rows = [line.split() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    return np.array(rows, dtype=float)
