"""The demo's Table 1: one function over a list of methods, mean +- std over draws, per patch and per pixel."""

from pathlib import Path

from specgpu.apps.demo import DemoResult, demo_profiles, table1_lines
from specgpu.rig.config import RigDescription


def result():
    r = DemoResult(Path("."), 0.0, {}, [], main="lab")
    r.draws = {"lab": {"narrowband": {"rmse": [0.004, 0.006], "dEab": [0.5, 0.7], "dE00": [0.3, 0.5],
                                      "px_rmse": [0.01, 0.01], "px_dE00": [1.3, 1.5], "K": 32},
                       "mine": {"dEab": [1.0], "dE00": [0.9], "px_dE00": [2.0], "K": 4}},
                "ideal": {"narrowband": {"rmse": [0.002, 0.002], "dEab": [0.2, 0.2], "dE00": [0.1, 0.1],
                                         "px_rmse": [0.004, 0.004], "px_dE00": [0.5, 0.5], "K": 31}}}
    return r


def test_table1_rows_for_the_methods_given():
    lines = table1_lines(result(), ["narrowband", "mine"])
    text = "\n".join(lines)
    assert "0.0050+-0.0014" in text and "1.40+-0.14" in text  # mean +- sample std of two draws
    assert "0.0020+-0.0000" in text
    assert any(line.split()[:2] == ["narrowband", "lab"] for line in lines)
    assert any(line.split()[:2] == ["narrowband", "ideal"] for line in lines)
    assert any("paper" in line and "0.0194" in line for line in lines)
    mine = [line for line in lines if line.startswith("mine")]
    assert len(mine) == 1 and mine[0].split()[2] == "-"  # no RMSE for an XYZ method
    assert "mine" not in "\n".join(table1_lines(result(), ["narrowband"]))


def test_demo_profiles():
    default = demo_profiles()
    assert list(default) == ["lab", "ideal"] and default["lab"].realism.any and not default["ideal"].realism.any
    assert list(demo_profiles(RigDescription())) == ["ideal"]


def test_table1_expected_columns_for_a_plan_that_records_one():
    r = result()
    r.draws["lab"]["optimal-9"] = {"rmse": [0.008, 0.008], "dEab": [0.4, 0.5], "dE00": [0.3, 0.3],
                                   "px_rmse": [0.01, 0.01], "px_dE00": [1.5, 1.6], "px_rms": [0.0110, 0.0130],
                                   "K": 10, "expected_rmse": 0.0100}
    lines = table1_lines(r, ["narrowband", "optimal-9"])
    row = next(line for line in lines if line.startswith("optimal-9"))
    assert row.split()[-3:] == ["0.0120+-0.0014", "0.0100", "1.20"]  # measured RMS, expected, their ratio
    plain = next(line for line in lines if line.startswith("narrowband"))
    assert plain.split()[-1] == "32"  # no expected RMSE: the row ends at the frame count
    assert lines[0].split()[-3:] == ["pixel", "expected", "ratio"]


def _small_lab():
    from dataclasses import replace

    from specgpu.apps.demo import demo_profiles

    lab = demo_profiles()["lab"]
    return replace(lab, camera=replace(lab.camera, roi_width=320, roi_height=240))


def test_estimator_rows_measured_on_the_chart_against_numpy():
    """The demo's new rows on a small lab twin: the designs and the Wiener decoder planned as the demo does,
    captured with the corrections, and px_rms against the NumPy RMS of the recovery's error over the patches."""
    import numpy as np

    from specgpu.apps.demo import ESTIMATOR_ROWS
    from specgpu.apps.demo_measure import chart_with_white, measure_methods
    from specgpu.calibration import calibrate
    from specgpu.pipeline.evaluate import truth_cube
    from specgpu.pipeline.recovery import EVALUATION_CHART, default_basis
    from specgpu.planning import default_prior
    from specgpu.planning.estimator_plans import study_plans

    desc = _small_lab()
    bundle = calibrate(desc, seed=0)
    prior = default_prior(EVALUATION_CHART)
    plans = study_plans(desc, bundle, prior, default_basis(EVALUATION_CHART), methods=ESTIMATOR_ROWS,
                        chart=EVALUATION_CHART)
    assert list(plans) == list(ESTIMATOR_ROWS)
    assert [p.K for p in plans.values()] == [9, 9, 6, 3]
    assert all(p.exposure_s <= 0.1 + 1e-9 for p in plans.values())
    scene, roi = chart_with_white(desc, EVALUATION_CHART)
    seen = {}

    def keep(name, draw, y, plan, res):
        seen[name] = np.asarray(y, np.float64)

    rows = measure_methods(desc, bundle, plans, scene, draws=1, seed=0, white_roi=roi, ambient=True,
                           on_result=keep)
    mask = np.any(list(scene.masks.values()), axis=0)
    for name, plan in plans.items():
        r = rows[name]
        assert r["K"] == plan.K + 1  # the ambient frame
        assert r["expected_rmse"] == plan.params["expected"]["rmse"] > 0
        err = (seen[name] - truth_cube(scene, plan.output_wavelengths))[mask]
        assert abs(r["px_rms"][0] - np.sqrt(np.mean(err ** 2))) < 1e-9
    # numbers that make sense: the designs beat the paper's decoder re-used, more frames beat fewer, and each
    # decoder's measured error on the chart is near what it expects on its prior (this chart is not in it)
    rms = {n: rows[n]["px_rms"][0] for n in plans}
    assert rms["optimal-9"] < rms["optimal-6"] < rms["optimal-3"] and rms["optimal-9"] < rms["wiener-9"]
    assert rms["optimal-9"] < 0.015 and rows["optimal-3"]["dEab"][0] < 1.5
    for n in plans:
        assert 0.6 < rms[n] / rows[n]["expected_rmse"] < 1.5, (n, rms[n], rows[n]["expected_rmse"])


