"""How many runs a campaign puts in one task: about TASK_SECONDS of a worker's CPU, measured as the campaign goes.

A task is a Python round-trip (a pickled job and values out, a list of rows back, one Parquet part written by the
parent; on dask also the scheduler's bookkeeping), so a task per run costs a few ms of the parent's CPU per run
and a batch amortises it; a batch that lasts minutes instead loses minutes of work to a kill and leaves one
worker alone at the end. The first task of each worker is one run (it measures the rate); later batches hold as
many runs as take TASK_SECONDS at the rate measured so far, and shrink near the end so the workers finish
together. Rows do not depend on the batches (each run's row is a pure function of its seed and id).
"""

from __future__ import annotations

import math

__all__ = ["TASK_SECONDS", "MAX_BATCH", "BatchSizer"]

#: CPU seconds of work a task aims at: a task's round-trip (4 ms of the parent's CPU on the local pool, ~15 ms of
#: client, scheduler and worker on dask) stays about 1 % of it, and a kill loses a second or two per worker
TASK_SECONDS = 1.5
#: the most runs in one task (short runs: the rows of a batch stay a small message and a small Parquet part)
MAX_BATCH = 512
#: near the end a batch holds at most the remaining runs over this many times the workers (the tail is balanced)
TAIL_SHARES = 2


class BatchSizer:
    """Cuts the run ids still to do into batches, in order: fixed-size batches when `fixed` is given, else sized by
    the seconds per run the workers report (`record`)."""

    def __init__(self, todo: list[int], workers: int, fixed: int | None = None, target: float = TASK_SECONDS,
                 max_batch: int = MAX_BATCH):
        self.todo = list(todo)
        self.workers = max(1, int(workers))
        self.fixed = None if fixed is None else max(1, int(fixed))
        self.target = float(target)
        self.max_batch = int(max_batch)
        self._next = 0              # index in todo of the next run to hand out
        self._probes = 0            # one-run batches handed out before any rate is known
        self.in_flight = 0          # batches handed out and not yet reported back
        self._runs = 0              # runs reported back, and the worker seconds they took
        self._seconds = 0.0
        self.sizes: list[int] = []  # every batch handed out, in order

    @property
    def remaining(self) -> int:
        """Runs not yet handed out."""
        return len(self.todo) - self._next

    @property
    def seconds_per_run(self) -> float | None:
        """Worker CPU seconds per run reported so far (None before the first batch came back)."""
        return self._seconds / self._runs if self._runs else None

    def ready(self) -> bool:
        """Whether a batch can be sized now: runs remain and either a size is fixed, a rate is known, a worker
        still lacks its one-run probe, or nothing is in flight (a rate that never came: one run more)."""
        return self.remaining > 0 and (self.fixed is not None or self._runs > 0 or self._probes < self.workers
                                       or self.in_flight == 0)

    def size(self) -> int:
        """The size the next batch would have."""
        if self.fixed is not None:
            return min(self.fixed, self.remaining)
        spr = self.seconds_per_run
        if spr is None:
            return 1
        n = self.target / spr if spr > 0 else self.max_batch
        tail = math.ceil(self.remaining / (TAIL_SHARES * self.workers))
        return int(max(1, min(self.max_batch, tail, self.remaining, math.floor(n))))

    def next(self) -> list[int]:
        """The next batch of run ids (an empty list when none is ready)."""
        if not self.ready():
            return []
        k = self.size()
        if self.fixed is None and self._runs == 0:
            self._probes += 1
        batch = self.todo[self._next:self._next + k]
        self._next += k
        self.in_flight += 1
        self.sizes.append(k)
        return batch

    def record(self, runs: int, seconds: float | None) -> None:
        """A batch of `runs` runs came back after `seconds` of its worker's CPU (None: not measured)."""
        self.in_flight = max(0, self.in_flight - 1)
        if runs > 0 and seconds is not None and math.isfinite(seconds) and seconds >= 0:
            self._runs += int(runs)
            self._seconds += float(seconds)
