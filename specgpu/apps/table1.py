"""Table 1 of the demo, built once (:func:`table1`) and rendered twice: as the console's fixed-width lines
(:func:`table1_text`) and as the report's HTML table (:func:`table1_html`), so both carry the same rows and
columns: every method per profile (mean +- std over the noise draws), the paper's row beneath it, and the
methods at equal sequence time under a heading per budget, with the limit of any design of that frame count.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from specgpu.apps import paper
from specgpu.apps.demo_measure import mean_std
from specgpu.apps.report_html import Cell, cell, html_table
from specgpu.planning.equal_time import EQUAL_TIME, row_name

__all__ = ["COLUMNS", "Value", "Row", "Table1", "table1", "method_rows", "equal_time_rows", "table1_text",
           "table1_html"]


@dataclass(frozen=True)
class Column:
    """A column: its console header and width, its HTML header, and whether its lowest value is marked."""

    text: str
    width: int
    html: str
    ranked: bool = False


#: Table 1's columns, in order (the first two, method and profile, are left-aligned text).
COLUMNS = (
    Column("method", 22, "method"), Column("profile", 8, "profile"),
    Column("RMSE patch", 16, "RMSE patch", True), Column("dEab patch", 13, "ΔE*ab patch", True),
    Column("dE00 patch", 13, "ΔE00 patch", True), Column("RMSE pixel", 16, "RMSE pixel", True),
    Column("dE00 pixel", 13, "ΔE00 pixel", True), Column("seq ms", 8, "sequence ms"), Column("proj.", 6, "frames"),
    Column("RMS pixel", 16, "RMS pixel"), Column("expected", 9, "expected RMSE"),
    Column("ratio", 6, "measured / expected"),
)


@dataclass(frozen=True)
class Value:
    """A number of the table: one value, or the mean and sample std of ``draws`` noise draws; ``digits`` after
    the point. A missing one is None in a row's cells."""

    mean: float
    digits: int = 2
    std: float | None = None
    draws: int = 1

    @classmethod
    def of(cls, values, digits: int):
        """The mean +- std of a list of draws (None when empty)."""
        if not values:
            return None
        mu, sd = mean_std(values)
        return cls(float(mu), digits, float(sd), len(values))


@dataclass
class Row:
    """A row: ``kind`` ``"ours"`` or ``"paper"`` (a method's ``name``, ``label`` and one cell per value column:
    a :class:`Value`, an int, or None), ``"section"`` (a heading, ``text``) or ``"limit"`` (a note, ``text``)."""

    kind: str
    name: str = ""
    label: str = ""
    cells: list = field(default_factory=list)
    text: str = ""


@dataclass
class Table1:
    """Table 1 of the paper as measured here: one row per method, the columns of :data:`COLUMNS`."""

    rows: list
    columns: tuple = COLUMNS


def _method_row(name, label, r) -> Row:
    exp = r.get("expected_rmse")
    expected = [None] * 3
    if exp is not None and r.get("px_rms"):
        expected = [Value.of(r["px_rms"], 4), Value(exp, 4), Value(mean_std(r["px_rms"])[0] / exp, 2)]
    seq_ms = Value(r["sequence_ms"], 1) if "sequence_ms" in r else None
    return Row("ours", name, label, [Value.of(r.get("rmse"), 4), Value.of(r.get("dEab"), 2),
                                     Value.of(r.get("dE00"), 2), Value.of(r.get("px_rmse"), 4),
                                     Value.of(r.get("px_dE00"), 2), seq_ms, int(r["K"]), *expected])


#: Table 1's paper row per tristimulus method (the paper's tristimulus imager has dE*ab only, Table 3).
_PAPER_TRISTIMULUS = {"tristimulus-D65": "D65", "tristimulus-A": "A"}


def method_rows(draws: dict, methods) -> list:
    """The rows of ``methods`` (names of ``draws``' methods; ``draws``: profile -> method -> metric -> values per
    draw): one per profile that ran it, then the paper's where it has one."""
    rows = []
    for name in methods:
        rows += [_method_row(name, label, runs[name]) for label, runs in draws.items() if name in runs]
        if name in paper.TABLE1:
            p = paper.TABLE1[name]
            rows.append(Row("paper", name, "paper", [Value(p[0], 4), Value(p[2], 2), None, None, None, None,
                                                     int(p[4])]))
        elif name in _PAPER_TRISTIMULUS:
            p = paper.TABLE3_SUMMARY[_PAPER_TRISTIMULUS[name]]
            rows.append(Row("paper", name, "paper", [None, Value(p[0], 2), None, None, None, None, 3]))
    return rows


