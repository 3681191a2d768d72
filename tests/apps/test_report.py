"""The HTML report: real tables with the best of each column marked, maps with colour bars on one scale, sRGB
renderings against colour-science, and a run folder's report that parses, embeds every image and reaches no
network."""

import base64
from html.parser import HTMLParser
from pathlib import Path

import colour
import numpy as np
import pytest
from capture_helpers import write_chart_capture

from specgpu.apps.report_figures import (
    DELTA_E_LABEL,
    common_scale,
    map_figure,
    spectra_figure,
    sRGB_rendering,
)
from specgpu.apps.report_html import Cell, cell, html_table, page


class Elements(HTMLParser):
    """Every start tag with its attributes, and the text inside <td> cells with their classes."""

    def __init__(self):
        super().__init__()
        self.tags, self.cells, self._td = [], [], None

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag == "td":
            self._td = [dict(attrs).get("class", ""), ""]

    def handle_data(self, data):
        if self._td is not None:
            self._td[1] += data

    def handle_endtag(self, tag):
        if tag == "td" and self._td is not None:
            self.cells.append(tuple(self._td))
            self._td = None


def parse(text) -> Elements:
    p = Elements()
    p.feed(text)
    p.close()
    return p


def test_table_marks_the_lowest_of_each_ranked_column_and_every_tie():
    rows = [["a", cell(0.5), cell(3.0)], ["b", cell(0.25), cell(3.0)], ["c", Cell("-"), cell(4.0)]]
    doc = parse(html_table(["m", "x", "y"], rows, best_columns=(1, 2)))
    best = [text for cls, text in doc.cells if "best" in cls]
    assert best == ["3.00", "0.25", "3.00"]  # row by row
    assert [t for t, _ in doc.tags][:2] == ["div", "table"]


def test_cell_formats_mean_and_std_and_dashes_nan():
    c = cell(1.234, 2, std=0.05)
    assert (c.text, c.value, c.sub) == ("1.23", 1.234, "± 0.05")
    assert "1.23<br><span class='sd'>± 0.05</span>" in html_table(["x"], [[c]], text_columns=0)
    assert cell(float("nan")).text == "-" and cell(None).value is None


def test_map_figure_has_a_colour_bar_with_its_unit_and_the_fixed_scale():
    data = np.linspace(0, 20, 12 * 16).reshape(12, 16)
    fig = map_figure(data, vmax=7.5, label=DELTA_E_LABEL, title="x")
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 1
    assert "CIELAB units" in bars[0].get_ylabel()
    image = fig.axes[0].images[0]
    assert image.get_clim() == (0.0, 7.5)
    with pytest.raises(ValueError, match="vmax"):
        map_figure(data, vmax=float("nan"), label="x")


def test_common_scale_is_the_largest_percentile_rounded_up():
    a = np.full((10, 10), 1.0)
    b = np.full((40, 40), 3.14159)
    b[0, :10] = 1e6  # a few outlier pixels (edges) do not set the scale
    assert common_scale([a, b]) == pytest.approx(3.2)
    assert common_scale([np.full((2, 2), np.nan)]) == 1.0


def test_sRGB_rendering_matches_colour_science_and_adapts_illuminant_A_to_white():
    XYZ = np.array([[[0.2, 0.3, 0.25], [0.5, 0.4, 0.1]]])
    ref = np.round(np.clip(colour.XYZ_to_sRGB(XYZ), 0, 1) * 255)
    assert np.abs(sRGB_rendering(XYZ).astype(int) - ref).max() <= 1
    white_A = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"])
    rgb = sRGB_rendering(white_A[None, None, :], "A")
    assert rgb.min() >= 253  # the perfect white under A renders white after adaptation
    with pytest.raises(ValueError, match="illuminant"):
        sRGB_rendering(XYZ, "nope")


def test_spectra_figure_draws_the_sigma_band():
    wl = np.arange(400.0, 701.0, 50.0)
    rec = np.full((2, wl.size), 0.5)
    fig = spectra_figure(("a", "b"), wl, rec, wl, rec * 0.9, sigma=np.full((2, wl.size), 0.1))
    band = fig.axes[0].collections[0]
    ys = band.get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(0.4) and ys.max() == pytest.approx(0.6)


