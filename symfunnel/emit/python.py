"""Emit a numpy-only Python module from SX instruction tapes, because CasADi's code generator has no Python target."""

from __future__ import annotations

import keyword
import math
import re
from collections.abc import Sequence

import casadi

from ..sx.tape import OP_NAMES, read_tape

__all__ = ["emit_python", "manifest_entry"]

_O = casadi

#: opcode -> format of the right-hand side; {0} and {1} are the argument work variables
_EXPR = {
    _O.OP_ASSIGN: "{0}",
    _O.OP_ADD: "{0} + {1}",
    _O.OP_SUB: "{0} - {1}",
    _O.OP_MUL: "{0} * {1}",
    _O.OP_DIV: "{0} / {1}",
    _O.OP_NEG: "-{0}",
    _O.OP_EXP: "_exp({0})",
    _O.OP_LOG: "np.log({0})",
    _O.OP_POW: "np.power({0}, {1})",
    _O.OP_CONSTPOW: "np.power({0}, {1})",
    _O.OP_SQRT: "np.sqrt({0})",
    _O.OP_SQ: "{0} * {0}",
    _O.OP_TWICE: "{0} + {0}",
    _O.OP_SIN: "np.sin({0})",
    _O.OP_COS: "np.cos({0})",
    _O.OP_TAN: "np.tan({0})",
    _O.OP_ASIN: "np.arcsin({0})",
    _O.OP_ACOS: "np.arccos({0})",
    _O.OP_ATAN: "np.arctan({0})",
    _O.OP_LT: "({0} < {1}) * 1.0",
    _O.OP_LE: "({0} <= {1}) * 1.0",
    _O.OP_EQ: "({0} == {1}) * 1.0",
    _O.OP_NE: "({0} != {1}) * 1.0",
    _O.OP_NOT: "({0} == 0.0) * 1.0",
    _O.OP_AND: "np.logical_and({0}, {1}) * 1.0",
    _O.OP_OR: "np.logical_or({0}, {1}) * 1.0",
    _O.OP_FLOOR: "np.floor({0})",
    _O.OP_CEIL: "np.ceil({0})",
    _O.OP_FMOD: "np.fmod({0}, {1})",
    _O.OP_REMAINDER: "_remainder({0}, {1})",
    _O.OP_FABS: "np.fabs({0})",
    _O.OP_SIGN: "np.sign({0})",
    _O.OP_COPYSIGN: "np.copysign({0}, {1})",
    _O.OP_IF_ELSE_ZERO: "np.where({0}, {1}, 0.0)",
    _O.OP_ERF: "_erf({0})",
    _O.OP_ERFINV: "_erfinv({0})",
    _O.OP_FMIN: "np.fmin({0}, {1})",
    _O.OP_FMAX: "np.fmax({0}, {1})",
    _O.OP_INV: "1.0 / {0}",
    _O.OP_SINH: "np.sinh({0})",
    _O.OP_COSH: "np.cosh({0})",
    _O.OP_TANH: "np.tanh({0})",
    _O.OP_ASINH: "np.arcsinh({0})",
    _O.OP_ACOSH: "np.arccosh({0})",
    _O.OP_ATANH: "np.arctanh({0})",
    _O.OP_ATAN2: "np.arctan2({0}, {1})",
    _O.OP_LOG1P: "np.log1p({0})",
    _O.OP_EXPM1: "np.expm1({0})",
    _O.OP_HYPOT: "np.hypot({0}, {1})",
    _O.OP_PRINTME: "{0}",
    _O.OP_LIFT: "{0}",
}

#: Every opcode the emitter maps (besides INPUT, OUTPUT, CONST), for tests and reports.
SUPPORTED_OPS = frozenset(OP_NAMES[o] for o in _EXPR)

_RUNTIME = '''
def _arg(a, r, c, what):
    """Return argument `a` flattened column-major to (r*c,) or, with a trailing batch axis, (r*c, B), and B."""
    a = np.asarray(a, dtype=float)
    n = r * c
    if a.shape == (r, c) or (a.ndim <= 1 and a.size == n and (r == 1 or c == 1)):
        return a.reshape(n, order="F"), None
    if a.ndim == 3 and a.shape[:2] == (r, c):
        return a.reshape(n, a.shape[2], order="F"), a.shape[2]
    if a.ndim == 2 and a.shape[0] == n and (r == 1 or c == 1):
        return a, a.shape[1]
    raise ValueError(f"{what}: expected shape ({r}, {c}) or ({r}, {c}, B), got {a.shape}")


def _batch(what, *sizes):
    """Return the common trailing batch shape of the arguments: () or (B,)."""
    sizes = sorted({b for b in sizes if b is not None})
    if len(sizes) > 1:
        raise ValueError(f"{what}: arguments have different batch sizes {sizes}")
    return tuple(sizes)
'''