def equal_time_rows(draws: dict, bounds=None) -> list:
    """The equal-time rows: per budget of :data:`~specgpu.planning.equal_time.EQUAL_TIME` with a method measured,
    a heading, its methods (each within the budget, ambient frame included) and the limit of any design of that
    frame count at that budget (``bounds``: budget ms -> :class:`~specgpu.planning.bound.Bound`)."""
    rows = []
    for T, (K, methods) in EQUAL_TIME.items():
        names = [row_name(n, T) for n in methods]
        if not any(n in runs for runs in draws.values() for n in names):
            continue
        rows.append(Row("section", text=f"{K} frames within {T:g} ms per sequence"))
        rows += method_rows(draws, names)
        b = (bounds or {}).get(T)
        if b is not None:
            rows.append(Row("limit", label="limit", text=f"expected RMSE on the prior: any {K}-frame design >= "
                            f"{b.lower_rmse:.4f}, best found {b.achieved_rmse:.4f} (noise-free rank limit "
                            f"{b.noise_free_rmse:.4f})"))
    return rows


def table1(draws: dict, methods, bounds=None) -> Table1:
    """Table 1: the rows of ``methods``, then the equal-time rows found in ``draws``."""
    return Table1(method_rows(draws, methods) + equal_time_rows(draws, bounds))


def _text(value, width: int) -> str:
    if value is None:
        return f"{'-':>{width}}"
    if isinstance(value, Value):
        d = value.digits
        text = f"{value.mean:.{d}f}" + (f"+-{value.std:.{d}f}" if value.std is not None else "")
        return f"{text:>{width}}"
    return f"{value:{width}d}"


def table1_text(table: Table1, *, header: bool = True) -> list[str]:
    """The console's lines: the header, then each row in fixed-width columns (a paper row under its method with
    the method left blank; a row ends at its last value; a heading between dashes; a limit as a sentence)."""
    cols = table.columns
    lines = []
    if header:
        lines.append("".join(f"{c.text:<{c.width}}" if j < 2 else f"{c.text:>{c.width}}" for j, c in
                             enumerate(cols)))
    for row in table.rows:
        if row.kind == "section":
            lines.append(f"-- {row.text} --")
            continue
        start = f"{'' if row.kind == 'paper' else row.name:<{cols[0].width}}{row.label:<{cols[1].width}}"
        if row.kind == "limit":
            lines.append(f"{start} {row.text}")
            continue
        cells = list(row.cells)
        while cells and cells[-1] is None:
            cells.pop()
        lines.append(start + "".join(_text(v, c.width) for v, c in zip(cells, cols[2:])))
    return lines


def _html_cell(value) -> Cell:
    if value is None:
        return Cell("-")
    if isinstance(value, Value):
        return cell(value.mean, value.digits, std=value.std if value.draws > 1 else None)  # one draw: no spread
    return Cell(str(value))


def table1_html(table: Table1, caption: str) -> str:
    """The report's ``<table>``: the same rows and columns, the lowest of each error column marked, the paper's
    rows in italics, a heading and a limit across the row."""
    n = len(table.columns)
    rows, classes = [], []
    for row in table.rows:
        if row.kind == "section":
            rows.append([Cell(row.text, span=n)])
        elif row.kind == "limit":
            rows.append([Cell(row.name), Cell(row.label), Cell(row.text, span=n - 2)])
        else:
            cells = [_html_cell(v) for v in row.cells] + [Cell("-")] * (n - 2 - len(row.cells))
            rows.append([Cell(row.name), Cell(row.label), *cells])
        classes.append(None if row.kind == "ours" else row.kind)
    ranked = [j for j, c in enumerate(table.columns) if c.ranked]
    return html_table([c.html for c in table.columns], rows, caption=caption, best_columns=ranked,
                      row_classes=classes, text_columns=2)
