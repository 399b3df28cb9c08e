"""The certificates' branch and bound with its per-box Python loops done as numpy passes (issue 43, `certify`
faster with byte-identical results): each vectorised piece is compared bit for bit with the per-box code it replaced,
kept here as the reference, on batches drawn independently of the code under test (random boxes, a few too thin to
halve, Jacobian entries with nan and inf)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import symfunnel.certificates.containment as containment
from symfunnel.certificates.face_bisect import bisect_open
from symfunnel.sx import batch_rules
from symfunnel.sx.batch import BatchCenteredForm
from symfunnel.sx.search import _sensitivities


def _bisect_reference(batch, open_rows, J, pos, split_of, faces, w_flat):
    """containment._decide's loop before the change, box by box (its early return as `thin`)."""
    wpos = {int(j): i for i, j in enumerate(w_flat)}
    children = []
    for k in open_rows:
        lo, hi, fk, vol = batch[k]
        split = split_of[fk]
        width = hi - lo
        wi = [wpos.get(int(j), -1) for j in split]
        with np.errstate(invalid="ignore"):              # inf * 0 scores 0 below, as in the code under test
            sens = np.array([J[k][pos[k], w] * wd if w >= 0 else np.nan for w, wd in zip(wi, width)])
        rel = width / np.where(faces[fk]["hi"][split] > faces[fk]["lo"][split],
                               faces[fk]["hi"][split] - faces[fk]["lo"][split], 1.0)
        score = np.where(np.isfinite(sens) & (sens > 0), sens, 0.0)
        s = int(np.argmax(score)) if np.any(score > 0) else int(np.argmax(rel))
        m = 0.5 * lo[s] + 0.5 * hi[s]
        if not (lo[s] < m < hi[s]):
            return children, int(k)
        h1, l2 = hi.copy(), lo.copy()
        h1[s] = m
        l2[s] = m
        children.append((lo, h1, fk, vol / 2))
        children.append((l2, hi, fk, vol / 2))
    return children, None


def _random_batch(rng, thin_row=None):
    """Three faces over 9 inputs with different split coordinates (face 2's include inputs without a derivative),
    40 boxes inside them; J with zeros, nan and inf entries."""
    n_in, n_out = 9, 3
    w_flat = np.array([0, 1, 2, 5])
    split_of = [np.array([0, 1, 2]), np.array([1, 3, 5, 6]), np.array([2, 4, 7, 8])]
    faces = []
    for f in range(3):
        lo = rng.uniform(-2, 0, n_in)
        hi = lo + rng.uniform(0.5, 2, n_in)
        hi[4] = lo[4]                                   # a degenerate face coordinate (scale 1)
        faces.append({"lo": lo, "hi": hi, "pos": f, "name": f"f{f}"})
    batch = []
    for _ in range(40):
        f = int(rng.integers(3))
        sl, sh = faces[f]["lo"][split_of[f]], faces[f]["hi"][split_of[f]]
        a, b = rng.uniform(sl, sh), rng.uniform(sl, sh)
        batch.append((np.minimum(a, b), np.maximum(a, b), f, float(rng.choice([1.0, 0.5, 0.125]))))
    if thin_row is not None:
        lo, hi, f, vol = batch[thin_row]
        batch[thin_row] = (lo.copy(), lo.copy(), f, vol)   # no coordinate can be halved
    J = np.abs(rng.normal(size=(40, n_out, w_flat.size)))
    J[rng.random(J.shape) < 0.2] = 0.0
    J[rng.random(J.shape) < 0.05] = np.nan
    J[rng.random(J.shape) < 0.05] = np.inf
    pos = np.array([faces[b[2]]["pos"] for b in batch])
    return batch, J, pos, split_of, faces, w_flat


def _same_children(a, b):
    assert len(a) == len(b)
    for (l1, h1, f1, v1), (l2, h2, f2, v2) in zip(a, b):
        assert f1 == f2 and v1 == v2
        assert l1.tobytes() == l2.tobytes() and h1.tobytes() == h2.tobytes()


@pytest.mark.parametrize("seed", range(6))
def test_bisect_open_matches_the_per_box_loop_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    batch, J, pos, split_of, faces, w_flat = _random_batch(rng)
    open_rows = np.flatnonzero(rng.random(len(batch)) < 0.7)
    got, thin = bisect_open(batch, open_rows, J, pos, split_of, faces, w_flat)
    ref, thin_ref = _bisect_reference(batch, open_rows, J, pos, split_of, faces, w_flat)
    assert thin is None and thin_ref is None
    assert len(got) == 2 * len(open_rows)
    _same_children(got, ref)
    # each pair halves its box: the children's union is the parent, one coordinate changed
    for i, k in enumerate(open_rows):
        lo, hi = batch[k][0], batch[k][1]
        (l1, h1, _, _), (l2, h2, _, _) = got[2 * i], got[2 * i + 1]
        assert np.array_equal(l1, lo) and np.array_equal(h2, hi)
        s = np.flatnonzero(h1 != hi)
        assert s.size == 1 and np.array_equal(np.flatnonzero(l2 != lo), s) and h1[s] == l2[s]
        assert lo[s] < h1[s] < hi[s]


