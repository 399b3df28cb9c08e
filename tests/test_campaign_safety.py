"""Campaigns that cannot mix: the fingerprint covers every input file, one sweep per directory (a lock), a resume
without its record is refused, damaged files are named, bad scheduler addresses are one line (issue 21, rows 1-3,
12, 13)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from symfunnel.cli import main
from symfunnel.core.toml_write import dumps
from symfunnel.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def _urdf_campaign(tmp_path, runs=4) -> Path:
    """A sweep over a URDF robot (a 2-joint chain, its scenario from `symfunnel init`): the robot is the URDF."""
    import tomllib

    from tests.test_signals import _chain_urdf
    (tmp_path / "robot.urdf").write_text(_chain_urdf(2))
    s = tmp_path / "s.toml"
    if not s.exists():
        assert main(["init", "--urdf", str(tmp_path / "robot.urdf"), "--out", str(s), "-q"]) == 0
    raw = tomllib.loads(s.read_text())
    raw["simulation"] = {**raw.get("simulation", {}), "t_final": 0.2}
    raw["uncertainty"] = [{"key": "plant.mass_scale", "dist": "uniform", "low": 0.9, "high": 1.1}]
    raw["sweep"] = {"runs": runs, "t_final": 0.2}
    s.write_text(dumps(raw), encoding="utf-8")
    return s


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def test_the_fingerprint_covers_the_urdf_and_the_version(tmp_path, monkeypatch):
    from symfunnel.campaigns.campaign import make_job
    s = _urdf_campaign(tmp_path)
    a = make_job(load_scenario(s))
    assert dict(a.files) and all(len(d) == 64 for d in dict(a.files).values())
    urdf = tmp_path / "robot.urdf"
    text = urdf.read_text()
    i = text.index('<mass value="')
    j = text.index('"', i + len('<mass value="'))
    urdf.write_text(text[:i] + '<mass value="7.5' + text[j:])        # one mass, the TOML untouched
    b = make_job(load_scenario(s))
    assert a.fingerprint != b.fingerprint
    urdf.write_text(text)
    assert make_job(load_scenario(s)).fingerprint == a.fingerprint     # the same content: the same campaign
    import symfunnel.core.version as version
    monkeypatch.setattr(version, "__version__", version.__version__ + "-other")
    assert make_job(load_scenario(s)).fingerprint != a.fingerprint


def test_resume_after_the_urdf_changed_is_another_campaign(tmp_path, capsys):
    """Row 1: the mass changed between the interrupted sweep and --resume; the rows would mix two robots."""
    s = _urdf_campaign(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    (out / "summary.json").unlink()                                   # as if it had been stopped
    urdf = tmp_path / "robot.urdf"
    text = urdf.read_text()
    i = text.index('<mass value="') + len('<mass value="')
    urdf.write_text(text[:i] + "3" + text[i:])
    rows = (out / "results.parquet").read_bytes()
    assert main(["sweep", str(s), "--out", str(out), "--resume", "-q"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "a different campaign" in err[0] and "robot.urdf changed" in err[0], err
    assert (out / "results.parquet").read_bytes() == rows             # nothing touched


def test_a_worker_that_reads_another_urdf_refuses(tmp_path):
    from symfunnel.campaigns.campaign import make_job, run_chunk
    from symfunnel.core.errors import InputError
    s = _urdf_campaign(tmp_path)
    job = make_job(load_scenario(s))
    urdf = tmp_path / "robot.urdf"
    urdf.write_text(urdf.read_text().replace("<robot", "<!-- edited -->\n<robot", 1))
    with pytest.raises(InputError, match="changed while the campaign ran"):
        run_chunk(job, [0])


def test_resume_without_campaign_json_is_refused(tmp_path, capsys):
    """Row 3: campaign.json deleted, --resume with other settings: '300 runs on disk, 10 to go', exit 0."""
    s = _urdf_campaign(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    (out / "campaign.json").unlink()
    assert main(["sweep", str(s), "--out", str(out), "--resume", "--runs", "6", "-q"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "no campaign.json" in err[0] and str(out) in err[0], err


@pytest.mark.parametrize("name, content, needle", [
    ("campaign.json", "[1,2", "campaign.json"),
    ("campaign.json", "[1, 2]", "no fingerprint"),
    ("results.parquet", None, "results.parquet"),
])
def test_damaged_files_of_a_sweep_directory_exit_2_naming_the_file(tmp_path, capsys, name, content, needle):
    """Row 12 (resume)."""
    s = _urdf_campaign(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    f = out / name
    if content is None:
        f.write_bytes(f.read_bytes()[:200])                     # truncated
    else:
        f.write_text(content)
    assert main(["sweep", str(s), "--out", str(out), "--resume", "-q"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and err[0].startswith("symfunnel: error: ") and needle in err[0], err


@pytest.mark.parametrize("name, content", [("summary.json", '{"runs": "x"}'), ("summary.json", "[1,2"),
                                           ("results.parquet", None), ("summary.json", '{"runs": 3}')])
def test_report_sweep_on_damaged_files_exits_2_naming_the_file(tmp_path, capsys, name, content):
    """Row 12 (report --sweep): exit 3 on main."""
    s = _urdf_campaign(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    f = out / name
    if content is None:
        f.write_bytes(f.read_bytes()[:200])
    else:
        f.write_text(content)
    assert main(["report", "--sweep", str(out), "-q"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and name in err[0], err
    assert not (out / "sweep.html").exists()


def test_a_second_sweep_into_the_same_directory_is_refused(tmp_path, capsys):
    """Row 2: two sweeps with the same --out at once: campaign.json of one, rows of the other."""
    from symfunnel.core.io import exclusive_lock
    out = tmp_path / "out"
    s = _urdf_campaign(tmp_path)
    prog = (f"import time\nfrom symfunnel.core.io import exclusive_lock\n"
            f"with exclusive_lock({str(out)!r}, what='sweep'):\n    print('held', flush=True)\n    time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", prog], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["sweep", str(s), "--out", str(out), "-q"]) == 2
        err = _err(capsys)
        assert len(err) == 1 and "in use by another sweep" in err[0] and f"process {holder.pid}" in err[0], err
        assert sorted(p.name for p in out.iterdir()) == [".lock"]         # nothing of the refused sweep
    finally:
        holder.kill()
        holder.wait()
    # the holder died (however): the lock is free again, and this sweep's lock file goes when it ends
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    assert not (out / ".lock").exists()
    with exclusive_lock(out, what="sweep"):
        with pytest.raises(Exception, match="in use by another sweep"):
            with exclusive_lock(out, what="sweep"):
                pass


@pytest.mark.parametrize("address, needle", [
    ("http://127.0.0.1:8786", "tcp://HOST:PORT"),
    ("tls://127.0.0.1:1", "certificates"),
    ("tcp://127.0.0.1:1", "cannot reach the scheduler"),
    ("tcp://127.0.0.1", "tcp://HOST:PORT"),
])
def test_bad_scheduler_addresses_are_one_line_at_once(tmp_path, address, needle):
    """Row 13: http:// hung 20 s and printed a traceback from Client.__del__; tls:// exited 3."""
    s = _urdf_campaign(tmp_path)
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "symfunnel", "sweep", str(s), "--scheduler", address, "--out",
                        str(tmp_path / "o"), "-q"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, lines
    assert time.monotonic() - t0 < 30


def test_summary_json_written_last_names_the_fingerprint(tmp_path):
    s = _urdf_campaign(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(s), "--out", str(out), "--workers", "1", "-q"]) == 0
    meta = json.loads((out / "campaign.json").read_text())
    assert str((tmp_path / "robot.urdf").resolve()) in meta["files"]
