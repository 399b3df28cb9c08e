"""A small TOML writer for the documents scenarios are made of (tables, arrays of tables, strings, numbers, booleans).

Floats are written with repr(), which round-trips exactly, so a scenario written here loads to the same numbers.
"""

from __future__ import annotations

import json
import math
import re

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else _string(k)


def _string(s: str) -> str:
    # JSON's escapes are valid TOML basic-string escapes; TOML also forbids DEL and other control characters raw
    out = json.dumps(s, ensure_ascii=False)
    return re.sub(r"[\x7f\x80-\x9f]", lambda m: f"\\u{ord(m.group()):04x}", out)


def value(v) -> str:
    """One TOML value (a string, number, boolean or list of them) as text, for a line written by hand."""
    return _value(v)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write a {type(v).__name__} as TOML")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def dumps(doc: dict) -> str:
    """The TOML text of a document (a dict as tomllib gives it)."""
    lines: list[str] = []
    _table(doc, [], lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _table(t: dict, path: list[str], lines: list[str]) -> None:
    for k, v in t.items():
        if not isinstance(v, dict) and not _is_table_array(v):
            lines.append(f"{_key(k)} = {_value(v)}")
    for k, v in t.items():
        if isinstance(v, dict):
            p = path + [_key(k)]
            lines.append("")
            lines.append("[" + ".".join(p) + "]")
            _table(v, p, lines)
    for k, v in t.items():
        if _is_table_array(v):
            p = path + [_key(k)]
            for item in v:
                lines.append("")
                lines.append("[[" + ".".join(p) + "]]")
                _table(item, p, lines)
