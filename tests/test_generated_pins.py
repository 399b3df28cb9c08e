"""The generated code of the shipped scenarios is pinned by its sha256: a change of the generated C or Python (or of
the trajectory and manifest shipped with it) is a deliberate act, not a side effect of moving code around.

After an intended change of the generated code, rewrite the pins with `python -m tests.test_generated_pins --write`
and say in the commit why the code changed.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import pytest

PINS = Path(__file__).parent / "data" / "generated_sha256.json"
ROOT = Path(__file__).resolve().parent.parent
#: (scenario, language, codegen options) whose files are pinned
CASES = [("paper", "c", {}), ("paper", "python", {}), ("paper", "c", {"prefix": "arm_", "rate_hz": 2000.0}),
         ("arm7", "c", {}), ("arm7", "python", {}),
         ("derivations/ppc_log_rbf.toml", "c", {}), ("derivations/ppc_log_rbf.toml", "python", {})]


def _key(scenario: str, lang: str, options: dict) -> str:
    return f"{Path(scenario).stem}/{lang}" + "".join(f"/{k}={v}" for k, v in sorted(options.items()))


def _hashes(scenario: str, lang: str, options: dict) -> dict[str, str]:
    import symfunnel as sf
    path = str(ROOT / scenario) if scenario.endswith(".toml") else scenario
    files = sf.codegen(path, lang, **options).files
    return {name: hashlib.sha256(text.encode("utf-8")).hexdigest() for name, text in sorted(files.items())}


@pytest.mark.parametrize("scenario, lang, options", CASES, ids=[_key(*c) for c in CASES])
def test_generated_files_are_the_pinned_bytes(scenario, lang, options):
    pinned = json.loads(PINS.read_text(encoding="utf-8"))[_key(scenario, lang, options)]
    got = _hashes(scenario, lang, options)
    changed = sorted(n for n in set(pinned) | set(got) if pinned.get(n) != got.get(n))
    assert not changed, f"generated files changed: {changed} (if intended: python -m tests.test_generated_pins --write)"


if __name__ == "__main__" and "--write" in sys.argv:
    PINS.write_text(json.dumps({_key(*c): _hashes(*c) for c in CASES}, indent=1, sort_keys=True) + "\n",
                    encoding="utf-8")
    print(f"wrote {PINS}")
