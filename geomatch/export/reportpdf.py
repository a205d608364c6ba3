"""The survey report as PDF, beside its Markdown: what WebODM's report button opens and what a
survey team attaches to a delivery note.

It renders the Markdown page of ``geomatch.report.to_markdown`` (headings, bullet lists, tables),
not a second report: the two never say different things. fpdf2 draws it (pure Python, no browser
or system renderer); with DejaVu Sans installed every character of an image or point name shows,
else the PDF's core font shows Latin-1 and a ``?`` for anything beyond it.
"""

from __future__ import annotations

import re
from pathlib import Path

from fpdf import FPDF

DEJAVU = Path("/usr/share/fonts/truetype/dejavu")
# CommonMark's backslash escapes (of ASCII punctuation): the report escapes client-chosen names
# so that the Markdown shows them as they are (geomatch.report.escape_markdown); the PDF shows them
# without the backslashes
_ESCAPED = re.compile(r"\\([!-/:-@\[-`{-~])")
_CELL_BORDER = re.compile(r"(?<!\\)\|")


def _font(pdf: FPDF) -> tuple[str, bool]:
    """The family to write with, and whether it covers Unicode."""
    regular, bold = DEJAVU / "DejaVuSans.ttf", DEJAVU / "DejaVuSans-Bold.ttf"
    if regular.is_file() and bold.is_file():
        pdf.add_font("DejaVu", "", str(regular))
        pdf.add_font("DejaVu", "B", str(bold))
        return "DejaVu", True
    return "Helvetica", False


def plain_text(markdown: str) -> str:
    """A line of the report as it reads: backslash escapes resolved."""
    return _ESCAPED.sub(r"\1", markdown)


def table_cells(line: str) -> list[str]:
    """The cells of a Markdown table row; an escaped ``\\|`` inside a cell is not a border."""
    inner = line.strip()
    inner = inner[1:] if inner.startswith("|") else inner
    inner = inner[:-1] if inner.endswith("|") and not inner.endswith("\\|") else inner
    return [plain_text(c.strip()) for c in _CELL_BORDER.split(inner)]


def markdown_pdf(markdown: str) -> bytes:
    """The PDF of a report page written by ``to_markdown``."""
    pdf = FPDF(format="A4")
    pdf.set_auto_page_break(True, margin=15)
    pdf.add_page()
    family, unicode_ok = _font(pdf)

    def shown(s: str) -> str:
        return s if unicode_ok else s.encode("latin-1", "replace").decode("latin-1")

    def text(s: str) -> str:
        return shown(plain_text(s))

    table: list[list[str]] = []

    def flush_table() -> None:
        if not table:
            return
        pdf.set_font(family, "", 8)
        with pdf.table(first_row_as_headings=True, text_align="LEFT") as t:
            for row in table:
                r = t.row()
                for cell in row:
                    r.cell(shown(cell))  # table_cells resolved the escapes
        table.clear()
        pdf.ln(2)

    for raw in markdown.splitlines():
        line = raw.rstrip()
        if line.startswith("|"):
            if set(line.replace("|", "").strip()) <= set("-: "):
                continue  # the header's separator row
            table.append(table_cells(line))
            continue
        flush_table()
        if line.startswith("# "):
            pdf.set_font(family, "B", 16)
            pdf.multi_cell(0, 9, text(line[2:]), new_x="LMARGIN", new_y="NEXT")
        elif line.startswith("## "):
            pdf.ln(2)
            pdf.set_font(family, "B", 12)
            pdf.multi_cell(0, 7, text(line[3:]), new_x="LMARGIN", new_y="NEXT")
        elif line.lstrip().startswith("- "):
            indent = (len(line) - len(line.lstrip())) // 2
            pdf.set_font(family, "", 9)
            pdf.set_x(pdf.l_margin + 4 + 5 * indent)
            bullet = "\u2022 " if unicode_ok else "- "
            pdf.multi_cell(0, 5, text(bullet + line.lstrip()[2:]), new_x="LMARGIN", new_y="NEXT")
        elif line:
            pdf.set_font(family, "", 9)
            pdf.multi_cell(0, 5, text(line), new_x="LMARGIN", new_y="NEXT")
        else:
            pdf.ln(2)
    flush_table()
    return bytes(pdf.output())


def write_pdf(path: Path, markdown: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(markdown_pdf(markdown))
    return path
