"""Formulas a reader can read: presentation-only clean-up of numerical noise, stretchy fences, and long expressions
broken into lines of a given width, with over-wide parts named and defined below (the top-level structure stays
visible). Nothing here changes a design's SX; it only decides how an already converted sympy expression is shown."""

from __future__ import annotations

import functools
import re

import sympy

NOISE_REL = 1e-10      # terms whose numeric coefficient is below this times the largest coefficient are dropped
FLOAT_DIGITS = 6       # significant digits of a floating-point number as shown
MAX_PARTS = 40         # at most this many named parts per formula; beyond it the formula is shown by its size only


class TooLarge(Exception):
    """A formula that would need more than MAX_PARTS named parts to fit its width."""


# --- numerical noise -------------------------------------------------------------------------------

def _coeff(term) -> float:
    c, _ = term.as_coeff_Mul()
    try:
        return abs(float(c))
    except (TypeError, ValueError):
        return 1.0


def _largest_coeff(expr) -> float:
    best = 0.0
    for a in sympy.preorder_traversal(expr):
        if isinstance(a, sympy.Add):
            for t in a.args:
                best = max(best, _coeff(t))
        elif a.is_Number:
            try:
                best = max(best, abs(float(a)))
            except (TypeError, ValueError):
                pass
    return best


def drop_noise(expr, rel: float = NOISE_REL):
    """(expr without the terms of any sum whose coefficient is below rel x the largest coefficient, terms dropped).

    Floating-point round-off of a URDF model (e.g. 8.7e-14*sin(q2) beside 9.81*sin(q2)) is removed this way; the
    dropped terms are counted so that the report can say so. Works entrywise on a Matrix with one common scale."""
    if isinstance(expr, sympy.MatrixBase):
        big = max((_largest_coeff(e) for e in expr), default=0.0)
        out, n = [], 0
        for e in expr:
            d, k = _drop(e, rel * big)
            out.append(d)
            n += k
        return sympy.Matrix(expr.shape[0], expr.shape[1], out), n
    return _drop(expr, rel * _largest_coeff(expr))


def _drop(expr, tol: float):
    if tol <= 0 or expr.is_Atom:
        return expr, 0
    n = 0
    args = []
    for a in expr.args:
        d, k = _drop(a, tol)
        args.append(d)
        n += k
    if isinstance(expr, sympy.Add):
        keep = [a for a in args if not (a.has(sympy.Float) and _coeff(a) < tol)]
        n += len(args) - len(keep)
        return (sympy.Add(*keep) if keep else sympy.Integer(0)), n
    return (expr.func(*args) if n else expr), n


def round_floats(expr, digits: int = FLOAT_DIGITS):
    """Floats shown with `digits` significant digits (0.00247487373415181 -> 0.00247487)."""
    reps = {f: sympy.Float(float(f), digits) for f in expr.atoms(sympy.Float)}
    return expr.xreplace(reps) if reps else expr


def present(expr):
    """The presentation form of a converted expression: noise dropped, floats rounded; (form, terms dropped)."""
    e, n = drop_noise(expr)
    return round_floats(e), n


# --- MathML markup ---------------------------------------------------------------------------------

_FENCE_MO = re.compile(r"<mo>([(\[\]){}|\u2016])</mo>")
_TAG = re.compile(r"<(/?)([A-Za-z][\w:-]*)([^>]*?)(/?)>")


def stretchy_fences(markup: str) -> str:
    """Fences that stretch with their content: `<mo>(</mo>` -> `<mo stretchy="true" ...>`, and <mfenced> (not in
    MathML Core, so Chromium ignores it) rewritten as an <mrow> of fence operators and its children."""
    markup = _unfence(markup)
    return _FENCE_MO.sub(lambda m: f'<mo stretchy="true" symmetric="true" fence="true">{m.group(1)}</mo>', markup)


def _attr(attrs: str, name: str, default: str) -> str:
    m = re.search(rf'\b{name}\s*=\s*"([^"]*)"', attrs)
    return m.group(1) if m else default


def _unfence(markup: str) -> str:
    if "<mfenced" not in markup:
        return markup
    # find the first <mfenced ...>, its matching close tag, and rewrite its content (recursively)
    out, pos = [], 0
    while True:
        m = re.compile(r"<mfenced\b([^>]*?)(/?)>").search(markup, pos)
        if m is None:
            out.append(markup[pos:])
            return "".join(out)
        out.append(markup[pos:m.start()])
        attrs, selfclosing = m.group(1), m.group(2)
        op, cl = _attr(attrs, "open", "("), _attr(attrs, "close", ")")
        seps = re.sub(r"\s", "", _attr(attrs, "separators", ","))
        if selfclosing:
            out.append(_fenced(op, cl, []))
            pos = m.end()
            continue
        children, end = _children(markup, m.end(), "mfenced")
        parts = []
        for i, ch in enumerate(children):
            if i and seps:
                parts.append(f"<mo separator=\"true\">{seps[min(i - 1, len(seps) - 1)]}</mo>")
            parts.append(_unfence(ch))
        out.append(_fenced(op, cl, parts))
        pos = end


