"""`certify.containment`'s branch and bound keeps its open boxes in the split coordinates only: its memory grows
with the number of boxes times the split coordinates, not times every input of the face function (at 10x the
default budget on paper_small_dead_zone the queue held ~1 GB). Memory is counted by tracemalloc (deterministic),
on a face problem built here: sin(x)^2 + cos(x)^2 + sin(y)^2 + cos(y)^2 - 2 - 1e-12 < 0 (only boxes ~1e-6 wide prove
it: dependency), with 400 inputs the objective does not use."""

from __future__ import annotations

import tracemalloc

import casadi as ca
import numpy as np

from symfunnel.certificates.containment import _decide
from symfunnel.sx.batch import BatchCenteredForm


def _problem():
    x, y, u = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("u", 400)
    f = ca.Function("face", [x, y, u], [ca.sin(x) ** 2 + ca.cos(x) ** 2 + ca.sin(y) ** 2 + ca.cos(y) ** 2 - 2 - 1e-12
                                         + 0 * ca.sum1(u)], ["x", "y", "u"], ["n"])
    F = BatchCenteredForm(f, ["x", "y"])
    lo = np.concatenate([[-1.0, -1.0], np.zeros(400)])
    hi = np.concatenate([[1.0, 1.0], np.ones(400)])
    face = {"name": "test +", "lo": lo, "hi": hi, "pos": 0, "sign": 1.0, "i": 2, "j": 0}
    return F, face, np.array([0, 1])


def test_open_boxes_are_stored_in_the_split_coordinates_only():
    F, face, split = _problem()
    _decide(F, [face], [split], 2048, None)             # warm-up: the evaluator's maps and buffers
    tracemalloc.start()
    try:
        res = _decide(F, [face], [split], 8192, None)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert res["status"] == "undecided" and res["fraction"] == 1.0, res
    # ~4,600 open boxes: with the 402 inputs each (two arrays of 3.2 kB) that is > 25 MB; in the two split
    # coordinates a few hundred bytes each, plus one batch of full boxes (1024 x 402 x 8 B = 3.3 MB per array)
    assert peak < 40e6, peak                        # measured: 19.9 MB (72.3 MB with full boxes)


def test_the_search_proves_the_face_and_finds_an_outward_point():
    """The same search on the small problem: proven where the objective is negative with room (x^2 + y^2 + 0.1),
    failed at a point where it is not (-(x^2) + 0.01 > 0 near x = 0), that point re-checked here."""
    F, face, split = _problem()
    x, y, u = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("u", 400)
    g = BatchCenteredForm(ca.Function("g", [x, y, u], [-(x ** 2 + y ** 2) - 0.1], ["x", "y", "u"], ["n"]), ["x", "y"])
    assert _decide(g, [face], [split], 4096, None)["status"] == "proven"
    h = BatchCenteredForm(ca.Function("h", [x, y, u], [0.01 - x ** 2 - 0 * y], ["x", "y", "u"], ["n"]), ["x", "y"])
    res = _decide(h, [face], [split], 4096, None)
    assert res["status"] == "failed" and 0.01 - res["x"][0] ** 2 >= 0
