"""Scrambled Sobol points in numpy, the same as scipy's `qmc.Sobol(d, scramble=True, seed=...)`, without
importing `scipy.stats` (about 0.4-0.6 CPU-s per process, paid by every command that samples).

The direction numbers are scipy's own (Joe and Kuo, read from the .npz scipy ships beside its Sobol engine); the
scrambling (a random linear matrix scramble and a digital shift) consumes the generator exactly as scipy does, so
the points and the generator's state afterwards are the ones scipy gives (tests/test_sobol.py compares them).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

BITS = 30                                    # scipy's default; uint32 arithmetic


@functools.lru_cache(maxsize=1)
def _table() -> tuple[np.ndarray, np.ndarray]:
    """(poly, vinit) of Joe and Kuo's direction numbers, from scipy's data file (numpy only, no scipy.stats)."""
    import importlib.util
    spec = importlib.util.find_spec("scipy")
    root = Path(spec.origin).parent if spec and spec.origin else None
    if root is None or not (root / "stats" / "_sobol_direction_numbers.npz").is_file():
        raise ImportError("scipy's Sobol direction numbers (scipy/stats/_sobol_direction_numbers.npz) not found")
    with np.load(root / "stats" / "_sobol_direction_numbers.npz") as z:
        return z["poly"].astype(np.int64), z["vinit"].astype(np.int64)


@functools.lru_cache(maxsize=32)
def _direction(d: int) -> np.ndarray:
    """Unscrambled direction numbers v (d, BITS) as uint32, column j scaled by 2^(BITS-1-j)."""
    poly, vinit = _table()
    if d > poly.size:
        raise ValueError(f"Sobol dimension {d} > {poly.size}")
    v = np.zeros((d, BITS), dtype=np.int64)
    v[:1, :] = 1                                 # the first dimension (none when d = 0)
    for i in range(1, d):
        p = int(poly[i])
        m = p.bit_length() - 1
        v[i, :m] = vinit[i, :m]
        for j in range(m, BITS):
            newv = int(v[i, j - m])
            pow2 = 1
            for k in range(m):
                pow2 <<= 1
                if (p >> (m - 1 - k)) & 1:
                    newv ^= pow2 * int(v[i, j - k - 1])
            v[i, j] = newv
    v = v * (2 ** np.arange(BITS - 1, -1, -1, dtype=np.int64))[None, :]
    out = v.astype(np.uint32)
    out.setflags(write=False)
    return out


def _rng(seed):
    """scipy's handling of `seed`: a Generator spawns a child (its seed sequence counts the spawn, its state is
    untouched), a RandomState is used as is, None or an int seeds default_rng."""
    if isinstance(seed, np.random.Generator):
        bg = seed.bit_generator
        return np.random.Generator(type(bg)(bg.seed_seq.spawn(1)[0]))
    if isinstance(seed, np.random.RandomState):
        return seed
    return np.random.default_rng(seed)


def _bits01(rng, size) -> np.ndarray:
    """scipy's rng_integers(rng, 2, size, dtype=uint32): the same draws from either kind of generator."""
    if isinstance(rng, np.random.Generator):
        return rng.integers(0, 2, size=size, dtype=np.uint32)
    return rng.randint(0, 2, size=size, dtype=np.uint32)


def _scrambled(d: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(scrambled direction numbers (d, BITS), shift (d,)) as uint64 holding 30-bit values."""
    pw = 2 ** np.arange(BITS, dtype=np.uint64)
    shift = (_bits01(rng, (d, BITS)).astype(np.uint64) * pw).sum(axis=1)
    ltm = np.tril(_bits01(rng, (d, BITS, BITS))).astype(np.uint64)
    ltm[:, np.arange(BITS), np.arange(BITS)] = 1                        # unit diagonal: the scramble is invertible
    # lsm[d, p]: row p of the lower-triangular matrix read as a binary number, its first entry the top bit
    lsm = (ltm * pw[::-1]).sum(axis=2)                                   # (d, BITS)
    sv = _direction(d).astype(np.uint64)                                 # (d, BITS)
    both = lsm[:, :, None] & sv[:, None, :]                              # (d, p, j)
    parity = np.zeros(both.shape, dtype=np.uint64)
    for k in range(BITS):
        parity ^= (both >> np.uint64(k)) & np.uint64(1)
    # bit (BITS - 1 - p) of the new sv[d, j] is the parity of lsm[d, p] & sv[d, j]
    new = (parity * pw[::-1][None, :, None]).sum(axis=1)                 # (d, j)
    return new, shift


def sobol(d: int, n: int, seed=None, *, skip: int = 0) -> np.ndarray:
    """Points skip .. skip+n-1 (rows, in [0, 1)^d) of the scrambled Sobol sequence scipy draws for (d, seed):
    `qmc.Sobol(d, scramble=True, seed=seed)`, fast-forwarded by `skip`, then `.random(n)`."""
    try:
        _table()
    except ImportError:                          # a scipy without the data file there: its own engine, same points
        import warnings

        from scipy.stats import qmc
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")      # balance of non-power-of-2 sizes: the callers' concern, not ours
            eng = qmc.Sobol(d, scramble=True, seed=seed)
            if skip:
                eng.fast_forward(skip)
            return eng.random(n)
    rng = _rng(seed)
    sv, shift = _scrambled(d, rng)
    idx = np.arange(skip, skip + n, dtype=np.uint64)
    gray = idx ^ (idx >> np.uint64(1))
    quasi = np.broadcast_to(shift, (n, d)).copy()
    for k in range(BITS):
        on = ((gray >> np.uint64(k)) & np.uint64(1)).astype(bool)
        if on.any():
            quasi[on] ^= sv[:, k]
    return quasi.astype(np.float64) * (1.0 / 2 ** BITS)
