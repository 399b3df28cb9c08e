"""Text for one terminal line: control and invisible characters escaped, whitespace runs collapsed, length bounded.

Every message symfunnel prints (errors, warnings, timeouts) goes through `one_line`, so input quoted in a message
(a key's value, a file name, CasADi's multi-line error) can neither break the line, hide in it nor flood it.
"""

from __future__ import annotations

import re
import unicodedata

#: the longest line a message becomes (characters); the rest is cut with a count
MAX_LINE = 400
#: the longest quoted value (`shown`) in a message
MAX_VALUE = 60

_SPACE = re.compile(r"[ \t\r\n\f\v]+")


def _escape(ch: str) -> str:
    o = ord(ch)
    return f"\\x{o:02x}" if o < 0x100 else (f"\\u{o:04x}" if o < 0x10000 else f"\\U{o:08x}")


def invisible(ch: str) -> bool:
    """Whether `ch` shows nothing or moves the cursor (control, format, separator other than space, unassigned)."""
    cat = unicodedata.category(ch)
    return cat in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp") or (cat == "Zs" and ch != " ")


def escape(text: str) -> str:
    """`text` with every invisible character written as a visible escape (\\x00, \\u200b, ...)."""
    return "".join(_escape(c) if invisible(c) else c for c in text)


def one_line(text: str, limit: int = MAX_LINE) -> str:
    """One printable line: whitespace runs to one space, invisible characters escaped, at most `limit` characters."""
    s = escape(_SPACE.sub(" ", str(text)).strip())
    if len(s) > limit:
        s = s[:limit - 30].rstrip() + f" ... ({len(s) - limit + 30} more characters)"
    return s


def shown(value, limit: int = MAX_VALUE) -> str:
    """A user's value quoted in a message: repr-like, escaped, cut to `limit` characters."""
    s = escape(str(value))
    if len(s) > limit:
        s = s[:limit] + f"... ({len(s)} characters)"
    return s


def article(word: str) -> str:
    """'a' or 'an' before `word` (by its first letter's sound, good enough for type names)."""
    return "an" if word[:1].lower() in "aeiou" else "a"


def plural(n: int, noun: str, nouns: str | None = None) -> str:
    """'1 warning', '2 warnings': a count and its noun in the number it takes."""
    return f"{n} {noun if n == 1 else (nouns or noun + 's')}"


#: what a table or a progress line shows for a number that does not exist (no margin after a transient a run never
#: finished, a rate not found): one sign everywhere, never `-inf`, `nan` or `None`
MISSING = "\u2014"


def number(value, spec: str = ".4g", unit: str = "") -> str:
    """`value` formatted by `spec` (with ` unit`), or MISSING for None, inf and nan."""
    import math
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return MISSING
    return f"{value:{spec}}" + (f" {unit}" if unit else "")


def reached(t_end: float, horizon: float, step: float) -> str:
    """'reached the horizon t = 5 s' when a run ended less than one step (of its output or sample grid) before its
    horizon, which a grid that does not divide the horizon leaves (4.99829 s on 5 s), else 'reached t = 3.2 s'."""
    if 0.0 <= horizon - t_end < step * (1 + 1e-9):
        return f"reached the horizon t = {horizon:g} s"
    return f"reached t = {t_end:g} s"
