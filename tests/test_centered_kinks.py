"""The batched mean-value form (`sx.batch.BatchCenteredForm`) across the kinks of fmax/fmin (a dead zone's
branches), and its second-order variant: enclosures checked against values computed here with plain numpy at points
drawn in the boxes, never from the evaluator under test."""

from __future__ import annotations

import casadi as ca
import numpy as np

from symfunnel.sx.batch import BatchCenteredForm
from symfunnel.sx.rewrite import kink_quotients

X, Y = ca.SX.sym("x"), ca.SX.sym("y")
# a dead zone of u = x*y - 0.3 (slopes 1.02 right of 0.2, 0.98 left of -0.2), times a smooth factor
U = X * Y - 0.3
# (and a product whose change is small against its size: x e^y (1.1 + sin(y)) - x e^y sin(y), dependency for the
# natural enclosure)
EXPR = ((1.02 * ca.fmax(U - 0.2, 0) + 0.98 * ca.fmin(U + 0.2, 0)) * (2 + ca.sin(X))
        + X * ca.exp(Y) * (1.1 + ca.sin(Y)) - X * ca.exp(Y) * ca.sin(Y))
F = ca.Function("dz", [X, Y], [EXPR], ["x", "y"], ["f"])


def _numpy(x, y):
    u = x * y - 0.3
    return ((1.02 * np.maximum(u - 0.2, 0) + 0.98 * np.minimum(u + 0.2, 0)) * (2 + np.sin(x))
            + 1.1 * x * np.exp(y))


def _boxes(rng, k, half):
    c = rng.uniform(-1.5, 1.5, (k, 2))
    return c - half, c + half


def test_kink_quotients_keep_every_value_and_bound_the_undecided_quotient():
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    q = (a <= b) / ((a <= b) + (b <= a))
    r = kink_quotients([q])[0]
    g = ca.Function("g", [a, b], [q, r])
    for va, vb in ((0.0, 1.0), (1.0, 0.0), (0.5, 0.5), (-2.0, 3.0)):
        v0, v1 = (float(v) for v in g(va, vb))
        assert v0 == v1, (va, vb, v0, v1)
    from symfunnel.sx.batch import BatchIntervalFunction
    L, H, _ = BatchIntervalFunction(ca.Function("r", [a, b], [r])).eval_batch(np.array([[-1.0, 0.0]]),
                                                                               np.array([[1.0, 0.0]]))
    assert -1e-15 <= L[0, 0] <= 0.0 and 1.0 <= H[0, 0] <= 1.0 + 1e-15      # [0, 1], outward rounded
    # a quotient of two comparisons that are not the swapped pair (0/0 possible) is left as it is
    c = ca.SX.sym("c")
    other = (a <= b) / ((a <= b) + (c <= a))
    kept = kink_quotients([other])[0]
    h = ca.Function("h", [a, b, c], [kept])
    assert np.isnan(float(h(1.0, 0.0, 2.0)))             # both comparisons false: 0/0 as before


def test_the_mean_value_form_is_finite_across_a_kink_and_contains_the_values():
    """Boxes that straddle the dead zone's breakpoints: CasADi's derivative of fmax divides by an interval containing
    0 there, so the Jacobian was infinite and the form fell back to the natural enclosure (on the faces of
    certify.containment: boxes that never closed). Now the Jacobian is finite and every value lies inside."""
    form = BatchCenteredForm(F, ["x", "y"])
    rng = np.random.default_rng(3)
    # centres on the breakpoint u = 0.2 (x y = 0.5): each box decides no branch
    x = rng.uniform(0.6, 1.5, 200)
    LO = np.c_[x, 0.5 / x] - 0.01
    HI = LO + 0.02
    L, H, sw, J = form.eval_batch(LO, HI, with_jacobian=True)
    assert np.all(np.isfinite(J)), "the Jacobian is infinite across the kink"
    NL, NH, _ = form.natural.eval_batch(LO, HI)
    assert np.mean(H - L < 0.9 * (NH - NL)) > 0.9          # the mean-value form pays: narrower than natural
    for k in range(LO.shape[0]):
        P = LO[k] + rng.random((50, 2)) * (HI[k] - LO[k])
        v = _numpy(P[:, 0], P[:, 1])
        assert np.all(L[k, 0] <= v) and np.all(v <= H[k, 0]), k


