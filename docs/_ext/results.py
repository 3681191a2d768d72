"""Tables of measured figures, rendered at build time from the JSON under ``docs/results/``.

``docs/results/refresh.py`` runs each measuring command and stores its JSON with the command, date, machine and
load; a page holds only the directive, so re-running the command and rebuilding updates the page::

    ```{results} bench
    ```

Each result name has a renderer here that turns its JSON into tables; every table is preceded by the line that
says when, where and by which command its figures were measured.
"""

from __future__ import annotations

import json
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive

RESULTS = Path(__file__).resolve().parents[1] / "results"


def _fmt(value, digits=3) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.0f}"
    return str(value)


def table(header: list[str], rows: list[list[str]]) -> nodes.table:
    """A docutils table of plain text cells."""
    tgroup = nodes.tgroup(cols=len(header))
    for _ in header:
        tgroup += nodes.colspec(colwidth=1)
    def row(cells):
        r = nodes.row()
        for cell in cells:
            entry = nodes.entry()
            entry += nodes.paragraph(text=str(cell))
            r += entry
        return r
    head = nodes.thead()
    head += row(header)
    body = nodes.tbody()
    for cells in rows:
        body += row(cells)
    tgroup += head
    tgroup += body
    out = nodes.table()
    out += tgroup
    return out


def provenance(record: dict) -> nodes.paragraph:
    """When, where and how: date, machine, load and the command (the one line above every result's tables)."""
    m = record["machine"]
    load = record.get("load_avg_1min") or {}
    para = nodes.paragraph()
    para += nodes.Text(f"Measured {record['date_utc']} on {m['cpu']} ({m['cores']} cores, {m['system']}, "
                       f"Python {m['python']}; load average {_fmt(load.get('start'))} at start, "
                       f"{_fmt(load.get('end'))} at end) in {record['wall_s']:g} s by ")
    para += nodes.literal(text=record["command"])
    para += nodes.Text(" (re-run with ")
    para += nodes.literal(text=f"python docs/results/refresh.py {record['name']}")
    para += nodes.Text(").")
    return para


def render_bench(result: dict) -> list[nodes.Node]:
    intro = nodes.paragraph(text=(
        f"Device {result['device']} ({result['platform']}); copy bandwidth "
        f"{_fmt(result['copy_bandwidth_GBps'])} GB/s on the device, {_fmt(result['numpy_copy_bandwidth_GBps'])} "
        f"GB/s for NumPy. Times are medians in ms; the baseline is the same work in NumPy / colour-science, "
        f"timed in the same run."))
    rows = [[c["case"], f"{c['width']} x {c['height']}", c["layout"] or "-", _fmt(c["device_ms"]),
             _fmt(c["api_ms"]), _fmt(c["baseline_ms"]), _fmt(c["speedup"]), _fmt(c["Mpix_per_s"]),
             _fmt(c["fraction_of_copy"]), _fmt(c["within_tolerance"])] for c in result["cases"]]
    cases = table(["case", "size", "layout", "device ms", "NumPy in/out ms", "baseline ms", "speed-up",
                   "Mpixel/s", "of copy bandwidth", "within tolerance"], rows)
    targets = table(["target", "threshold", "met"],
                    [[name, _fmt(t["threshold"]), _fmt(t["passed"])] for name, t in result["targets"].items()])
    return [intro, cases, nodes.paragraph(text="The kernel targets on this run:"), targets]


def render_accuracy(result: dict) -> list[nodes.Node]:
    header = ["method", "K", "exposure ms", "RMSE avg", "RMSE max", "dE*ab avg", "dE*ab max", "dE2000 avg",
              "dE2000 max", "runs"]
    rows = []
    for name, m in result["methods"].items():
        runs = m.get("runs") or []
        rows.append([name, m["K"], _fmt(m["exposure_ms"]),
                     *(_fmt(m[key][i], 3) if key in m else "-" for key in ("rmse", "delta_E_ab", "delta_E_2000")
                       for i in (0, 1)), len(runs)])
    spread = []
    for name, m in result["methods"].items():
        for key, label in (("rmse", "RMSE"), ("delta_E_ab", "dE*ab"), ("delta_E_2000", "dE2000")):
            values = [r[key][0] for r in m.get("runs", []) if key in r]
            if len(values) > 1:
                mean = sum(values) / len(values)
                std = (sum((v - mean) ** 2 for v in values) / len(values)) ** 0.5
                spread.append([name, label, _fmt(mean), _fmt(std)])
    out = [nodes.paragraph(text="The first run's patch means (24 patches; dE under D65 on 400-700 nm for the "
                                "reflectance methods, under the plan's illuminant for tristimulus):"),
           table(header, rows)]
    if spread:
        out += [nodes.paragraph(text="The per-run average over the runs with fresh noise:"),
                table(["method", "metric", "mean", "std"], spread)]
    cv = result.get("cumulative_variance")
    if cv:
        out.append(nodes.paragraph(text="Basis cumulative variance, m = 1..9: " + ", ".join(f"{v:.4f}" for v in cv)))
    return out


RENDERERS = {"bench": render_bench, "accuracy": render_accuracy}


class Results(Directive):
    """The ``results`` directive: one committed results file rendered as tables with its provenance."""

    required_arguments = 1
    has_content = False

    def run(self):
        name = self.arguments[0]
        path = RESULTS / f"{name}.json"
        env = self.state.document.settings.env
        env.note_dependency(str(path))  # a new measurement rebuilds the page
        if name not in RENDERERS:
            raise self.error(f"results: no renderer for {name!r} (known: {', '.join(RENDERERS)})")
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise self.error(f"results: cannot read {path.name}: {error}")
        return [provenance(record), *RENDERERS[name](record["result"])]


def setup(app):
    app.add_directive("results", Results)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
