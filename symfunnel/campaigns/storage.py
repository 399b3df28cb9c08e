"""A sweep's results on disk: results.parquet, fed by finished chunks of rows (each written at once as a small
Parquet file beside it) and merged atomically every few seconds and at the end, so a killed sweep loses at most its
runs in flight.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.io import atomic_path
from ..simulation.metrics import CAMPAIGN_METRICS

__all__ = ["RESULT_COLUMNS", "ResultStore"]

RESULT_COLUMNS = ["status", "t_end", "min_margin_e1", "min_margin_e2", "max_abs_tau",
                  "min_margin_e1_after_transient", "min_margin_e2_after_transient", "settle_time",
                  *CAMPAIGN_METRICS]
PARTS = ".results.parts"
FLUSH_SECONDS = 10.0

def _schema(columns):
    import pyarrow as pa
    fields = [pa.field("run", pa.int64())] + [pa.field(c, pa.float64()) for c in columns]
    fields += [pa.field("status", pa.string())] + [pa.field(c, pa.float64()) for c in RESULT_COLUMNS[1:]]
    return pa.schema(fields)


def _table(rows, columns):
    import pyarrow as pa
    schema = _schema(columns)
    return pa.Table.from_pylist(rows, schema=schema)


def _write_parquet(table, path: Path) -> None:
    import pyarrow.parquet as pq
    with atomic_path(path) as tmp:
        pq.write_table(table, str(tmp))


class ResultStore:
    """results.parquet of a sweep directory, fed by finished chunks (each written at once) and merged periodically."""

    def __init__(self, out: Path, columns: list[str]):
        self.out = Path(out)
        self.columns = columns
        self.parts = self.out / PARTS
        self.final = self.out / "results.parquet"
        self._count = 0
        self._last_merge = time.monotonic()

    def read(self):
        """Every row written so far (results.parquet and unmerged chunks), one per run, sorted by run."""
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq
        tables = []
        if self.final.exists():
            try:
                tables.append(pq.read_table(str(self.final)))
            except Exception as exc:  # noqa: BLE001 - a damaged file of the user's: bad input, named
                raise InputError(f"cannot be read ({type(exc).__name__}: {exc})", file=str(self.final),
                                 expected="results.parquet written by `symfunnel sweep` (delete it, or the "
                                 "directory, to start afresh)") from None
        if self.parts.is_dir():
            for p in sorted(self.parts.glob("*.parquet")):
                try:
                    tables.append(pq.read_table(str(p)))
                except Exception:  # noqa: BLE001 - a chunk cut short by a kill: its runs are simply redone
                    continue
        if not tables:
            return _table([], self.columns)
        schema = _schema(self.columns)
        try:
            t = pa.concat_tables([x.select(schema.names).cast(schema) for x in tables])
        except (KeyError, ValueError, pa.ArrowInvalid) as exc:
            raise InputError(f"has other columns than this campaign ({exc})", file=str(self.final),
                             expected="results of the same campaign") from None
        t = t.take(pc.sort_indices(t, sort_keys=[("run", "ascending")]))
        runs = t.column("run").to_numpy()
        keep = np.ones(runs.size, dtype=bool)
        keep[1:] = runs[1:] != runs[:-1]
        return t.filter(pa.array(keep))

    def has_rows(self) -> bool:
        """Whether any result of an earlier sweep is on disk."""
        return self.final.exists() or (self.parts.is_dir() and any(self.parts.glob("*.parquet")))

    def done(self) -> set[int]:
        """Run ids already on disk."""
        return set(int(r) for r in self.read().column("run").to_numpy())

    def add(self, rows: list[dict]) -> None:
        """Write one finished chunk at once; merge into results.parquet every FLUSH_SECONDS."""
        if rows:
            self._count += 1
            name = f"part-{os.getpid()}-{time.time_ns()}-{self._count}.parquet"
            _write_parquet(_table(rows, self.columns), self.parts / name)
        if time.monotonic() - self._last_merge > FLUSH_SECONDS:
            self.merge()

    def merge(self):
        """Rewrite results.parquet from everything written so far (atomically), then drop the merged chunks."""
        merged = list(self.parts.glob("*.parquet")) if self.parts.is_dir() else []
        t = self.read()
        _write_parquet(t, self.final)
        for p in merged:
            p.unlink(missing_ok=True)
        self._last_merge = time.monotonic()
        return t

    def clear(self) -> None:
        """Forget a previous sweep in this directory (a fresh start)."""
        shutil.rmtree(self.parts, ignore_errors=True)
        for name in ("results.parquet", "results.csv", "summary.json", "worst.toml", "campaign.json"):
            (self.out / name).unlink(missing_ok=True)
