"""The rig, grid and module-scoped fixtures the estimator tests share (planning's estimators and the apps' study)."""

import numpy as np
import pytest

import specgpu.planning as E
from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning.priors import training_spectra
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

H, W = 240, 320
DESC = RigDescription(camera=CameraParameters(roi_width=W, roi_height=H))
WL = np.arange(400.0, 700.0 + 1e-9, 5.0)


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def spectra():
    return training_spectra()


@pytest.fixture(scope="module")
def prior(spectra):
    return E.prior_from_spectra(spectra, WL, "test")


def noise_at(exposure_s):
    """The noise model of DESC's camera at an exposure (s)."""
    return E.NoiseModel.from_rig(DESC, exposure_s)
