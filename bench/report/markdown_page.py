"""A Markdown report as an HTML page beside it (the campaign reports, written as Markdown): the same
text, tables and pictures, with the run reports' style. markdown-it-py (CommonMark with its table
rule) is already installed as rich's Markdown renderer."""
from __future__ import annotations

import html
from pathlib import Path

from markdown_it import MarkdownIt

from bench.report.document import _STYLE


def write_html_beside(md_path: Path) -> Path:
    """<stem>.html beside <stem>.md: the Markdown rendered; image paths stay relative."""
    md_path = Path(md_path)
    text = md_path.read_text()
    title = next((line[2:].strip() for line in text.splitlines() if line.startswith("# ")), md_path.stem)
    body = MarkdownIt("commonmark", {"html": False}).enable("table").render(text)
    page = md_path.with_suffix(".html")
    page.write_text(f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
                    f"<style>{_STYLE}</style></head><body>\n{body}</body></html>\n")
    return page
