"""Integration of the compiled closed loop over a relative output grid: one `Runner` per run, its integrators
shared by every run on the same compiled loop, with the integrator statistics of the run."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from .closedloop import ClosedLoop
from ..family.integrators import INTEGRATORS
from .compiled import Buffered, Compiled
from . import sundials
from .between import density

#: take a chunk's samples between output points from its kept steps (direct backend) instead of integrating a chunk
#: that took more steps than it was sampled for again (a third of CVODES' time in the 20 s paper run); tests switch
#: it off to compare the two
SAMPLE_FROM_STEPS = True
#: the direct backend writes its states in the public order (a gather per state in C) instead of every output array
#: being permuted by numpy afterwards; the bench switches it off for its baseline
PUBLIC_ORDER_IN_C = True

if TYPE_CHECKING:
    from ..scenario import SimulationSpec


class Timeout(Exception):
    """The run's wall-clock limit was reached."""


class Runner:
    """Chunked integration on the output grid (used by the run loop and the breach location); one per run."""

    def __init__(self, cl: ClosedLoop, comp: Compiled, method: str, h: float, sim: SimulationSpec):
        self.cl, self.comp, self.method, self.h, self.sim = cl, comp, method, h, sim
        self.perm = comp.perm
        self.inv = np.argsort(comp.perm)
        # integrators are shared by every run on this compiled loop (a campaign builds them once)
        self._integrators: dict = comp.integrators
        self.stats = {"steps": 0, "rhs_evaluations": 0, "jacobian_evaluations": 0, "error_test_failures": 0,
                      "integrate_time": 0.0}
        self.unchecked = 0          # chunks whose samples between output points could not be taken

    def integrator(self, K: int, h: float | None = None, sub: int = 1) -> tuple[ca.Function, Buffered | None]:
        """An integrator over the relative output grid h, 2h, ..., K h (p = the chunk's start time), with its
        evaluation on numpy buffers (None when an input or output is sparse). With sub > 1 (CVODES) the grid also
        has sub - 1 points inside every step after the first (`between` module: the same steps as without)."""
        h = self.h if h is None else h
        key = (self.method, K, h, self.h, self.sim.atol, self.sim.rtol, self.sim.rk_substeps,
               self.sim.max_step, sub)
        if key not in self._integrators:
            grid = self.grid(K, h, sub).tolist()
            opts = self._options(K, h)
            if sub > 1:
                # CVODES counts its step limit per output point: per stored output step as without the extra points
                opts["max_num_steps"] = -(-opts["max_num_steps"] // sub)
            F = ca.integrator(f"sim_{K}" + (f"x{sub}" if sub > 1 else ""), self.method, self.comp.dae, 0.0, grid,
                              opts)
            self._integrators[key] = (F, Buffered(F, stats=True) if Buffered.supports(F) else None)
        return self._integrators[key]

    @staticmethod
    def grid(K: int, h: float, sub: int = 1) -> np.ndarray:
        """The relative output times h, 2h, ..., K h, with sub - 1 points inside every step after the first."""
        plain = h * np.arange(1, K + 1, dtype=float)          # h * (k + 1): the plain grid's times, bit for bit
        if sub <= 1 or K <= 1:
            return plain
        full = np.empty((K, sub))
        full[:, 0] = plain
        full[:-1, 1:] = Runner.between_times(K, h, sub, plain).reshape(K - 1, sub - 1)
        return full.reshape(-1)[:K * sub - (sub - 1)]

    @staticmethod
    def between_times(K: int, h: float, sub: int, plain: np.ndarray | None = None) -> np.ndarray:
        """The dense grid's points inside output steps 2..K: h (k + 1) + j (h / sub), k < K - 1, 0 < j < sub."""
        if sub <= 1 or K <= 1:
            return np.zeros(0)
        plain = h * np.arange(1, K + 1, dtype=float) if plain is None else plain
        return (plain[:-1, None] + np.arange(1, sub, dtype=float) * (h / sub)).reshape(-1)

    def _options(self, K: int, h: float) -> dict:
        opts = INTEGRATORS.get(self.method)(self.sim, h, self.h, K)
        opts["show_eval_warnings"] = False
        return opts

    def direct(self) -> sundials.DirectCvodes | None:
        """The CVODES driver on this compiled loop (`simulation.sundials`), when the run uses CVODES on compiled C
        and the backend is "direct"; shared by every run on the loop. None: use casadi.integrator."""
        if self.method != "cvodes" or self.comp.mode != "compiled" or not self.comp.library \
                or sundials.backend() != "direct":
            return None
        opts = self._options(1, self.h)           # the options do not depend on the grid
        key = ("direct", PUBLIC_ORDER_IN_C, sundials.SCHEDULED_LU, sundials.WIDE_VECTORS,
               tuple(sorted((k, repr(v)) for k, v in opts.items())))
        if key not in self._integrators:
            try:
                d = sundials.DirectCvodes(self.comp.library, self.cl.nx, 1 + len(self.comp.pvals), opts,
                                          order=self.inv if PUBLIC_ORDER_IN_C else None) \
                    if sundials.available() else None
            except RuntimeError as exc:
                import warnings
                warnings.warn(f"{exc}; integrating with casadi.integrator instead", RuntimeWarning, stacklevel=2)
                d = None
            self._integrators[key] = d
        return self._integrators[key]

    def run_dense(self, t0: float, x0: np.ndarray, K: int, sub: int, *,
                  adapt: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """States (K, n_x) at t0 + h, ..., t0 + K h -- the same as `run`'s -- and samples between them about as dense
        as the integrator's steps (`between` module): (X, t_between (B,), X_between (B, n_x)). RuntimeError when the
        chunk's integration fails; a failing extra integration only leaves its samples out (`self.unchecked`).
        `sub` samples per output step; with `adapt` (CVODES), at least as many as this chunk's own steps ask for
        (`between.density`), the density used left in `self.last_density`: the direct backend keeps the chunk's
        steps and takes the samples from them (`DirectCvodes.run_sampled`), the others integrate a chunk that took
        more steps than `sub` again, on the denser grid (the same steps, counted once)."""
        h = self.h
        none = np.zeros(0), np.zeros((0, x0.size))
        self.last_density = sub
        if self.method != "cvodes":
            if sub <= 1:
                return self.run(t0, x0, K), *none
            X = self.run(t0, x0, K)
            try:
                Xf = self.run(t0, x0, K * sub, h / sub, count=False)
            except RuntimeError:
                self.unchecked += 1
                return X, *none
            keep = np.arange(K * sub) % sub != sub - 1
            tf = t0 + (h / sub) * np.arange(1, K * sub + 1)
            return X, tf[keep], Xf[keep]
        D = self.direct() if adapt and SAMPLE_FROM_STEPS else None
        if D is not None:
            res = self._dense_from_steps(D, t0, x0, K, sub)
            if res is not None:
                return res
        steps0 = self.stats["steps"]
        if sub <= 1:
            X, Xg = self.run(t0, x0, K), None
        else:
            try:
                Xg = self.run(t0, x0, K, sub=sub)
            except RuntimeError:
                return self.run(t0, x0, K), *none    # the plain grid decides (its failure is the run's)
            X = Xg[np.arange(Xg.shape[0]) % sub == 0]
        if adapt:
            need = density(self.stats["steps"] - steps0, K)
            if need > sub:
                try:
                    Xg = self.run(t0, x0, K, sub=need, count=False)
                except RuntimeError:                 # (its step limit per point is the plain grid's / need)
                    return X, *none
                sub = self.last_density = need
        if sub <= 1:
            return X, *none
        stored = np.arange(Xg.shape[0]) % sub == 0
        return self._with_first_step(t0, x0, K, sub, Xg[stored], Xg[~stored])

    def _dense_from_steps(self, D: sundials.DirectCvodes, t0: float, x0: np.ndarray, K: int,
                          sub: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """`run_dense` with `adapt` on the direct backend: one integration on the plain grid that keeps its steps,
        then the samples of the dense grid of max(sub, the chunk's own density) taken from them (a history too
        large for memory: integrated again for them); None where the driver leaves the chunk to the plain path
        (a failure, the step limit)."""
        h = self.h
        p = np.concatenate([[t0], self.comp.pvals])
        chosen = {}

        def times(st: dict) -> np.ndarray:
            s = chosen["sub"] = max(sub, density(st["nsteps"], K))
            return self.between_times(K, h, s)                  # the very doubles of the dense grid

        c0 = time.perf_counter()
        try:
            res = D.run_sampled(p, x0[self.perm], self.grid(K, h), times)
        finally:
            self.stats["integrate_time"] += time.perf_counter() - c0
        if res is None:
            return None
        Xp, st, Y = res
        self.stats["cvodes_backend"] = "direct"
        self._count(st)
        s = self.last_density = chosen["sub"]
        X = self._public(D, Xp)
        none = np.zeros(0), np.zeros((0, x0.size))
        if s <= 1:
            return X, *none
        if Y is None:                                   # the kept steps did not fit in memory
            try:
                Xg = self.run(t0, x0, K, sub=s, count=False)
            except RuntimeError:
                return X, *none
            Y = Xg[np.arange(Xg.shape[0]) % s != 0]
            return self._with_first_step(t0, x0, K, s, X, Y)
        return self._with_first_step(t0, x0, K, s, X, self._public(D, Y))

    def _with_first_step(self, t0: float, x0: np.ndarray, K: int, sub: int, X: np.ndarray,
                         Xin: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(X, t_between, X_between) of a chunk from its samples inside output steps 2..K (the dense grid's), with
        those of the first output step from an integration of its own on sub points (extra points inside the first
        output step would change CVODES' first step)."""
        h = self.h
        tb, Xb = t0 + self.between_times(K, h, sub), Xin
        try:                                           # the first output step: its own grid of sub points
            X1 = self.run(t0, x0, sub, h / sub, count=False)
            t1 = t0 + (h / sub) * np.arange(1, sub)
            tb, Xb = np.concatenate([t1, tb]), np.concatenate([X1[:-1], Xb])
        except RuntimeError:
            self.unchecked += 1
        return X, tb, Xb

    def run(self, t0: float, x0: np.ndarray, K: int, h: float | None = None, *, sub: int = 1,
            count: bool = True) -> np.ndarray:
        """States (K, n_x), public order, at t0 + h, ..., t0 + K h (with `sub`, the dense grid of `integrator`);
        RuntimeError when the integrator fails. `count=False`: an extra integration, left out of the statistics."""
        p = np.concatenate([[t0], self.comp.pvals])
        D = self.direct()
        if D is not None:
            self.stats["cvodes_backend"] = "direct"
            return self._run_direct(D, p, x0, K, self.h if h is None else h, sub, count)
        if self.method == "cvodes":
            self.stats["cvodes_backend"] = "casadi"
        F, B = self.integrator(K, h, sub)
        c0 = time.perf_counter()
        xf = None
        if B is not None:
            B.args[F.index_in("x0")][:] = x0[self.perm]
            B.args[F.index_in("p")][:] = p
            try:
                if B.evaluate() == 0:
                    xf, st = B.res[F.index_out("xf")], B.stats
            except RuntimeError as exc:
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)
        if xf is None:       # no buffers, or a failure: the plain call raises CasADi's error (the run's message)
            try:
                xf = np.asarray(F(x0=x0[self.perm], p=p)["xf"]).T.reshape(-1)
            except RuntimeError as exc:
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)                 # a signal during the integration is not an integrator failure
                from .hints import error_line
                self.last_error = error_line(str(exc))
                raise
            st = F.stats()
        self.stats["integrate_time"] += time.perf_counter() - c0
        if not count:
            pass
        elif self.method == "cvodes":
            self.stats["steps"] += int(st.get("nsteps", 0))
            self.stats["rhs_evaluations"] += int(st.get("nfevals", 0))
            self.stats["jacobian_evaluations"] += int(st.get("n_call_jacF", 0))
            self.stats["error_test_failures"] += int(st.get("netfails", 0))
        else:
            self.stats["steps"] += int(st.get("n_call_step", 0)) * 1
            self.stats["rhs_evaluations"] += int(st.get("n_call_daeF", 0))
        return xf.reshape(-1, self.comp.dae.nnz_out(0))[:, self.inv]

    def _run_direct(self, D: sundials.DirectCvodes, p: np.ndarray, x0: np.ndarray, K: int, h: float, sub: int = 1,
                    count: bool = True) -> np.ndarray:
        grid = self.grid(K, h, sub)                          # the very doubles casadi.integrator's grid holds
        c0 = time.perf_counter()
        try:
            X, st = D.run(p, x0[self.perm], grid)
        except RuntimeError as exc:
            self.last_error = str(exc)
            raise
        finally:
            self.stats["integrate_time"] += time.perf_counter() - c0
        if count:
            self._count(st)
        return self._public(D, X)

    def _public(self, D: sundials.DirectCvodes, X: np.ndarray) -> np.ndarray:
        """The driver's states (K, n_x) in the public order (written so by the driver, or permuted here)."""
        return X if D.order is not None else X[:, self.inv]

    def _count(self, st: dict) -> None:
        """Add a direct-backend integration's statistics to the run's."""
        self.stats["steps"] += st["nsteps"]
        self.stats["rhs_evaluations"] += st["nfevals"]
        self.stats["jacobian_evaluations"] += st["n_call_jacF"]
        self.stats["error_test_failures"] += st["netfails"]
