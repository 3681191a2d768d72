"""The demo's LED rig beside its DMD rig: the same camera and chart with a 12-LED array as the light, calibrated by
the same procedure, its rows at 60 ms per sequence measured as the DMD's; Table 1's equal-time rows then show
both lights, one table."""

from __future__ import annotations

from dataclasses import replace

from specgpu.apps.demo_measure import chart_with_white, measure_methods
from specgpu.calibration import calibrate
from specgpu.pipeline.recovery import EVALUATION_CHART
from specgpu.planning.equal_time import equal_time_plans
from specgpu.rig.led import LEDParameters
from specgpu.rig.realism import Drift, Realism

__all__ = ["LED_LABEL", "LED_BUDGET_MS", "led_draws", "led_rig"]

#: The LED rig's label in Table 1 (a profile column of its own), and the budget of its rows.
LED_LABEL = "led12"
LED_BUDGET_MS = 60.0


def led_rig(description):
    """``description`` with the ``led12`` preset as its light, on the ideal bench (the lab profile's
    imperfections are the DMD lamp's and the room's; the LED array's own are off by default)."""
    return replace(description, light=LEDParameters(preset="led12"), profile="ideal", realism=Realism(),
                   drift=Drift(), capture_delay_s=None)


def led_draws(description, prior, basis, training, *, seed: int = 0, draws: int = 2, device=None,
              rows=None, bundle=None) -> dict:
    """``{LED_LABEL: method -> metric -> values per draw}`` for the demo's ``result.draws``: the rows of
    :data:`~specgpu.planning.equal_time.EQUAL_TIME` at :data:`LED_BUDGET_MS` on :func:`led_rig` of the demo's
    rig, calibrated, planned (one start, 100 iterations, as the demo's) and measured on the demo's chart; ``rows``:
    the row names to run (None: all); ``bundle``: the LED rig's calibration when made already (by
    :func:`specgpu.calibration.cache.cached_calibration`; None: calibrated here)."""
    led = led_rig(description)
    bundle = calibrate(led, seed=seed) if bundle is None else bundle
    plans = equal_time_plans(led, bundle, prior, basis, training=training, budgets=(LED_BUDGET_MS,), rows=rows)
    scene, _ = chart_with_white(led, EVALUATION_CHART)
    runs = measure_methods(led, bundle, plans, scene, draws=draws, seed=seed, device=device)
    for rows in runs.values():
        rows.pop("reports", None)
    return {LED_LABEL: runs}
