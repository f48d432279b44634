"""``report.html``: one page per result folder (a demo's, an evaluation's, a restore's, a replicate run's) that opens
from disk without a server and shows what the folder holds: the run record (commit, machine, timings), the
tables with their intervals and verdicts, Fig. 6, each scene's qualitative grid and video and its refined PLYs.

The page is made from the folder's own files alone (never from the command writing it), so every command that
writes into one folder writes the same page, and a rerun that makes nothing writes the same bytes (no time of
writing in it). Every link is relative to the folder, so the folder can be copied or moved with its page.
"""

from __future__ import annotations

import html
import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from urllib.parse import quote

from tracegs.eval.conclusions import HOLDS, REVERSED
from tracegs.eval.merge import unit_records, view_names
from tracegs.io import atomic_write

REPORT_PAGE = "report.html"
# A demo's tables.md holds the evaluation's tables beside the run that made them; the parts it is made of show
# only where it is absent (an evaluation's or a restore's folder). tracegs-replicate's tables are in replicate.md.
COMBINED = ("tables.md", "replicate.md")
INTERVALS = "intervals.md"
PARTS = {"table.md": "Results", INTERVALS: "95% intervals and the paper's orderings",
         "held_out_clips.md": "Held-out clips", "per_step_intervals.md": "Fig. 6 at each reverse step"}