# numpy's SIMD exp differs from the C library's (which CasADi and the generated C use) in the last bit for a few
# percent of arguments; the funnel variables amplify such differences near the boundary, so exp goes through libm.
_RUNTIME_EXP = '''

_exp = np.vectorize(math.exp, otypes=[float])
'''

_RUNTIME_ERF = '''

_erf = np.vectorize(math.erf, otypes=[float])
'''

_RUNTIME_ERFINV = '''

def _erfinv(y):
    """Inverse error function: normal quantile as first guess, then two Newton steps on erf."""
    y = np.asarray(y, dtype=float)
    p = np.clip((y + 1.0) / 2.0, 1e-300, 1.0 - 2.0**-53)
    x = np.vectorize(_NORMAL.inv_cdf, otypes=[float])(p) / math.sqrt(2.0)
    with np.errstate(all="ignore"):
        for _ in range(2):
            x = x - (_erf(x) - y) / (2.0 / math.sqrt(math.pi) * np.exp(-x * x))
    x = np.where(np.abs(y) == 1.0, np.copysign(np.inf, y), x)
    return np.where(np.abs(y) <= 1.0, x, np.nan)


_NORMAL = statistics.NormalDist()
'''

_RUNTIME_REMAINDER = '''

_remainder = np.vectorize(math.remainder, otypes=[float])
'''

_RESERVED = {"np", "math", "statistics", "FUNCTIONS", "MANIFEST"}
_WORK = re.compile(r"w\d+\Z")


def manifest_entry(f: casadi.Function) -> dict:
    """Describe `f`'s name and its inputs'/outputs' names and shapes, the same for every code generator."""
    return {
        "name": f.name(),
        "inputs": [{"name": f.name_in(i), "shape": [f.size1_in(i), f.size2_in(i)]} for i in range(f.n_in())],
        "outputs": [{"name": f.name_out(i), "shape": [f.size1_out(i), f.size2_out(i)]} for i in range(f.n_out())],
    }


def _check_name(name: str, what: str) -> None:
    """Refuse names that are not usable, or would clash with generated helpers, as Python identifiers."""
    if not name.isidentifier() or keyword.iskeyword(name) or name.startswith("_") or name in _RESERVED:
        raise ValueError(f"{what} {name!r} cannot be used as a Python name in generated code")


def _signature(entry: dict) -> str:
    """One-line signature such as f(x[2x1], y[2x2]) -> (o[2x1]) for docstrings."""
    def part(items):
        return ", ".join(f"{d['name']}[{d['shape'][0]}x{d['shape'][1]}]" for d in items)

    return f"{entry['name']}({part(entry['inputs'])}) -> ({part(entry['outputs'])})"


def _doc(text: str) -> str:
    """Escape text for a triple-quoted docstring: backslashes, quotes, and control characters (e.g. NUL)."""
    text = text.replace("\\", "\\\\").replace('"""', '\\"\\"\\"')
    return "".join(_escape_char(c) for c in text)


def _escape_char(c: str) -> str:
    """`c`, or its escape sequence when it may not appear literally in Python source (NUL, CR, other controls)."""
    o = ord(c)
    if c == "\n" or c == "\t" or (32 <= o < 127) or (o >= 160 and c not in "\u2028\u2029"
                                                     and not 0xD800 <= o < 0xE000):
        return c
    return f"\\x{o:02x}" if o < 256 else f"\\u{o:04x}"


def _literal(x: float) -> str:
    """Exact Python literal for a tape constant (repr round-trips; inf/nan via numpy)."""
    if math.isnan(x):
        return "np.nan"
    if math.isinf(x):
        return "np.inf" if x > 0 else "-np.inf"
    return repr(float(x))


