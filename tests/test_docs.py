"""The documentation cannot drift from the code: the site builds with warnings as errors (broken links and anchors
included), its command-line reference is the parser's, and every shell and Python example of README.md and
docs/*.md runs.

Examples: a fenced block whose language is `python` is executed (warnings are errors, as from the Python API); one
whose language is `sh`, `bash`, `console` or `shell` has each command line run (`symfunnel ...` through this
environment's command line; any other program is refused, so an example cannot quietly stop being run). The blocks
of one file run in order in one temporary directory (which sees the repository's `derivations/`), so a later block
may use what an earlier one wrote. A block that must not run is preceded, on the line just above its fence, by the
visible marker `<!-- not-run: REASON -->`; there are few of them and each says why.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import REPO, _command_once, cli_once

SHELL = {"sh", "bash", "console", "shell"}
NOT_RUN = re.compile(r"^<!--\s*not-run:\s*(\S.*?)\s*-->$")
FENCE = re.compile(r"^```([A-Za-z0-9_+-]*)\s*$")
#: at most this many examples may be marked not-run (each says why)
MAX_NOT_RUN = 6


@dataclass
class Block:
    path: Path
    line: int            # of the opening fence, 1-based
    lang: str
    code: str
    not_run: str | None  # the marker's reason


def doc_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def blocks(path: Path) -> list[Block]:
    """The fenced code blocks of a Markdown file, with the not-run marker of each."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, body = i, []
        i += 1
        while i < len(lines) and lines[i].rstrip() != "```":
            body.append(lines[i])
            i += 1
        assert i < len(lines), f"{path.name}:{start + 1}: unclosed code fence"
        prev = next((ln.strip() for ln in reversed(lines[:start]) if ln.strip()), "")
        marker = NOT_RUN.match(prev)
        out.append(Block(path, start + 1, m.group(1).lower(), "\n".join(body) + "\n",
                         marker.group(1) if marker else None))
        i += 1
    return out


def examples(path: Path) -> list[Block]:
    return [b for b in blocks(path) if b.lang == "python" or b.lang in SHELL]


def _where(b: Block) -> str:
    return f"{b.path.relative_to(REPO)}:{b.line}"


def _command(line: str) -> list[str] | None:
    """The argv of one shell line (None for a blank or comment line); `$ ` prompts are allowed."""
    line = line.strip()
    if line.startswith("$ "):
        line = line[2:]
    argv = shlex.split(line, comments=True)
    return argv or None


def _symfunnel() -> list[str]:
    exe = shutil.which("symfunnel", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "symfunnel"]


#: commands that read no file of their directory unless named, and write none without one of WRITES
READ_ONLY = {"derive", "audit", "simulate", "verify", "certify", "rate"}
WRITES = ("--out", "--latex", "--figures")


def _anywhere(argv: list[str], cwd: Path) -> bool:
    """Whether the command line gives the same result in any directory: a READ_ONLY command without WRITES that names
    no path of `cwd` (the same line on several pages, e.g. `symfunnel verify --t-final 0.5`, then runs once)."""
    return (len(argv) > 1 and argv[1] in READ_ONLY and not any(a.startswith(WRITES) for a in argv)
            and not any((cwd / a.split("=", 1)[-1]).exists() for a in argv[2:] if not a.startswith("-") or "=" in a))