def _fenced(op: str, cl: str, parts: list[str]) -> str:
    f = '<mo stretchy="true" symmetric="true" fence="true">{}</mo>'
    return "<mrow>" + (f.format(op) if op else "") + "".join(parts) + (f.format(cl) if cl else "") + "</mrow>"


def _children(markup: str, start: int, tag: str) -> tuple[list[str], int]:
    """The top-level child elements of the element whose start tag ends at `start`; and the end of its close tag."""
    depth, children, cur = 0, [], None
    for m in _TAG.finditer(markup, start):
        closing, selfc = m.group(1) == "/", m.group(4) == "/"
        if depth == 0 and closing:
            return children, m.end()
        if depth == 0:
            cur = m.start()
        if selfc:
            if depth == 0:
                children.append(markup[cur:m.end()])
            continue
        depth += -1 if closing else 1
        if depth == 0:
            children.append(markup[cur:m.end()])
    raise ValueError(f"unclosed <{tag}>")


# --- width and line breaking -----------------------------------------------------------------------

def width(e) -> float:
    """An upper estimate of an expression's rendered width in em (presentation MathML, display style)."""
    if isinstance(e, sympy.MatrixBase):
        cols = [max((width(e[i, j]) for i in range(e.rows)), default=0) for j in range(e.cols)]
        return sum(cols) + 1.2 * max(e.cols - 1, 0) + 1.6
    return _width(e)


@functools.lru_cache(maxsize=1 << 16)
def _width(e) -> float:
    """`width` of an (immutable, hashable) expression, remembered: line breaking asks for the same sub-expressions'
    widths over and over (an arm7 report: 140,000 calls, 2,900 of them from outside the recursion)."""
    if e.is_Symbol:
        return 0.62 * len(e.name) + 0.2
    if e.is_Integer:
        return 0.55 * len(str(e))
    if e.is_Rational:
        return 0.55 * max(len(str(e.p)), len(str(e.q))) + 0.4
    if e.is_Float:
        return 0.55 * len(str(e)) if len(str(e)) < 12 else 0.55 * len(sympy.sstr(e, full_prec=False))
    if e.is_Atom:
        return 0.6 * len(str(e)) + 0.2
    if isinstance(e, sympy.Add):
        return sum(width(a) for a in e.args) + 1.3 * (len(e.args) - 1)
    if isinstance(e, sympy.Mul):
        num, den = sympy.fraction(e)
        if den != 1:
            return max(width(num), width(den)) + 0.6 + (1.0 if e.could_extract_minus_sign() else 0.0)
        w = 0.0
        for a in e.args:
            w += width(a) + 0.25 + (1.0 if isinstance(a, sympy.Add) else 0.0)
        return w
    if isinstance(e, sympy.Pow):
        b, x = e.args
        if x == sympy.S.Half:
            return width(b) + 1.2
        if x.is_negative:
            return width(1 / e) + 0.6
        return width(b) + (1.0 if not b.is_Atom else 0.0) + 0.75 * width(x)
    if isinstance(e, sympy.exp):
        return 0.7 + 0.75 * width(e.args[0])
    if isinstance(e, sympy.Abs):
        return width(e.args[0]) + 0.8
    if isinstance(e, sympy.Function) or hasattr(e, "func"):
        name = getattr(e.func, "__name__", str(e.func))
        return 0.55 * len(name) + 1.0 + sum(width(a) for a in e.args) + 0.6 * (len(e.args) - 1)
    return 0.6 * len(str(e))


def _part_names(exclude: set[str]):
    """Fresh symbols P1, P2, ... for named parts of a formula, avoiding names in use."""
    base = next(b for b in ("P", "R", "S", "U", "Y") if not any(re.fullmatch(rf"{b}\d+", n) for n in exclude))
    k = 0
    while True:
        k += 1
        yield sympy.Symbol(f"{base}{k}")


def _unwrap(e):
    """The part worth naming inside a thin wrapper: |X|, f(X), -X, X^2 -> X."""
    while True:
        if isinstance(e, (sympy.Abs, sympy.Function)) and len(e.args) == 1 and not e.args[0].is_Atom:
            e = e.args[0]
        elif isinstance(e, sympy.Mul) and len(e.args) == 2 and e.args[0].is_Number and not e.args[1].is_Atom:
            e = e.args[1]
        elif isinstance(e, sympy.Pow) and e.args[1].is_Number and not e.args[0].is_Atom:
            e = e.args[0]
        else:
            return e


