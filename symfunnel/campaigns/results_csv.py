"""A campaign's results.parquet also as results.csv beside it: a `#` header with each column's unit, the names row,
one row per run (for a spreadsheet or MATLAB's readtable)."""

from __future__ import annotations

import io
import math
from pathlib import Path

__all__ = ["write_results_csv", "column_units"]


def column_units(columns: list[str], joint_types, n: int) -> dict[str, str]:
    """The unit of each results column (the uncertain keys' own units are the scenario's: left blank)."""
    from ..core.names import joint_units, unit_label
    u = joint_units(joint_types, n)
    tau, e1 = unit_label(u, "tau"), unit_label(u, "e1")
    energy = " | ".join(dict.fromkeys("N^2 m^2 s" if x["tau"] == "N m" else "N^2 s" for x in u))
    known = {"run": "", "status": "", "t_end": "s", "settle_time": "s", "max_abs_tau": tau,
             "min_margin_e1": "1", "min_margin_e2": "1", "min_margin_e1_after_transient": "1",
             "min_margin_e2_after_transient": "1", "e1_rms_after_transient": e1, "peak_tau_after_t0": tau,
             "control_energy": energy, "chattering": f"{tau}/s" if " | " not in tau else "N m/s | N/s"}
    return {c: known.get(c, "") for c in columns}


def write_results_csv(table, path: Path, joint_types, n: int) -> Path:
    """Write the results table (pyarrow) as CSV with a units header, atomically."""
    from ..core.io import atomic_write
    names = list(table.column_names)
    units = column_units(names, joint_types, n)
    buf = io.StringIO()
    buf.write("# symfunnel sweep results, one row per run (the same as results.parquet); 3 header lines: "
              "numpy.genfromtxt(path, delimiter=',', skip_header=3, dtype=None, encoding='utf-8'); pandas.read_csv(path, comment='#')\n")
    buf.write("# units: " + ",".join(units[c] or "-" for c in names) + "\n")
    buf.write(",".join(names) + "\n")
    rows = table.to_pydict()
    for i in range(table.num_rows):
        cells = []
        for c in names:
            v = rows[c][i]
            if isinstance(v, float):
                cells.append("" if not math.isfinite(v) else repr(v))
            else:
                cells.append(str(v))
        buf.write(",".join(cells) + "\n")
    atomic_write(path, buf.getvalue())
    return path
