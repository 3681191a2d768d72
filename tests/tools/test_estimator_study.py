"""The estimator study (``tools/studies/estimator_study.py`` and its ``estimator_rows``): the study's plans captured,
recovered and measured beside their expected error, the table it prints, and Hadamard's measured SNR gain over
narrowband."""

import numpy as np
import pytest
from estimator_helpers import DESC, H, W
from tool_helpers import load_tool

import specgpu.planning as E
from specgpu.planning.estimator_plans import study_plans
from specgpu.planning.priors import held_out_basis, held_out_spectra
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import patch_scene

study = load_tool("studies/estimator_rows.py")


def test_study_rows_on_the_held_out_chart(bundle, prior):
    names, wl, spec = held_out_spectra()
    scene = patch_scene(names, wl, spec, H, W)
    plans = study_plans(DESC, bundle, prior, held_out_basis(), methods=["narrowband-31", "tristimulus-D65"])
    rows = study.study_rows(DESC, bundle, scene, plans, runs=2)
    nb, tri = rows
    assert nb["name"] == "narrowband-31" and nb["K"] == 31 and nb["runs"] == 2
    assert 0 < nb["rmse"][0] < 0.01 and nb["dE2000"][0] < 1.0 and nb["rmse"][1] >= 0
    assert 0.75 < nb["rms"][0] / nb["expected_rmse"] < 1.33
    assert 0.8 <= nb["z"][0] <= 1.25 and 0.8 <= tri["z"][0] <= 1.25
    assert "rmse" not in tri and tri["dEab"][0] > 0 and tri["expected_rmse"] is None
    text = study.format_study(rows)
    assert "narrowband-31" in text and "tristimulus-D65" in text


def test_study_rows_on_the_lab_profile_with_corrections():
    """The lab profile's corrections in the study: an ambient frame per sequence and the white's rescaling; the
    recovery's error and the sigma above the ambient frame still agree (z std near 1)."""
    from dataclasses import replace

    from specgpu.calibration import calibrate
    from specgpu.rig.config import rig_from_dict
    from specgpu.rig.scene import white_tile_roi

    lab = rig_from_dict({"twin": {"profile": "lab"}, "camera": {"roi_width": W, "roi_height": H}}, source="<lab>")
    bundle = calibrate(lab, seed=0)
    prior = E.default_prior()
    names, wl, spec = held_out_spectra()
    scene = patch_scene(names, wl, spec, H, W, white_tile=0.99 * (1 + lab.realism.white_error))
    plans = study_plans(lab, bundle, prior, None, methods=["optimal-3"])
    rows = study.study_rows(lab, bundle, scene, plans, runs=1, de_sigma=False, white_roi=white_tile_roi(H, W))
    (r,) = rows
    assert r["K"] == 4  # the ambient frame beside the three designed ones
    assert 0.8 <= r["z"][0] <= 1.25 and r["dEab"][0] < 1.5
    assert 0.75 < r["rms"][0] / r["expected_rmse"] < 1.33
    # without the white tile's ROI the same plan is read raw (no ambient frame)
    raw = study.study_rows(replace(lab), bundle, scene, plans, runs=1, de_sigma=False)
    assert raw[0]["K"] == 3


def test_hadamard_recovers_like_narrowband_and_gains_snr():
    """Equal exposure (2 ms), 15 bands each, a read-noise-limited camera (300 e-) and a steady light: Hadamard's
    noise is lower by about the theory's (N + 1) / (2 sqrt N) = 2.07. (With the paper's camera, 14 e- of read
    noise, the frames are shot-noise-limited and multiplexing loses instead.)"""
    from dataclasses import replace

    desc = RigDescription(camera=CameraParameters(roi_width=W, roi_height=H, read_noise_e=300.0))
    desc = replace(desc, light=replace(desc.light, fluctuation_rms=0.0))
    g = study.hadamard_gain(desc, bands=15, exposure_s=0.002, seed=11)
    assert g["exposure_ms"] == pytest.approx(2.0) and g["narrowband_exposure_ms"] == pytest.approx(2.0)
    np.testing.assert_allclose(g["hadamard_mean"], 0.5, atol=0.02)
    np.testing.assert_allclose(g["narrowband_mean"], 0.5, atol=0.02)
    assert g["theory"] == pytest.approx(16 / (2 * np.sqrt(15)))
    assert 1.6 < g["gain"] < 2.4


def test_study_table_prints_no_none():
    row = {"name": "symmetric-9", "K": 9, "exposure_ms": 6.5, "rmse": (0.03, 0.001), "z": (1.0, 0.0),
           "expected_rmse": None, "rms": None}
    text = study.format_study([row])
    assert "None" not in text and "symmetric-9" in text
