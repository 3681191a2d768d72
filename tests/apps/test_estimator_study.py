"""The estimator study: the held-out chart as a scene, the study's plans captured, recovered and measured beside
their expected error, the cross-validated error of a Wiener plan, the training sets, and Hadamard's measured SNR
gain over narrowband."""

import numpy as np
import pytest

import specgpu.planning as E
from specgpu.planning.priors import held_out_basis, held_out_spectra, training_database
from specgpu.apps import estimator_study as study
from specgpu.planning import make_plan
from specgpu.planning.estimators import interp_rows
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

from estimator_helpers import DESC, H, W, WL



def test_study_rows_on_the_held_out_chart(bundle, prior):
    names, wl, spec = held_out_spectra()
    scene = study.patch_scene(names, wl, spec, H, W)
    plans = study.study_plans(DESC, bundle, prior, held_out_basis(), methods=["narrowband-31", "tristimulus-D65"])
    rows = study.study_rows(DESC, bundle, scene, plans, runs=2)
    nb, tri = rows
    assert nb["name"] == "narrowband-31" and nb["K"] == 31 and nb["runs"] == 2
    assert 0 < nb["rmse"][0] < 0.01 and nb["dE2000"][0] < 1.0 and nb["rmse"][1] >= 0
    assert 0.75 < nb["rms"][0] / nb["expected_rmse"] < 1.33
    assert 0.8 <= nb["z"][0] <= 1.25 and 0.8 <= tri["z"][0] <= 1.25
    assert "rmse" not in tri and tri["dEab"][0] > 0 and tri["expected_rmse"] is None
    text = study.format_study(rows)
    assert "narrowband-31" in text and "tristimulus-D65" in text


def test_patch_scene_white_tile():
    from specgpu.rig.scene import white_tile_roi

    names, wl, spec = held_out_spectra()
    plain = study.patch_scene(names, wl, spec, H, W)
    tiled = study.patch_scene(names, wl, spec, H, W, white_tile=0.97)
    x, y, w, h = white_tile_roi(H, W)
    np.testing.assert_array_equal(tiled.reflectance[y:y + h, x:x + w], np.float32(0.97))
    assert set(tiled.masks) == set(plain.masks)
    outside = np.ones((H, W), bool)
    outside[max(0, y - 3):y + h + 3, max(0, x - 3):x + w + 3] = False
    np.testing.assert_array_equal(tiled.reflectance[outside], plain.reflectance[outside])
    with pytest.raises(ValueError, match="white_tile") as err:
        study.patch_scene(names, wl, spec, H, W, white_tile=-1.0)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="no room"):
        many = [f"{n}-{i}" for i in range(10) for n in names]
        study.patch_scene(many, wl, np.vstack([spec] * 10), H, W, white_tile=0.99)


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
    scene = study.patch_scene(names, wl, spec, H, W, white_tile=0.99 * (1 + lab.realism.white_error))
    plans = study.study_plans(lab, bundle, prior, None, methods=["optimal-3"])
    rows = study.study_rows(lab, bundle, scene, plans, runs=1, de_sigma=False, white_roi=white_tile_roi(H, W))
    (r,) = rows
    assert r["K"] == 4  # the ambient frame beside the three designed ones
    assert 0.8 <= r["z"][0] <= 1.25 and r["dEab"][0] < 1.5
    assert 0.75 < r["rms"][0] / r["expected_rmse"] < 1.33
    # without the white tile's ROI the same plan is read raw (no ambient frame)
    raw = study.study_rows(replace(lab), bundle, scene, plans, runs=1, de_sigma=False)
    assert raw[0]["K"] == 3


def test_cross_validated_error_against_numpy(bundle, spectra):
    prior = E.prior_from_spectra(spectra, WL, "test")
    noise = E.NoiseModel.from_rig(DESC, 0.05)
    plan = E.with_estimator(make_plan("narrowband", bundle, step_nm=30.0), bundle, "wiener", prior=prior,
                            noise=noise)
    rng = np.random.default_rng(5)
    idx = rng.permutation(spectra.shape[0])
    sets = {"a": spectra[idx[:40]], "b": spectra[idx[40:100]], "c": spectra[idx[100:]]}
    F = bundle.forward_matrix(plan.patterns, WL, plan.exposure_s)
    Wm = interp_rows(plan.output_wavelengths, WL)
    g, rv, lr = noise.gain_e_per_dn, noise.read_var_dn2, noise.light_rms
    per = []
    for name, held in sets.items():
        rest = np.concatenate([r for n, r in sets.items() if n != name])
        S = rest.T @ rest / rest.shape[0]
        o = F @ rest.mean(axis=0)
        N = np.diag(np.maximum(o, 0) / g + rv + lr ** 2 * np.diag(F @ S @ F.T))
        A = Wm @ S @ F.T @ np.linalg.inv(F @ S @ F.T + N)
        per.append(np.mean((held @ (Wm - A @ F).T) ** 2))
    S = prior.moment
    N = np.diag(np.maximum(F @ prior.mean, 0) / g + rv + lr ** 2 * np.diag(F @ S @ F.T))
    noise_part = np.mean(np.diag(plan.A @ N @ plan.A.T))
    cv = study.cross_validated_error(plan, bundle, sets, prior, noise)
    assert cv["rmse"] == pytest.approx(np.sqrt(np.mean(per) + noise_part), rel=1e-9)
    assert cv["mismatch"]["b"] == pytest.approx(np.sqrt(per[1]), rel=1e-9)
    with pytest.raises(ValueError, match="at least two training sets") as err:
        study.cross_validated_error(plan, bundle, {"a": spectra}, prior, noise)
    assert "\n" not in str(err.value)


def test_training_sets_split_the_database_by_set():
    sets = study.training_sets()
    db = training_database()
    assert sum(len(r) for r in sets.values()) == len(db) and "CIE 1995 TCS" not in sets
    assert sets["CIE 2017 CES"].shape == (99, db.reflectance.shape[1])
    first = db.labels.index(next(label for label in db.labels if label.startswith("RAW to ACES v1/")))
    np.testing.assert_array_equal(sets["RAW to ACES v1"][0], db.reflectance[first])


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
