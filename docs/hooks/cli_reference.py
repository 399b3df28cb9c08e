"""MkDocs hook: the command-line reference (docs/cli.md) rendered from symfunnel's own argument parser.

docs/cli.md holds the marker `<!-- cli-reference -->`; this hook replaces it with every subcommand of
`symfunnel.cli.build_parser()`: its one-line help, its usage and each option (flags, value, choices, default, help),
so the page cannot drift from the parser. `render()` is also what tests/test_docs.py checks against the parser.
"""

from __future__ import annotations

import argparse
import html
import os
import re

MARKER = "<!-- cli-reference -->"


def _md(text: str) -> str:
    """Help text as Markdown text: HTML-escaped, emphasis characters and table pipes escaped."""
    text = html.escape(" ".join(str(text).split()), quote=False)
    return re.sub(r"([*_\[\]|`])", r"\\\1", text)


def _subparsers(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            return [(name, sp, helps.get(name)) for name, sp in action.choices.items()]
    return []


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None:
        return "{" + ",".join(map(str, action.choices)) + "}"
    metavar = action.metavar or action.dest.upper()
    if action.nargs in ("+", "*"):
        return f"{metavar} ..."
    return str(metavar)


def _option(action: argparse.Action) -> str:
    names = ", ".join(action.option_strings) if action.option_strings else action.dest
    value = _value(action)
    head = f"`{names}{' ' + value if value and action.option_strings else ''}`"
    parts = [_md(action.help % {"default": action.default, "prog": ""}) if action.help else ""]
    if action.option_strings and action.nargs != 0 and action.default not in (None, argparse.SUPPRESS) \
            and "default" not in (action.help or ""):
        parts.append(f"(default: `{action.default}`)")
    if action.required and action.option_strings:
        parts.append("(required)")
    return f"| {head} | {' '.join(p for p in parts if p)} |"


def render() -> str:
    """Markdown for every subcommand of `symfunnel`, in the parser's order."""
    from symfunnel.cli import build_parser
    os.environ.setdefault("COLUMNS", "100")
    parser = build_parser()
    out = [f"`symfunnel --version` prints the version; `symfunnel COMMAND --help` prints what follows for one "
           f"command.", ""]
    for name, sp, summary in _subparsers(parser):
        out += [f"## `symfunnel {name}`", ""]
        if summary:
            out += [_md(summary), ""]
        if sp.description and sp.description != summary:
            out += [_md(sp.description), ""]
        usage = sp.format_usage().strip()
        out += ["```text", usage, "```", ""]
        rows = [_option(a) for a in sp._actions if a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction)]
        if rows:
            out += ["| option | meaning |", "|---|---|", *rows, ""]
    return "\n".join(out)


def on_page_markdown(markdown, page, config, files):  # noqa: ARG001 (MkDocs' hook signature)
    if MARKER in markdown:
        return markdown.replace(MARKER, render())
    return markdown
