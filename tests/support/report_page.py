"""What every result folder's ``report.html`` (tracegs.eval.html_report) must be, checked without a browser: its
tables' text is present, every file it links or embeds exists relative to the page, no link leaves the folder,
and a second write of it changes no byte."""

from __future__ import annotations

import html
import re
from pathlib import Path
from urllib.parse import unquote

from tracegs.eval.html_report import REPORT_PAGE, write_report_page


def table_cells(markdown: str) -> list[str]:
    """The cells of the pipe tables in ``markdown`` (separator rows excluded)."""
    return [cell.strip() for line in markdown.splitlines() if line.startswith("|") and "---" not in line
            for cell in line.strip().strip("|").split("|")]


def checked_page(folder: Path, tables: str) -> tuple[str, list[str]]:
    """(text, links) of ``folder``'s page, checked as the module docstring says; ``tables`` names the markdown
    file whose table cells the page must show."""
    page = folder / REPORT_PAGE
    text = page.read_text(encoding="utf-8")
    cells = table_cells((folder / tables).read_text())
    # What a reader sees: the text without tags, each cell without its markdown marks (bold, code).
    shown = html.unescape(re.sub(r"<[^>]+>", "", text))
    assert cells and not [cell for cell in cells if re.sub(r"\*\*|`", "", cell) not in shown]
    links = re.findall(r'(?:src|href)="([^"]+)"', text)
    assert links and not [link for link in links if link.startswith(("/", "file:", "..")) or "://" in link]
    assert not [link for link in links if not (folder / unquote(html.unescape(link))).is_file()]
    assert str(folder.resolve()) not in text
    made = page.read_bytes(), page.stat().st_mtime_ns
    write_report_page(folder)
    assert (page.read_bytes(), page.stat().st_mtime_ns) == made
    return text, links
