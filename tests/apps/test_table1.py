"""Table 1 built once and rendered twice: the console's lines and the report's HTML carry the same rows and
columns (the sequence time, the equal-time rows and their limit included)."""

from html.parser import HTMLParser

from specgpu.apps.table1 import COLUMNS, table1, table1_html, table1_text
from specgpu.planning.bound import Bound

DRAWS = {"lab": {"narrowband": {"rmse": [0.004, 0.006], "dEab": [0.5, 0.7], "dE00": [0.3, 0.5],
                                "px_rmse": [0.01, 0.01], "px_dE00": [1.3, 1.5], "K": 32, "sequence_ms": 330.4},
                 "optimal-9@60ms": {"rmse": [0.01], "dEab": [0.5], "dE00": [0.4], "px_rmse": [0.012],
                                    "px_dE00": [0.9], "px_rms": [0.013], "K": 10, "sequence_ms": 59.9,
                                    "expected_rmse": 0.0125}}}
BOUNDS = {60.0: Bound(9, 0.054, 0.0059, 0.0082, 0.0078, 0.0121, 4)}


class Rows(HTMLParser):
    """The header cells and each body row's cells (text, colspan)."""

    def __init__(self):
        super().__init__()
        self.header, self.rows, self._cell, self._in = [], [], None, None

    def handle_starttag(self, tag, attrs):
        if tag == "tr":
            self._in = []
        elif tag in ("td", "th"):
            self._cell = [tag, "", int(dict(attrs).get("colspan", 1)), dict(attrs).get("class", "")]

    def handle_data(self, data):
        if self._cell is not None:
            self._cell[1] += data

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._in.append(tuple(self._cell))
            self._cell = None
        elif tag == "tr":
            (self.header if self._in and self._in[0][0] == "th" else self.rows).append(self._in)


def rendered():
    table = table1(DRAWS, ["narrowband"], BOUNDS)
    parser = Rows()
    parser.feed(table1_html(table, "Table 1"))
    return table, table1_text(table), parser


def test_console_and_html_carry_the_same_rows_and_columns():
    table, lines, html = rendered()
    assert len(html.header[0]) == len(COLUMNS) and len(lines[0].split()) >= len(COLUMNS)
    assert [c[1] for c in html.header[0]][7] == "sequence ms" and "seq ms" in lines[0]
    assert len(html.rows) == len(lines) - 1 == len(table.rows)  # narrowband, paper, heading, optimal, limit
    heading, limit = html.rows[2], html.rows[4]
    assert lines[3] == "-- 9 frames within 60 ms per sequence --"
    assert heading == [("td", "9 frames within 60 ms per sequence", len(COLUMNS), "text")]
    assert limit[1][1] == "limit" and limit[2][2] == len(COLUMNS) - 2 and ">= 0.0082" in limit[2][1]
    assert ">= 0.0082" in lines[5] and "limit" in lines[5]
    optimal = html.rows[3]
    assert optimal[0][1] == "optimal-9@60ms" and optimal[7][1] == "59.9" and optimal[8][1] == "10"
    assert lines[4].split()[0] == "optimal-9@60ms" and lines[4].split()[-5:-3] == ["59.9", "10"]
    assert html.rows[0][7][1] == "330.4" and lines[1].split()[-2:] == ["330.4", "32"]


def test_the_lowest_is_marked_among_the_rows_with_values():
    _, _, html = rendered()
    best = [(r[0][1], j) for r in html.rows for j, c in enumerate(r) if "best" in c[3]]
    # per-patch RMSE: ours 0.0050 beside the paper's 0.0194 and the optimal row's 0.0100
    assert ("narrowband", 2) in best and ("optimal-9@60ms", 6) in best
    assert all(j in (2, 3, 4, 5, 6) for _, j in best)  # only the error columns are ranked
