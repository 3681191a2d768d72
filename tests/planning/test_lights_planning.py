"""Plans for any light: designs within an LED array's primaries and duty steps, exposures of whole PWM periods,
and the narrow-band methods refused on a light that cannot make narrow bands, naming the bands it has."""

import numpy as np
import pytest

from specgpu.calibration import oracle_calibration
from specgpu.core.validate import BadArgument
from specgpu.planning import NoiseModel, make_plan
from specgpu.planning.bound import design_bound, primaries_limit
from specgpu.planning.design import _system_on, columns_within, plan_optimal
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.led import LED_PRESETS, LEDParameters

CAM = CameraParameters(roi_width=320, roi_height=240)


@pytest.fixture(scope="module")
def led():
    return oracle_calibration(RigDescription(light=LEDParameters(preset="led12"), camera=CAM))


@pytest.mark.parametrize("method", ["narrowband", "reciprocal"])
def test_narrow_bands_are_refused_on_leds_naming_their_bands(led, method):
    with pytest.raises(BadArgument) as err:
        make_plan(method, led)
    msg = str(err.value)
    assert "\n" not in msg and "12 fixed bands at " + ", ".join(f"{x:.0f}" for x in LED_PRESETS["led12"]) in msg
    assert "optimal" in msg and "narrowband" not in msg.split("use one of")[1]


def test_hadamard_multiplexes_groups_of_leds(led):
    plan = make_plan("hadamard", led, bands=7)
    assert plan.K == 7 and plan.patterns.shape == (7, 12)
    assert set(np.unique(plan.patterns)) <= {0, 255}
    assert np.all(np.diff(plan.output_wavelengths) > 0)
    with pytest.raises(ValueError, match="must not exceed this light's 12 LEDs"):
        make_plan("hadamard", led, bands=31)


def test_a_design_keeps_within_the_leds_duty_steps_whole_periods_and_budget(led, prior):
    desc = RigDescription(light=LEDParameters(preset="led12"), camera=CAM)
    plan = plan_optimal(led, prior, lambda t: NoiseModel.from_rig(desc, t), frames=9, sequence_s=0.060, starts=2)
    assert plan.K == 9 and plan.patterns.shape == (9, 12)
    assert plan.patterns.min() >= 0 and plan.patterns.max() <= 255
    periods = plan.exposure_s * 20000.0
    assert periods == pytest.approx(round(periods), abs=1e-6)
    assert plan.sequence_s <= 0.060 * (1 + 1e-9)
    assert plan.params["expected"]["rmse"] < 0.05


def test_a_tristimulus_plan_works_on_leds(led):
    plan = make_plan("tristimulus", led, illuminant="D65")
    assert plan.output_labels == ("X", "Y", "Z")
    assert plan.patterns.shape[1] == 12
    assert plan.exposure_s * 20000.0 == pytest.approx(round(plan.exposure_s * 20000.0), abs=1e-6)


def test_the_bound_knows_the_leds_span(led, bundle, prior):
    assert primaries_limit(_system_on(bundle, prior.wavelengths), prior.moment) is None  # the DMD spans every band
    r, mse = primaries_limit(_system_on(led, prior.wavelengths), prior.moment)
    assert r == columns_within(led, prior.wavelengths).sum() == 12 and mse > 0  # every LED within 400-700 nm
    desc = RigDescription(light=LEDParameters(preset="led12"), camera=CAM)
    b = design_bound(led, prior, lambda t: NoiseModel.from_rig(desc, t), frames=9, sequence_s=0.060, starts=1)
    limit = float(np.sqrt(mse / prior.wavelengths.size))
    assert b.primaries_rmse == pytest.approx(limit)
    assert limit <= b.lower_rmse <= b.achieved_rmse
    assert any("primaries" in line for line in b.lines())