class _Layout:
    """Named parts of one formula and the lines laid out so far (a name replaces its expression everywhere)."""

    def __init__(self, expr, budget: float):
        self.budget = budget
        self.names = _part_names({str(x) for x in expr.free_symbols})
        self.parts: list[list] = []          # [symbol, expression]
        self.defs: list[list] = []           # [symbol or None, rows]

    def name(self, big):
        for sym, ex in self.parts:
            if ex == big:
                return sym
        if len(self.parts) >= MAX_PARTS:
            raise TooLarge
        s = next(self.names)
        rep = {big: s}
        for p in self.parts:
            p[1] = p[1].xreplace(rep)
        for d in self.defs:
            d[1] = [[(sg, t.xreplace(rep)) for sg, t in row] for row in d[1]]
        self.parts.append([s, big])
        return s

    def shrink(self, e):
        """e with its widest sub-expressions named until it fits the line (sums are broken into lines instead)."""
        for p in self.parts:
            e = e.xreplace({p[1]: p[0]})
        if isinstance(e, sympy.Add):
            return e
        while width(e) > self.budget - 1.6 and not e.is_Atom:
            # a wide part that occurs more than once is named first (the reader sees it once), then the widest child
            cands = sorted(_repeated(e), key=width, reverse=True)
            cands += sorted((_unwrap(a) for a in _children_of(e) if not a.is_Atom), key=width, reverse=True)
            for big in cands:
                if big.is_Atom:
                    continue
                d = sympy.Dummy()
                e2 = e.xreplace({big: d})
                if e2 != e:
                    e = e2.xreplace({d: self.name(big)})
                    break
            else:
                return e
        return e


def _repeated(e, min_width: float = 6.0) -> list:
    """Sub-expressions of e at least min_width em wide that occur more than once in it."""
    from collections import Counter
    counts = Counter(a for a in sympy.preorder_traversal(e) if not a.is_Atom)
    return [a for a, c in counts.items() if c > 1 and a != e and width(a) >= min_width]


def _children_of(e):
    """The sub-expressions a reader sees as the parts of e (a quotient's denominator rather than its reciprocal)."""
    out = []
    for a in e.args:
        if isinstance(a, sympy.Pow) and a.args[1].is_negative and not a.args[0].is_Atom:
            out.append(a.args[0])
        else:
            out.append(a)
    return out


def lines(expr, budget: float) -> list[tuple[object, list[list[tuple[str, object]]]]]:
    """expr laid out to `budget` em: [(lhs symbol or None, lines), ...], the first for expr itself, then one per
    named part; each line is a list of (sign, term) with sign '' (first), '+' or '-'. Raises TooLarge."""
    L = _Layout(expr, budget)
    L.defs.append([None, []])
    L.defs[0][1] = _break(expr, L)
    i = 0
    while i < len(L.parts):
        sym = L.parts[i][0]
        L.defs.append([sym, []])
        L.defs[-1][1] = _break(L.parts[i][1], L)
        i += 1
    return [(d[0], d[1]) for d in L.defs]


def _break(e, L: _Layout) -> list[list[tuple[str, object]]]:
    terms = list(e.as_ordered_terms()) if isinstance(e, sympy.Add) else [e]
    rows, cur, w = [], [], 0.0
    for i, t in enumerate(terms):
        sign = ""
        if i:
            sign = "-" if t.could_extract_minus_sign() else "+"
            t = -t if sign == "-" else t
        t = L.shrink(t)
        tw = width(t) + (1.3 if sign else 0.0)
        if cur and w + tw > L.budget:
            rows.append(cur)
            cur, w = [], 0.0
        cur.append((sign, t))
        w += tw
    if cur:
        rows.append(cur)
    return rows


def render(lhs: str, expr, budget: float, body) -> str:
    """HTML of `lhs = expr` laid out to `budget` em: a grid of one-line <math> elements, named parts below.

    `lhs` is MathML markup; `body(expr)` gives the MathML markup of an expression (without <math>)."""
    defs = lines(expr, budget)
    return render_defs(lhs, defs, body)


def render_defs(lhs: str, defs, body) -> str:
    """HTML of definitions from `lines` (see `render`)."""
    def math(inner: str) -> str:
        return f'<math xmlns="{_NS}" displaystyle="true">{inner}</math>'
    out = ['<div class="eqn">']
    for k, (sym, rows) in enumerate(defs):
        if k == 1:
            out.append('<div class="eqn-where">where</div>')
        head = lhs if sym is None else body(sym)
        for r, row in enumerate(rows):
            inner = "".join((f"<mo>{'&#8722;' if sg == '-' else '+'}</mo>" if sg else "") + _group(body(t))
                            for sg, t in row)
            out.append(f'<div class="eqn-lhs">{math(head + "<mo>=</mo>") if r == 0 else ""}</div>'
                       f'<div class="eqn-rhs">{math(inner)}</div>')
    out.append("</div>")
    return "".join(out)


def _group(markup: str) -> str:
    return markup if markup.startswith("<mrow>") else f"<mrow>{markup}</mrow>"


_NS = "http://www.w3.org/1998/Math/MathML"     # a namespace name, never fetched
