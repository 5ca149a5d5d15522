"""The page machinery every HTML report shares: templates, layout, figures, number formats.

Owns the one Jinja2 :data:`ENV` (autoescape on: every value a template prints is
HTML-escaped unless it is :class:`~markupsafe.Markup`), the templates shipped in
``vfm_core/reporting/templates`` (``base.html.j2`` is the layout: title, header and the
inline style sheet ``page.css``), embedding matplotlib figures as base64 PNG
(:func:`png`, :func:`figure`), the generic data table (:func:`table`), the number filters
(``pct``, ``fixed``, ``signed``, ``thousands``, ``cell``), readable date axes
(:func:`date_axis`) and writing a page atomically (:func:`write_page`).

A report module (``study``, ``diagnosis``, ``drift``) computes numbers, plain-text
pieces and figures, and hands them to its template through :func:`render`; it
never writes HTML in Python, so text taken from the data (well, model and effect names,
file paths) is escaped by the engine, not by hand. Pages are self-contained: no external
URL, no script, figures inline.

Figures are drawn on :class:`matplotlib.figure.Figure` objects directly, without pyplot:
no global figure registry to leak into, no GUI backend to select.
"""

from __future__ import annotations

import base64
import io
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib.dates as mdates
from jinja2 import Environment, PackageLoader, StrictUndefined
from markupsafe import Markup
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from PIL import Image

from vfm_core.fileio import write_with

__all__ = [
    "ENV",
    "DPI",
    "Png",
    "png",
    "figure",
    "table",
    "date_axis",
    "fmt_pct",
    "fmt_fixed",
    "fmt_signed",
    "fmt_thousands",
    "fmt_cell",
    "render",
    "write_page",
]

#: Resolution of the embedded figures (dots per inch).
DPI = 100
#: What a table cell shows for a missing or non-finite number.
MISSING = "–"


# --------------------------------------------------------------------------- number formats


def _finite(value: Any) -> float | None:
    """``value`` as a finite float, or ``None`` (None, NaN, inf, text)."""
    if value is None or isinstance(value, bool):
        return None
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def fmt_pct(value: Any, digits: int = 1) -> str:
    """A percentage for a table cell, without the sign; huge values (diverged models) in
    scientific notation, missing ones as a dash: ``fmt_pct(12.345)`` is ``"12.3"``."""
    v = _finite(value)
    if v is None:
        return MISSING
    if abs(v) >= 1e4:
        return f"{v:.1e}"
    return f"{v:.{digits}f}"


def fmt_fixed(value: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals, a dash when missing."""
    v = _finite(value)
    return MISSING if v is None else f"{v:.{digits}f}"


def fmt_signed(value: Any, digits: int = 2) -> str:
    """A change with its sign (``+0.25``, ``-1.30``), a dash when missing."""
    v = _finite(value)
    return MISSING if v is None else f"{v:+.{digits}f}"


def fmt_thousands(value: Any) -> str:
    """A count with thousands separators (``12,345``)."""
    v = _finite(value)
    return MISSING if v is None else f"{int(round(v)):,}"


def fmt_cell(value: Any) -> str:
    """A generic table cell: floats to 3 significant digits (dash when not finite), the
    rest as text (``True``, ``12``, a name)."""
    if isinstance(value, float):
        return f"{value:.3g}" if math.isfinite(value) else "-"
    return "" if value is None else str(value)


# --------------------------------------------------------------------------- figures


@dataclass(frozen=True)
class Png:
    """A figure encoded as PNG, ready to embed: ``src`` is a ``data:`` URI."""

    data: str  #: base64 of the PNG bytes

    @property
    def src(self) -> str:
        return "data:image/png;base64," + self.data


def png(fig: Figure) -> Png:
    """Encode a figure as an embeddable PNG (palette of 256 colours).

    A 256-colour palette looks the same for line plots and makes the PNG about 3x smaller.
    Encode as soon as a figure is drawn: the encoded form holds no matplotlib state.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    buf.seek(0)
    with Image.open(buf) as image:
        small = io.BytesIO()
        image.convert("RGB").quantize(colors=256).save(small, format="PNG", optimize=True)
    return Png(base64.b64encode(small.getvalue()).decode("ascii"))


def figure(fig: Figure | Png, caption: str = "", alt: str = "") -> Markup:
    """A figure element with the embedded PNG and its caption, as safe markup.

    ``caption`` and ``alt`` are escaped unless they are :class:`~markupsafe.Markup` (a
    caption rendered by a template, e.g. with ``{% set caption %}...{% endset %}``).
    """
    image = fig if isinstance(fig, Png) else png(fig)
    return Markup(render("figure.html.j2", image=image, caption=caption, alt=alt))


def table(
    rows: Iterable[Mapping[str, Any]],
    columns: Sequence[tuple[str, str]],
    caption: str = "",
) -> Markup:
    """A data table of ``rows`` (dicts); ``columns`` are ``(key, heading)`` pairs.

    Cells go through :func:`fmt_cell`; the table scrolls sideways when it is wider than
    the page.
    """
    return Markup(render("table.html.j2", rows=list(rows), columns=list(columns), caption=caption))


def bottom_legend(fig: Figure, handles: Sequence[Any], **kwargs: Any) -> None:
    """One legend for the whole figure, centred below the panels (up to five columns), and
    the panels laid out to leave room for it."""
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(len(handles), 5),
        fontsize=8,
        bbox_to_anchor=(0.5, -0.01),
        frameon=False,
        **kwargs,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))


def date_axis(ax: Axes) -> None:
    """Date ticks that do not overlap: a few ticks, each labelled only with what changes
    (``ConciseDateFormatter``: 'Apr', 'Jul', then '2020' at the year)."""
    locator = mdates.AutoDateLocator(minticks=3, maxticks=7)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))


# --------------------------------------------------------------------------- templates

ENV = Environment(
    loader=PackageLoader("vfm_core.reporting", "templates"),
    autoescape=True,
    undefined=StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
    keep_trailing_newline=True,
    auto_reload=False,
)
ENV.filters.update(
    pct=fmt_pct,
    fixed=fmt_fixed,
    signed=fmt_signed,
    thousands=fmt_thousands,
    cell=fmt_cell,
)
ENV.globals.update(figure=figure, table=table)


def render(template_name: str, /, **context: Any) -> str:
    """Render one template of ``vfm_core/reporting/templates`` with ``context``."""
    return ENV.get_template(template_name).render(**context)


def _default_file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


#: Mode of a new page: what ``open()`` would give. The atomic writer's temporary file is
#: private (0600); a report is meant to be read by others.
_PAGE_MODE = _default_file_mode()


def write_page(path: str | os.PathLike[str], html: str) -> Path:
    """Write a rendered page to ``path`` atomically (never half-written); return the path."""

    def write(temp: Path) -> None:
        temp.write_text(html, encoding="utf-8")
        temp.chmod(_PAGE_MODE)

    return write_with(path, write)
