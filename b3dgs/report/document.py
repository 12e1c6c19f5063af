"""A report as a list of blocks (headings, paragraphs, tables, figures), rendered to Markdown and to a
self-contained HTML page (figures embedded as base64 PNG)."""
from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

__all__ = ["Heading", "Para", "Table", "Figure", "to_markdown", "to_html", "fmt", "markdown_table"]


@dataclass
class Heading:
    text: str
    level: int = 2


@dataclass
class Para:
    text: str


@dataclass
class Table:
    header: list[str]
    rows: list[list[str]]
    caption: str = ""
    note: Optional[str] = None


@dataclass
class Figure:
    path: Path
    caption: str
    alt: str = field(default="")


Block = Union[Heading, Para, Table, Figure]


def fmt(v, spec: str = ".4g", signed: bool = False) -> str:
    """A table cell: numbers formatted with ``spec`` ("—" for missing values)."""
    if v is None:
        return "—"
    if isinstance(v, (int, float)):
        return format(v, ("+" if signed else "") + spec)
    return str(v)


def _md_cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def markdown_table(header, rows) -> list[str]:
    """The lines of one Markdown table: b3dgs's one table writer (the report, the study tables, benchmarks)."""
    return ["| " + " | ".join(map(_md_cell, header)) + " |", "|" + "|".join("---" for _ in header) + "|",
            *["| " + " | ".join(map(_md_cell, r)) + " |" for r in rows]]


def to_markdown(title: str, blocks: list[Block]) -> str:
    out = [f"# {title}", ""]
    for b in blocks:
        if isinstance(b, Heading):
            out += ["#" * b.level + " " + b.text, ""]
        elif isinstance(b, Para):
            out += [b.text, ""]
        elif isinstance(b, Table):
            if b.caption:
                out += [f"**{b.caption}**", ""]
            out += markdown_table(b.header, b.rows)
            out += [""] + ([b.note, ""] if b.note else [])
        elif isinstance(b, Figure):
            out += [f"![{b.alt or b.caption}]({b.path.name})", "", f"*{b.caption}*", ""]
    return "\n".join(out)


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:14px}th,td{border:1px solid #ccc;padding:3px 8px;
text-align:right}th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}caption{font-weight:600;
text-align:left;padding:4px 0}img{max-width:100%;border:1px solid #ddd}figure{margin:1em 0 2em}
figcaption{font-style:italic;font-size:14px}.note{font-size:13px;color:#555}"""


def to_html(title: str, blocks: list[Block]) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{e(title)}</title>",
           f"<style>{CSS}</style></head><body>", f"<h1>{e(title)}</h1>"]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{e(b.text)}</h{b.level}>")
        elif isinstance(b, Para):
            out.append(f"<p>{e(b.text)}</p>")
        elif isinstance(b, Table):
            out.append("<table>" + (f"<caption>{e(b.caption)}</caption>" if b.caption else ""))
            out.append("<thead><tr>" + "".join(f"<th>{e(str(h))}</th>" for h in b.header) + "</tr></thead><tbody>")
            out += ["<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in r) + "</tr>" for r in b.rows]
            out.append("</tbody></table>" + (f'<p class="note">{e(b.note)}</p>' if b.note else ""))
        elif isinstance(b, Figure):
            data = base64.b64encode(Path(b.path).read_bytes()).decode("ascii")
            out.append(f'<figure><img src="data:image/png;base64,{data}" alt="{e(b.alt or b.caption)}">'
                       f"<figcaption>{e(b.caption)}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)
