"""A report as data (sections of text, tables and figures) and its two renderings, Markdown and HTML.

The numbers are built once into a Document; `to_markdown` and `to_html` only lay it out, so the
two files always say the same thing. Figures are PNG files referenced by relative path.
"""
from __future__ import annotations

import html
import re
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Table:
    columns: list[str]
    rows: list[list[str]]


@dataclass
class Figure:
    path: Path          # relative to the report file
    caption: str


@dataclass
class Section:
    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)


@dataclass
class Document:
    title: str
    sections: list[Section] = field(default_factory=list)


def fmt(value, digits: int = 3) -> str:
    """A table cell: numbers to `digits` significant figures, None as a dash."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def to_markdown(doc: Document) -> str:
    lines = [f"# {doc.title}", ""]
    for section in doc.sections:
        lines += [f"## {section.title}", ""]
        for paragraph in section.paragraphs:
            lines += [paragraph, ""]
        for table in section.tables:
            lines.append("| " + " | ".join(table.columns) + " |")
            lines.append("|" + "|".join(" --- " for _ in table.columns) + "|")
            lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in table.rows]
            lines.append("")
        for figure in section.figures:
            lines += [f"![{figure.caption}]({figure.path.as_posix()})", "", f"*{figure.caption}*", ""]
    return "\n".join(lines)


_STYLE = """
body { font-family: sans-serif; max-width: 1300px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { border: 1px solid #bbb; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #eee; }
figure { margin: 1em 0; }
img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-style: italic; color: #555; }
"""


def to_html(doc: Document) -> str:
    e = html.escape
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(doc.title)}</title>",
             f"<style>{_STYLE}</style></head><body><h1>{e(doc.title)}</h1>"]
    for section in doc.sections:
        parts.append(f"<section><h2>{e(section.title)}</h2>")
        # the Markdown's one emphasis, **bold**, as HTML's (the verdict): not a literal **PASS**
        parts += ["<p>" + re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", e(p)) + "</p>" for p in section.paragraphs]
        for table in section.tables:
            parts.append("<table><tr>" + "".join(f"<th>{e(c)}</th>" for c in table.columns) + "</tr>")
            parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in table.rows]
            parts.append("</table>")
        for figure in section.figures:
            parts.append(f"<figure><img src='{e(figure.path.as_posix())}' alt='{e(figure.caption)}'>"
                         f"<figcaption>{e(figure.caption)}</figcaption></figure>")
        parts.append("</section>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write(doc: Document, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """<out_dir>/<stem>.md and <stem>.html."""
    md, page = out_dir / f"{stem}.md", out_dir / f"{stem}.html"
    md.write_text(to_markdown(doc))
    page.write_text(to_html(doc))
    return md, page
