"""The suite's own helpers that make it cheaper must not change what it checks: `cli_once` runs a command once per
session and gives every later caller the first run's exit code and output, `main_once` the same for the command run in
the process (what the subprocess would have said), `text_once` the same for a text built in the process (a report); test_docs runs a documentation command
line once for all pages only when no file of its directory is read or written."""

from __future__ import annotations

import sys

import pytest

from tests import conftest
from tests.conftest import cli_once, main_once, module_order, text_once
from tests.test_docs import _anywhere


def test_cli_once_runs_a_command_once_and_replays_its_result(tmp_path_factory, monkeypatch):
    args = ("derive", f"--suite-helpers-{id(tmp_path_factory)}")      # a key no other test uses; a usage error
    first = cli_once(tmp_path_factory, *args)
    assert first.returncode == 2 and "--suite-helpers-" in first.stderr
    assert first.args == [sys.executable, "-m", "symfunnel", *args]

    def no_second_run(*a, **k):
        raise AssertionError("cli_once ran the command again")
    monkeypatch.setattr(conftest.subprocess, "run", no_second_run)
    again = cli_once(tmp_path_factory, *args)
    assert (again.returncode, again.stdout, again.stderr) == (first.returncode, first.stdout, first.stderr)
    with pytest.raises(AssertionError, match="ran the command again"):
        cli_once(tmp_path_factory, "derive", f"--another-key-{id(tmp_path_factory)}")


def test_main_once_says_what_the_cli_says_runs_once_and_replays_it(tmp_path_factory, monkeypatch):
    args = ("derive", f"--suite-helpers-main-{id(tmp_path_factory)}")  # a key no other test uses; a usage error
    first = main_once(tmp_path_factory, *args)
    sub = cli_once(tmp_path_factory, *args)                              # the same command as its own process
    assert first.returncode == sub.returncode == 2 and first.args == ["symfunnel", *args]
    assert first.stderr.strip() == sub.stderr.strip() and "--suite-helpers-main-" in first.stderr
    assert first.stdout == sub.stdout

    def no_second_run(argv):
        raise AssertionError("main_once ran the command again")
    import symfunnel.cli
    monkeypatch.setattr(symfunnel.cli, "main", no_second_run)
    again = main_once(tmp_path_factory, *args)
    assert (again.returncode, again.stdout, again.stderr) == (first.returncode, first.stdout, first.stderr)
    with pytest.raises(AssertionError, match="ran the command again"):
        main_once(tmp_path_factory, "derive", f"--another-main-key-{id(tmp_path_factory)}")


def test_text_once_builds_once_per_key_and_a_failed_build_is_tried_again(tmp_path_factory):
    key = f"suite-helpers {id(tmp_path_factory)}"                      # a key no other test uses
    calls = []

    def build(text):
        def b():
            calls.append(text)
            return text
        return b
    assert text_once(tmp_path_factory, key, build("r\u00e9port 1")) == "r\u00e9port 1"
    assert text_once(tmp_path_factory, key, build("report 2")) == "r\u00e9port 1"    # the first build's text
    assert text_once(tmp_path_factory, key + " other", build("report 3")) == "report 3"
    assert calls == ["r\u00e9port 1", "report 3"]

    def fails():
        raise RuntimeError("build failed")
    with pytest.raises(RuntimeError):
        text_once(tmp_path_factory, key + " fails", fails)
    assert text_once(tmp_path_factory, key + " fails", build("report 4")) == "report 4"   # nothing half-written
    assert calls[-1] == "report 4"


def test_only_lines_that_touch_no_file_of_their_directory_run_once(tmp_path):
    (tmp_path / "robot.toml").write_text("", encoding="utf-8")
    (tmp_path / "derivations").mkdir()
    shared = [["symfunnel", "derive"], ["symfunnel", "verify", "--t-final", "0.5"],
              ["symfunnel", "certify", "--only", "input_gain"], ["symfunnel", "rate", "arm7", "--plant", "mujoco"]]
    own = [["symfunnel", "simulate", "robot.toml", "--t-final", "0.5"],          # reads a file of the directory
           ["symfunnel", "audit", "derivations"],                                # names a directory of it
           ["symfunnel", "simulate", "--t-final", "0.5", "--out", "run.npz"],   # writes one
           ["symfunnel", "simulate", "--out=run.npz"],
           ["symfunnel", "derive", "--latex", "signals.tex"],                   # writes one too
           ["symfunnel", "derive", "--eval=robot.toml"],                        # reads one, as --option=value
           ["symfunnel", "init", "--from", "arm7", "--out", "arm7.toml"],       # not a read-only command
           ["symfunnel", "report", "--t-final", "0.5"],                         # writes reports/ by default
           ["symfunnel", "codegen", "--lang", "c", "--rate", "2000"],
           ["symfunnel"]]
    assert [_anywhere(a, tmp_path) for a in shared] == [True] * len(shared)
    assert [_anywhere(a, tmp_path) for a in own] == [False] * len(own)


class _Item:
    """What module_order reads of a pytest item: its node id and its closest `slow` marker."""

    def __init__(self, nodeid, slow=None):
        self.nodeid, self.slow = nodeid, slow

    def get_closest_marker(self, name):
        return pytest.mark.slow(**self.slow).mark if name == "slow" and self.slow is not None else None


def test_a_module_with_a_test_marked_first_starts_the_run_and_modules_stay_whole():
    items = [_Item("a.py::x"), _Item("a.py::y", {}), _Item("b.py::x"), _Item("b.py::y", {"first": True}),
             _Item("c.py::x", {}), _Item("c.py::y", {}), _Item("d.py::x")]
    got = [it.nodeid for it in module_order(items)]
    # b first (its test marked first, its other test kept beside it), then by slow count: c (2), a (1), d (0)
    assert got == ["b.py::x", "b.py::y", "c.py::x", "c.py::y", "a.py::x", "a.py::y", "d.py::x"]
    # without the mark, b is a module with one slow test: after c, in collection order with a
    items[3] = _Item("b.py::y", {})
    assert [it.nodeid for it in module_order(items)] == ["c.py::x", "c.py::y", "a.py::x", "a.py::y", "b.py::x",
                                                         "b.py::y", "d.py::x"]

