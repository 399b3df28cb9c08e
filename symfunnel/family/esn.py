"""Echo state network in continuous time (paper eq. 8): deterministic weights from a seed, reservoir ODE as CasADi SX.

The reservoir is

    dX/dt = (1/time_constant) * (-leak * X + tanh(W_in u + W X + b)),

which is eq. 8 with C = 1/time_constant, a = leak, f = tanh and W_back = 0: there is no output feedback, because
the ESN output y = W_hat^T Phi(X) is the controller's adaptive estimate, and feeding it back would couple the
reservoir to the adaptation law, which the paper's stability proof (Section 3) does not cover. The bias b plays the
role of a constant input.

Determinism: every random number comes from ``numpy.random.default_rng(seed)`` (PCG64, ``uniform``/``random``
only, in a fixed order: W_in, b, then W), whose output is specified bit for bit on every platform. The one
platform-dependent step is the spectral radius of the raw W, computed by LAPACK (``numpy.linalg.eigvals``), whose
last bits can differ between BLAS/LAPACK builds; the scale factor spectral_radius / rho(W_raw) is therefore rounded
to 13 significant digits before it is applied, so that two machines agree bit for bit unless the exact factor lies
within LAPACK round-off of a 13-digit rounding boundary (probability about delta / 1e-12 for a relative
disagreement delta between builds, i.e. ~1e-3 at delta ~ 1e-15; larger for big, strongly non-normal W). The cost
is that rho(W) matches the configured value to within 5e-13 relative (so within 1e-12) rather than to the last bit.

Echo-state property: tanh is 1-Lipschitz and |tanh| <= 1, so each X_i is attracted to [-1/leak, 1/leak] for any
bounded input, and the reservoir is contracting (its state forgets its initial condition exponentially) when
||W||_2 < leak, since the Jacobian (1/time_constant)(-leak I + D W), D = diag(tanh') in [0, 1], then has a negative
2-norm matrix measure. The discrete-time ESN heuristic rho(W) < 1 is enforced; contraction is only reported
(``ESN.contracting``), not required.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..core.threads import one_blas_thread

_SCALE_DIGITS = 13          # significant digits kept of the spectral-radius scale factor (see module docstring)
_MAX_REDRAWS = 100
_RHO_FLOOR = 1e-8           # a drawn W with a smaller spectral radius is treated as nilpotent and redrawn


class ConfigError(ValueError):
    """An invalid ESN setting, naming the field and what was expected so the caller can locate it in its input."""

    def __init__(self, key: str, message: str, expected: str):
        self.key = key
        self.reason = message
        self.expected = expected
        super().__init__(f"{key}: {message} (expected {expected})")


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class ESNConfig:
    """Settings of the echo state network; checked on construction (raises ConfigError, a ValueError)."""

    size: int = 50                 # N reservoir units
    leak: float = 1.0              # a, leaking decay rate (> 0)
    time_constant: float = 0.05    # seconds; eq. 8's C = 1/time_constant
    spectral_radius: float = 0.9   # of W, in (0, 1)
    input_scaling: float = 0.5     # W_in and b are uniform in [-input_scaling, input_scaling]
    sparsity: float = 0.9          # fraction of zero entries of W, in [0, 1)
    seed: int = 0
    bias: bool = True              # regressor Phi = [X; 1] when True, else X (the reservoir's b is always used)

    def __post_init__(self):
        if not _is_int(self.size) or self.size < 1:
            raise ConfigError("size", f"is {self.size!r}", "an integer >= 1")
        for key in ("leak", "time_constant"):
            v = getattr(self, key)
            if not _is_num(v) or v <= 0:
                raise ConfigError(key, f"is {v!r}", "a finite number > 0")
        r = self.spectral_radius
        if not _is_num(r) or not 0 < r < 1:
            raise ConfigError("spectral_radius", f"is {r!r}", "a number > 0 and < 1")
        if not _is_num(self.input_scaling) or self.input_scaling < 0:
            raise ConfigError("input_scaling", f"is {self.input_scaling!r}", "a finite number >= 0")
        s = self.sparsity
        if not _is_num(s) or not 0 <= s < 1:
            raise ConfigError("sparsity", f"is {s!r}", "a number >= 0 and < 1")
        if not _is_int(self.seed) or self.seed < 0:
            raise ConfigError("seed", f"is {self.seed!r}", "an integer >= 0")
        if not isinstance(self.bias, bool):
            raise ConfigError("bias", f"is {self.bias!r}", "true or false")


def _draw_reservoir(rng: np.random.Generator, n: int, sparsity: float) -> np.ndarray:
    """One raw sparse N x N matrix: uniform[-1, 1] entries, a `sparsity` fraction zeroed, at least one nonzero per row."""
    values = rng.uniform(-1.0, 1.0, size=(n, n))
    keep = rng.random(size=(n, n)) >= sparsity
    rescue_col = np.minimum((rng.random(size=n) * n).astype(np.int64), n - 1)   # used for rows left empty
    for i in np.flatnonzero(~keep.any(axis=1)):
        keep[i, rescue_col[i]] = True
    return np.where(keep, values, 0.0)


#: reservoirs up to this size use dense LAPACK for the spectral radius and the 2-norm; larger ones ARPACK (a 2000-unit
#: reservoir: 30 s of dense eigenvalues against 2 s, agreeing to ~1e-14 relative), falling back to dense
DENSE_UP_TO = 500


def _spectral_radius(W: np.ndarray) -> float:
    """max |eigenvalue| of W: dense for small W, else ARPACK's six largest (deterministic start vector)."""
    n = W.shape[0]
    if n > DENSE_UP_TO:
        import scipy.sparse as sp
        import scipy.sparse.linalg as sl
        try:
            ev = sl.eigs(sp.csr_matrix(W), k=6, which="LM", v0=np.ones(n), tol=1e-13, maxiter=100 * n,
                         return_eigenvectors=False)
            return float(np.max(np.abs(ev)))
        except sl.ArpackError:
            pass
    with one_blas_thread():                        # a second BLAS thread only oversubscribes (core/threads.py)
        return float(np.max(np.abs(np.linalg.eigvals(W))))