FIG6 = "fig6_per_step.png"
# The verdicts that settle an ordering, coloured so a reader finds them in a long table (each is its CSS class).
VERDICT_COLOURS = {HOLDS: "#1a7f37", REVERSED: "#cf222e"}
STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 72em; padding: 0 1em; color: #1f2328; }
table { border-collapse: collapse; margin: 0.8em 0; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #d0d7de; padding: 0.25em 0.6em; text-align: left; }
th { background: #f6f8fa; }
code { background: #f6f8fa; padding: 0 0.2em; }
img, video { max-width: 100%; }
figure { margin: 1em 0; }
.run { color: #59636e; }
""" + "".join(f".{verdict} {{ color: {colour}; }}\n" for verdict, colour in VERDICT_COLOURS.items())

_SEPARATOR_ROW = re.compile(r"^\|?\s*:?-+:?\s*(\|\s*:?-+:?\s*)*\|?$")
_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def _inline(text: str) -> str:
    """Escaped ``text`` with the project's inline marks: ``code`` and **bold** (a verdict coloured)."""
    text = _CODE.sub(r"<code>\1</code>", html.escape(text, quote=False))

    def bold(match: re.Match) -> str:
        word = match.group(1)
        return f'<strong class="{word}">{word}</strong>' if word in VERDICT_COLOURS else f"<strong>{word}</strong>"

    return _BOLD.sub(bold, text)


def _cells(row: str) -> list[str]:
    return [cell.strip() for cell in row.strip().strip("|").split("|")]


def _table(rows: Sequence[str]) -> list[str]:
    """A pipe table (header row, separator row, body rows) as an HTML table."""
    head, body = rows[0], [r for r in rows[1:] if not _SEPARATOR_ROW.match(r.strip())]
    out = ["<table>", "<thead><tr>" + "".join(f"<th>{_inline(c)}</th>" for c in _cells(head)) + "</tr></thead>",
           "<tbody>"]
    out += ["<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in _cells(r)) + "</tr>" for r in body]
    return [*out, "</tbody>", "</table>"]


def markdown_html(text: str) -> str:
    """The markdown the project writes (headings, pipe tables, ``- `` lists, paragraphs, inline code and bold)
    as HTML; any other text stays a paragraph."""
    out: list[str] = []
    block: list[str] = []

    def flush() -> None:
        if block:
            out.append("<p>" + " ".join(_inline(line) for line in block) + "</p>")
            block.clear()

    lines = text.splitlines()
    index = 0
    while index < len(lines):
        line = lines[index].strip()
        heading = re.match(r"^(#{1,5})\s+(.*)$", line)
        if not line:
            flush()
        elif heading:
            flush()
            level = len(heading.group(1)) + 1  # the page's own title is the one <h1>
            out.append(f"<h{level}>{_inline(heading.group(2))}</h{level}>")
        elif line.startswith("|"):
            flush()
            end = index
            while end < len(lines) and lines[end].strip().startswith("|"):
                end += 1
            out += _table([r.strip() for r in lines[index:end]])
            index = end
            continue
        elif line.startswith("- "):
            flush()
            end = index
            while end < len(lines) and lines[end].strip().startswith("- "):
                end += 1
            out += ["<ul>", *(f"<li>{_inline(r.strip()[2:])}</li>" for r in lines[index:end]), "</ul>"]
            index = end
            continue
        else:
            block.append(line)
        index += 1
    flush()
    return "\n".join(out)


def _href(relative: str | Path) -> str:
    """A path relative to the folder (as units name their files, tracegs.eval.scoring) as an escaped link."""
    return html.escape(quote(Path(relative).as_posix()))


def _run_header(record: dict) -> list[str]:
    """The run record (run.json of a demo or of tracegs-replicate): commit, seed, machine, wall time, peak memory and
    the time of each step."""
    machine = record.get("machine", {})
    facts = [f"commit <code>{html.escape(str(record['commit']))}</code>" if "commit" in record else "",
             f"seed {record['seed']}" if "seed" in record else "",
             html.escape(f"{machine.get('cpu', '')} ({machine.get('cores', '?')} cores), GPU {machine.get('gpu')}, "
                         f"torch {machine.get('torch')}, {machine.get('platform', '')}") if machine else "",
             f"wall time {record['wall_s'] / 60:.1f} min" if "wall_s" in record else "",
             f"peak RSS {record['peak_rss_gib']:.2f} GiB" if "peak_rss_gib" in record else ""]
    out = ['<p class="run">' + "; ".join(f for f in facts if f) + "</p>"]
    steps = record.get("step_s", {})
    if steps:
        out += ["<details><summary>Time of each step</summary>", "<table>",
                "<thead><tr><th>step</th><th>seconds</th></tr></thead>", "<tbody>",
                *(f"<tr><td>{html.escape(step)}</td><td>{seconds:.1f}</td></tr>" for step, seconds in steps.items()),
                "</tbody>", "</table>", "</details>"]
    return out


def _documents(folder: Path) -> list[tuple[str | None, Path]]:
    """(section heading, markdown file) of the folder's tables in reading order. The intervals over scenes are
    left out of the page of one scene (a capture restored): an interval of one value says nothing."""
    combined = [folder / name for name in COMBINED if (folder / name).is_file()]
    if combined:
        return [(None, path) for path in combined]
    one_scene = len(_scenes(folder)) == 1
    return [(heading, folder / name) for name, heading in PARTS.items()
            if (folder / name).is_file() and not (one_scene and name == INTERVALS)]


def _scenes(folder: Path) -> list[str]:
    """The scenes the folder's evaluation units are of, in order."""
    return sorted({unit["scene"] for unit in unit_records(folder)})


def _media(path: str) -> str:
    href = _href(path)
    if Path(path).suffix == ".mp4":
        return f'<video src="{href}" controls loop muted playsinline></video>'
    return f'<img src="{href}" alt="{href}">'  # a grid, or the GIF written where ffmpeg is missing


def _units(folder: Path) -> list[str]:
    """Each evaluation unit's grid, video and refined PLYs (the files its record names)."""
    out: list[str] = []
    for unit in unit_records(folder):
        media, models = unit.get("media", {}), unit.get("models", {})
        if not media and not models:
            continue
        out.append(f"<h3>{html.escape(unit['scene'])}, {unit['views']} input views</h3>")
        if "captured" in unit and "test" in unit:
            out.append(f"<p>Fitted from {html.escape(view_names(unit, 'captured'))}, scored on held-out "
                       f"{html.escape(view_names(unit, 'test'))}.</p>")
        out += [f"<figure>{_media(media[kind])}</figure>" for kind in ("grid", "video") if kind in media]
        if models:
            out.append("<p>Refined 3DGS: " + ", ".join(
                f'<a href="{_href(ply)}">{html.escape(method)}</a>'
                for method, ply in models.items()) + "</p>")
    return ["<h2>Qualitative results</h2>", *out] if out else []


def _nested(folder: Path) -> list[str]:
    """Links to the pages of the folders inside this one (tracegs-replicate's evaluations)."""
    pages = sorted(p for p in folder.rglob(REPORT_PAGE) if p.parent != folder)
    if not pages:
        return []
    links = (f'<li><a href="{_href(p.relative_to(folder))}">{html.escape(p.parent.relative_to(folder).as_posix())}'
             "</a></li>" for p in pages)
    return ["<h2>Reports inside this folder</h2>", "<ul>", *links, "</ul>"]


def report_html(folder: str | Path) -> str:
    """The page of ``folder`` (see the module docstring)."""
    folder = Path(folder)
    scenes = _scenes(folder)
    # A capture restored is one scene: the page is titled by it, not by the run folder's digest.
    title = html.escape(f"{scenes[0] if len(scenes) == 1 else folder.name}: tracegs results")
    body: list[str] = [f"<h1>{title}</h1>"]
    record = folder / "run.json"
    if record.is_file():
        body += _run_header(json.loads(record.read_text()))
    for heading, path in _documents(folder):
        if heading:
            body.append(f"<h2>{html.escape(heading)}</h2>")
        body += [markdown_html(path.read_text()), f'<p><a href="{_href(path.name)}">{path.name}</a></p>']
    if (folder / FIG6).is_file():
        body += ["<h2>Fig. 6</h2>", f'<figure><img src="{FIG6}" alt="Fig. 6: clean-frame PSNR at each reverse step">'
                 "<figcaption>Clean-frame PSNR at each reverse step (shaded: 95% interval over scenes)."
                 "</figcaption></figure>"]
    body += _units(folder) + _nested(folder)
    return _page(title, body)


def _page(title: str, body: Iterable[str]) -> str:
    return "\n".join(["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
                      f"<title>{title}</title>", f"<style>{STYLE}</style>", "</head>", "<body>", *body, "</body>",
                      "</html>", ""])


def write_report_page(folder: str | Path) -> Path:
    """Write ``report.html`` into ``folder`` (unchanged when it holds the same page already); returns its path."""
    path = Path(folder) / REPORT_PAGE
    with atomic_write(path) as tmp:
        tmp.write_text(report_html(folder), encoding="utf-8")
    return path
