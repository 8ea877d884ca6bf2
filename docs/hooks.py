"""mkdocs hooks: the command line's own --help text, and the changelog, put into the pages at build time.

``<!-- cli-help: register -->`` in a page becomes ``logdesc-rt register --help``'s output, so the
CLI reference cannot drift from the parser. ``<!-- include: CHANGELOG.md -->`` becomes that file
of the repository root.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HELP = re.compile(r"<!-- cli-help:\s*([\w-]*)\s*-->")
INCLUDE = re.compile(r"<!-- include:\s*([\w./-]+)\s*-->")


def _help(command: str) -> str:
    from logdesc_rt.tools.cli import build_parser

    os.environ["COLUMNS"] = "100"
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.suppress(SystemExit):
        build_parser().parse_args([command, "--help"] if command else ["--help"])
    return "```text\n" + buffer.getvalue().rstrip() + "\n```"


def on_page_markdown(markdown, page, config, files):
    markdown = HELP.sub(lambda match: _help(match.group(1)), markdown)
    return INCLUDE.sub(lambda match: (ROOT / match.group(1)).read_text(), markdown)
