"""codegen against hostile titles and output directories: the module imports, renames stay on one file system."""

from __future__ import annotations

import errno
import importlib.util
import os
from pathlib import Path

from tests.conftest import PAPER


def test_control_characters_in_title_give_an_importable_module(tmp_path):
    from symfunnel.emit import BASENAME, write_output
    from symfunnel.scenario import load_scenario
    title = 'a\u0000b\u001b[31m\r\\x """ \u2028 \u00e9'
    text = PAPER.read_text(encoding="utf-8")
    start = text.index("\ntitle = ") + 1
    end = text.index("\n", start)
    esc = title.replace("\\", "\\\\").replace('"', '\\"').replace("\u0000", "\\u0000").replace(
        "\u001b", "\\u001b").replace("\r", "\\r").replace("\u2028", "\\u2028")
    p = tmp_path / "t.toml"
    p.write_text(text[:start] + f'title = "{esc}"' + text[end:], encoding="utf-8")
    sc = load_scenario(p)
    assert sc.title == title
    from symfunnel.pipeline import Run, RunOptions
    files = Run(sc, RunOptions(t_final=0.5)).code("python")
    write_output(files, tmp_path / "out")
    spec = importlib.util.spec_from_file_location("gen_ctl", tmp_path / "out" / (BASENAME + ".py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert title in mod.__doc__                                  # escaped in the source, exact once imported
    assert "\u0000" not in (tmp_path / "out" / (BASENAME + ".py")).read_text(encoding="utf-8")


def test_existing_out_directory_on_another_file_system(tmp_path, monkeypatch):
    """Renames must stay inside the destination: a rename from its parent fails across a mount point (EXDEV)."""
    from symfunnel.emit import write_output
    out = tmp_path / "mnt"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    real_rename, real_replace = os.rename, os.replace

    def guarded(real):
        def f(src, dst, *a, **k):
            s, d = Path(src).absolute(), Path(dst).absolute()
            inside = (s == out or out in s.parents) == (d == out or out in d.parents)
            if not inside:
                raise OSError(errno.EXDEV, "Invalid cross-device link")
            return real(src, dst, *a, **k)
        return f
    monkeypatch.setattr(os, "rename", guarded(real_rename))
    monkeypatch.setattr(os, "replace", guarded(real_replace))
    paths = write_output({"a.txt": "1\n", "b.txt": "2\n"}, out)
    assert [p.read_text() for p in paths] == ["1\n", "2\n"]
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "b.txt", "keep.txt"]   # no temporary left
    new = tmp_path / "fresh"
    write_output({"a.txt": "3\n"}, new)                            # a missing directory is renamed into place
    assert (new / "a.txt").read_text() == "3\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh", "mnt"]
