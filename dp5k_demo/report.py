"""A small HTML report writer: sections of prose, tables and figures, one self-contained page.

Figures are PNG files beside the report, referenced by relative paths. Every number shown in a table is
also kept in ``report.json`` (the same values, unformatted) so tests can check the report against its
sources.
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_common.software import provenance

_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{border-bottom:2px solid #444;padding-bottom:.2em} h2{margin-top:2em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em} th,td{border:1px solid #bbb;padding:.3em .6em;text-align:right}
th{background:#eee} td:first-child,th:first-child{text-align:left}
figure{margin:1em 0} figure img{max-width:100%;border:1px solid #ddd} figcaption{font-size:.9em;color:#555}
.ok{color:#0a0;font-weight:bold} .bad{color:#c00;font-weight:bold} .note{color:#555;font-size:.92em}
code{background:#f4f4f4;padding:0 .2em}
"""


def fmt(value: Any, digits: int = 3) -> str:
    """Format a number for a table: floats to ``digits`` significant places, the rest as str."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if value != value:
            return "n/a"
        return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.0f}"
    return str(value)


@dataclass
class Section:
    title: str
    parts: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)

    def text(self, paragraph: str, *, raw_html: bool = False) -> None:
        self.parts.append(f"<p>{paragraph if raw_html else html.escape(paragraph)}</p>")

    def table(self, key: str, header: list[str], rows: list[list[Any]], caption: str = "", digits: int = 3) -> None:
        """Add a table; its raw values are kept under ``key`` in report.json."""
        self.data[key] = {"header": header, "rows": rows}
        head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(v, digits))}</td>" for v in row) + "</tr>" for row in rows)
        note = f'<p class="note">{html.escape(caption)}</p>' if caption else ""
        self.parts.append(f"{note}<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")

    def figure(self, rel_path: str, caption: str) -> None:
        self.parts.append(
            f'<figure><img src="{html.escape(rel_path)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )


@dataclass
class Report:
    title: str
    intro: str
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str) -> Section:
        s = Section(title)
        self.sections.append(s)
        return s

    def write(self, out_dir: Path, name: str = "report") -> Path:
        """Write ``<name>.html`` and ``<name>.json`` atomically into ``out_dir``; return the HTML path."""
        toc = "".join(f'<li><a href="#s{i}">{html.escape(s.title)}</a></li>' for i, s in enumerate(self.sections))
        body = "".join(
            f'<h2 id="s{i}">{html.escape(s.title)}</h2>' + "".join(s.parts) for i, s in enumerate(self.sections)
        )
        page = (
            f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{html.escape(self.title)}</h1><p>{html.escape(self.intro)}</p>"
            f"<ol>{toc}</ol>{body}</body></html>"
        )
        path = out_dir / f"{name}.html"
        write_bytes_atomic(path, page.encode())
        write_json_atomic(out_dir / f"{name}.json",
                          {**{s.title: s.data for s in self.sections}, "provenance": provenance()})
        return path