def test_second_order_form_contains_the_values_and_is_tighter():
    """order = 2 (the Jacobian by its own mean-value form): every value drawn in a box lies inside its enclosure
    (the Jacobian taken at the centre only, its Hessian term dropped, fails this; a Hessian halved was not caught
    here: the intersection with the natural enclosures hides it), and it is no wider than the first-order one."""
    one, two = BatchCenteredForm(F, ["x", "y"]), BatchCenteredForm(F, ["x", "y"], order=2)
    rng = np.random.default_rng(5)
    LO, HI = _boxes(rng, 400, rng.uniform(0.02, 0.3, (400, 1)))
    L1, H1, _ = one.eval_batch(LO, HI)
    L2, H2, _ = two.eval_batch(LO, HI)
    assert np.all(H2 - L2 <= H1 - L1 + 1e-12)
    assert np.mean(H2 - L2 < 0.9 * (H1 - L1)) > 0.2
    for k in range(LO.shape[0]):
        P = LO[k] + rng.random((200, 2)) * (HI[k] - LO[k])
        P[:4] = [[LO[k, 0], LO[k, 1]], [LO[k, 0], HI[k, 1]], [HI[k, 0], LO[k, 1]], [HI[k, 0], HI[k, 1]]]
        v = _numpy(P[:, 0], P[:, 1])
        assert np.all(L2[k, 0] <= v) and np.all(v <= H2[k, 0]), (k, L2[k], H2[k], v.min(), v.max())


def _kinks_rebuilding_every_node(exprs):
    """kink_quotients as first written (its rule builds every operation a second time): the reference the faster
    rule must match node for node."""
    from symfunnel.sx.rewrite import replace_nodes
    syms = ca.vertcat(*ca.symvar(ca.vertcat(*[ca.vec(e) for e in exprs])))

    def rule(name, _tags, vals):
        if name == "DIV":
            a, s_ = vals
            if a.is_op(ca.OP_LE) and s_.is_op(ca.OP_ADD) and ca.is_equal(s_.dep(0), a, 0):
                x, y = a, s_.dep(1)
                if (y.is_op(ca.OP_LE) and ca.is_equal(x.dep(0), y.dep(1), 0) and ca.is_equal(x.dep(1), y.dep(0), 0)):
                    return 0.5 * (1 + a - s_.dep(1)), True
        op = getattr(ca, "OP_" + name)
        return (ca.SX.unary(op, vals[0]) if len(vals) == 1 else ca.SX.binary(op, vals[0], vals[1])), True
    return replace_nodes(exprs, syms, syms, tags=[{True}] * syms.numel(), rule=rule)


def test_kink_quotients_build_each_operation_once_and_the_same_graph(monkeypatch):
    """The rewrite of a Jacobian with fmax/fmin kinks: the same tape, instruction for instruction, as the rewrite that
    rebuilt every node twice, with one SX.binary per binary operation of the tape (not two)."""
    J = ca.jacobian(EXPR, ca.vertcat(X, Y))
    ref = _kinks_rebuilding_every_node([J])[0]
    calls = []
    real = ca.SX.binary
    monkeypatch.setattr(ca.SX, "binary", staticmethod(lambda *a: calls.append(a[0]) or real(*a)))
    got = kink_quotients([J])[0]
    monkeypatch.undo()
    tape = ca.Function("t", [X, Y], [got], {"cse": True})
    assert str(ca.Function("t", [X, Y], [ref], {"cse": True})) == str(tape)
    assert [tape.instruction_id(k) for k in range(tape.n_instructions())] == \
        [f.instruction_id(k) for f in [ca.Function("r", [X, Y], [ref], {"cse": True})]
         for k in range(f.n_instructions())]
    assert ca.is_equal(got, ref, 1000)
    # the rewrite's own tape (the input plus the symbols) bounds the binary operations rebuilt; the old rule doubled
    src = ca.Function("s", [X, Y], [J], {"cse": True})
    n_binary = sum(1 for k in range(src.n_instructions()) if len(src.instruction_input(k)) == 2)
    assert 0 < len(calls) <= n_binary + 8, (len(calls), n_binary)
