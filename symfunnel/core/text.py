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