def test_bisect_open_stops_at_the_first_box_too_thin_to_halve():
    rng = np.random.default_rng(11)
    batch, J, pos, split_of, faces, w_flat = _random_batch(rng, thin_row=17)
    open_rows = np.arange(len(batch))
    got, thin = bisect_open(batch, open_rows, J, pos, split_of, faces, w_flat)
    ref, thin_ref = _bisect_reference(batch, open_rows, J, pos, split_of, faces, w_flat)
    assert thin == thin_ref == 17
    _same_children(got, ref)


def test_decide_gives_the_same_result_and_box_count_as_the_per_box_loop(monkeypatch):
    """The whole containment search on two faces whose objective has dependency (sin^2 + cos^2 of the same
    variable: about a hundred boxes to prove), with a budget that runs out and one that suffices, the new and the
    reference bisection: the same status, box count and fractions. u[0] is split without a derivative (the form
    is centered in x, y only), u[2] is a degenerate coordinate."""
    x, y, u = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("u", 3)
    e = ca.sin(x) ** 2 + ca.cos(x) ** 2 + ca.sin(y) ** 2 + ca.cos(y) ** 2 - 2
    g = ca.Function("g", [x, y, u], [ca.vertcat(e + 0.01 * u[0] * x - 0.02, e + 0.01 * u[1] * y - 0.02)],
                    ["x", "y", "u"], ["n"])
    F = BatchCenteredForm(g, ["x", "y"])
    lo = np.array([-1.0, -1.0, 0.0, 0.0, 0.0])
    hi = np.array([1.0, 1.0, 1.0, 1.0, 0.0])
    faces = [{"name": "a", "lo": lo, "hi": hi, "pos": 0, "sign": 1.0},
             {"name": "b", "lo": lo, "hi": hi, "pos": 1, "sign": 1.0}]
    split_of = [np.array([0, 1, 2]), np.array([0, 1, 3])]
    results = {}
    for which in ("new", "reference"):
        if which == "reference":
            monkeypatch.setattr(containment, "bisect_open", _bisect_reference)
        results[which] = [containment._decide(F, faces, split_of, budget, None) for budget in (50, 50000)]
    assert results["new"] == results["reference"]
    assert [r["status"] for r in results["new"]] == ["undecided", "proven"]
    assert results["new"][1]["boxes"] > 50
    # the proof re-checked at points: the objective is below 0 on a grid of the face
    X, Y = np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41))
    for U in (0.0, 1.0):
        V = np.array(g(X.ravel()[None, :], Y.ravel()[None, :], np.array([[U], [U], [0.0]]) @ np.ones((1, X.size))))
        assert np.all(V < 0)


def _sensitivities_reference(J, wpos, width, pos, K, nsplit):
    """extrema's per-box code before the change."""
    out = []
    for r in range(K):
        if J is not None:
            out.append(np.where(wpos >= 0, J[r][:, np.maximum(wpos, 0)] * width[r], np.nan)[pos])
        else:
            out.append(np.full((len(pos), nsplit), np.nan))
    return np.array(out)


@pytest.mark.parametrize("with_jacobian", [True, False])
def test_search_sensitivities_match_the_per_box_code(with_jacobian):
    rng = np.random.default_rng(3)
    K, n_out, n_w = 33, 5, 4
    J = np.abs(rng.normal(size=(K, n_out, n_w))) if with_jacobian else None
    if J is not None:
        J[rng.random(J.shape) < 0.1] = np.inf
        J[rng.random(J.shape) < 0.1] = np.nan
    wpos = np.array([2, -1, 0, 3, -1, 1])
    width = rng.uniform(0, 2, size=(K, wpos.size))
    pos = np.array([4, 0, 4])
    got = _sensitivities(J, wpos, width, pos, K, wpos.size)
    ref = _sensitivities_reference(J, wpos, width, pos, K, wpos.size)
    assert got.shape == (K, 3, wpos.size) and got.tobytes() == ref.tobytes()


