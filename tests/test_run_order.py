"""run._in_time_order: the chunk's start and its samples in time order, written in one pass, are the stacked arrays
indexed by the argsort of their times (the definition the run loop used before), bit for bit."""

import numpy as np

from symfunnel.simulation.run import _in_time_order


def test_in_time_order_is_the_stacked_samples_indexed_by_their_order():
    rng = np.random.default_rng(5)
    for K, B in ((1, 0), (1, 3), (25, 24 * 7), (500, 2000)):
        x, X, Xb = rng.normal(size=9), rng.normal(size=(K, 9)), rng.normal(size=(B, 9))
        t = np.concatenate([np.arange(1, K + 1, dtype=float), rng.uniform(0, K, B)])
        order = np.argsort(t, kind="stable")
        want = np.concatenate([x[None, :], np.concatenate([X, Xb])[order]])
        got = _in_time_order(x, X, Xb, order)
        assert got.flags.c_contiguous and np.array_equal(got, want)
        assert np.array_equal(got[1:][order < K], X)        # output times ascending: X's rows keep their order
