"""The report as a list of blocks, rendered to Markdown and to one self-contained HTML file.

Both outputs come from the same blocks, so they hold the same content. Every piece of text
is plain text (run messages come from user input): the HTML renderer escapes all of it and
the Markdown renderer escapes what Markdown or embedded HTML would interpret. Figures are
SVG text: written as files beside ``report.md`` and inlined, sanitised, into the HTML.
Figure names come from user text (problem specs, study names): :func:`file_stem` bounds
and sanitises them before they name a file.
"""

from __future__ import annotations

import hashlib
import html
import re
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.files import replace_file
from benchmarks.records import Status
from reports.svg import clean


#: Longest figure file stem: far below any file system's name limit (255 bytes) with room
#: for the ``.svg`` suffix and any prefix a caller adds.
MAX_STEM = 80


def slug(text: str, empty: str) -> str:
    """``text`` in lower-case letters, digits and single ``-``; ``empty`` if nothing is left."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or empty


def file_stem(name: str) -> str:
    """A file stem for ``name``: lower-case letters, digits and ``-`` only, at most
    :data:`MAX_STEM` characters. A name that had to change gets a short hash of its full
    text, so different names (``pendulum:L=1`` and ``pendulum:L-1``) never share a file."""
    stem = slug(name, "figure")
    if stem == name and len(stem) <= MAX_STEM:
        return stem
    digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return f"{stem[:MAX_STEM - len(digest) - 1].rstrip('-')}-{digest}"


@dataclass
class Heading:
    level: int  # 1 = title, 2 = section, 3 = subsection
    text: str
    anchor: str = ""
    collapsible: bool = False  # a section (level 2) that a reader can fold away


@dataclass
class Para:
    text: str


@dataclass
class Bullets:
    items: list[str]


@dataclass
class Table:
    columns: list[str]
    rows: list[list[str]]
    caption: str = ""
    fit: bool = False  # wraps every cell to fit the page's width instead of scrolling sideways


@dataclass
class Figure:
    name: str  # unique in the report; any text (the file is named by file_stem(name))
    svg: str | Future  # the SVG text, or its future (reports.figures.Drawing)
    caption: str = ""
    trusted: bool = True  # drawn by the report itself; False keeps its styles out of the page


def svg_text(figure: Figure) -> str:
    """The figure's SVG text, waiting for it where it is still being drawn."""
    return figure.svg.result() if isinstance(figure.svg, Future) else figure.svg


@dataclass
class Document:
    title: str
    blocks: list = field(default_factory=list)

    def add(self, *blocks) -> None:
        self.blocks.extend(blocks)

    def heading(self, level: int, text: str, collapsible: bool = False) -> Heading:
        """Append a heading with an anchor unique in the document; ``collapsible`` folds a
        section (level 2) and everything up to the next section in the HTML page."""
        base = slug(text, "section")
        taken = {b.anchor for b in self.blocks if isinstance(b, Heading)}
        anchor, k = base, 2
        while anchor in taken:
            anchor, k = f"{base}-{k}", k + 1
        block = Heading(level, text, anchor, collapsible)
        self.blocks.append(block)
        return block


# --------------------------------------------------------------------------- Markdown

def _md_text(text: str) -> str:
    """Plain text made inert in Markdown: no raw HTML, no emphasis, code or links by
    accident (an underscore inside a word is literal in CommonMark and left alone)."""
    text = str(text).replace("\r", " ")
    text = re.sub(r"&(?=#?\w+;)", "&amp;", text).replace("<", "&lt;")
    text = re.sub(r"([\\`*\[\]])", r"\\\1", text)
    text = re.sub(r"(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", r"\\_", text)
    return re.sub(r"^([#>+-])", r"\\\1", text, flags=re.M)


def _md_cell(text: str) -> str:
    return _md_text(text).replace("\n", " ").replace("|", "\\|")


def to_markdown(doc: Document, out_dir: Path,
                figure_dir: str = "figures") -> tuple[str, list[Path]]:
    """Markdown text of ``doc``; figures are written to ``out_dir/figure_dir/NAME.svg``."""
    lines: list[str] = [f"# {_md_text(doc.title)}", ""]
    written: list[Path] = []
    (out_dir / figure_dir).mkdir(parents=True, exist_ok=True)
    for b in doc.blocks:
        if isinstance(b, Heading):
            lines += [f"{'#' * b.level} {_md_text(b.text)}", ""]
        elif isinstance(b, Para):
            lines += [_md_text(b.text), ""]
        elif isinstance(b, Bullets):
            lines += [f"- {_md_text(item)}" for item in b.items] + [""]
        elif isinstance(b, Table):
            if b.caption:
                lines += [f"*{_md_text(b.caption)}*", ""]
            lines.append("| " + " | ".join(_md_cell(c) for c in b.columns) + " |")
            lines.append("|" + "---|" * len(b.columns))
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows]
            lines.append("")
        elif isinstance(b, Figure):
            stem = file_stem(b.name)
            path = out_dir / figure_dir / f"{stem}.svg"
            replace_file(path, clean(svg_text(b), "", keep_style=b.trusted))
            written.append(path)
            lines += [f"![{_md_cell(b.name)}]({figure_dir}/{stem}.svg)", ""]
            if b.caption:
                lines += [f"*{_md_text(b.caption)}*", ""]
    return "\n".join(lines), written


# --------------------------------------------------------------------------- HTML

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0;
       color: #1b1b1b; background: #fff; line-height: 1.45; }
main { max-width: 1200px; margin: 0 auto; padding: 1em 2em 3em; }
nav.toc { background: #f4f6f8; border: 1px solid #dde2e6; padding: 0.3em 1.2em;
          margin: 0.6em 0 1em; }
