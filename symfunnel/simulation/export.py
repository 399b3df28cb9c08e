"""A run's trajectory written by the file's suffix: .npz (numpy), .csv (a `#` header with units, a row of column
names, `t` first, one column per signal and joint) or .mat (MATLAB, the npz's arrays by name with `units` and
`description` structs); always atomically (a temporary file renamed into place)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

__all__ = ["SUFFIXES", "signal_units", "write_trajectory", "check_suffix"]

#: the suffixes `simulate --out` writes
SUFFIXES = (".npz", ".csv", ".mat")

_POS = ("q", "qd", "e1", "F1")
_VEL = ("dq", "dqd", "e2", "F2", "alpha2")
_ACC = ("ddq", "ddqd", "ddq_nom", "f_true", "w_phi", "esn_error", "w_hat", "W_star")
_TAU = ("tau", "tau_applied", "friction", "disturbance")
_ONE = ("z1", "z2", "m1", "m2", "margins", "x_esn")

#: what each signal is (the .mat's `description`, the .csv's header)
DESCRIPTIONS = {
    "t": "time", "q": "joint position", "dq": "joint velocity", "qd": "reference position",
    "dqd": "reference velocity", "ddqd": "reference acceleration", "e1": "tracking error q - qd",
    "F1": "funnel boundary of e1", "e2": "velocity error dq - alpha2", "F2": "funnel boundary of e2",
    "alpha2": "virtual control", "z1": "transformed error of e1", "z2": "transformed error of e2",
    "tau": "commanded torque (force for a prismatic joint)", "tau_applied": "torque after the dead zone",
    "friction": "friction torque", "disturbance": "disturbance torque", "ddq": "joint acceleration",
    "ddq_nom": "nominal joint acceleration", "f_true": "true unknown term", "w_phi": "the approximator's estimate",
    "esn_error": "estimate - true unknown term", "m1": "funnel margin 1 - |e1|/F1", "m2": "funnel margin 1 - |e2|/F2",
    "margins": "true funnel margins 1 - |e|/F at the samples: e1 columns, then e2",
    "x_esn": "reservoir state", "w_hat": "approximator weights", "W_star": "fitted ideal weights",
    "V": "Lyapunov function",
}


def check_suffix(path: str, key: str = "--out") -> str:
    """The suffix of an output file, one of SUFFIXES (InputError naming the key otherwise)."""
    from ..core.errors import InputError
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(f"is '{path}'", key=key, expected="a file name ending in .npz, .csv or .mat")
    return suffix


def signal_units(name: str, joint_types, n: int) -> list[str] | str:
    """The unit of a signal: per joint (rad or m, N m or N, ...) for the joint-indexed ones, else one string
    ('1' for a dimensionless quantity)."""
    from ..core.names import joint_units
    u = joint_units(joint_types, n)
    if name == "t":
        return "s"
    if name in _POS:
        return [x["e1"] for x in u]
    if name in _VEL:
        return [x["e2"] for x in u]
    if name in _ACC:
        return [x["e1"] + "/s^2" for x in u]
    if name in _TAU:
        return [x["tau"] for x in u]
    if name in _ONE:
        return "1"
    return "mixed" if name == "V" else ""


def _column_names(name: str, shape: tuple) -> list[str]:
    """'q' -> q[1], q[2]; a (T, a, b) array -> name[i][j] (1-based; no comma in a CSV name); a (T,) array -> name."""
    rest = shape[1:]
    if not rest:
        return [name]
    idx = np.indices(rest).reshape(len(rest), -1).T + 1
    return [name + "".join(f"[{int(i)}]" for i in ix) for ix in idx]


def _column_units(unit, k: int) -> list[str]:
    """The units of a signal's k columns (flattened in C order: the joint index is the last, fastest one)."""
    if isinstance(unit, list) and unit:
        return [unit[i % len(unit)] for i in range(k)]
    return [unit if isinstance(unit, str) else ""] * k


def write_trajectory(path, arrays: dict, *, joint_types, n: int, meta: dict | None = None) -> Path:
    """Write `arrays` (`t` first; arrays with the time axis first, a torque held over periods with one row less)
    and `meta` (strings and numbers: status, message, ...) to `path`, by its suffix, atomically."""
    from ..core.io import atomic_path
    path = Path(path)
    suffix = check_suffix(str(path))
    meta = dict(meta or {})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            if suffix == ".npz":
                data = {k: np.asarray(v) for k, v in arrays.items()}
                data.update({k: np.array(v) for k, v in meta.items()})
                np.savez_compressed(fh, **data)
            elif suffix == ".csv":
                fh.write(_csv(arrays, joint_types, n, meta).encode("utf-8"))
            else:
                _mat(fh, arrays, joint_types, n, meta)
    return path


def _csv(arrays: dict, joint_types, n: int, meta: dict) -> str:
    """The .csv text: `#` lines (what, units, metadata, arrays left out), the names row, the rows."""
    t = np.asarray(arrays["t"], float)
    T = t.size
    cols, names, units, left, held = [t.reshape(T, 1)], ["t"], ["s"], [], []
    for k, v in arrays.items():
        if k == "t":
            continue
        a = np.asarray(v)
        if a.ndim == 0 or a.dtype.kind not in "fiub" or a.shape[0] not in (T, T - 1) or T == 0:
            left.append(k)
            continue
        a = a.astype(float).reshape(a.shape[0], -1)
        if a.shape[0] == T - 1:             # held over [t_k, t_k+1): no value after the last sample
            held.append(k)
            a = np.vstack([a, np.full((1, a.shape[1]), np.nan)])
        cols.append(a)
        names += _column_names(k, np.asarray(v).shape)
        units += _column_units(signal_units(k, joint_types, n), a.shape[1])
    head = [f"symfunnel trajectory: {', '.join(f'{k} = {v}' for k, v in meta.items())}",
            "one row per time point; the columns' units below, the names after this header"
            + (f"; {', '.join(held)} (held over the period [t_k, t_k+1)) on row k, empty on the last row"
               if held else ""),
            "units: " + ",".join(units),
            "signals: " + "; ".join(f"{k}: {DESCRIPTIONS[k]}" for k in arrays if k in DESCRIPTIONS and k not in left)]
    if left:
        head.append("not in this file (no time axis; see the .npz or .mat): " + ", ".join(left))
    lines = len(head) + 2
    head.insert(0, f"{lines} header lines: numpy.genfromtxt(path, delimiter=',', skip_header={lines}); "
                   "pandas.read_csv(path, comment='#')")
    buf = io.StringIO()
    for h in head:
        buf.write("# " + " ".join(h.split()) + "\n")
    buf.write(",".join(names) + "\n")
    data = np.hstack(cols) if cols else np.zeros((0, 0))
    for row in data:
        buf.write(",".join("" if not np.isfinite(x) else repr(float(x)) for x in row) + "\n")
    return buf.getvalue()


def _mat(fh, arrays: dict, joint_types, n: int, meta: dict) -> None:
    """The .mat file: every array by its name (as in the .npz), `units` and `description` structs, the metadata."""
    from scipy.io import savemat
    data = {k: np.asarray(v) for k, v in arrays.items()}
    units, desc = {}, {}
    for k in arrays:
        u = signal_units(k, joint_types, n)
        units[k] = ", ".join(u) if isinstance(u, list) else u
        desc[k] = DESCRIPTIONS.get(k, "")
    data.update({k: (v if isinstance(v, str) else np.asarray(v)) for k, v in meta.items()})
    data["units"] = units
    data["description"] = desc
    savemat(fh, data, do_compression=True, long_field_names=True)
