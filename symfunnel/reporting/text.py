"""Numbers, places and check details as short, escaped HTML text for the report's tables."""

from __future__ import annotations

import html as _html
import re

import numpy as np

# --- small helpers ---------------------------------------------------------------------------------

def fmt(x, digits: int = 4) -> str:
    if x is None:
        return "—"
    if isinstance(x, (list, tuple, np.ndarray)):
        return "[" + ", ".join(fmt(v, digits) for v in np.ravel(x)) + "]"
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.{digits}g}"
    return str(x)


def where_text(w) -> str:
    if not w:
        return ""
    parts = []
    for k, v in w.items():
        if k in ("q", "dq", "e1") and isinstance(v, (list, tuple)):
            parts.append(f"{k} = {fmt(v)}")
        elif k == "t":
            parts.append(f"t = {fmt(v)} s")
        else:
            parts.append(f"{k} {fmt(v)}")
    return ", ".join(parts)


_MATRIX = re.compile(r"Matrix\(\[")


def detail_html(text) -> str:
    """A check's detail as HTML: plain text escaped, and each `Matrix([[a, b], [c, d]])` (sympy's str of a matrix)
    shown as a small table of its entries instead of raw text. The text is split by brackets, never evaluated."""
    from markupsafe import Markup
    text = "" if text is None else str(text)
    out, pos = [], 0
    for m in _MATRIX.finditer(text):
        if m.start() < pos:
            continue
        rows, end = matrix_rows(text, m.end() - 1)
        if rows is None:
            continue
        out.append(_html.escape(text[pos:m.start()]))
        cells = "".join("<tr>" + "".join(f"<td><code>{_html.escape(c)}</code></td>" for c in r) + "</tr>"
                        for r in rows)
        out.append(f'<table class="matrix">{cells}</table>')
        pos = end
    out.append(_html.escape(text[pos:]))
    return Markup("".join(out))


def split_top(s: str) -> list[str]:
    """s split at the commas outside any brackets."""
    parts, depth, cur = [], 0, []
    for ch in s:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur).strip())
    return parts


def matrix_rows(text: str, start: int):
    """The rows of the bracketed list at text[start] ('[' of 'Matrix([...])') and the end of ')'; (None, 0) if it is
    not a well-formed matrix literal."""
    depth = 0
    for i in range(start, len(text)):
        ch = text[i]
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
            if depth == 0:
                if not text.startswith(")", i + 1):
                    return None, 0
                inner = text[start + 1:i].strip()
                rows = []
                for r in split_top(inner):
                    if not (r.startswith("[") and r.endswith("]")):
                        return None, 0
                    rows.append(split_top(r[1:-1]))
                return rows, i + 2
    return None, 0


def flatten(d, prefix: str = "") -> list[tuple[str, str]]:
    out = []
    if isinstance(d, dict):
        for k, v in d.items():
            out.extend(flatten(v, f"{prefix}{k}." if not isinstance(v, dict) else f"{prefix}{k}."))
        return [(k.rstrip("."), v) for k, v in out]
    return [(prefix, fmt(d) if not isinstance(d, str) else d)]
