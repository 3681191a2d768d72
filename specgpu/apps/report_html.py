"""The report's HTML: one self-contained page (images embedded as data URIs, no script, no font or style sheet
from the network), tables as real ``<table>`` elements with the best figure of each column marked, and a style
sheet that keeps every table and image within the page from 1000 to 1900 px wide (wide tables scroll inside
their own box, images shrink to the column, figure cards wrap onto as many rows as the width needs)."""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass

__all__ = ["Cell", "cell", "html_table", "image_tag", "figure_card", "card_grid", "page", "STYLE"]

STYLE = """
*{box-sizing:border-box}
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;padding:1.2em 2vw;color:#222;
 line-height:1.4;max-width:1860px}
h1{font-size:1.5em;margin:.2em 0 .4em} h2{font-size:1.25em;margin:1.6em 0 .5em;border-bottom:1px solid #ccc}
h3{font-size:1.05em;margin:1em 0 .3em}
p,li{max-width:110ch}
.summary{background:#f4f6f8;border:1px solid #d8dde3;border-radius:6px;padding:.6em 1em}
.table-wrap{max-width:100%;overflow-x:auto;margin:.4em 0 1em}
table{border-collapse:collapse;font-size:13px;font-variant-numeric:tabular-nums}
caption{text-align:left;font-weight:600;padding:.3em 0;caption-side:top}
th,td{border:1px solid #d0d0d0;padding:.2em .5em;text-align:right;white-space:nowrap}
th{background:#eef1f4;white-space:normal;vertical-align:bottom;max-width:9em}
.sd{font-size:11px;color:#555;font-weight:400}
td.text,th.text{text-align:left}
tr.paper td{color:#555;font-style:italic;background:#fafafa}
tr.section td{background:#eef1f4;font-weight:600}
tr.limit td{color:#555}
td.best{background:#dff3e0;font-weight:700}
img{max-width:100%;height:auto;display:block}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:1em;align-items:start}
.grid.wide{grid-template-columns:repeat(auto-fill,minmax(640px,1fr))}
figure{margin:0;min-width:0} figcaption{font-size:12px;color:#444;margin-top:.2em}
.note{font-size:12px;color:#555}
"""


@dataclass(frozen=True)
class Cell:
    """A table cell: its text, the number that ranks it (None: not ranked) for the best-of-column mark, a
    second line in small type (a standard deviation), so wide ``mean ± std`` columns stay narrow, and the number
    of columns it spans (a section heading or a note across a table's row)."""

    text: str
    value: float | None = None
    sub: str = ""
    span: int = 1


def cell(value, digits: int = 2, *, std=None) -> Cell:
    """A numeric cell (``-`` for None or NaN), ``mean ± std`` when a std is given, ranked by the value."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return Cell("-")
    return Cell(f"{value:.{digits}f}", float(value), f"± {std:.{digits}f}" if std is not None else "")


def html_table(columns, rows, *, caption: str = "", best_columns=(), row_classes=None, text_columns=1) -> str:
    """A ``<table>`` in a scrolling box: ``columns`` the header texts, ``rows`` lists of cells (:class:`Cell` or
    plain text), the lowest ranked value of each column in ``best_columns`` (indices) marked best (every tie);
    ``row_classes`` a class per row (e.g. ``"paper"``); the first ``text_columns`` columns left-aligned. A column
    is marked only where it has two ranked values or more: a lone value is the lowest of nothing. A cell spanning
    several columns (``Cell.span``) stands for them all and is never ranked."""
    rows = [[c if isinstance(c, Cell) else Cell(str(c)) for c in row] for row in rows]
    at = [{j: c for j, c in zip(_columns(r), r) if c.span == 1 and c.value is not None} for r in rows]
    best = {}
    for j in best_columns:
        values = [cells[j].value for cells in at if j in cells]
        if len(values) > 1:
            best[j] = min(values)
    out = ["<div class='table-wrap'><table>"]
    if caption:
        out.append(f"<caption>{html.escape(caption)}</caption>")
    out.append("<thead><tr>" + "".join(
        f"<th class='text'>{html.escape(c)}</th>" if j < text_columns else f"<th>{html.escape(c)}</th>"
        for j, c in enumerate(columns)) + "</tr></thead><tbody>")
    for i, row in enumerate(rows):
        klass = (row_classes or [None] * len(rows))[i]
        tr = f"<tr class='{html.escape(klass)}'>" if klass else "<tr>"
        tds = []
        for j, c in zip(_columns(row), row):
            classes = (["text"] if j < text_columns or c.span > 1 else []) + (
                ["best"] if j in best and c.span == 1 and c.value is not None and c.value <= best[j] + 1e-12 else [])
            attr = (f" class='{' '.join(classes)}'" if classes else "") + (f" colspan='{c.span}'" if c.span > 1
                                                                            else "")
            sub = f"<br><span class='sd'>{html.escape(c.sub)}</span>" if c.sub else ""
            tds.append(f"<td{attr}>{html.escape(c.text)}{sub}</td>")
        out.append(tr + "".join(tds) + "</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


def _columns(row) -> list[int]:
    """The column each cell of ``row`` starts in (a cell spanning several moves the ones after it)."""
    starts, j = [], 0
    for c in row:
        starts.append(j)
        j += max(1, c.span)
    return starts


def image_tag(image: bytes, alt: str, mime: str = "image/png") -> str:
    """An ``<img>`` holding ``image`` (of type ``mime``) as a data URI (the page needs no other file)."""
    data = base64.b64encode(image).decode("ascii")
    return f"<img src='data:{mime};base64,{data}' alt='{html.escape(alt, quote=True)}'>"


def figure_card(image: bytes, caption: str, mime: str = "image/png") -> str:
    """An image with its caption below."""
    return f"<figure>{image_tag(image, caption, mime)}<figcaption>{html.escape(caption)}</figcaption></figure>"


def card_grid(cards, *, wide: bool = False) -> str:
    """Figure cards in a grid that wraps to the page's width."""
    return f"<div class='grid{' wide' if wide else ''}'>" + "".join(cards) + "</div>"


def page(title: str, body: str) -> str:
    """The whole document around ``body`` (HTML), with the report's style sheet inline."""
    return (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>{body}</body></html>\n")
