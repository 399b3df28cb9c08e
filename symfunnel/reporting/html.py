"""The report as HTML: the Jinja2 template rendered with the sections' data (autoescape on), and the check that the
page references nothing on the network."""

from __future__ import annotations

import html as _html
import re
from pathlib import Path

from .text import detail_html, fmt


def environment():
    """The Jinja2 environment (autoescape on) reading symfunnel/reporting/templates."""
    import jinja2
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(Path(__file__).parent / "templates")),
                             autoescape=jinja2.select_autoescape(["html", "j2"], default=True),
                             trim_blocks=True, lstrip_blocks=True, undefined=jinja2.StrictUndefined)
    env.filters["fmt"] = fmt
    env.filters["detail"] = detail_html
    from ..simulation.hints import status_text
    env.filters["status_words"] = status_text       # a run's status in words ('initial_outside' is JSON's)
    return env


def render(context: dict) -> str:
    """Render the report template with a context."""
    return environment().get_template("report.html.j2").render(**context)


def escape(s: str) -> str:
    """HTML-escape plain text."""
    return _html.escape(s)


def no_network_references(text: str) -> list[str]:
    """http(s) references in src/href/xlink:href/url()/@import of an HTML text (namespace declarations excluded)."""
    bad = []
    for m in re.finditer(r'\b(?:src|href|xlink:href|action|poster|data|srcset|background)\s*=\s*["\']?\s*(https?:[^"\'\s>]*)',
                         text, flags=re.I):
        bad.append(m.group(0))
    for m in re.finditer(r"url\(\s*['\"]?\s*(https?:[^)'\"]*)", text, flags=re.I):
        bad.append(m.group(0))
    for m in re.finditer(r"@import\s+['\"]?https?:", text, flags=re.I):
        bad.append(m.group(0))
    return bad
