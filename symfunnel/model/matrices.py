"""`type = "matrices"`: M, C and G typed in as expressions; C from Christoffel symbols when absent."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..core import validate as V
from ..core.errors import InputError
from ..expr import parse_expression
from ..core.names import IDENT, KEYWORDS, RESERVED
from .base import RigidBodyModel, christoffel_C, symbols


def _names(table: dict, file: str) -> tuple[list[str], list[str], list[float]]:
    """Coordinates and parameters of a matrices model, checked for clashes with reserved names."""
    coords = V.get_list(table, "coordinates", file=file, prefix="model")
    if not coords:
        raise InputError("is empty", file=file, key="model.coordinates", expected="at least one coordinate name")
    if len(coords) > 20:
        raise InputError(f"has {len(coords)} entries", file=file, key="model.coordinates",
                         expected="at most 20 coordinates for a matrices model")
    for i, c in enumerate(coords):
        if not isinstance(c, str) or not IDENT.match(c) or c in RESERVED or ("d" + c) in RESERVED or c in KEYWORDS:
            raise InputError(f"is {c!r}", file=file, key=f"model.coordinates[{i}]",
                             expected="an identifier that is not a reserved name such as t, u, q, e1 "
                                      "(velocities are named 'd' + coordinate)")
    if len(set(coords)) != len(coords) or set(coords) & {"d" + c for c in coords}:
        raise InputError("has duplicates", file=file, key="model.coordinates", expected="distinct names, none of them 'd' + another")
    params = table.get("parameters", {})
    if not isinstance(params, dict):
        raise InputError(f"is {V.a_type(params)}", file=file, key="model.parameters", expected="a table")
    taken = set(coords) | {"d" + c for c in coords}
    p_names, p_values = [], []
    for k, v in params.items():
        if not IDENT.match(k) or k in RESERVED or k in taken or k in KEYWORDS:
            raise InputError("is not a usable parameter name", file=file, key=f"model.parameters.{k}",
                             expected="an identifier other than t, u, the coordinates, velocities and signal names")
        p_names.append(k)
        p_values.append(V.as_float(v, file=file, key=f"model.parameters.{k}"))
    return coords, p_names, p_values


def build_matrices(table: dict, *, file: str) -> RigidBodyModel:
    """Build M(q), C(q, dq), G(q) from expression strings in `[model.matrices]`."""
    coords, p_names, p_values = _names(table, file)
    n = len(coords)
    mats = table.get("matrices")
    if mats is None:
        raise InputError("is missing", file=file, key="model.matrices", expected="a table with M (and C, G)")
    V.check_keys(mats, ["M", "C", "G"], file=file, prefix="model.matrices", required=["M"])
    q, dq = symbols(coords)
    p = ca.vertcat(*[ca.SX.sym(k) for k in p_names]) if p_names else ca.SX(0, 1)
    env = {c: q[i] for i, c in enumerate(coords)}
    env.update({"d" + c: dq[i] for i, c in enumerate(coords)})
    env.update({k: p[i] for i, k in enumerate(p_names)})
    q_names = set(coords) | set(p_names)
    qdq_names = q_names | {"d" + c for c in coords}

    M = _matrix(mats["M"], n, n, q_names, env, file, "model.matrices.M")
    if "C" in mats:
        C = _matrix(mats["C"], n, n, qdq_names, env, file, "model.matrices.C")
        C_source = "given"
    else:
        C = christoffel_C(M, q, dq)
        C_source = "christoffel"
    G = _matrix(mats.get("G", ["0"] * n), n, 1, q_names, env, file, "model.matrices.G")
    model = RigidBodyModel(kind="matrices", coordinates=list(coords), q=q, dq=dq, M=M, C=C, G=G, p=p,
                           p_names=p_names, p_values=np.array(p_values, dtype=float), C_source=C_source,
                           joint_types=["revolute"] * n)
    _check_finite(model, file)
    return model


def _matrix(value, rows: int, cols: int, names: set[str], env: dict, file: str, key: str) -> ca.SX:
    """An r x c SX matrix from an array of arrays of expression strings (or a flat array when c == 1)."""
    shape = f"{rows} x {cols}" if cols > 1 else f"{rows}"
    if cols == 1 and isinstance(value, list) and all(not isinstance(v, list) for v in value):
        value = [[v] for v in value]
    if not isinstance(value, list) or len(value) != rows or not all(isinstance(r, list) and len(r) == cols
                                                                    for r in value):
        raise InputError("has the wrong shape", file=file, key=key,
                         expected=f"an array of {shape} expression strings")
    out = ca.SX.zeros(rows, cols)
    for i, row in enumerate(value):
        for j, s in enumerate(row):
            k = f"{key}[{i}][{j}]" if cols > 1 else f"{key}[{i}]"
            if isinstance(s, (int, float)) and not isinstance(s, bool):
                s = repr(float(s))
            if not isinstance(s, str):
                raise InputError(f"is {V.a_type(s)}", file=file, key=k, expected="an expression string")
            e = parse_expression(s, names, file=file, key=k).to_casadi(env)
            if e.shape != (1, 1):
                raise InputError(f"has shape {e.shape}", file=file, key=k, expected="a scalar expression")
            out[i, j] = e
    return out


def _check_finite(model: RigidBodyModel, file: str) -> None:
    """Evaluate M, C, G once at a generic point so that e.g. log(0) or 1/0 surfaces as an input error."""
    f = ca.Function("f", [model.q, model.dq, model.p], [model.M, model.C, model.G])
    rng = np.random.default_rng(0)
    vals = f(rng.uniform(-1, 1, model.n), rng.uniform(-1, 1, model.n), model.p_values)
    for name, v in zip("MCG", vals):
        if not np.all(np.isfinite(np.array(v))):
            raise InputError("evaluates to a non-finite number at a generic point", file=file,
                             key=f"model.matrices.{name}", expected="finite expressions")
