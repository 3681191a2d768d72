"""The dark level on a realistic bench: calibration tells the camera's dark from the light the object gets with every
mirror off (room light, the DMD's off-state), plans add an ambient frame by default where there is such light, the
dark level is measured over the exposures plans use, and recover says in one line when the level it subtracts
cannot be trusted. The default command-line path on a lab bench must recover a chart of measured spectra without
bias."""

from dataclasses import replace

import numpy as np
import pytest
from cli_helpers import RIG, calibrated_rig, run
from hypothesis import given, settings
from hypothesis import strategies as st
from tool_helpers import load_tool

from specgpu.calibration.bundle import load_calibration
from specgpu.io.npz import read_cube_npz
from specgpu.planning import load_plan
from specgpu.planning.correction import ambient_index
from specgpu.rig.config import load_rig
from specgpu.rig.scene import write_scene

measured_chart = load_tool("studies/measured_chart.py")
LEVEL_EDGES, chart_errors = measured_chart.LEVEL_EDGES, measured_chart.chart_errors
measured_chart_with_white = measured_chart.measured_chart_with_white

SMALL = "[camera]\nroi_width = 320\nroi_height = 240\n"
STRIP = 0.95


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A small lab-profile rig calibrated through the CLI, and a chart of the 99 CIE 2017 samples with a white
    strip written as a scene file."""
    d = tmp_path_factory.mktemp("lab")
    (d / "rig.toml").write_text('[twin]\nprofile = "lab"\n' + SMALL)
    run("calibrate", "--rig", d / "rig.toml", "--out", d / "calib.npz")
    scene, roi = measured_chart_with_white(load_rig(d / "rig.toml"), 240, 320, white=STRIP)
    write_scene(d / "chart.npz", scene)
    return d, scene, roi


def _capture_recover(d, plan, roi, name):
    seq, cube = d / f"seq-{name}", d / f"cube-{name}.npz"
    run("capture", "--rig", d / "rig.toml", "--plan", plan, "--calib", d / "calib.npz", "--scene", d / "chart.npz",
        "--out", seq, "--seed", 7)
    res = run("recover", seq, "--out", cube, "--white-roi", ",".join(map(str, roi)), "--white-reflectance", STRIP)
    return res, cube


def test_default_plan_on_a_lab_bench_is_unbiased(lab):
    """Default options (no --ambient) on a lab bench: the plan gets an ambient frame, and narrowband-31 recovers the
    measured chart to a per-pixel RMSE <= 0.012 with every reflectance level's bias within +-0.005 (the calibration's
    all-off level of its white, subtracted everywhere, read the chart about 0.05 too dark)."""
    d, scene, roi = lab
    out = run("plan", "narrowband", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", d / "nb.npz")
    res, cube = _capture_recover(d, d / "nb.npz", roi, "nb")
    y, wl, meta = read_cube_npz(cube)
    err = chart_errors(y, wl, scene)
    assert err["px_rmse_patches"] <= 0.012, err
    levels = np.array(err["bias_by_level"])
    assert np.all(np.abs(levels[np.isfinite(levels)]) <= 0.005), dict(zip(LEVEL_EDGES, levels))
    assert abs(err["bias_400nm"]) <= 0.02, err
    # how: the plan got an ambient frame, said so, and recover trusts the dark it subtracts
    assert "adding an ambient frame" in out.output
    plan = load_plan(d / "nb.npz")
    assert ambient_index(plan) == plan.K - 1 and plan.K == 32
    assert "dark level not trusted" not in res.output


def test_no_ambient_on_a_lab_bench_is_flagged(lab):
    """--no-ambient where the calibration found light with every mirror off: the plan warns, recover prints one
    warning line and records it with the cube (the recovery is biased dark, as measured)."""
    d, scene, roi = lab
    out = run("plan", "narrowband", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", d / "nb0.npz",
              "--no-ambient")
    assert "Warning: no ambient frame" in out.output
    plan = load_plan(d / "nb0.npz")
    assert ambient_index(plan) is None and plan.K == 31
    res, cube = _capture_recover(d, d / "nb0.npz", roi, "nb0")
    warnings = [line for line in res.output.splitlines() if line.startswith("Warning:")]
    assert len(warnings) == 1 and "dark level not trusted" in warnings[0], res.output
    assert "light with every mirror off" in warnings[0] and "below that level" in warnings[0], warnings[0]
    y, wl, meta = read_cube_npz(cube)
    assert "dark level not trusted" in str(meta)
    assert chart_errors(y, wl, scene)["bias_by_level"][0] < -0.02  # what the warning is about


def test_calibration_measures_the_light_with_every_mirror_off(lab):
    """The lab calibration finds the room light and off-state (ideal: none), measures the dark level up to the
    longest default exposure, and dark_at reproduces each measured level."""
    from specgpu.planning.correction import ambient_needed

    d, _, _ = lab
    b = load_calibration(d / "calib.npz")
    r = b.reports
    assert b.mirrors_off_light is True and r["mirrors_off_fraction"] > 0.05
    assert ambient_needed(b)[0]
    ts, lv = b.dark_table
    assert ts[0] < b.exposure_s < ts[-1] and ts[-1] >= 0.25
    for t, level in zip(ts, lv):
        assert float(np.mean(b.dark_at(t))) == pytest.approx(level, abs=0.01)
    # the camera's own (capped) dark is below the white's all-off level, by the light: about 24 DN at 55 ms
    assert r["camera_dark_levels_dn"][-1] < lv[-1] - 50
    # a bundle that could not tell (no capped dark: a real rig without a shutter, an older file) gets the frame
    unknown = replace(b, reports={k: v for k, v in r.items() if k != "mirrors_off_light"})
    assert unknown.mirrors_off_light is None and ambient_needed(unknown)[0]


def test_ideal_bench_keeps_its_plans(tmp_path):
    """On the ideal twin (no light with every mirror off) the default plan is unchanged: no ambient frame, and
    recover trusts the calibration's dark. The rig is the small ideal one, whose ``specgpu calibrate`` bundle the
    session makes once (``calibrated_rig``)."""
    from specgpu.planning.correction import ambient_needed

    assert RIG == SMALL
    calibrated_rig(tmp_path)
    b = load_calibration(tmp_path / "calib.npz")
    assert b.mirrors_off_light is False and not ambient_needed(b)[0]
    out = run("plan", "narrowband", "--calib", tmp_path / "calib.npz", "--out", tmp_path / "nb.npz")
    assert "ambient" not in out.output
    assert ambient_index(load_plan(tmp_path / "nb.npz")) is None
    run("capture", "--plan", tmp_path / "nb.npz", "--calib", tmp_path / "calib.npz", "--rig", tmp_path / "rig.toml",
        "--scene", "colorchecker", "--out", tmp_path / "seq", "--seed", 1)
    res = run("recover", tmp_path / "seq", "--out", tmp_path / "cube.npz")
    assert "Warning" not in res.output


def test_dark_warning_names_an_exposure_outside_the_measured_range(lab):
    """A bundle measured its dark level at some exposures only: a plan exposed outside them is flagged."""
    from specgpu.pipeline.capture_folder import SequenceFolder
    from specgpu.pipeline.recovery import dark_warning
    from specgpu.planning import make_plan

    d, _, _ = lab
    b = load_calibration(d / "calib.npz")
    b = replace(b, reports={**b.reports, "mirrors_off_light": False,
                            "dark_exposures_s": [0.005, 0.011], "dark_levels_dn": [16.0, 16.1]})
    plan = make_plan("narrowband", b)
    assert plan.exposure_s > 0.011
    frames = np.broadcast_to(b.dark_at(plan.exposure_s).astype(np.uint16) + np.uint16(40),
                             (1, plan.K, *b.frame_shape)).copy()
    msg = dark_warning(SequenceFolder(d, frames, plan, b, [], {}))
    assert msg is not None and "outside the 5-11 ms" in msg and "\n" not in msg
    inside = replace(b, reports={**b.reports, "dark_exposures_s": [0.005, 0.25], "dark_levels_dn": [16.0, 18.0]})
    assert dark_warning(SequenceFolder(d, frames, make_plan("narrowband", inside), inside, [], {})) is None


@pytest.fixture(scope="module")
def oracle():
    from specgpu.calibration.bundle import oracle_calibration
    from specgpu.rig.camera import CameraParameters
    from specgpu.rig.config import RigDescription

    return oracle_calibration(RigDescription(camera=CameraParameters(roi_width=320, roi_height=240)))


@settings(max_examples=60, deadline=None)
@given(table=st.one_of(
    st.lists(st.tuples(st.floats(1e-4, 1.0), st.floats(-1e3, 1e3)), min_size=2, max_size=5,
             unique_by=lambda p: p[0]).map(lambda ps: tuple(map(list, zip(*sorted(ps))))),
    st.tuples(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3), st.none()),
                       max_size=5), st.lists(st.floats(-1e3, 1e3), max_size=5))),
    t=st.floats(1e-5, 1.0))
def test_dark_table_from_any_report_is_used_or_ignored(oracle, table, t):
    """Whatever a bundle's reports hold for the dark table, dark_at stays finite: a valid table (increasing, finite,
    as long as its levels) is interpolated, anything else falls back to the dark current."""
    ts, lv = table
    b = replace(oracle, reports={**oracle.reports, "dark_exposures_s": ts, "dark_levels_dn": lv})
    table, levels = b.dark_table
    d = b.dark_at(t)
    assert d.shape == b.frame_shape and np.all(np.isfinite(d))
    if table is None:
        np.testing.assert_allclose(d, oracle.dark + oracle.dark_rate_dn_per_s * (t - oracle.exposure_s), atol=1e-3)
    else:
        assert table.size == levels.size >= 2 and np.all(np.diff(table) > 0)
        if table[0] <= t <= table[-1] and table[0] <= b.exposure_s <= table[-1]:
            want = np.interp(t, table, levels) - np.interp(b.exposure_s, table, levels)
            assert float(np.mean(d - b.dark)) == pytest.approx(want, abs=1e-3 * (1 + abs(want)))
