"""The named estimator and design configurations: the cross-validated error of a Wiener plan against NumPy and the
training sets it leaves out one at a time."""

import numpy as np
import pytest
from estimator_helpers import DESC, WL

import specgpu.planning as E
from specgpu.planning import make_plan
from specgpu.planning.estimator_plans import cross_validated_error, training_sets
from specgpu.planning.estimators import interp_rows
from specgpu.planning.priors import training_database


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
    cv = cross_validated_error(plan, bundle, sets, prior, noise)
    assert cv["rmse"] == pytest.approx(np.sqrt(np.mean(per) + noise_part), rel=1e-9)
    assert cv["mismatch"]["b"] == pytest.approx(np.sqrt(per[1]), rel=1e-9)
    with pytest.raises(ValueError, match="at least two training sets") as err:
        cross_validated_error(plan, bundle, {"a": spectra}, prior, noise)
    assert "\n" not in str(err.value)


def test_training_sets_split_the_database_by_set():
    sets = training_sets()
    db = training_database()
    assert sum(len(r) for r in sets.values()) == len(db) and "CIE 1995 TCS" not in sets
    assert sets["CIE 2017 CES"].shape == (99, db.reflectance.shape[1])
    first = db.labels.index(next(label for label in db.labels if label.startswith("RAW to ACES v1/")))
    np.testing.assert_array_equal(sets["RAW to ACES v1"][0], db.reflectance[first])
