"""MkDocs hook: the docstrings' reST idioms read as Markdown in the reference pages.

The code's docstrings are free text with a few reST habits: roles such as
``:func:`make_model``` and ``:mod:`~vfm_core.learning.online``` and simple tables framed by
``=====  =====`` lines. mkdocstrings renders docstrings as Markdown, where those come out as
stray colons and runs of equals signs. This hook adds a Markdown preprocessor (to every page,
where neither idiom otherwise occurs) that writes a role as inline code and a simple table as
a Markdown table. Nothing else changes: the docstrings stay as they are.
"""

from __future__ import annotations

import re

from markdown import Markdown
from markdown.extensions import Extension
from markdown.preprocessors import Preprocessor
from mkdocs.plugins import event_priority

_ROLE = re.compile(
    r":(?:py:)?(?:mod|func|class|meth|attr|data|exc|obj|const|term|ref):`(~?)([^`]+)`"
)
_BORDER = re.compile(r"^\s*=+(?: +=+)+\s*$")


def _role(match: re.Match[str]) -> str:
    text = match.group(2)
    if match.group(1):  # ~a.b.c shows as c
        text = text.rsplit(".", 1)[-1]
    return f"`{text}`"


def _columns(border: str) -> list[tuple[int, int]]:
    """The (start, end) of each column of a simple table's border line."""
    return [(m.start(), m.end()) for m in re.finditer(r"=+", border)]


def _cells(line: str, cols: list[tuple[int, int]]) -> list[str]:
    cells = []
    for i, (start, _) in enumerate(cols):
        end = cols[i + 1][0] if i + 1 < len(cols) else len(line)
        cells.append(line[start:end].strip().replace("|", "\\|"))
    return cells


def _table(block: list[str], cols: list[tuple[int, int]]) -> list[str]:
    """A simple table (border, header, border, rows, border) as Markdown lines."""
    borders = [i for i, ln in enumerate(block) if _BORDER.match(ln)]
    header_rows = block[borders[0] + 1 : borders[1]] if len(borders) >= 3 else []
    body = block[borders[1] + 1 : borders[-1]] if len(borders) >= 3 else block[1:-1]
    rows: list[list[str]] = []
    for ln in body:
        if not ln.strip():
            continue
        cells = _cells(ln, cols)
        if rows and not cells[0]:  # a continuation line: the first column is empty
            rows[-1] = [f"{a} {b}".strip() for a, b in zip(rows[-1], cells, strict=True)]
        else:
            rows.append(cells)
    header = _cells(header_rows[0], cols) if header_rows else [""] * len(cols)
    out = ["", "| " + " | ".join(header) + " |", "|" + " --- |" * len(cols)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out + [""]


class _RstIdioms(Preprocessor):
    def run(self, lines: list[str]) -> list[str]:
        out: list[str] = []
        i, fence = 0, False
        while i < len(lines):
            line = lines[i]
            if line.lstrip().startswith(("```", "~~~")):
                fence = not fence
            if not fence and _BORDER.match(line):
                # a simple table: three borders (header) or two, within the next 200 lines
                ends = [
                    j for j in range(i + 1, min(len(lines), i + 200)) if _BORDER.match(lines[j])
                ]
                last = ends[1] if len(ends) >= 2 else (ends[0] if ends else None)
                if last is not None:
                    out.extend(_table(lines[i : last + 1], _columns(line)))
                    i = last + 1
                    continue
            out.append(line if fence else _ROLE.sub(_role, line))
            i += 1
        return out


class RstIdiomsExtension(Extension):
    def extendMarkdown(self, md: Markdown) -> None:  # noqa: N802 (Markdown's API)
        md.preprocessors.register(_RstIdioms(md), "rst_idioms", 27)


@event_priority(100)  # before mkdocstrings takes the list of extensions
def on_config(config):  # type: ignore[no-untyped-def]
    config.markdown_extensions.append(RstIdiomsExtension())
    return config
