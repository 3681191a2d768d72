"""The demo's LED rig: its 60 ms rows measured on the demo's chart, shown in Table 1's equal-time rows beside
the DMD rig's."""

import pytest
from estimator_helpers import DESC

from specgpu.apps.demo_lights import LED_LABEL, led_draws, led_rig
from specgpu.apps.table1 import Table1, equal_time_rows, table1_text
from specgpu.pipeline.recovery import EVALUATION_CHART, default_basis
from specgpu.planning import default_prior
from specgpu.planning.priors import training_spectra


@pytest.mark.slow  # an LED rig calibrated, planned and captured as the demo does: about a minute
def test_the_led_rows_join_the_equal_time_table():
    prior = default_prior(EVALUATION_CHART)
    draws = led_draws(DESC, prior, default_basis(EVALUATION_CHART),
                      training_spectra(EVALUATION_CHART, prior.wavelengths), draws=1)
    assert set(draws) == {LED_LABEL} and led_rig(DESC).light.columns == 12
    runs = draws[LED_LABEL]
    assert {"symmetric-9@60ms", "wiener-9@60ms", "optimal-9@60ms"} <= set(runs)
    assert 0 < runs["optimal-9@60ms"]["dE00"][0] < 3
    text = "\n".join(table1_text(Table1(equal_time_rows(draws)), header=False))
    assert "9 frames within 60 ms per sequence" in text and LED_LABEL in text