def _norm2(W: np.ndarray) -> float:
    """The largest singular value of W: dense for small W, else ARPACK (deterministic start vector)."""
    n = W.shape[0]
    if n > DENSE_UP_TO:
        import scipy.sparse as sp
        import scipy.sparse.linalg as sl
        try:
            return float(sl.svds(sp.csr_matrix(W), k=1, v0=np.ones(n), tol=1e-13, maxiter=100 * n,
                                 return_singular_vectors=False)[0])
        except sl.ArpackError:
            pass
    with one_blas_thread():
        return float(np.linalg.norm(W, 2))


def _round_sig(x: float, digits: int) -> float:
    """x rounded to `digits` significant decimal digits (correctly rounded by Python's float formatting)."""
    return float(f"{x:.{digits - 1}e}")


#: `_wx_blocks` up to this many blocks (32 bytes of constants each, 4x the scalar rows' 8 per nonzero): measured
#: 1.07-1.13x over the scalar rows at 204 and 566 blocks, none or a loss at 1,030 (the constants leave L1)
WX_BLOCKS_MAX = 600
#: groups of 4 rows whose sums `_wx_blocks` keeps in registers in one pass over the columns (AVX2's 16 registers:
#: 12 sums, the broadcast x[j] and a weight vector)
WX_PASS_GROUPS = 12


