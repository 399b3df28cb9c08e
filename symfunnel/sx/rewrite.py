"""Graph substitution for SX: replace given *nodes* (not only symbols) of expressions by other expressions.

CasADi's `graph_substitute` exists for MX only; `substitute` replaces symbols. `replace_nodes` rebuilds the
expressions from their instruction tape (one `SX.unary` / `SX.binary` per instruction) and puts the replacement in
place of every instruction that computes one of the nodes, so everything computed from a node is computed from its
replacement. Where the replacement equals the node (e.g. e1 = q - q_d replaced by the region's expression for e1,
on the region where q = q_d + that expression), the rebuilt expressions are the same real functions there: the
interval evaluation then sees the replacement instead of a difference of two wide intervals.
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca

__all__ = ["replace_nodes", "REBUILT"]

#: a rule's value meaning "the operation as rebuilt" (saves building the same node twice; only its tag is new)
REBUILT = object()


def _scalars(exprs: Sequence[ca.SX]) -> list[ca.SX]:
    return [ca.SX(e) for e in exprs]


def replace_nodes(exprs: Sequence[ca.SX], nodes: ca.SX, values: ca.SX, *, tags: Sequence | None = None,
                  rule=None) -> list[ca.SX]:
    """`exprs` with every occurrence of each nonzero of `nodes` replaced by the matching nonzero of `values`.

    `nodes` and `values` have the same shape; a node that is a symbol is replaced wherever the symbol occurs (then
    this is ordinary substitution). Structurally identical copies of a node are merged by CasADi's CSE and replaced
    too. Sparsity of each expression is kept.

    `tags` (a set per nonzero of `nodes`; a node CSE merged from several nonzeros gets their union) and
    `rule(opname, arg_tags, arg_values) -> (value, tag) | None` rewrite operations on tagged nodes as well: e.g. with
    e tagged {('e', i)} and F tagged {('F', i)}, a rule can replace F - e by F (1 - s); the tag it returns marks the
    new value for the operations after it; a rule returning (`REBUILT`, tag) keeps the operation as rebuilt and
    tags it. A node listed in `nodes` with its own value as replacement is only tagged.
    """
    exprs = _scalars(exprs)
    nodes, values = ca.SX(nodes), ca.SX(values)
    if nodes.shape != values.shape or nodes.nnz() != values.nnz():
        raise ValueError(f"nodes {nodes.shape} and values {values.shape} must have the same shape and sparsity")
    syms = ca.symvar(ca.vertcat(*[ca.vec(e) for e in exprs], ca.vec(nodes)))
    outs = [ca.vec(e) for e in exprs] + [ca.vec(nodes)]
    f = ca.Function("rewrite", syms, outs, {"cse": True, "allow_free": False})
    n_ins = f.n_instructions()
    ops = [f.instruction_id(k) for k in range(n_ins)]
    args = [f.instruction_input(k) for k in range(n_ins)]
    res = [f.instruction_output(k) for k in range(n_ins)]
    node_out = len(outs) - 1
    # pass 1: which instruction computes each node nonzero (the last writer of the slot the node's output reads)
    writer: dict[int, int] = {}
    replace_at: dict[int, list[int]] = {}      # instruction index -> nonzero indices into values (CSE merges)
    for k in range(n_ins):
        op = ops[k]
        if op == ca.OP_OUTPUT:
            o, j = res[k][0], res[k][1]
            if o == node_out:
                replace_at.setdefault(writer[args[k][0]], []).append(j)
        elif res[k]:
            writer[res[k][0]] = k
    vv = ca.vec(values)
    vals = [vv.nz[i] for i in range(vv.nnz())]
    # pass 2: rebuild
    work: dict[int, ca.SX] = {}
    tag: dict[int, object] = {}
    out_nz: list[dict[int, ca.SX]] = [dict() for _ in outs]
    for k in range(n_ins):
        op, a, r = ops[k], args[k], res[k]
        if op == ca.OP_INPUT:
            v = ca.vec(syms[a[0]])[a[1]]
        elif op == ca.OP_OUTPUT:
            out_nz[r[0]][r[1]] = work[a[0]]
            continue
        elif op == ca.OP_CONST:
            v = ca.SX(f.instruction_constant(k))
        elif op == ca.OP_PARAMETER:
            raise ValueError("free variables in an expression to rewrite")
        elif len(a) == 1 or op in _UNARY:
            v = ca.SX.unary(op, work[a[0]])
        else:
            v = ca.SX.binary(op, work[a[0]], work[a[1]])
        t = None
        if rule is not None and op not in (ca.OP_INPUT, ca.OP_CONST):
            nargs = 1 if (len(a) == 1 or op in _UNARY) else 2
            at = tuple(tag.get(j) for j in a[:nargs])
            if any(x is not None for x in at):
                got = rule(_NAMES.get(op), at, [work[j] for j in a[:nargs]])
                if got is not None:
                    v, t = (v, got[1]) if got[0] is REBUILT else got
        if k in replace_at:
            js = replace_at[k]
            v = vals[js[0]]
            t = None if tags is None else frozenset().union(*[tags[j] for j in js])
        work[r[0]] = v
        tag[r[0]] = t
    rebuilt = []
    for i, e in enumerate(exprs):
        nz = [out_nz[i][j] for j in range(e.nnz())]
        rebuilt.append(ca.SX(e.sparsity(), ca.vertcat(*nz)) if nz else ca.SX(e.sparsity()))
    return rebuilt


_NAMES = {getattr(ca, n): n[3:] for n in dir(ca) if n.startswith("OP_")}
_UNARY = frozenset(getattr(ca, "OP_" + n) for n in (
    "ASSIGN", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN",
    "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL", "NOT", "ERF", "ERFINV", "LOG1P", "EXPM1")
    if hasattr(ca, "OP_" + n))



def kink_quotients(exprs: Sequence[ca.SX]) -> list[ca.SX]:
    """`exprs` with every quotient (a <= b) / ((a <= b) + (b <= a)) -- CasADi's derivative of fmax and fmin --
    written (1 + (a <= b) - (b <= a)) / 2: the same value for every real a, b (1, 0, or 1/2 at a = b) and the same
    floating-point value, but enclosed in [0, 1] by interval arithmetic where the box does not decide the branch,
    where the quotient's denominator [0, 2] contains 0 (an infinite enclosure: a mean-value form over such a box
    had an infinite Jacobian). [0, 1] is the hull of the two branches' slopes (Clarke's gradient at the kink)."""
    exprs = _scalars(exprs)
    syms = ca.vertcat(*ca.symvar(ca.vertcat(*[ca.vec(e) for e in exprs])))
    if syms.numel() == 0:
        return list(exprs)

    def swapped(x, y):
        return (x.is_op(ca.OP_LE) and y.is_op(ca.OP_LE) and ca.is_equal(x.dep(0), y.dep(1), 0)
                and ca.is_equal(x.dep(1), y.dep(0), 0))

    def rule(name, _tags, vals):
        if name == "DIV":
            a, s_ = vals
            if a.is_op(ca.OP_LE) and s_.is_op(ca.OP_ADD) and ca.is_equal(s_.dep(0), a, 0) \
                    and swapped(a, s_.dep(1)):
                return 0.5 * (1 + a - s_.dep(1)), True
        return REBUILT, True
    return replace_nodes(exprs, syms, syms, tags=[{True}] * syms.numel(), rule=rule)