def _inputs(argv: list[str], cwd: Path) -> dict[str, str] | None:
    """For a READ_ONLY command without WRITES that names files of `cwd` (not `_anywhere`): the files it can read
    there -- the ones it names and, transitively, every file of `cwd` whose relative path the text of one of those
    contains (a scenario's URDF) -- as {relative path: sha256 of the content}; None for any other command line or
    one that names a directory. The same line with the same inputs gives the same result in any directory, so it
    runs once for all files (`init --urdf arm7.urdf --out robot.toml` then `simulate robot.toml` on two pages)."""
    import hashlib
    if len(argv) < 2 or argv[1] not in READ_ONLY or any(a.startswith(WRITES) for a in argv):
        return None
    named = [cwd / a.split("=", 1)[-1] for a in argv[2:] if not a.startswith("-") or "=" in a]
    named = [p for p in named if p.exists() or p.is_symlink()]
    if not named or any(not p.is_file() or p.is_symlink() for p in named):
        return None
    files = {str(f.relative_to(cwd)): f for f in cwd.rglob("*") if f.is_file() and not f.is_symlink()
             and "derivations" not in f.relative_to(cwd).parts[:1]}
    files.update({str(p.relative_to(cwd)): p for p in named})      # derivations/..., through its link
    todo, seen = [str(p.relative_to(cwd)) for p in named], {}
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        data = files[rel].read_bytes()
        seen[rel] = hashlib.sha256(data).hexdigest()
        text = data.decode("utf-8", errors="replace")
        todo += [other for other in files if other not in seen and other in text]
    return dict(sorted(seen.items()))


