"""The compiled-code cache of the generated tapes (core/pycode.py): the code it gives back runs as freshly compiled
code does, a damaged entry is rebuilt, and the interval search gives the same enclosure from a warm cache."""

from __future__ import annotations

import numpy as np

from symfunnel.core import pycode


def _source(k: int) -> str:
    body = "\n".join(f"    x = x * 0.5 + {j}" for j in range(k))
    return f"def run(x):\n{body}\n    return x\n"


def _run(code, x):
    ns: dict = {}
    exec(code, ns)
    return ns["run"](x)


def test_a_cached_code_object_computes_what_compile_gives(tmp_path, monkeypatch):
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(pycode, "_MEMORY", {})
    src = _source(2000)                                      # large enough to be kept on disk
    fresh = _run(compile(src, "<t>", "exec"), 0.25)
    first = pycode.compile_source(src, "<t>")
    files = list((tmp_path / "pycode").glob("*.marshal"))
    assert len(files) == 1 and _run(first, 0.25) == fresh
    pycode._MEMORY.clear()
    second = pycode.compile_source(src, "<t>")               # read back from disk
    assert second is not first and _run(second, 0.25) == fresh
    # another source (one constant changed) is another entry, with its own value
    other = src.replace("+ 1999", "+ 1998")
    assert _run(pycode.compile_source(other, "<t>"), 0.25) == fresh - 1.0 != fresh
    assert len(list((tmp_path / "pycode").glob("*.marshal"))) == 2
    assert not list((tmp_path / "pycode").glob(".pycode.*"))


def test_a_damaged_entry_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(pycode, "_MEMORY", {})
    src = _source(2000)
    pycode.compile_source(src, "<t>")
    (entry,) = (tmp_path / "pycode").glob("*.marshal")
    entry.write_bytes(b"\x00 not marshal data")
    pycode._MEMORY.clear()
    assert _run(pycode.compile_source(src, "<t>"), 0.5) == _run(compile(src, "<t>", "exec"), 0.5)
    assert entry.read_bytes() != b"\x00 not marshal data"


def test_the_interval_search_is_the_same_from_a_warm_cache(tmp_path, monkeypatch):
    import casadi as ca

    from symfunnel.sx.batch import BatchIntervalFunction
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path))
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "numpy")        # the backend whose tapes are Python code
    monkeypatch.setattr(pycode, "_MEMORY", {})
    x = ca.SX.sym("x", 3)
    y = x[0]
    for k in range(400):                                     # a long tape: stored on disk
        y = ca.sin(y * (1 + k / 997)) + x[1 + k % 2] / (2 + x[0] ** 2)
    f = ca.Function("long_tape", [x], [y])
    lo, hi = np.array([[-1.0, 0.0, 0.5]]), np.array([[-0.5, 0.25, 1.0]])
    cold = BatchIntervalFunction(f).eval_batch(lo, hi)
    assert list((tmp_path / "pycode").glob("*.marshal"))
    pycode._MEMORY.clear()
    warm = BatchIntervalFunction(f).eval_batch(lo, hi)
    for a, b in zip(cold, warm):
        np.testing.assert_array_equal(a, b)
    # and the enclosure holds the double values inside the box
    pts = lo + (hi - lo) * np.random.default_rng(0).random((200, 3))
    vals = np.array([float(f(p)) for p in pts])
    assert np.all(cold[0][0, 0] <= vals) and np.all(vals <= cold[1][0, 0])
