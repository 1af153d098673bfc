"""MkDocs hooks of rotcal's documentation site (mkdocs.yml ``hooks``).

- The site's home page is the README: one text for the repository's front
  page and the site's, its links to ``docs/PAGE.md`` turned into the site's.
- The command-line reference is generated from the typer app by typer's own
  Markdown generator (what ``typer rotcal.cli utils docs`` prints), in this
  process: no ``typer`` executable on the PATH is needed.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File, Files

README = Path(__file__).resolve().parents[1] / "README.md"
CLI_MARKER = "<!-- rotcal: cli reference -->"


def site_home(readme: str) -> str:
    """The README as the site's ``index.md``: ``docs/`` links made relative to
    the site, links to files outside ``docs/`` (LICENSE) left as plain text."""
    text = re.sub(r"\]\(docs/", "](", readme)
    return re.sub(r"\[([^\]]+)\]\(([^)#:]+)\)", _outside, text)


def _outside(match: re.Match[str]) -> str:
    return match.group(0) if match.group(2).endswith(".md") else f"`{match.group(1)}`"


def cli_reference() -> str:
    """Every command's usage, arguments and options, as Markdown."""
    import typer
    import typer.main
    from typer.cli import get_docs_for_click

    from rotcal.cli import app

    command = typer.main.get_command(app)
    text = get_docs_for_click(obj=command, ctx=typer.Context(command), name="rotcal", indent=1)
    # the generator's Markdown carries rich's escapes of [table] names
    return text.replace("\\[", "[")


def on_files(files: Files, config) -> Files:
    files.append(File.generated(config, "index.md", content=site_home(README.read_text(encoding="utf-8"))))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    if CLI_MARKER in markdown:
        return markdown.replace(CLI_MARKER, cli_reference())
    return markdown