def run_shell(b: Block, cwd: Path, tmp_path_factory=None) -> None:
    for n, line in enumerate(b.code.splitlines()):
        argv = _command(line)
        if argv is None:
            continue
        assert argv[0] == "symfunnel", (
            f"{_where(b)}: line {n + 1} runs {argv[0]!r}; only `symfunnel ...` lines are run: change the example or "
            f"mark the block <!-- not-run: REASON -->")
        env = dict(os.environ, PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
        inputs = _inputs(argv, cwd) if tmp_path_factory is not None else None
        if tmp_path_factory is not None and _anywhere(argv, cwd):
            proc = cli_once(tmp_path_factory, *argv[1:], timeout=300, cwd=cwd)
        elif inputs is not None:
            def call(argv=argv):
                p = subprocess.run([*_symfunnel(), *argv[1:]], cwd=cwd, capture_output=True, text=True, timeout=300,
                                   env=env)
                return p.returncode, p.stdout, p.stderr
            proc = _command_once(tmp_path_factory, "docs-once", [*argv, inputs], call)
        else:
            proc = subprocess.run([*_symfunnel(), *argv[1:]], cwd=cwd, capture_output=True, text=True, timeout=300,
                                  env=env)
        assert proc.returncode == 0, (
            f"{_where(b)}: `{line.strip()}` exited {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


def run_python(b: Block, cwd: Path) -> None:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            exec(compile(b.code, _where(b), "exec"), {"__name__": "__docs_example__"})
    finally:
        os.chdir(old)


# --- every example runs --------------------------------------------------------------------------------------

#: the files whose examples take more than ~10 s together with a cold compile cache
SLOW = {"README.md", "getting-started.md", "deployed.md", "reports.md", "sweep.md"}


def _file_params():
    for p in doc_files():
        if any(b.not_run is None for b in examples(p)):
            marks = [pytest.mark.slow] if p.name in SLOW else []
            yield pytest.param(p, id=str(p.relative_to(REPO)), marks=marks)


@pytest.mark.parametrize("path", list(_file_params()))
def test_examples_run(path, tmp_path, tmp_path_factory):
    """Each shell and Python example of one file, in order, in one directory that sees `derivations/` (a command line
    that reads and writes nothing there runs once for all files: `_anywhere`)."""
    (tmp_path / "derivations").symlink_to(REPO / "derivations", target_is_directory=True)
    for b in examples(path):
        if b.not_run is not None:
            continue
        if b.lang == "python":
            run_python(b, tmp_path)
        else:
            run_shell(b, tmp_path, tmp_path_factory)


def test_every_example_runs_or_says_why_not():
    """Examples are found in README and every page, and the few that are not run carry a visible reason."""
    found = [b for p in doc_files() for b in examples(p)]
    skipped = [b for b in found if b.not_run is not None]
    assert len(found) - len(skipped) >= 10, "the examples were not found"
    assert len(skipped) <= MAX_NOT_RUN, [f"{_where(b)}: {b.not_run}" for b in skipped]
    stray = [f"{p.relative_to(REPO)}:{i}" for p in doc_files()
             for i, ln in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if "not-run" in ln and not NOT_RUN.match(ln.strip())]
    assert stray == [], f"malformed not-run markers: {stray}"
    for p in doc_files():
        lines = p.read_text(encoding="utf-8").splitlines()
        for i, ln in enumerate(lines):
            if NOT_RUN.match(ln.strip()):
                nxt = next((x for x in lines[i + 1:] if x.strip()), "")
                assert FENCE.match(nxt), f"{p.relative_to(REPO)}:{i + 1}: a not-run marker must stand above a fence"


def test_runner_refuses_other_programs(tmp_path):
    b = Block(REPO / "README.md", 1, "sh", "symfunnel --version\nrm -rf build\n", None)
    with pytest.raises(AssertionError, match="only `symfunnel ...` lines are run"):
        run_shell(b, tmp_path)


def test_a_line_reading_files_of_its_directory_is_keyed_by_their_contents(tmp_path):
    """`_inputs`: the same read-only line on two pages shares its run only when the files it reads (named, and the
    files those name) have the same bytes; a changed URDF, a written output or a named directory keep it apart."""
    pages = []
    for k in range(3):
        d = tmp_path / f"page{k}"
        d.mkdir()
        (d / "robot.toml").write_text('[model]\npath = "arm7.urdf"\n', encoding="utf-8")
        (d / "arm7.urdf").write_text("<robot/>" if k < 2 else "<robot name='other'/>", encoding="utf-8")
        (d / f"unrelated{k}.html").write_text(str(k), encoding="utf-8")       # another example's output
        pages.append(d)
    line = ["symfunnel", "simulate", "robot.toml", "--t-final", "0.5"]
    keys = [_inputs(line, d) for d in pages]
    assert sorted(keys[0]) == ["arm7.urdf", "robot.toml"]          # the URDF the scenario names, not the html
    assert keys[0] == keys[1] and keys[2] != keys[0]
    assert _inputs([*line, "--out", "run.npz"], pages[0]) is None   # writes a file
    assert _inputs(["symfunnel", "init", "--urdf", "arm7.urdf", "--out", "r.toml"], pages[0]) is None
    assert _inputs(["symfunnel", "verify", "--t-final", "0.5"], pages[0]) is None   # names nothing (cli_once's)
    assert _inputs(["symfunnel", "audit", "."], pages[0]) is None   # a directory


def test_block_parser_reads_markers_and_languages(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("text\n\n<!-- not-run: needs a cluster -->\n```sh\ndask scheduler\n```\n\n```python\nx = 1\n```\n"
                  "```toml\n[a]\n```\n", encoding="utf-8")
    got = [(b.lang, b.not_run, b.code) for b in blocks(md)]
    assert got == [("sh", "needs a cluster", "dask scheduler\n"), ("python", None, "x = 1\n"), ("toml", None, "[a]\n")]
    assert [b.lang for b in examples(md)] == ["sh", "python"]


# --- the command-line reference is the parser's --------------------------------------------------------------

def _hook():
    spec = importlib.util.spec_from_file_location("cli_reference", REPO / "docs" / "hooks" / "cli_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cli_reference_renders_every_subcommand_and_option():
    import argparse

    from symfunnel.cli import build_parser
    hook = _hook()
    text = hook.render()
    assert hook.MARKER in (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    for name, sp, _ in hook._subparsers(build_parser()):
        head = f"## `symfunnel {name}`"
        assert head in text, name
        section = text.split(head, 1)[1].split("\n## ", 1)[0]
        for action in sp._actions:
            if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
                continue
            for opt in action.option_strings or [action.dest]:
                assert re.search(rf"^\| `[^`]*(?<![\w-]){re.escape(opt)}(?![\w-])[^`]*` \|", section, re.M), (name, opt)


# --- the site builds with warnings as errors -----------------------------------------------------------------

def test_site_builds_strict(tmp_path):
    """`mkdocs build --strict` (the documented command): no warning, links and anchors between pages checked."""
    for mod in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(mod, reason=f"{mod} not installed (pip install '.[docs]')")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(REPO / "mkdocs.yml"),
                           "-d", str(tmp_path / "site")], capture_output=True, text=True, timeout=300, env=env,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "WARNING" not in proc.stderr, proc.stderr[-4000:]
    cli = (tmp_path / "site" / "cli" / "index.html").read_text(encoding="utf-8")
    assert "symfunnel certify" in cli and "--wall-limit" in cli and "cli-reference" not in cli
    api = (tmp_path / "site" / "api" / "index.html").read_text(encoding="utf-8")
    assert 'id="symfunnel.api.verify"' in api


def test_commands_quoted_in_the_text_use_real_options():
    """Every `symfunnel CMD ... --option` quoted inline in README or a page names an option CMD has (the guide's
    synopses cannot drift from the parser either)."""
    from symfunnel.cli import build_parser
    options = {name: {o for a in sp._actions for o in a.option_strings}
               for name, sp, _ in _hook()._subparsers(build_parser())}
    bad, seen = [], 0
    for p in doc_files():
        text = re.sub(r"^```.*?^```", "", p.read_text(encoding="utf-8"), flags=re.S | re.M)
        for span in re.findall(r"`(symfunnel [^`]+)`", text.replace("\n", " ")):
            words = span.split()
            if len(words) < 2 or words[1] not in options:
                continue
            seen += 1
            for flag in re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", span):
                if flag not in options[words[1]] and flag not in ("-h", "--help"):
                    bad.append(f"{p.relative_to(REPO)}: `{span}`: {flag}")
    assert seen >= 20 and bad == [], bad


def _slug(heading: str) -> str:
    """The anchor MkDocs (Python-Markdown's toc) gives a heading."""
    import unicodedata
    text = re.sub(r"[`*]", "", heading)
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    return re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text).strip().lower())


def test_readme_links_reach_files_and_headings():
    """README is not a page of the site, so its relative links are checked here: the file exists, the heading too."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)\s]+)\)", readme)
    assert len(links) >= 10
    for link in links:
        if re.match(r"[a-z]+://", link):
            continue
        path, _, anchor = link.partition("#")
        target = REPO / path if path else REPO / "README.md"
        assert target.exists(), link
        if anchor:
            text = target.read_text(encoding="utf-8")
            text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
            slugs = {_slug(h) for h in re.findall(r"^#+\s+(.*?)\s*$", text, re.M)}
            assert anchor in slugs, (link, sorted(slugs))


def test_slug_matches_the_site():
    assert _slug("`[design]` and `[approximator]`") == "design-and-approximator"
    assert _slug("`symfunnel bench`: each figure beside its baseline") == "symfunnel-bench-each-figure-beside-its-baseline"


def test_dotted_names_in_the_docs_exist():
    """Every `symfunnel.x.y` the pages and README name is a module or an attribute of one (the changelog, which names
    former places on purpose, aside)."""
    import importlib
    missing, seen = [], 0
    for p in doc_files():
        if p.name == "changelog.md":
            continue
        for name in sorted(set(re.findall(r"\bsymfunnel(?:\.[A-Za-z_]\w*)+", p.read_text(encoding="utf-8")))):
            seen += 1
            parts = name.split(".")
            obj, i = None, len(parts)
            while i > 0:
                try:
                    obj = importlib.import_module(".".join(parts[:i]))
                    break
                except ModuleNotFoundError:
                    i -= 1
            for attr in parts[i:]:
                obj = getattr(obj, attr, None)
            if obj is None:
                missing.append(f"{p.relative_to(REPO)}: {name}")
    assert seen >= 20 and missing == [], missing


def test_repository_paths_in_the_docs_exist():
    """Every file of the repository the pages and README name (`symfunnel/...py`, `tests/...`, `derivations/...`)
    exists (the changelog aside)."""
    pattern = re.compile(r"\b(?:symfunnel|tests|derivations|benchmarks|docs)/[\w/.-]+\.(?:py|toml|md|urdf|json)\b")
    missing, seen = [], 0
    for p in doc_files():
        if p.name == "changelog.md":
            continue
        for path in sorted(set(pattern.findall(p.read_text(encoding="utf-8")))):
            seen += 1
            if not (REPO / path).exists():
                missing.append(f"{p.relative_to(REPO)}: {path}")
    assert seen >= 10 and missing == [], missing
