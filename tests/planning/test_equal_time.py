"""Methods at equal sequence time: every row of every budget is made within it (its ambient frame included),
records its expected error, and the limit at each budget lies below the designs'."""

import pytest

import specgpu.planning as E
from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning.correction import with_ambient_frame
from specgpu.planning.equal_time import EQUAL_TIME, equal_time_bounds, equal_time_plans, row_name
from specgpu.planning.priors import HELD_OUT_CHART, held_out_basis, training_spectra
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


@pytest.fixture(scope="module")
def made():
    bundle = oracle_calibration(DESC)
    prior = E.default_prior()
    training = training_spectra(HELD_OUT_CHART, prior.wavelengths)
    plans = equal_time_plans(DESC, bundle, prior, held_out_basis(), training=training, extra_frames=1,
                             iterations=40)
    bounds = equal_time_bounds(DESC, bundle, prior, extra_frames=1, starts=1, iterations=40)
    return plans, bounds


def test_every_row_keeps_its_budget_with_its_ambient_frame(made):
    plans, _ = made
    assert len(plans) == sum(len(rows) for _, rows in EQUAL_TIME.values())
    for T, (K, rows) in EQUAL_TIME.items():
        for name in rows:
            plan = with_ambient_frame(plans[row_name(name, T)])
            assert plan.K == K + 1 and plan.sequence_s <= T / 1e3 * (1 + 1e-9), (name, T, plan.timing)
            if plan.output == "reflectance":
                assert plan.params["expected"]["rmse"] > 0


def test_the_limit_lies_below_the_rmse_designs(made):
    plans, bounds = made
    for T, (K, rows) in EQUAL_TIME.items():
        b = bounds[T]
        assert b.frames == K and b.lower_rmse <= b.achieved_rmse
        for name in rows:
            plan = plans[row_name(name, T)]
            if plan.output == "reflectance" and plan.params.get("objective", "rmse") == "rmse":
                # on the output grid, not the prior's: a little margin for the resampling
                assert plan.params["expected"]["rmse"] >= 0.95 * b.lower_rmse, (name, T)


def test_rows_designed_for_the_filter_sit_beside_the_optimal_ones():
    bundle = oracle_calibration(DESC)
    prior = E.default_prior()
    plans = equal_time_plans(DESC, bundle, prior, held_out_basis(), budgets=(40.0,), iterations=30,
                             denoise_radius=2)
    assert set(plans) == {row_name(n, 40.0) for n in ("biased-6", "wiener-6", "optimal-6", "optimal-6+denoise")}
    plain, filtered = plans[row_name("optimal-6", 40.0)], plans[row_name("optimal-6+denoise", 40.0)]
    assert "denoise" not in plain.params and filtered.params["denoise"]["radius"] == 2
    assert filtered.sequence_s <= 0.040 * (1 + 1e-9)
    assert filtered.params["expected"]["rmse_at_decoder_noise"] < plain.params["expected"]["rmse"]
