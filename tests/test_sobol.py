"""core.sobol against scipy's own engine: the same points, bit for bit, and the caller's generator left as scipy
leaves it (the funnel samples drawn after the Sobol points depend on it)."""

import warnings

import numpy as np
import pytest

from symfunnel.core.sobol import sobol

qmc = pytest.importorskip("scipy.stats.qmc")


def _scipy(d, n, seed, skip=0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        eng = qmc.Sobol(d, scramble=True, seed=seed)
        if skip:
            eng.fast_forward(skip)
        return eng.random(n)


@pytest.mark.parametrize("d", [0, 1, 2, 5, 23])
@pytest.mark.parametrize("seed", [0, 7, 2024])
def test_int_seed_points_and_fast_forward(d, seed):
    for n, skip in ((1, 0), (16, 0), (13, 0), (9, 5), (40, 100)):
        assert np.array_equal(sobol(d, n, seed, skip=skip), _scipy(d, n, seed, skip))


@pytest.mark.parametrize("d", [1, 3, 12])
def test_generator_seed_same_points_and_same_state_after(d):
    g_ref, g = np.random.default_rng(11), np.random.default_rng(11)
    a = _scipy(d, 32, g_ref)
    b = sobol(d, 32, g)
    assert np.array_equal(a, b)
    # a second engine from the same generator: scipy's spawn counter moved on, ours too
    assert np.array_equal(_scipy(d, 8, g_ref), sobol(d, 8, g))
    assert g_ref.random() == g.random()


def test_randomstate_seed_consumed_as_scipy_does():
    r_ref, r = np.random.RandomState(3), np.random.RandomState(3)
    assert np.array_equal(_scipy(4, 8, r_ref), sobol(4, 8, r))
    assert r_ref.random_sample() == r.random_sample()


def test_points_are_a_low_discrepancy_net():
    """Independent of scipy: 2^m scrambled Sobol points put exactly one point in each of 2^m equal intervals of
    every coordinate (a (0, m, 1)-net per axis)."""
    pts = sobol(6, 64, 5)
    for j in range(6):
        counts = np.bincount(np.floor(pts[:, j] * 64).astype(int), minlength=64)
        assert (counts == 1).all()


def test_sampling_paths_do_not_import_scipy_stats():
    """The funnel samples, the RBF centres and the campaign's Sobol draws give scipy's points without importing
    scipy.stats (0.4-0.6 CPU-s per process); on the previous code each of them imported it."""
    import subprocess
    import sys
    code = (
        "import sys, numpy as np\n"
        "from symfunnel.design.sampling import unit_samples\n"
        "from symfunnel.family.approximators import RBFSpec, rbf_centres\n"
        "from symfunnel.scenario.uncertainty import _sobol\n"
        "u = unit_samples(100, 3, np.random.default_rng(0), method='sobol')\n"
        "c, _ = rbf_centres(RBFSpec(size=12, seed=4), 2)\n"
        "s = _sobol(3, 9, np.array([0, 1, 2, 7]))\n"
        "assert u.shape == (100, 3) and c.shape == (12, 2) and s.shape == (4, 3)\n"
        "print('scipy.stats' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_callers_give_scipys_points():
    """The three callers, each against scipy's engine used the way the previous code used it."""
    from symfunnel.design.sampling import unit_samples
    from symfunnel.family.approximators import RBFSpec, rbf_centres
    from symfunnel.scenario.uncertainty import _sobol
    g_ref, g = np.random.default_rng(8), np.random.default_rng(8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = qmc.Sobol(d=4, scramble=True, seed=g_ref).random_base2(7)[:100]
    assert np.array_equal(unit_samples(100, 4, g, method="sobol"), want) and g.random() == g_ref.random()
    assert np.array_equal(rbf_centres(RBFSpec(size=12, seed=4), 2)[0], _scipy(2, 12, 4))
    ids = np.array([5, 0, 1, 2, 9, 10])
    full = _scipy(3, 11, 9)
    assert np.array_equal(_sobol(3, 9, ids), full[ids])


def test_without_the_data_file_scipys_engine_gives_the_points(monkeypatch):
    from symfunnel.core import sobol as S

    def missing():
        raise ImportError("no file")
    monkeypatch.setattr(S, "_table", missing)
    g_ref, g = np.random.default_rng(2), np.random.default_rng(2)
    assert np.array_equal(S.sobol(3, 10, g, skip=4), _scipy(3, 10, g_ref, 4)) and g.random() == g_ref.random()
