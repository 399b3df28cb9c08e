"""The safe expression language of scenario files: one whitelisted parse that feeds both CasADi and sympy.

Scenario files are user input and may be hostile, so an expression string is never handed to
``eval``, ``sympify`` or ``parse_expr``.  It is parsed with ``ast.parse(mode="eval")`` (which builds a
syntax tree and evaluates nothing), every node is checked against a whitelist and converted to a
small immutable tree of our own, and limits against CAS hangs (size, depth, literal magnitude,
constant exponents) are enforced before anything is evaluated.

Grammar::

    expr := number | name | pi | expr (+ - * / ** ^) expr | (+ -) expr | ( expr ) | f(expr, ...)

``^`` means power (with the precedence and right associativity of ``**``, so ``-x^2`` is ``-(x^2)``
and ``2*x^2`` is ``2*(x^2)``).  ``pi`` is the constant, never a free symbol.

Values are scalars or matrices.  ``+ - * / ^`` and the elementwise functions work elementwise with
broadcasting: equal shapes; a 1x1 value against any shape; an (r,1) column against a (1,c) row gives
(r,c).  Anything else is an error naming both shapes.  ``outer``, ``dot``, ``transpose`` and
``mtimes`` are the linear-algebra operations (see `FUNCTIONS`).
"""

from .limits import (
           MAX_DEPTH,
           MAX_EXACT_DIGITS,
           MAX_EXPONENT,
           MAX_LENGTH,
           MAX_LITERAL,
           MAX_NODES,
)
from .parse import parse_expression
from .tree import CONSTANTS, FUNCTIONS, Expression

__all__ = ["Expression", "parse_expression", "FUNCTIONS", "CONSTANTS", "MAX_LENGTH", "MAX_NODES",
           "MAX_DEPTH", "MAX_LITERAL", "MAX_EXPONENT", "MAX_EXACT_DIGITS"]