nav.toc summary { cursor: pointer; }
nav.toc ul { margin: 0.2em 0; padding-left: 1.2em; font-size: 0.9em; }
h1 { border-bottom: 2px solid #333; padding-bottom: 0.2em; }
h2 { border-bottom: 1px solid #bbb; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em; font-size: 0.85em; }
div.scroll { overflow-x: auto; }
th, td { border: 1px solid #ccd; padding: 0.2em 0.5em; text-align: right;
         vertical-align: top; white-space: nowrap; }
th { background: #eef1f5; text-align: left; white-space: normal; }
td.word { text-align: left; }
td.text { text-align: left; white-space: normal; min-width: 18em; max-width: 40em;
          overflow-wrap: anywhere; }
tr.bad td { background: #fdecea; }
table.fit { width: 100%; }
table.fit td, table.fit td.text { white-space: normal; min-width: 0; max-width: none;
                                  overflow-wrap: anywhere; text-align: left; }
caption { caption-side: top; text-align: left; font-style: italic; padding: 0.2em 0; }
figure { margin: 1em 0 2em; }
figure svg { max-width: 100%; height: auto; }
figcaption { font-style: italic; font-size: 0.9em; }
details.section > summary { cursor: pointer; list-style-position: outside; }
details.section > summary > h2 { display: inline-block; margin: 1.2em 0 0.4em; }
footer { margin-top: 3em; font-size: 0.85em; color: #444; border-top: 1px solid #bbb; }
"""

#: Statuses whose table rows are highlighted.
BAD = (Status.FAILED, Status.ERROR, Status.TIMEOUT)


#: Cells longer than this wrap (messages, verdicts); shorter ones stay on one line.
WRAP_AT = 40


def _cell_class(text: str) -> str:
    """Numbers right-aligned on one line, words left-aligned, long text wrapped."""
    if re.fullmatch(r"[-+0-9.e]*", text):
        return ""
    return ' class="text"' if len(text) > WRAP_AT else ' class="word"'


def _toc(doc: Document) -> str:
    """The contents: one line per section (level 2), its subsections as links on that line,
    named without the section's own subject (``pendulum: summary`` under ``Problem:
    pendulum`` is ``summary``); folded, so that the headline opens the page."""
    esc = html.escape
    lines: list[list[str]] = []
    subject = ""
    for b in doc.blocks:
        if not isinstance(b, Heading) or b.level not in (2, 3):
            continue
        link = f'<a href="#{esc(b.anchor)}">{{}}</a>'
        if b.level == 2:
            subject = b.text.split(": ", 1)[-1] + ": "
            lines.append([link.format(esc(b.text))])
        elif lines:
            name = b.text[len(subject):] if b.text.startswith(subject) else b.text
            lines[-1].append(link.format(esc(name)))
    items = "".join(f"<li>{line[0]}" + (": " + " · ".join(line[1:]) if line[1:] else "")
                    + "</li>" for line in lines)
    return (f'<nav class="toc"><details><summary><strong>Contents</strong> '
            f"({len(lines)} sections)</summary><ul>{items}</ul></details></nav>")


def to_html(doc: Document, footer: list[str] | None = None) -> str:
    """One self-contained HTML page: inline CSS, inline SVG, no script, no outside resource."""
    esc = html.escape
    body: list[str] = []
    open_details = False
    n_fig = 0
    for b in doc.blocks:
        if isinstance(b, Heading):
            heading = f'<h{b.level} id="{esc(b.anchor)}">{esc(b.text)}</h{b.level}>'
            if b.level == 2:
                if open_details:
                    body.append("</details>")
                    open_details = False
                if b.collapsible:
                    # Closed: the page stays short; a link to anything inside opens it
                    # (browsers open a <details> that holds the target of a fragment link).
                    heading = f'<details class="section"><summary>{heading}</summary>'
                    open_details = True
            body.append(heading)
        elif isinstance(b, Para):
            body.append(f"<p>{esc(b.text)}</p>")
        elif isinstance(b, Bullets):
            body.append("<ul>" + "".join(f"<li>{esc(i)}</li>" for i in b.items) + "</ul>")
        elif isinstance(b, Table):
            wide = "" if b.fit else '<div class="scroll">'
            parts = [wide + ('<table class="fit">' if b.fit else "<table>")]
            if b.caption:
                parts.append(f"<caption>{esc(b.caption)}</caption>")
            parts.append("<thead><tr>" + "".join(f"<th>{esc(c)}</th>" for c in b.columns)
                         + "</tr></thead><tbody>")
            for row in b.rows:
                bad = ' class="bad"' if any(str(c) in BAD for c in row) else ""
                parts.append(f"<tr{bad}>" + "".join(
                    f"<td{_cell_class(str(c))}>{esc(str(c))}</td>" for c in row) + "</tr>")
            parts.append("</tbody></table>" + ("" if b.fit else "</div>"))
            body.append("".join(parts))
        elif isinstance(b, Figure):
            n_fig += 1
            svg = clean(svg_text(b), f"f{n_fig}-", keep_style=b.trusted)
            cap = f"<figcaption>{esc(b.caption)}</figcaption>" if b.caption else ""
            body.append(f'<figure id="fig-{file_stem(b.name)}">{svg}{cap}</figure>')
    if open_details:
        body.append("</details>")
    foot = "".join(f"<p>{esc(line)}</p>" for line in (footer or []))
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{esc(doc.title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<main>\n"
        f"<h1>{esc(doc.title)}</h1>\n{_toc(doc)}\n"
        + "\n".join(body)
        + f"\n<footer>{foot}</footer>\n</main>\n</body>\n</html>\n"
    )