def _emit_function(f: casadi.Function, used: set[str]) -> list[str]:
    """Straight-line Python for one function; adds the names of needed runtime helpers to `used`."""
    tape = read_tape(f)
    name = f.name()
    if tape.free:
        raise ValueError(f"function {name!r} has free variables {list(tape.free)}; they must be inputs")
    for n in tape.in_names:
        _check_name(n, f"input of {name!r}")
        if _WORK.match(n):
            raise ValueError(f"input {n!r} of {name!r} clashes with the generated work variables w0, w1, ...")
    if len(set(tape.in_names)) != len(tape.in_names):
        raise ValueError(f"function {name!r} has duplicate input names")
    entry = manifest_entry(f)
    lines = [
        "",
        "",
        f"def {name}({', '.join(tape.in_names)}):",
        f'    """{_doc(_signature(entry))}."""',
    ]
    for i, (n, (r, c)) in enumerate(zip(tape.in_names, tape.in_shapes)):
        lines.append(f'    {n}, _b{i} = _arg({n}, {r}, {c}, "{name}: {n}")')
    lines.append(f'    _b = _batch("{name}"{"".join(f", _b{i}" for i in range(len(tape.in_names)))})')
    for j, (r, c) in enumerate(tape.out_shapes):
        lines.append(f"    _o{j} = np.zeros(({r * c},) + _b)")
    lines.append('    with np.errstate(all="ignore"):')
    body = []
    for ins in tape.instructions:
        op, a, res = ins.op, ins.args, ins.res
        fmt = _EXPR.get(op)
        if fmt is not None:
            rhs = fmt.format(*(f"w{k}" for k in a))
            if rhs.startswith("_"):
                used.add(rhs[1 : rhs.index("(")])
            body.append(f"w{res[0]} = {rhs}")
        elif op == _O.OP_CONST:
            body.append(f"w{res[0]} = {_literal(ins.constant)}")
        elif op == _O.OP_INPUT:
            body.append(f"w{res[0]} = {tape.in_names[a[0]]}[{tape.in_nz[a[0]][a[1]]}]")
        elif op == _O.OP_OUTPUT:
            body.append(f"_o{res[0]}[{tape.out_nz[res[0]][res[1]]}] = w{a[0]}")
        else:
            hint = " (build the SX without never_inline calls, or expand it)" if op == _O.OP_CALL else ""
            raise NotImplementedError(
                f"codegen.python: CasADi operation OP_{ins.name} on the tape of {name!r} is not supported{hint}"
            )
    lines.extend("        " + b for b in body or ["pass"])
    outs = [f'_o{j}.reshape(({r}, {c}) + _b, order="F")' for j, (r, c) in enumerate(tape.out_shapes)]
    if len(outs) == 1:
        lines.append(f"    return ({outs[0]},)")
    else:
        lines.append("    return (")
        lines.extend(f"        {o}," for o in outs)
        lines.append("    )")
    return lines


def emit_python(functions: Sequence[casadi.Function], *, module_doc: str = "") -> str:
    """Return the text of one numpy-only module with a function per casadi.Function plus FUNCTIONS and MANIFEST; deterministic."""
    functions = list(functions)
    names = [f.name() for f in functions]
    for n in names:
        _check_name(n, "function name")
    if len(set(names)) != len(names):
        raise ValueError(f"function names must be unique, got {names}")
    used: set[str] = set()
    code: list[str] = []
    for f in functions:
        code.extend(_emit_function(f, used))
    if "erfinv" in used:
        used.add("erf")
    entries = [manifest_entry(f) for f in functions]

    doc = _doc(module_doc.strip())
    head = [doc, ""] if doc else []
    head.append("Generated by symfunnel from CasADi SX instruction tapes; needs only numpy.")
    head.append("Arguments take shape (r, c), a flat (r*c,) vector for row/column vectors, or a trailing batch axis.")
    head.append("")
    head.append("Functions:")
    head.extend(f"    {_doc(_signature(e))}" for e in entries)
    out = ['"""' + head[0], *head[1:], '"""', ""]
    if used & {"exp", "erf", "erfinv", "remainder"}:
        out.append("import math")
    if "erfinv" in used:
        out.append("import statistics")
    if used & {"exp", "erf", "erfinv", "remainder"}:
        out.append("")
    out.append("import numpy as np")
    out.append("")
    out.append(_RUNTIME.rstrip("\n"))
    if "exp" in used:
        out.append(_RUNTIME_EXP.rstrip("\n"))
    if "erf" in used:
        out.append(_RUNTIME_ERF.rstrip("\n"))
    if "erfinv" in used:
        out.append(_RUNTIME_ERFINV.rstrip("\n"))
    if "remainder" in used:
        out.append(_RUNTIME_REMAINDER.rstrip("\n"))
    out.extend(code)
    out.extend(["", "", "FUNCTIONS = {"])
    out.extend(f"    {n!r}: {n}," for n in names)
    out.append("}")
    out.extend(["", "MANIFEST = ["])
    for e in entries:
        out.append("    {")
        out.append(f"        'name': {e['name']!r},")
        for key in ("inputs", "outputs"):
            out.append(f"        {key!r}: [")
            out.extend(f"            {{'name': {d['name']!r}, 'shape': {d['shape']!r}}}," for d in e[key])
            out.append("        ],")
        out.append("    },")
    out.append("]")
    out.append("")
    return "\n".join(out)
