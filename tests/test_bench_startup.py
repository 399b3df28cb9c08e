"""The start-up bench's baseline switch: SYMFUNNEL_EAGER_IMPORTS=1 makes the CLI import EAGER_IMPORTS first; without
it `--version` imports none of them (the figure `startup.version_cpu_s` compares)."""

import json
import os
import subprocess
import sys

from symfunnel.bench import startup

CODE = ("import sys\nfrom symfunnel.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass\n"
        "print('LOADED', ' '.join(m for m in sys.argv[1].split(',') if m in sys.modules))\n")


def _loaded(eager: bool) -> list[str]:
    """The EAGER_IMPORTS modules loaded after `main(['--version'])` in a fresh process."""
    env = {k: v for k, v in os.environ.items() if k != startup.ENV}
    if eager:
        env[startup.ENV] = "1"
    out = subprocess.run([sys.executable, "-c", CODE, ",".join(startup.EAGER_IMPORTS)], env=env,
                         capture_output=True, text=True, check=True).stdout
    return out.split("LOADED", 1)[1].split()


def test_eager_switch_imports_the_baselines_modules_and_only_then():
    assert _loaded(False) == []
    assert _loaded(True) == list(startup.EAGER_IMPORTS)


def test_area_reports_both_figures_in_the_contract_form(monkeypatch):
    monkeypatch.setattr(startup, "ROUNDS", 1)
    monkeypatch.setattr(startup, "COMMANDS", {"startup.version_cpu_s": ["--version"]})
    [r] = startup.run(lambda s: None)
    json.dumps(r)
    assert r["id"] == "startup.version_cpu_s" and r["unit"] == "CPU-s" and startup.ENV in r["baseline"]
    assert r["value"] > 0 and r["baseline_value"] > 0 and len(r["runs"]) == len(r["baseline_runs"]) == 1
    assert abs(r["ratio"] - r["baseline_value"] / r["value"]) < 1e-12