def test_rounding_directions_as_arrays_give_numpy_nextafter_bits():
    """_dn/_up and the rules that call nextafter directly against np.nextafter(x, -inf / inf) with Python floats,
    on random bit patterns (every class: subnormals, zeros of both signs, infinities, NaN) and on a scalar."""
    rng = np.random.default_rng(5)
    bits = rng.integers(np.iinfo(np.int64).min, np.iinfo(np.int64).max, size=20000, dtype=np.int64)
    x = np.concatenate([bits.view(np.float64), [0.0, -0.0, np.inf, -np.inf, np.nan, 5e-324, -5e-324]])
    y = rng.permutation(x)
    with np.errstate(all="ignore"):
        assert batch_rules._dn(x).tobytes() == np.nextafter(x, -np.inf).tobytes()
        assert batch_rules._up(x).tobytes() == np.nextafter(x, np.inf).tobytes()
        lo, hi = np.minimum(x, y), np.maximum(x, y)
        al, ah = batch_rules.ADD(lo, hi, y, y)[:2]
        assert al.tobytes() == np.nextafter(lo + y, -np.inf).tobytes()
        assert ah.tobytes() == np.nextafter(hi + y, np.inf).tobytes()
        sl, sh = batch_rules.SUB(lo, hi, y, y)[:2]
        assert sl.tobytes() == np.nextafter(lo - y, -np.inf).tobytes()
        assert sh.tobytes() == np.nextafter(hi - y, np.inf).tobytes()
        ml, mh = batch_rules.MUL(lo, hi, lo, hi)[:2]
        p = np.stack([lo * lo, lo * hi, hi * lo, hi * hi])
        ref_lo = np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], p[3]))
        ref_hi = np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))
        assert ml.tobytes() == np.nextafter(ref_lo, -np.inf).tobytes()
        assert mh.tobytes() == np.nextafter(ref_hi, np.inf).tobytes()
        cl, ch = batch_rules._mulc(lo, hi, -3.0)
        assert cl.tobytes() == np.nextafter(np.minimum(lo * -3.0, hi * -3.0), -np.inf).tobytes()
        assert ch.tobytes() == np.nextafter(np.maximum(lo * -3.0, hi * -3.0), np.inf).tobytes()
    s = batch_rules._dn(1.0)
    assert type(s) is np.float64 and s == np.nextafter(1.0, -np.inf) and batch_rules._up(1.0) == np.nextafter(1.0, 2)


def _old_work_per_box(F):
    """RegionProblem.work_per_box before the change: every tape's operations counted by reading it again."""
    from symfunnel.sx.tape import count_ops

    def cost(F):
        f = count_ops(F.natural.function)["operations"]
        jac = getattr(F.jac, "inner", F.jac)
        hook = getattr(getattr(F, "refine", None), "F", None)
        extra = F.refine_passes * count_ops(hook.function)["operations"] if hook is not None else 0
        return 2 * f + extra + (cost(jac) if isinstance(jac, BatchCenteredForm)
                                else count_ops(jac.function)["operations"])
    return cost(F)


@pytest.mark.parametrize("order", [1, 2])
def test_work_per_box_counts_the_tapes_without_reading_them_again(monkeypatch, order):
    """The box budget's operations per box from the counts taken when the tapes were read: the same number as
    count_ops over each tape (the old way), and count_ops is not called."""
    from types import SimpleNamespace

    import symfunnel.sx.tape as tape
    from symfunnel.certificates.problem import RegionProblem
    from symfunnel.sx.batch import BatchIntervalFunction

    x, y, u = ca.SX.sym("x", 2), ca.SX.sym("y"), ca.SX.sym("u", 3)
    g = ca.Function("g", [x, y, u], [ca.vertcat(ca.sin(x[0]) * ca.exp(y) + 2.5 * u[0] * x[1] - 1.0,
                                                 ca.fmax(x[0], y) * u[1] + ca.sqrt(1 + x[1] ** 2))],
                    ["x", "y", "u"], ["n"], {"cse": True})
    F = BatchCenteredForm(g, ["x", "y"], order=order)
    h = ca.Function("h", [x, y, u], [x[0] * y + u[2]], ["x", "y", "u"], ["r"])
    F.refine, F.refine_passes = SimpleNamespace(F=BatchIntervalFunction(h)), 2
    expected = _old_work_per_box(F)
    calls = []
    real = tape.count_ops
    monkeypatch.setattr(tape, "count_ops", lambda f: calls.append(f) or real(f))
    assert RegionProblem.work_per_box(SimpleNamespace(F=F)) == expected
    assert calls == []
    for G in (F.natural, F.refine.F):
        assert G.operations == real(G.function)["operations"] > 0
