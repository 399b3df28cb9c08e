"""Formulas for the report: SX signals and printed claims as MathML (sympy's presentation printer), within a size
budget."""

from __future__ import annotations

import html as _html

from . import formula as FM

MATHML_NS = "http://www.w3.org/1998/Math/MathML"     # a namespace name (a URI), not a reference: nothing is fetched


FORMULA_MAX_OPS = 120          # sympy count_ops of one entry above which a signal is shown by its size only


FORMULA_MAX_CHARS = 12000      # MathML markup above which a formula is shown by its size only


DOT = "<mo>&#729;</mo>"


DDOT = "<mo>&#168;</mo>"


# <mi>NAME</mi> produced by sympy's presentation printer -> nicer markup
_MI = {
    "dq": f"<mover><mi>q</mi>{DOT}</mover>",
    "ddq": f"<mover><mi>q</mi>{DDOT}</mover>",
    "qd": "<msub><mi>q</mi><mi>d</mi></msub>",
    "dqd": f"<msub><mover><mi>q</mi>{DOT}</mover><mi>d</mi></msub>",
    "ddqd": f"<msub><mover><mi>q</mi>{DDOT}</mover><mi>d</mi></msub>",
    "dF": f"<mover><mi>F</mi>{DOT}</mover>",
    "de": f"<mover><mi>e</mi>{DOT}</mover>",
    "dz": f"<mover><mi>z</mi>{DOT}</mover>",
    "alphadot": f"<mover><mi>&#945;</mi>{DOT}</mover>",
    "zdot": f"<mover><mi>z</mi>{DOT}</mover>",
    "What": "<mover><mi>W</mi><mo>^</mo></mover>",
    "Whatdot": f"<mover><mover><mi>W</mi><mo>^</mo></mover>{DOT}</mover>",
}


# claim / signal names -> sympy symbol names the printer renders well (letters + trailing digits)
_CLAIM_NAMES = {"alpha2_dot": "alphadot2", "z1_dot": "zdot1", "z2_dot": "zdot2", "w_hat": "What",
                "w_hat_dot": "Whatdot", "x_esn": "xesn", "x_esn_dot": "xesndot"}


def mathml_body(expr) -> str:
    """The presentation MathML of a sympy expression without <math>: dots and hats fixed up, fences stretchy."""
    from sympy.printing.mathml import mathml as _mm
    body = _mm(expr, printer="presentation")
    for k, v in _MI.items():
        body = body.replace(f"<mi>{k}</mi>", v)
    return FM.stretchy_fences(body)


def mathml(expr, *, display: bool = False) -> str:
    """A sympy expression (or Matrix) as a <math> element (presentation MathML, with dots and hats fixed up)."""
    body = mathml_body(expr)
    disp = ' display="block"' if display else ""
    return f'<math xmlns="{MATHML_NS}"{disp}>{body}</math>'


def mathml_eq(lhs: str, rhs_expr, *, display: bool = True) -> str:
    """'lhs = rhs' as one <math> element; lhs is MathML markup (e.g. from symbol_mathml)."""
    m = mathml(rhs_expr, display=display)
    return m.replace(">", f">{lhs}<mo>=</mo>", 1)


def symbol_mathml(name: str) -> str:
    """Markup of a signal's name (e.g. alpha2_dot -> alpha-dot with subscript 2)."""
    import sympy
    from sympy.printing.mathml import mathml as _mm
    body = _mm(sympy.Symbol(_CLAIM_NAMES.get(name, name)), printer="presentation")
    for k, v in _MI.items():
        body = body.replace(f"<mi>{k}</mi>", v)
    return body


# widths (em) formulas are laid out to: the page, a table's formula row, one side of the alpha2_dot panel. The
# estimate of formula.width is an upper bound (rendered/estimated <= 0.87 in Chromium on paper, arm7 and a URDF
# robot), so these fit a 1024-px window (tests/test_report_layout.py measures it).
WIDTH_PAGE, WIDTH_TABLE = 50.0, 50.0
#: the formula column of the signals table (about 60 % of the page) and of the claims table (about 40 %)
WIDTH_SIGNAL, WIDTH_CLAIM = 30.0, 20.0


MAX_LINES = 12                 # a formula needing more lines than this (parts included) is shown by its size only


def formula_html(lhs: str, expr, budget: float, *, max_lines: int = MAX_LINES) -> str | None:
    """`lhs = expr` as HTML laid out to `budget` em (long sums broken into lines, wide parts named and defined
    below), or None when it needs more than max_lines lines. Numerical noise is dropped first (see formula.present)."""
    e, dropped = FM.present(expr)
    try:
        defs = FM.lines(e, budget)
    except FM.TooLarge:
        return None
    if sum(len(rows) for _, rows in defs) > max_lines:
        return None
    note = f'<div class="note">{_html.escape(noise_note(dropped))}</div>' if dropped else ""
    return FM.render_defs(lhs, defs, mathml_body) + note


def signal_sympy(design, name: str, entry: int | None = 0):
    """One entry (or the whole matrix when entry is None) of a design signal as sympy, exact, unsimplified."""
    from ..sx.tosympy import sx_to_sympy
    e = design.signals[name]
    if entry is not None:
        e = e[entry]
    inputs = [design.sym[x] for x in design.inputs_of(name)]
    m = sx_to_sympy(e, inputs)
    return m[0] if m.shape == (1, 1) else m


def claim_sympy(claim):
    """A printed claim's expression as sympy with scalar symbols (the printed law per joint)."""
    import sympy
    env = {}
    for nm in claim.expression.names:
        env[nm] = sympy.Symbol(_CLAIM_NAMES.get(nm, nm), real=True)
    return claim.expression.to_sympy(env)


def noise_note(dropped: int) -> str:
    """What the reader is told when terms were dropped for presentation."""
    if not dropped:
        return ""
    return (f"{dropped} term(s) with a coefficient below {FM.NOISE_REL:g} times the largest coefficient "
            "(floating-point round-off) are left out of this display; the model itself keeps them.")


def matrix_html(name: str, mat) -> str | None:
    """A model matrix as one display formula when it fits the page, else entry by entry (each laid out to the page
    width; only the upper triangle of a symmetric matrix; zero entries listed by index). None when too large."""
    import sympy
    if FM.width(mat) <= WIDTH_PAGE:
        return mathml_eq(f"<mi>{name}</mi>", mat)
    sym = mat.shape[0] == mat.shape[1] and mat == mat.T
    parts, zeros = [], []
    for i in range(mat.shape[0]):
        for j in range(mat.shape[1]):
            if sym and j < i:
                continue
            idx = f"{i + 1}" if mat.shape[1] == 1 else f"{i + 1},{j + 1}"
            if mat[i, j] == 0:
                zeros.append(idx)
                continue
            lhs = f"<msub><mi>{name}</mi><mn>{idx}</mn></msub>"
            h = formula_html(lhs, sympy.sympify(mat[i, j]), WIDTH_PAGE)
            if h is None:
                return None
            parts.append(h)
    head = (f'<p class="note">{name} entry by entry ({mat.shape[0]}&times;{mat.shape[1]}'
            + (", symmetric: upper triangle" if sym else "")
            + (f"; zero: {name}<sub>{', '.join(zeros)}</sub>" if zeros else "") + ")</p>")
    return head + "".join(parts)