def test_page_needs_no_network():
    text = page("t", "<p>x</p>")
    assert "http" not in text.replace("http-equiv", "")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A capture of the chart (narrowband, 20 nm steps) on a small twin, written as `specgpu capture` does."""
    root = tmp_path_factory.mktemp("run")
    write_chart_capture(root, "narrowband", noise_seed=3, noise_model=True)
    return root


def test_report_of_a_run_folder_parses_embeds_its_images_and_scores_the_capture(run_folder):
    from specgpu.apps.report import report_folder

    path = report_folder(run_folder)
    assert path == run_folder / "report.html"
    text = path.read_text()
    doc = parse(text)
    tags = [t for t, _ in doc.tags]
    assert "pre" not in tags and tags.count("table") >= 2  # the summary and the per-patch table
    images = [a["src"] for t, a in doc.tags if t == "img"]
    # truth and recovery under D65 and A, one spectra plot, one dE map, one sigma map, one illuminant plot
    assert len(images) == 8
    # the four renderings as JPEG (a photograph's content), the plots and maps as PNG, each a complete image
    kinds = [src.split(";")[0] for src in images]
    assert kinds.count("data:image/jpeg") == 4 and kinds.count("data:image/png") == 4
    for src in images:
        raw = base64.b64decode(src.split(",", 1)[1])
        assert raw.startswith(b"\xff\xd8") and raw.endswith(b"\xff\xd9") if "jpeg" in src else \
            raw.startswith(b"\x89PNG") and raw.endswith(b"IEND\xaeB`\x82")
    for t, a in doc.tags:
        for key in ("src", "href"):
            assert not str(a.get(key, "")).startswith(("http:", "https:", "//"))
    assert "url(" not in text and "@import" not in text
    assert "Recovered vs true spectra" in text and "± 1σ" in text and "CIEDE2000" in text
    # the summary row's per-patch dE2000 is what `specgpu evaluate` computes on the same recovery
    from specgpu.pipeline import evaluate_reflectance, read_capture, recover
    from specgpu.rig import colorchecker_scene

    seq = read_capture(run_folder / "narrowband")
    y = recover(seq)
    expected = evaluate_reflectance(y, seq.plan.output_wavelengths, colorchecker_scene(240, 320)).summary()
    row = [c for c in doc.cells][:10]
    assert row[0][1] == "narrowband"
    assert float(row[6][1]) == pytest.approx(expected["delta_E_2000"][0], abs=0.006)


def test_report_of_a_folder_without_a_capture_is_one_clear_error(tmp_path):
    from specgpu.apps.report import report_folder

    with pytest.raises(ValueError, match="no capture"):
        report_folder(tmp_path)
    with pytest.raises(FileNotFoundError, match="not a folder"):
        report_folder(tmp_path / "missing")


def test_cli_report_writes_the_page(run_folder, tmp_path):
    from click.testing import CliRunner

    from specgpu.apps.cli import main

    out = tmp_path / "r.html"
    res = CliRunner().invoke(main, ["report", str(run_folder), "--out", str(out), "--truth", "white"])
    assert res.exit_code == 0, res.output
    assert out.is_file() and "wrote" in res.output
    assert Path(out).read_text().count("<table") >= 1


def test_report_without_a_truth_shows_renderings_and_no_errors(run_folder, tmp_path):
    """A capture whose recorded scene cannot be rebuilt: no error figure is made up, the page says so."""
    import shutil

    from specgpu.apps.report import report_folder

    copy = tmp_path / "run"
    shutil.copytree(run_folder / "narrowband", copy / "narrowband")
    doc = (copy / "narrowband" / "sequence.json")
    doc.write_text(doc.read_text().replace('"scene": "colorchecker"', '"scene": "elsewhere.exr"'))
    text = report_folder(copy).read_text()
    assert "No truth for this run" in text and "Error maps" not in text and "Recovered vs true" not in text
    assert "narrowband under D65" in text and "Predicted uncertainty" in text


def test_a_report_on_one_capture_names_it_by_its_plan_and_marks_no_lowest(run_folder, tmp_path):
    import shutil

    from specgpu.apps.report import report_folder

    shutil.copytree(run_folder / "narrowband", tmp_path / "my-run")
    doc = parse(report_folder(tmp_path / "my-run", out=tmp_path / "r.html").read_text())
    assert doc.cells[0][1] == "narrowband"  # the plan's method, not the folder's name
    assert not any("best" in cls for cls, _ in doc.cells[:10])  # one row: nothing to be lowest against


def test_capture_names_tell_apart_captures_of_one_method():
    from types import SimpleNamespace

    from specgpu.apps.report import capture_names

    plans = {"tristimulus-D65": SimpleNamespace(method="tristimulus"), "a": SimpleNamespace(method="symmetric"),
             "tristimulus": SimpleNamespace(method="tristimulus")}
    assert capture_names(plans) == {"tristimulus-D65": "tristimulus (tristimulus-D65)", "a": "symmetric",
                                    "tristimulus": "tristimulus"}


def test_report_runtime_counts_the_figures(run_folder, tmp_path, monkeypatch):
    import re
    import time

    import specgpu.apps.report as report

    real = report.figure_png

    def slow(fig, *args, **kwargs):
        time.sleep(0.5)
        return real(fig, *args, **kwargs)

    monkeypatch.setattr(report, "figure_png", slow)  # 4 figures: 2 s of figures the run time must count
    start = time.perf_counter()
    text = report.report_folder(run_folder, out=tmp_path / "r.html").read_text()
    seconds = float(re.search(r"Run time ([0-9.]+) s, figures included", text).group(1))
    assert 2.0 <= seconds <= time.perf_counter() - start + 0.05


@pytest.fixture(scope="module")
def moving_folder(tmp_path_factory):
    """A capture of one sequence of the moving natural scene, with its motion truth: the report decodes and scores
    the first sequence of a capture that moved, and each further sequence's truth (a compressed 31-band cube) took
    seconds to write."""
    from capture_helpers import write_moving_capture

    root = tmp_path_factory.mktemp("moving")
    return write_moving_capture(root, "seqm", sequences=1)


@pytest.mark.slow  # the report's motion-compensated decoding, then the same decoded again to check its score
def test_report_of_a_moving_capture_compensates_and_scores_against_its_motion_truth(moving_folder, tmp_path):
    from click.testing import CliRunner

    from specgpu.apps.cli import main
    from specgpu.pipeline import evaluate_pixels, read_capture, recover
    from specgpu.rig.scene import load_scene

    res = CliRunner().invoke(main, ["report", str(moving_folder), "--out", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    line, = [line for line in res.output.splitlines() if "--motion" in line]
    assert "captured while the scene moved" in line and "--motion global --sequence 0" in line
    text = (tmp_path / "r.html").read_text()
    assert "motion-compensated" in text and "motion truth" in text
    seq = read_capture(moving_folder)
    truth0 = load_scene(moving_folder / "motion_truth" / "sequence_0000.npz", 240, 320)
    wl = seq.plan.output_wavelengths
    compensated = evaluate_pixels(recover(seq, sequence=0, motion="global"), truth0, wavelengths=wl).statistics()
    averaged = evaluate_pixels(recover(seq), truth0, wavelengths=wl).statistics()
    row = parse(text).cells[:10]
    assert row[0][1] == "narrowband"
    got = float(row[8][1])  # the per-pixel dE00 mean
    assert got == pytest.approx(compensated["delta_E_2000"]["mean"], abs=0.006)
    assert got < 0.7 * averaged["delta_E_2000"]["mean"]  # what the report said before: the frames averaged


def test_a_lone_value_is_not_marked_lowest_and_a_spanning_cell_is_not_ranked():
    one = parse(html_table(["m", "x"], [["a", cell(0.5)]], best_columns=(1,)))
    assert one.cells == [("text", "a"), ("", "0.50")]
    rows = [["a", cell(0.5), cell(2.0)], [Cell("a note", 0.1, span=3)], ["b", cell(0.7), cell(1.0)]]
    doc = parse(html_table(["m", "x", "y"], rows, best_columns=(1, 2)))
    assert [text for cls, text in doc.cells if "best" in cls] == ["0.50", "1.00"]
    assert ("td", {"class": "text", "colspan": "3"}) in doc.tags


def test_illuminant_figure_tells_targets_from_emitted_by_style_and_legend():
    from specgpu.apps.report_figures import illuminant_figure
    from specgpu.calibration import oracle_calibration
    from specgpu.planning import make_plan
    from specgpu.rig import CameraParameters, RigDescription

    bundle = oracle_calibration(RigDescription(camera=CameraParameters(roi_width=320, roi_height=240)))
    plan = make_plan("narrowband", bundle, step_nm=50.0)
    ax = illuminant_figure(plan, bundle).axes[0]
    styles = [line.get_linestyle() for line in ax.get_lines()]
    assert styles == ["-", "--"] * plan.K  # each illuminant: its target a faint band, what it emits dashed
    targets, emitted = ax.get_lines()[0::2], ax.get_lines()[1::2]
    assert all(t.get_color() == e.get_color() for t, e in zip(targets, emitted))
    assert min(t.get_linewidth() for t in targets) > max(e.get_linewidth() for e in emitted)
    legend = ax.get_legend()
    assert min(t.get_alpha() for t in targets) < 0.5 <= min(e.get_alpha() for e in emitted)
    assert [t.get_text() for t in legend.get_texts()] == ["target", "emitted by its quantized pattern"]
    assert [h.get_linestyle() for h in legend.legend_handles] == ["-", "--"]


def test_a_moving_capture_the_compensation_refuses_is_reported_as_still_with_the_reason(moving_folder, tmp_path,
                                                                                      monkeypatch):
    import specgpu.apps.report as report

    real = report.recover

    def refusing(folder, **kwargs):
        if kwargs.get("motion", "none") != "none":
            raise ValueError("motion=global does not combine with a reference white")
        return real(folder, **kwargs)

    monkeypatch.setattr(report, "recover", refusing)
    said = []
    text = report.report_folder(moving_folder, out=tmp_path / "r.html", say=said.append).read_text()
    line, = said
    assert "averaged" in line and "could not compensate it: motion=global does not combine" in line
    assert "could not compensate" in text
