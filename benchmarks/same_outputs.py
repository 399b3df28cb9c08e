"""Are two builds' outputs the same? Compares files of the same name in two directories, what a speed change must
leave unchanged: a report's HTML with its timings and timestamps masked, JSON with its seconds removed, anything
else (a tuned TOML) byte for byte.

    python benchmarks/same_outputs.py BEFORE_DIR AFTER_DIR [NAME ...]     # exit 0: all the same; 1: a difference

Masked in HTML: the timings table's values ("1.23 s"), the "generated" timestamp, wall time and real-time factor of
the simulation summary, the certificates' seconds (their total and the table's "time [s]" column), the generated
code check's seconds. Removed from JSON: every key containing "seconds", "cpu" or "wall", and "realtime_factor",
"timings", "elapsed*". Each difference is printed with its first differing lines.
"""

from __future__ import annotations

import difflib
import json
import re
import sys
from pathlib import Path

#: JSON keys holding a time: any containing "seconds", "cpu" or "wall", and these
_TIME_KEYS = re.compile(r"^(realtime_factor|timings|elapsed.*)$")
_HTML_MASKS = [
    (re.compile(r"\d+(\.\d+)? s</td>"), "# s</td>"),                                  # the timings table
    (re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC"), "#DATE#"),                            # generated at
    (re.compile(r"wall time</t[dh]>\s*<td>[^<]*"), "wall time</td><td>#"),               # simulation summary
    (re.compile(r"real-time factor [^)]*\)"), "real-time factor #)"),
    (re.compile(r"\d+(\.\d+)? s in all"), "# s in all"),                              # the certificates' total
    (re.compile(r"points \(\d+(\.\d+)? s\)"), "points (# s)"),                          # the code check's seconds
]
#: the certificates table's "time [s]" column (after "boxes", before "undecided fraction")
_CERT_TIME = re.compile(r'(<td class="num">[^<]*</td><td class="num">)\d+(\.\d+)?(</td><td class="num">[^<]*</td>\s*<td>)')


def _timing(key) -> bool:
    """Whether a JSON key holds a time (removed before comparing)."""
    k = str(key)
    return any(s in k.lower() for s in ("seconds", "cpu", "wall")) or bool(_TIME_KEYS.match(k))


def _strip(x):
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if not _timing(k)}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def normalised(path: Path) -> str:
    """The file's text as compared: HTML masked, JSON without its timings (sorted, indented), else as it is."""
    text = path.read_text(encoding="utf-8", errors="replace")
    if path.suffix in (".html", ".htm"):
        for rx, sub in _HTML_MASKS:
            text = rx.sub(sub, text)
        a = text.find('<section id="certificates">')
        if a >= 0:
            b = text.find("</section>", a)
            text = text[:a] + _CERT_TIME.sub(r"\1#\3", text[a:b]) + text[b:]
        return text
    if path.suffix == ".json" or path.suffix == ".out":
        try:
            return json.dumps(_strip(json.loads(text)), indent=1, sort_keys=True)
        except ValueError:
            return text
    return text


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    a, b, *names = argv
    a, b = Path(a), Path(b)
    names = names or sorted(p.name for p in a.iterdir() if p.is_file())
    differ = 0
    for name in names:
        pa, pb = a / name, b / name
        if not pb.exists():
            print(f"{name}: missing in {b}")
            differ += 1
            continue
        ta, tb = normalised(pa), normalised(pb)
        if ta == tb:
            print(f"{name}: same ({len(ta)} characters compared)")
            continue
        differ += 1
        diff = list(difflib.unified_diff(ta.splitlines(), tb.splitlines(), str(pa), str(pb), n=0, lineterm=""))
        print(f"{name}: DIFFERENT ({len(diff)} diff lines)")
        for line in diff[:12]:
            print("   ", line[:200])
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
