"""Whether two builds give the same `--json` outputs: a recursive diff that ignores keys holding time (a key containing
"seconds", "cpu" or "wall"), for comparing `certify` / `rate --certify` before and after a change meant to keep
every result.

    python benchmarks/json_diff.py OLD_DIR NEW_DIR NAME...      # compares OLD_DIR/NAME.json with NEW_DIR/NAME.json

Exit 0 when every pair is identical, 1 otherwise (the first ten differences of each pair are printed).
"""

from __future__ import annotations

import json
import sys

SKIP = ("seconds", "cpu", "wall")


def diff(a, b, path: str = "$", out: list | None = None) -> list[str]:
    """The paths where a and b differ (NaN equals NaN), timing keys left out."""
    out = [] if out is None else out
    if isinstance(a, dict) and isinstance(b, dict):
        ka = {k for k in a if not any(s in k.lower() for s in SKIP)}
        kb = {k for k in b if not any(s in k.lower() for s in SKIP)}
        for k in sorted(ka ^ kb):
            out.append(f"{path}.{k}: only in {'old' if k in ka else 'new'}")
        for k in sorted(ka & kb):
            diff(a[k], b[k], f"{path}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b)):
            diff(x, y, f"{path}[{i}]", out)
    elif a != b and not (a != a and b != b):
        out.append(f"{path}: {str(a)[:120]!r} != {str(b)[:120]!r}")
    return out


def main(argv: list[str]) -> int:
    old, new, *names = argv
    bad = 0
    for name in names:
        try:
            with open(f"{old}/{name}.json", encoding="utf-8") as fa, open(f"{new}/{name}.json", encoding="utf-8") as fb:
                a, b = json.load(fa), json.load(fb)
        except (OSError, ValueError) as exc:
            print(f"{name}: cannot read ({exc})")
            bad += 1
            continue
        d = diff(a, b)
        print(f"{name}: {'identical' if not d else f'{len(d)} differences'}")
        for line in d[:10]:
            print("   ", line)
        bad += bool(d)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
