"""Fixtures the calibration tests share: the small rig and its bundles (oracle, calibrated from a perturbed start,
calibrated on the lab bench with the design and the measured line shape), each made once for the folder."""

from dataclasses import replace

import pytest
from small_rig import DESC

from specgpu.calibration import calibrate, oracle_calibration
from specgpu.rig.realism import LAB


@pytest.fixture(scope="package")
def small_rig():
    """The paper's rig (its noise) at the camera's smallest region of interest."""
    return DESC


@pytest.fixture(scope="package")
def oracle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="package")
def calibrated():
    return calibrate(DESC, perturbation=0.3, repeats=4, seed=5)


@pytest.fixture(scope="package")
def lab_calibrated():
    desc = replace(DESC, profile="lab", realism=LAB)
    return desc, calibrate(desc, seed=3)


@pytest.fixture(scope="package")
def lab_measured(lab_calibrated):
    desc, gaussian = lab_calibrated
    return desc, gaussian, calibrate(desc, seed=3, line_shape="measured")