def _wx_preamble(name: str) -> list[str]:
    """File-scope C lines before `name`: `name`_FMA4 (and AVX's intrinsics) where the target has AVX2 and FMA
    (-march=native on x86-64 since Haswell) unless -DSYMFUNNEL_NO_FMA or -DSYMFUNNEL_SCALAR_WX. Elsewhere W x
    stays the scalar rows (unfused, the same blocks in gcc vectors gained 1.03 at most: not kept)."""
    return ["#if defined(__AVX2__) && defined(__FMA__) \\",
            "    && !defined(SYMFUNNEL_NO_FMA) && !defined(SYMFUNNEL_SCALAR_WX)",
            "#include <immintrin.h>",
            f"#define {name}_FMA4 1",
            "#endif"]


def _wx_block_map(N: int, rp: list, cj: list, vals: list) -> dict[tuple[int, int], list[float]]:
    """W's blocks of 4 rows x 1 column with a nonzero: (column j, group g) -> the weights of rows 4g..4g+3 in j."""
    block: dict[tuple[int, int], list[float]] = {}
    for i in range(N):
        for q in range(rp[i], rp[i + 1]):
            block.setdefault((cj[q], i // 4), [0.0] * 4)[i % 4] = vals[q]
    return block


def _wx_blocks(name: str, N: int, rp: list, cj: list, vals: list) -> list[str]:
    """C lines of W x by blocks of four consecutive rows and one column with AVX's fused multiply-add, adding
    (W x)_i into zu[i] as the scalar rows do: (zu[i] + s_i) + b[i].

    Column j's x[j] is broadcast once and multiplied into every group of rows 4g..4g+3 with a nonzero in column j
    (the group's weights in column j as one vector constant, 0.0 where a row has none): 204 vector multiply-adds
    for the paper's 247 nonzeros, against 247 multiplies, 247 additions and 494 loads. The columns run ascending,
    so each row's products are summed in the graph's order; a 0.0 weight adds 0.0 * x[j] = +-0.0 and s + +-0.0 = s
    (s starts at +0.0 and a round-to-nearest sum is -0.0 only from two -0.0); a non-finite x[j] makes its whole
    group's lanes NaN, not only the rows it enters (the step's finiteness check rejects either). What differs from
    the scalar rows is the rounding: one per product and sum instead of two, so each partial sum's error is at most
    the unfused one's first-order bound (sum over its terms of |product| + |partial sum|, in units of u)."""
    G = -(-N // 4)
    block = _wx_block_map(N, rp, cj, vals)
    out = ["  /* W x by blocks of 4 rows x 1 column, fused multiply-adds (family/esn.py, _wx_blocks) */",
           "  {",
           f"    double sv[{4 * G}];",
           "    __m256d xj, " + ", ".join(f"s{g}" for g in range(G)) + ";"]
    for first in range(0, G, WX_PASS_GROUPS):         # a pass's sums stay in registers (AVX2 has 16)
        groups = range(first, min(G, first + WX_PASS_GROUPS))
        out.append(f"    /* rows {4 * first}..{min(N, 4 * groups[-1] + 4) - 1} */")
        out.append("    " + " ".join(f"s{g} = _mm256_setzero_pd();" for g in groups))
        for j in sorted({j for j, g in block if g in groups}):          # one line per column
            out.append(" ".join([f"    xj = _mm256_set1_pd(x[{j}]);"] + [
                f"s{g} = _mm256_fmadd_pd(_mm256_setr_pd({', '.join(repr(v) for v in block[(j, g)])}), xj, s{g});"
                for g in groups if (j, g) in block]))
        out += [f"    _mm256_storeu_pd(sv + {4 * g}, s{g});" for g in groups]
    out += [f"    for (i = 0; i < {N}; ++i) zu[i] = (zu[i] + sv[i]) + {name}_b[i];", "  }"]
    return out


class ESN:
    """A continuous-time echo state network with fixed random weights; the controller adapts only W_hat in W_hat^T Phi(X)."""

    #: `xdot_c` emits W x as straight-line code up to this many nonzeros of W, as loops above (compile time)
    UNROLL_W_MAX = 1500
    #: the straight-line W x by blocks of rows in AVX's fused multiply-adds (`_wx_blocks`) where the target has them,
    #: the scalar rows kept as the fallback; False: the scalar rows only (the bench's previous path)
    VECTOR_WX = True

    def __init__(self, config: ESNConfig, n_inputs: int):
        """Draw W_in (N x K), b (N) and W (N x N) from `config.seed` and scale W to the configured spectral radius."""
        if not _is_int(n_inputs) or n_inputs < 1:
            raise ConfigError("n_inputs", f"is {n_inputs!r}", "an integer >= 1")
        self.config = config
        self.n_inputs = int(n_inputs)
        N, K = config.size, self.n_inputs
        rng = np.random.default_rng(config.seed)
        W_in = config.input_scaling * rng.uniform(-1.0, 1.0, size=(N, K))
        b = config.input_scaling * rng.uniform(-1.0, 1.0, size=N)
        for _ in range(_MAX_REDRAWS):
            W_raw = _draw_reservoir(rng, N, config.sparsity)
            rho_raw = _spectral_radius(W_raw)
            if rho_raw > _RHO_FLOOR:
                break
        else:  # pragma: no cover - every row has a nonzero, so the pattern has a cycle and rho = 0 has probability 0
            raise ConfigError("seed", f"drew a nilpotent reservoir {_MAX_REDRAWS} times", "another seed")
        self.scale = _round_sig(config.spectral_radius / rho_raw, _SCALE_DIGITS)
        W = W_raw * self.scale
        self.W_in = _frozen(W_in)
        self.W = _frozen(W)
        self.b = _frozen(b)
        self.spectral_radius = _spectral_radius(self.W)
        self.norm2 = _norm2(self.W)
        self._W_in_dm = ca.sparsify(ca.DM(self.W_in))
        self._W_dm = ca.sparsify(ca.DM(self.W))
        self._b_dm = ca.DM(self.b)

    @property
    def size(self) -> int:
        """N, the number of reservoir units."""
        return self.config.size

    @property
    def n_regressor(self) -> int:
        """Length of the regressor Phi(X): N + 1 with the constant term, else N."""
        return self.size + (1 if self.config.bias else 0)

    @property
    def contracting(self) -> bool:
        """True when ||W||_2 < leak, a sufficient condition for the reservoir to forget its initial state exponentially."""
        return self.norm2 < self.config.leak

    @property
    def sparsity_actual(self) -> float:
        """Fraction of zero entries of W as drawn (close to, not exactly, the configured sparsity)."""
        return float(np.mean(self.W == 0.0))

    def _check_sx(self, x, u=None):
        x = ca.SX(x) if not isinstance(x, (ca.SX, ca.MX)) else x
        if x.shape != (self.size, 1):
            raise ValueError(f"reservoir state has shape {x.shape}, expected ({self.size}, 1)")
        if u is None:
            return x, None
        u = ca.SX(u) if not isinstance(u, (ca.SX, ca.MX)) else u
        if u.shape != (self.n_inputs, 1):
            raise ValueError(f"ESN input has shape {u.shape}, expected ({self.n_inputs}, 1)")
        return x, u

    def xdot(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """Reservoir dynamics (1/time_constant)(-leak x + tanh(W_in u + W x + b)), eq. 8 with W_back = 0, as SX."""
        x, u = self._check_sx(x, u)
        c = self.config
        z = ca.mtimes(self._W_in_dm, u) + ca.mtimes(self._W_dm, x) + self._b_dm
        return (1.0 / c.time_constant) * (-c.leak * x + ca.tanh(z))

    def regressor(self, x: ca.SX) -> ca.SX:
        """The regressor Phi(X) = [X; 1] (or X without bias) that the adaptive weights multiply, as SX."""
        x, _ = self._check_sx(x)
        return ca.vertcat(x, 1) if self.config.bias else x

    def _functions(self) -> ca.Function:
        """(x, u) -> (xdot, Phi) from the SX, built once."""
        if "_f" not in self.__dict__:
            x, u = ca.SX.sym("x", self.size), ca.SX.sym("u", self.n_inputs)
            self.__dict__["_f"] = ca.Function("esn", [x, u], [self.xdot(x, u), self.regressor(x)])
        return self.__dict__["_f"]

    def _evaluate(self, k: int, x, u) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = np.zeros((self.n_inputs,) + x.shape[1:]) if u is None else np.asarray(u, dtype=float)
        m = 1 if x.ndim == 1 else x.shape[1]
        X, U = x.reshape(self.size, m), np.broadcast_to(u.reshape(self.n_inputs, -1), (self.n_inputs, m))
        out = np.asarray(self._functions().map(m)(X, U)[k])
        return out.ravel() if x.ndim == 1 else out

    def xdot_numpy(self, x, u) -> np.ndarray:
        """`xdot` evaluated (from its SX) for x of shape (N,) or (N, m) and u of shape (K,) or (K, m)."""
        return self._evaluate(0, x, u)

    def regressor_numpy(self, x) -> np.ndarray:
        """`regressor` evaluated (from its SX) for x of shape (N,) or (N, m)."""
        return self._evaluate(1, x, None)

    def xdot_c(self, name: str, tanh: str = "tanh", ma: str | None = None) -> str:
        """C twin of `xdot`: `static void name(const double *x, const double *u, double *xdot)` as loops over the
        weights in static const arrays (sizes fixed here), which a compiler vectorises; `tanh` names the tanh used,
        `ma` (a macro name) the multiply-add of W_in u (None: unfused, s += w u).

        The sums run in the SX graph's order (W_in u and W x each over their columns ascending, then
        (W_in u + W x) + b), so with libm's tanh the result is the graph's value bit for bit (up to the sign of
        a zero sum). Up to UNROLL_W_MAX nonzeros W x is emitted as straight-line code with the weights as constants
        (the same products and sums in the same order: the same doubles; the paper's step 342 -> 266 ns), above
        it as loops over the arrays (the compile time of large reservoirs)."""
        c = self.config
        N, K = self.size, self.n_inputs
        W = np.asarray(self.W)
        Win = np.asarray(self.W_in)
        rp, cj, vals = [0], [], []
        for i in range(N):                       # W by rows (CSR): row i's nonzero columns, ascending
            nz = np.nonzero(W[i, :])[0]
            cj.extend(int(j) for j in nz)
            vals.extend(float(W[i, j]) for j in nz)
            rp.append(len(cj))
        ip, jp, ivals = [0], [], []
        for j in range(K):                       # W_in likewise (the graph multiplies its nonzeros only)
            nz = np.nonzero(Win[:, j])[0]
            jp.extend(int(i) for i in nz)
            ivals.extend(float(Win[i, j]) for i in nz)
            ip.append(len(jp))

        def num(a) -> str:
            return ", ".join(repr(float(v)) for v in a) or "0.0"

        def ints(a) -> str:
            return ", ".join(str(int(v)) for v in a) or "0"
        dense_in = len(jp) == N * K
        unroll = len(cj) <= self.UNROLL_W_MAX
        lines = [f"/* {name}: the reservoir's x_esn_dot = (1/time_constant)(-leak x + tanh(W_in u + W x + b)), "
                 f"N = {N}, K = {K} (family/esn.py) */"]
        if dense_in:
            lines.append(f"static const double {name}_Win[{K * N}] = {{{num(Win.T.ravel())}}};  "
                         "/* W_in by columns */")
        else:
            lines += [f"static const int {name}_Winp[{K + 1}] = {{{ints(ip)}}};",
                      f"static const int {name}_Wini[{max(len(jp), 1)}] = {{{ints(jp)}}};",
                      f"static const double {name}_Winx[{max(len(jp), 1)}] = {{{num(ivals)}}};"]
        lines.append(f"static const double {name}_b[{N}] = {{{num(self.b)}}};")
        if not unroll:
            lines += [f"static const int {name}_Wp[{N + 1}] = {{{ints(rp)}}};",
                      f"static const int {name}_Wj[{max(len(cj), 1)}] = {{{ints(cj)}}};",
                      f"static const double {name}_Wx[{max(len(cj), 1)}] = {{{num(vals)}}};"]
        blocks = self.VECTOR_WX and unroll and len(_wx_block_map(N, rp, cj, vals)) <= WX_BLOCKS_MAX
        if blocks:
            lines += _wx_preamble(name)
        lines += [f"static void {name}(const double *restrict x, const double *restrict u, double *restrict xdot) {{",
                  f"  double zu[{N}];",
                  "  int i, j;" if unroll and dense_in else "  int i, j, p;"]
        if dense_in:                             # row by row, the sum in a register over the columns ascending
            acc = f"s = {ma}({name}_Win[j * {N} + i], u[j], s);" if ma else f"s += {name}_Win[j * {N} + i] * u[j];"
            lines += [f"  for (i = 0; i < {N}; ++i) {{",
                      "    double s = 0.0;",
                      f"    for (j = 0; j < {K}; ++j) {acc}",
                      "    zu[i] = s;",
                      "  }"]
        else:
            lines += [f"  for (i = 0; i < {N}; ++i) zu[i] = 0.0;",
                      f"  for (j = 0; j < {K}; ++j)",
                      f"    for (p = {name}_Winp[j]; p < {name}_Winp[j + 1]; ++p) "
                      f"zu[{name}_Wini[p]] += {name}_Winx[p] * u[j];"]
        if unroll:                               # row by row, the weights as constants: no index loads, no branches
            if blocks:
                lines += [f"#ifdef {name}_FMA4"] + _wx_blocks(name, N, rp, cj, vals) + ["#else"]
            lines.append("  /* W x row by row, the weights as constants */")
            for i in range(N):
                lines.append("  {")
                lines.append("    double s = 0.0;")
                lines += [f"    s += {vals[q]!r} * x[{cj[q]}];" for q in range(rp[i], rp[i + 1])]
                lines.append(f"    zu[{i}] = (zu[{i}] + s) + {name}_b[{i}];")
                lines.append("  }")
            if blocks:
                lines.append("#endif")
        else:
            lines += [f"  for (i = 0; i < {N}; ++i) {{               /* W x row by row (a gather, no scatter) */",
                      "    double s = 0.0;",
                      f"    for (p = {name}_Wp[i]; p < {name}_Wp[i + 1]; ++p) s += {name}_Wx[p] * x[{name}_Wj[p]];",
                      f"    zu[i] = (zu[i] + s) + {name}_b[i];",
                      "  }"]
        lines += [f"  for (i = 0; i < {N}; ++i) zu[i] = {tanh}(zu[i]);",
                  f"  for (i = 0; i < {N}; ++i) xdot[i] = {1.0 / c.time_constant!r} * ({-c.leak!r} * x[i] + zu[i]);",
                  "}"]
        return "\n".join(lines) + "\n"

    def fingerprint(self) -> str:
        """sha256 of the weights' shapes and little-endian float64 bytes (W_in, W, b), to show determinism in reports."""
        h = hashlib.sha256()
        for name, arr in (("W_in", self.W_in), ("W", self.W), ("b", self.b)):
            h.update(f"{name}{arr.shape};".encode())
            h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
        return h.hexdigest()

    def summary(self) -> dict:
        """Numbers a report shows about the reservoir."""
        return {"size": self.size, "n_inputs": self.n_inputs, "n_regressor": self.n_regressor,
                "spectral_radius": self.spectral_radius, "norm2": self.norm2, "leak": self.config.leak,
                "contracting": self.contracting, "sparsity": self.sparsity_actual, "scale": self.scale,
                "seed": self.config.seed, "fingerprint": self.fingerprint()}


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, order="C")
    a.flags.writeable = False
    return a
