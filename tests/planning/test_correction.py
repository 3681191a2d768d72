"""Drift correction at capture: the white ROI and the ambient frame."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from correction_helpers import DESC, white_chart_setup
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.evaluate import evaluate_reflectance
from specgpu.pipeline.recovery import recover
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning import make_plan
from specgpu.planning.correction import (
    ambient_index,
    corrected_decoder,
    parse_roi,
    probe_indices,
    white_gains,
    white_reflectance_curve,
    with_ambient_frame,
    with_drift_probes,
)
from specgpu.rig.realism import Drift, Realism


@pytest.fixture(scope="module")
def setup():
    return white_chart_setup()


def run(desc, bundle, plan, scene, **kw):
    res = capture_plan(desc, plan, scene, noise_seed=5, calibration=bundle)
    folder = SequenceFolder(Path("<memory>"), np.stack([s.frames for s in res.sequences]), plan, bundle, [], {})
    y = recover(folder, **kw)
    return evaluate_reflectance(y, plan.output_wavelengths, scene).summary()["rmse"][0], folder


def test_white_roi_undoes_lamp_drift(setup):
    bundle, plan, scene, roi = setup
    base, _ = run(DESC, bundle, plan, scene)
    drifted = replace(DESC, drift=Drift(lamp_cct_K=-300, lamp_output=-0.05))
    lost, folder = run(drifted, bundle, plan, scene)
    gains = white_gains(folder.frames[0], plan, bundle, roi)
    assert np.all(gains < 0.99) and np.all(gains > 0.85)
    assert gains[0] < gains[-1]  # a redder lamp lost more in the blue
    fixed, _ = run(drifted, bundle, plan, scene, white_roi=roi)
    assert lost > 2 * base
    assert fixed < 1.3 * base + 0.002


def test_ambient_frame_removes_light_not_from_the_mirrors(setup):
    bundle, plan, scene, roi = setup
    amb = with_ambient_frame(plan)
    assert amb.K == plan.K + 1 and ambient_index(amb) == plan.K and ambient_index(plan) is None
    np.testing.assert_array_equal(amb.A[:, -1], 0.0)
    bright = replace(DESC, realism=Realism(ambient_lux=40.0))
    lost, _ = run(bright, bundle, plan, scene)
    fixed, _ = run(bright, bundle, amb, scene)
    base, _ = run(DESC, bundle, plan, scene)
    assert lost > 3 * base and fixed < 1.5 * base + 0.002


def test_corrected_decoder_scales_columns(setup):
    _, plan, _, _ = setup
    g = np.linspace(0.9, 1.1, plan.K)
    np.testing.assert_allclose(corrected_decoder(plan, g) * g[None, :], plan.A)


@pytest.mark.parametrize("text,word", [
    ("1,2,3", "X,Y,W,H"), ("a,b,c,d", "X,Y,W,H"), ("300,10,40,5", "outside the 320 x 240 frame"),
    ("-1,0,5,5", "outside"), ("0,0,0,5", "width and height must be >= 1"),
])
def test_roi_errors_are_one_line(text, word):
    with pytest.raises(ValueError) as err:
        parse_roi(text, (240, 320))
    assert word in str(err.value) and "\n" not in str(err.value)


@settings(max_examples=50, deadline=None)
@given(st.integers(-10, 330), st.integers(-10, 250), st.integers(-2, 100), st.integers(-2, 100))
def test_roi_property(x, y, w, h):
    inside = x >= 0 and y >= 0 and w >= 1 and h >= 1 and x + w <= 320 and y + h <= 240
    if inside:
        assert parse_roi(f"{x},{y},{w},{h}", (240, 320)) == (x, y, w, h)
    else:
        with pytest.raises(ValueError, match="--white-roi"):
            parse_roi(f"{x},{y},{w},{h}", (240, 320))


def test_saturated_white_is_refused(setup):
    bundle, plan, scene, roi = setup
    frames = np.zeros((plan.K, 240, 320), np.uint16) + 100
    x, y, w, h = roi
    frames[3, y + 1, x + 1] = bundle.max_code
    with pytest.raises(ValueError, match=r"saturated in frame 3"):
        white_gains(frames, plan, bundle, roi)


def test_white_reflectance_values_and_csv(tmp_path):
    wl = np.array([400.0, 500.0, 600.0])
    np.testing.assert_allclose(white_reflectance_curve(None, wl), 0.99)
    np.testing.assert_allclose(white_reflectance_curve("0.95", wl), 0.95)
    p = tmp_path / "white.csv"
    p.write_text("400,0.9\n600,1.0\n")
    np.testing.assert_allclose(white_reflectance_curve(str(p), wl), [0.9, 0.95, 1.0])
    with pytest.raises(ValueError, match="neither a number nor a CSV"):
        white_reflectance_curve("nothing.csv", wl)
    with pytest.raises(ValueError, match=r"\(0, 1.5\]"):
        white_reflectance_curve(2.0, wl)


def test_spectral_refit_is_the_identity_without_drift_and_follows_a_colour_change(setup):
    bundle, plan, _, _ = setup
    ones = np.ones(plan.K)
    A1 = corrected_decoder(plan, ones, bundle)
    assert np.max(np.abs(A1 - plan.A)) < 1e-3 * np.max(np.abs(plan.A))
    # a light 10 % redder across 400-700 nm: the white's gains; the refit decoder undoes it on a grey
    grid = bundle.wavelengths
    r = np.exp(0.1 * (grid - 550.0) / 150.0)
    F = bundle.forward_matrix(plan.patterns, grid, plan.exposure_s)
    gains = (F @ (r * 0.99)) / (F @ np.full(grid.size, 0.99))
    A2 = corrected_decoder(plan, gains, bundle)
    grey = np.full(grid.size, 0.5)
    y = A2 @ (F @ (r * grey))
    assert np.max(np.abs(y - 0.5)) < 0.01


def test_drift_probe_is_a_thinned_narrow_band_the_decoder_does_not_use(setup):
    bundle, _, _, _ = setup
    plan = make_plan("tristimulus", bundle, illuminant="D65")
    assert probe_indices(with_drift_probes(plan, bundle)) == [plan.K, plan.K + 1]  # 430 and 650 nm by default
    probed = with_drift_probes(plan, bundle, (430.0,))
    assert probed.K == plan.K + 1 and probe_indices(probed) == [plan.K] and probe_indices(plan) == []
    np.testing.assert_array_equal(probed.A[:, :plan.K], plan.A)
    np.testing.assert_array_equal(probed.A[:, plan.K], 0.0)
    np.testing.assert_array_equal(probed.patterns[:plan.K], plan.patterns)
    lit = bundle.column_wavelengths[probed.patterns[-1] > 0]
    assert lit.min() > 419.0 and lit.max() < 441.0  # 20 nm around 430 nm
    # never brighter on a white than the plan's brightest frame
    F = bundle.forward_matrix(probed.patterns, bundle.wavelengths, probed.exposure_s).sum(axis=1)
    assert F[-1] <= F[:plan.K].max() * (1 + 1e-9)
    assert probed.expected_level[-1] <= plan.expected_level.max() * (1 + 1e-9)
    assert with_drift_probes(probed, bundle, (430.0,)) is probed
    both = with_ambient_frame(probed)
    assert ambient_index(both) == plan.K + 1 and probe_indices(both) == [plan.K]


@pytest.mark.parametrize("centres,word", [((200.0,), "must lie within the light's"),
                                          ((float("nan"),), "must lie within the light's")])
def test_drift_probe_errors_are_one_line(setup, centres, word):
    bundle, plan, _, _ = setup
    with pytest.raises(ValueError) as err:
        with_drift_probes(plan, bundle, centres)
    assert word in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match="before the ambient frame"):
        with_drift_probes(with_ambient_frame(plan), bundle)


def test_drift_probe_lets_a_three_frame_plan_follow_a_colour_drift(setup):
    """Tristimulus (3 broad frames) under -200 K / -3 % / +5 nm, 4 sequences (the colour fitted once on their mean
    gains): the white's 3 numbers alone cannot tell a cut-on shift from a colour-temperature change; probes at 430
    and 650 nm halve the colour error the drift leaves."""
    from specgpu.pipeline.evaluate import evaluate_XYZ

    bundle, _, scene, roi = setup
    plan = make_plan("tristimulus", bundle, illuminant="D65")
    probed = with_drift_probes(plan, bundle)
    drifted = replace(DESC, drift=Drift(lamp_cct_K=-200, lamp_output=-0.03, cut_on_nm=5))

    def de(desc, p, seed):
        res = capture_plan(desc, p, scene, noise_seed=seed, calibration=bundle, sequences=4)
        folder = SequenceFolder(Path("<memory>"), np.stack([s.frames for s in res.sequences]), p, bundle, [], {})
        y = recover(folder, white_roi=roi)
        return evaluate_XYZ(y, scene, illuminant="D65").summary()["delta_E_2000"][0]

    three = np.mean([de(drifted, plan, s) for s in (3, 4)])
    four = np.mean([de(drifted, probed, s) for s in (3, 4)])
    assert three > 0.25  # the 3-frame fit's bias (0.30 over 6 seeds; 0.11 without drift)
    assert four < 0.75 * three


def test_colour_is_fitted_once_on_the_sequences_mean_gains(setup, monkeypatch):
    import specgpu.pipeline.sequence_decoder as decoding
    import specgpu.planning.correction as corr

    bundle, plan, scene, roi = setup
    seen = []
    real = corr.corrected_decoder
    # patch the name where recover looks it up: its module's own binding when it imports the name at the top,
    # else the correction module's attribute (read at call time); a missed patch leaves ``seen`` empty
    where = decoding if hasattr(decoding, "corrected_decoder") else corr
    monkeypatch.setattr(where, "corrected_decoder",
                        lambda p, g, *a, **k: seen.append(np.array(g)) or real(p, g, *a, **k))
    res = capture_plan(DESC, plan, scene, noise_seed=2, calibration=bundle, sequences=3)
    frames = np.stack([s.frames for s in res.sequences])
    folder = SequenceFolder(Path("<memory>"), frames, plan, bundle, [], {})
    y = recover(folder, white_roi=roi)
    assert len(seen) == 1
    per = np.array([white_gains(frames[i], plan, bundle, roi, dark=bundle.dark_at(plan.exposure_s))
                    for i in range(3)])
    np.testing.assert_allclose(seen[0], np.exp(np.log(per).mean(axis=0)), rtol=1e-6)
    # each sequence decoded with its own frames' scaling: the mean of the three single-sequence recoveries
    one = [recover(folder, sequence=i, white_roi=roi) for i in range(3)]
    assert np.nanmax(np.abs(y - np.mean(one, axis=0))) < 0.02


def test_colour_is_fitted_only_beyond_the_lights_own_fluctuation(setup):
    """With the light's fluctuation measured (as ``calibrate`` does), gains spread within it are one power change
    (per-pattern scaling); a colour tilt well beyond it is fitted (a decoder that is not a column scaling)."""
    from specgpu.planning.correction import gain_noise

    bundle, plan, _, _ = setup
    assert gain_noise(plan, bundle) is None  # the oracle bundle measured nothing
    rep = {**bundle.reports, "light_fluctuation": 0.01, "light_fluctuation_exposure_s": plan.exposure_s * 4}
    b = replace(bundle, reports=rep)
    assert gain_noise(plan, b) == pytest.approx(0.02)
    assert gain_noise(plan, b, sequences=4) == pytest.approx(0.01)
    rng = np.random.default_rng(3)
    noisy = np.exp(0.02 * rng.standard_normal(plan.K))
    np.testing.assert_allclose(corrected_decoder(plan, noisy, b), plan.A / noisy[None, :])
    grid = b.wavelengths
    F = b.forward_matrix(plan.patterns, grid, plan.exposure_s)
    r = np.exp(0.25 * (grid - 550.0) / 150.0)  # a light 25 % redder across 400-700 nm
    tilted = (F @ (r * 0.99)) / (F @ np.full(grid.size, 0.99))
    A = corrected_decoder(plan, tilted, b)
    assert not np.allclose(A, plan.A / tilted[None, :], rtol=1e-3)
    # the same tilt within a fluctuation ten times larger is not told from noise
    loud = replace(bundle, reports={**rep, "light_fluctuation": 1.0})
    np.testing.assert_allclose(corrected_decoder(plan, tilted, loud), plan.A / tilted[None, :])
