"""Echo state network: deterministic weights, enforced spectral radius, SX/numpy agreement, bounded reservoir."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symfunnel.family.esn import ESN, ConfigError, ESNConfig

ROOT = Path(__file__).resolve().parents[1]


def _bytes(esn: ESN) -> tuple[bytes, bytes, bytes]:
    return esn.W_in.tobytes(), esn.W.tobytes(), esn.b.tobytes()


def test_same_seed_same_bytes():
    a = ESN(ESNConfig(seed=7), n_inputs=6)
    b = ESN(ESNConfig(seed=7), n_inputs=6)
    assert _bytes(a) == _bytes(b)
    assert a.fingerprint() == b.fingerprint()
    assert len(a.fingerprint()) == 64


def test_same_seed_same_bytes_in_subprocess():
    code = ("import json; from symfunnel.family.esn import ESN, ESNConfig; e = ESN(ESNConfig(seed=7), n_inputs=6); "
            "print(json.dumps([e.fingerprint(), e.W.tobytes().hex(), e.W_in.tobytes().hex(), e.b.tobytes().hex()]))")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                         check=True).stdout
    fp, w, w_in, b = json.loads(out)
    here = ESN(ESNConfig(seed=7), n_inputs=6)
    assert fp == here.fingerprint()
    assert (w, w_in, b) == (here.W.tobytes().hex(), here.W_in.tobytes().hex(), here.b.tobytes().hex())


def test_different_seeds_differ():
    a = ESN(ESNConfig(seed=0), n_inputs=4)
    b = ESN(ESNConfig(seed=1), n_inputs=4)
    assert a.fingerprint() != b.fingerprint()
    assert not np.array_equal(a.W, b.W) and not np.array_equal(a.W_in, b.W_in) and not np.array_equal(a.b, b.b)


def test_weights_are_read_only():
    e = ESN(ESNConfig(size=5), n_inputs=2)
    with pytest.raises(ValueError):
        e.W[0, 0] = 1.0


@pytest.mark.parametrize("size,rho,sparsity,seed", [(50, 0.9, 0.9, 0), (10, 0.5, 0.0, 3), (1, 0.99, 0.5, 2),
                                                     (200, 0.95, 0.95, 11), (3, 0.1, 0.9, 5)])
def test_spectral_radius_and_sparsity(size, rho, sparsity, seed):
    e = ESN(ESNConfig(size=size, spectral_radius=rho, sparsity=sparsity, seed=seed), n_inputs=3)
    measured = np.max(np.abs(np.linalg.eigvals(e.W)))
    assert abs(measured - rho) <= 1e-12
    assert measured < 1
    assert abs(e.spectral_radius - rho) <= 1e-12
    assert e.scale == float(f"{e.scale:.12e}")          # the scale factor is rounded to 13 significant digits
    assert np.all(np.any(e.W != 0, axis=1))             # at least one nonzero per row
    if size >= 50:
        assert abs(e.sparsity_actual - sparsity) < 0.02
    assert e.norm2 >= e.spectral_radius - 1e-12         # ||W||_2 >= rho(W) always
    assert e.contracting == (e.norm2 < e.config.leak)


def test_shapes_and_regressor_length():
    e = ESN(ESNConfig(size=8), n_inputs=3)
    assert e.W_in.shape == (8, 3) and e.W.shape == (8, 8) and e.b.shape == (8,)
    assert e.n_regressor == 9
    assert ESN(ESNConfig(size=8, bias=False), n_inputs=3).n_regressor == 8
    assert np.all(np.abs(e.W_in) <= 0.5) and np.all(np.abs(e.b) <= 0.5)


@pytest.mark.parametrize("kwargs,key", [
    ({"spectral_radius": 1.0}, "spectral_radius"), ({"spectral_radius": 1.5}, "spectral_radius"),
    ({"spectral_radius": 0.0}, "spectral_radius"), ({"spectral_radius": -0.5}, "spectral_radius"),
    ({"sparsity": 1.0}, "sparsity"), ({"sparsity": -0.1}, "sparsity"),
    ({"size": 0}, "size"), ({"size": 2.5}, "size"), ({"size": True}, "size"),
    ({"time_constant": 0.0}, "time_constant"), ({"time_constant": -1.0}, "time_constant"),
    ({"leak": 0.0}, "leak"), ({"leak": -1.0}, "leak"), ({"leak": float("nan")}, "leak"),
    ({"input_scaling": -1.0}, "input_scaling"), ({"seed": -1}, "seed"), ({"bias": 1}, "bias"),
])
def test_bad_config_raises_value_error(kwargs, key):
    with pytest.raises(ValueError) as info:
        ESNConfig(**kwargs)
    assert isinstance(info.value, ConfigError) and info.value.key == key


def test_bad_n_inputs():
    with pytest.raises(ValueError):
        ESN(ESNConfig(size=4), n_inputs=0)


def test_sx_matches_numpy():
    cfg = ESNConfig(size=20, leak=1.3, time_constant=0.1, seed=4)
    e = ESN(cfg, n_inputs=5)
    x, u = ca.SX.sym("x", 20), ca.SX.sym("u", 5)
    f = ca.Function("f", [x, u], [e.xdot(x, u), e.regressor(x)])
    rng = np.random.default_rng(123)
    for _ in range(20):
        xv, uv = rng.uniform(-2, 2, 20), rng.uniform(-3, 3, 5)
        xd, phi = f(xv, uv)
        formula = (1 / 0.1) * (-1.3 * xv + np.tanh(e.W_in @ uv + e.W @ xv + e.b))          # eq. 8, by hand
        np.testing.assert_allclose(np.asarray(xd).ravel(), formula, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(np.asarray(phi).ravel(), np.append(xv, 1.0), rtol=0, atol=0)
    expected = (1 / 0.1) * (-1.3 * xv + np.tanh(e.W_in @ uv + e.W @ xv + e.b))
    np.testing.assert_allclose(e.xdot_numpy(xv, uv), expected, rtol=1e-14)
    # the array form (the SX evaluated) batched agrees with column-by-column evaluation
    X, U = rng.uniform(-1, 1, (20, 4)), rng.uniform(-1, 1, (5, 4))
    batch = e.xdot_numpy(X, U)
    for k in range(4):
        np.testing.assert_allclose(batch[:, k], e.xdot_numpy(X[:, k], U[:, k]), rtol=1e-14)
    assert e.regressor_numpy(X).shape == (21, 4)


def test_regressor_without_bias():
    e = ESN(ESNConfig(size=6, bias=False), n_inputs=2)
    x = ca.SX.sym("x", 6)
    assert e.regressor(x).shape == (6, 1)
    np.testing.assert_array_equal(e.regressor_numpy(np.arange(6.0)), np.arange(6.0))


def test_xdot_shape_errors():
    e = ESN(ESNConfig(size=6), n_inputs=2)
    with pytest.raises(ValueError):
        e.xdot(ca.SX.sym("x", 5), ca.SX.sym("u", 2))
    with pytest.raises(ValueError):
        e.xdot(ca.SX.sym("x", 6), ca.SX.sym("u", 3))


def test_nilpotent_draw_is_redrawn(monkeypatch):
    """A reservoir drawn with spectral radius 0 is replaced by the next draw, deterministically."""
    real = np.linalg.eigvals
    calls = {"n": 0}

    def fake(a):
        calls["n"] += 1
        return np.zeros(a.shape[0]) if calls["n"] == 1 else real(a)

    monkeypatch.setattr(np.linalg, "eigvals", fake)
    e1 = ESN(ESNConfig(size=6, seed=9), n_inputs=2)
    calls["n"] = 0
    e2 = ESN(ESNConfig(size=6, seed=9), n_inputs=2)
    monkeypatch.setattr(np.linalg, "eigvals", real)
    plain = ESN(ESNConfig(size=6, seed=9), n_inputs=2)
    assert e1.fingerprint() == e2.fingerprint() != plain.fingerprint()
    assert abs(np.max(np.abs(real(e1.W))) - 0.9) <= 1e-12


@pytest.mark.parametrize("leak", [1.0, 2.5])
def test_reservoir_stays_bounded_cvodes(leak):
    """|tanh| <= 1 makes d|x_i|/dt <= C(1 - a|x_i|), so from x(0) = 0 the state stays in [-1/a, 1/a]."""
    cfg = ESNConfig(size=30, leak=leak, time_constant=0.05, seed=2, input_scaling=2.0)
    e = ESN(cfg, n_inputs=3)
    x, u = ca.SX.sym("x", 30), ca.SX.sym("u", 3)
    dt = 0.05
    F = ca.integrator("F", "cvodes", {"x": x, "p": u, "ode": e.xdot(x, u)}, 0.0, dt,
                      {"abstol": 1e-10, "reltol": 1e-10})
    xk = np.zeros(30)
    worst = 0.0
    for k in range(60):                      # 3 s of a bounded, large, switching input
        t = k * dt
        uk = 5.0 * np.array([np.sin(3 * t), np.sign(np.sin(7 * t)), np.cos(t)])
        xk = np.asarray(F(x0=xk, p=uk)["xf"]).ravel()
        worst = max(worst, np.max(np.abs(xk)))
    assert worst <= 1 / leak + 1e-8
    assert worst > 0.5 / leak                 # the bound is not vacuous: the input drives the reservoir near it


def test_reservoir_attracted_from_outside_solve_ivp():
    from scipy.integrate import solve_ivp

    cfg = ESNConfig(size=20, leak=1.0, time_constant=0.05, seed=5)
    e = ESN(cfg, n_inputs=2)
    x0 = np.full(20, 4.0)
    T = 1.0
    sol = solve_ivp(lambda t, xv: e.xdot_numpy(xv, [np.sin(5 * t), 2.0]), (0.0, T), x0, rtol=1e-9, atol=1e-11,
                    dense_output=True)
    ts = np.linspace(0.0, T, 200)
    xs = np.abs(sol.sol(ts))
    rate = cfg.leak / cfg.time_constant
    envelope = 1 / cfg.leak + (4.0 - 1 / cfg.leak) * np.exp(-rate * ts)
    assert np.all(xs <= envelope[None, :] + 1e-7)
    assert np.max(xs[:, -1]) <= 1 / cfg.leak + 1e-7