def test_equal_time_rows_with_their_sequence_time_and_limit():
    from specgpu.apps.demo import equal_time_lines
    from specgpu.planning.bound import Bound

    r = result()
    r.draws["lab"]["optimal-9@60ms"] = {"rmse": [0.01], "dEab": [0.5], "dE00": [0.4], "px_rmse": [0.012],
                                        "px_dE00": [0.9], "px_rms": [0.013], "K": 10, "sequence_ms": 59.9,
                                        "expected_rmse": 0.0125}
    r.bounds = {60.0: Bound(9, 0.054, 0.0059, 0.0082, 0.0078, 0.0121, 4)}
    lines = equal_time_lines(r)
    assert lines[0] == "-- 9 frames within 60 ms per sequence --"
    row = next(line for line in lines if line.startswith("optimal-9@60ms"))
    assert row.split()[-5:-3] == ["59.9", "10"]  # the sequence time beside the frame count
    assert any("limit" in line and ">= 0.0082" in line and "0.0121" in line for line in lines)
    assert not any("40 ms" in line for line in lines)  # a budget with no row measured is left out


def test_the_demo_pages_run_time_counts_its_figures(monkeypatch):
    import time

    import specgpu.apps.report as report
    from specgpu.apps.demo import _html

    def slow_figures(summaries, bundle, keep=None):  # the page's last figures, drawn in half a second
        time.sleep(0.5)
        return "<h2>Illuminant sequences</h2>"

    monkeypatch.setattr(report, "_illuminants_section", slow_figures)
    r = result()
    start = time.perf_counter()
    page = _html(r, None, None, None, start)
    assert 0.5 <= r.seconds <= time.perf_counter() - start
    assert f"Run time {r.seconds:.1f} s, figures included" in page and "Illuminant sequences" in page


def test_each_recovery_is_scored_once_for_the_tables_and_the_report(monkeypatch):
    """measure_methods hands each recovery with its reports to ``on_scored``; the report's summary takes them
    instead of scoring the recovery again."""
    import pytest

    import specgpu.apps.report as report
    from specgpu.apps.demo_measure import chart_with_white, measure_methods
    from specgpu.calibration import oracle_calibration
    from specgpu.pipeline.recovery import EVALUATION_CHART
    from specgpu.planning import make_plan

    desc = RigDescription(camera=_small_lab().camera)
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0)
    scene, _ = chart_with_white(desc, EVALUATION_CHART)
    seen = []
    rows = measure_methods(desc, bundle, {"nb": plan}, scene, on_scored=lambda *args: seen.append(args))
    (name, draw, y, made, _, patch, pixels), = seen
    assert (name, draw, made) == ("nb", 0, plan) and patch is rows["nb"]["reports"][0]
    assert pixels.statistics()["delta_E_2000"]["mean"] == pytest.approx(rows["nb"]["px_dE00"][0])

    def not_again(*args, **kwargs):
        raise AssertionError("scored again")

    monkeypatch.setattr(report, "evaluate_pixels", not_again)
    monkeypatch.setattr(report, "evaluate_reflectance", not_again)
    summary = report.summarise_method(name, plan, y, scene, patch=patch, pixels=pixels)
    assert summary.patch is patch and summary.pixels == pixels.statistics()
    assert summary.delta_E is pixels.delta_E_2000
