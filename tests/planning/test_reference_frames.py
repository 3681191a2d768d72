"""Broadband reference frames interleaved in a plan (``specgpu plan --reference-every M``)."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning import make_plan
from specgpu.planning.budget import budget_plan
from specgpu.planning.correction import with_ambient_frame, with_drift_probes
from specgpu.planning.reference_frames import (
    check_reference_every,
    pattern_indices,
    reference_count,
    reference_indices,
    reference_positions,
    with_reference_frames,
)
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


@pytest.fixture(scope="module")
def setup():
    bundle = oracle_calibration(DESC)
    return bundle, make_plan("hadamard", bundle, bands=7)


@pytest.mark.parametrize("every, refs", [(3, [0, 4, 8, 10]), (7, [0, 8]), (1, [0, 2, 4, 6, 8, 10, 12, 14]),
                                         (2, [0, 3, 6, 9, 11])])
def test_frames_at_their_places_with_zero_decoder_columns(setup, every, refs):
    bundle, plan = setup
    out = with_reference_frames(plan, bundle, every)
    assert reference_indices(out) == refs == reference_positions(plan.K, every)
    assert out.K == plan.K + len(refs) == plan.K + reference_count(plan.K, every)
    assert out.params["reference_every"] == every
    pats = pattern_indices(out)
    assert len(pats) == plan.K
    # the plan's own frames keep their order, patterns, decoder columns and levels
    np.testing.assert_array_equal(out.patterns[pats], plan.patterns)
    np.testing.assert_array_equal(out.A[:, pats], plan.A)
    np.testing.assert_array_equal(out.expected_level[pats], plan.expected_level)
    np.testing.assert_array_equal(out.A[:, refs], 0.0)
    # one broadband pattern: the same count of mirrors in every column, a white at the brightest frame's level
    ref = out.patterns[refs]
    assert np.all(ref == ref[0, 0]) and 1 <= ref[0, 0] <= plan.rows
    level = out.expected_level[refs[0]]
    assert level <= plan.expected_level.max() * (1 + 1e-9) and level > 0.9 * plan.expected_level.max()
    np.testing.assert_allclose(out.target_spectra[refs[0]], bundle.emitted(ref[:1])[0])


def test_the_timing_counts_the_reference_frames(setup):
    bundle, plan = setup
    out = with_reference_frames(plan, bundle, 3)
    assert out.frame_period_s == plan.frame_period_s
    assert out.timing["frames"] == 11
    np.testing.assert_allclose(out.sequence_s, 11 * plan.frame_period_s)
    np.testing.assert_allclose(out.sequence_s / plan.sequence_s, 11 / 7)


def test_a_budget_holds_the_reference_frames_or_is_refused(setup):
    bundle, _ = setup
    budget = 0.030
    extra = lambda k: reference_count(k, 3)  # noqa: E731
    fitted = budget_plan("hadamard", bundle, budget, bands=7, extra_frames=extra)
    out = with_reference_frames(fitted, bundle, 3)
    assert out.K == 11 and out.sequence_s <= budget * (1 + 1e-9)
    assert out.sequence_s > 0.9 * budget  # the exposure was made for 11 frames, not 7
    # a plan made for its 7 frames alone overruns the budget with 4 more: refused in one line
    tight = budget_plan("hadamard", bundle, budget, bands=7)
    with pytest.raises(ValueError, match=r"11 frames of .* ms take .* over the 30 ms budget") as err:
        with_reference_frames(tight, bundle, 3)
    assert "\n" not in str(err.value)


def test_combinations_refused_in_one_line(setup):
    bundle, plan = setup
    with pytest.raises(ValueError, match="ambient frame or drift probes"):
        with_reference_frames(with_ambient_frame(plan), bundle, 3)
    with pytest.raises(ValueError, match="ambient frame or drift probes"):
        with_reference_frames(with_drift_probes(plan, bundle, (430.0,)), bundle, 3)
    with pytest.raises(ValueError, match="reference frames already"):
        with_reference_frames(with_reference_frames(plan, bundle, 3), bundle, 2)


def test_reference_indices_refuse_an_edited_plan(setup):
    bundle, plan = setup
    assert reference_indices(plan) == [] and pattern_indices(plan) == list(range(plan.K))
    out = with_reference_frames(plan, bundle, 3)
    with pytest.raises(ValueError, match="zero decoder columns"):
        reference_indices(replace(out, params={**out.params, "reference_frames": [0, 1]}))
    with pytest.raises(ValueError, match="at least two distinct frames"):
        reference_indices(replace(out, params={**out.params, "reference_frames": [0, 40]}))


BAD_INTERVALS = st.one_of(
    st.integers(-1000, 0), st.integers(-1000, 0).map(float), st.integers(-1000, 0).map(str),
    st.floats(allow_nan=True, allow_infinity=True).filter(lambda x: not (1 <= x < float("inf") and x == int(x))),
    st.text(alphabet="abc.-xe ,", max_size=5), st.booleans(), st.none())


@settings(max_examples=80, deadline=None)
@given(BAD_INTERVALS)
def test_a_bad_interval_is_refused_in_one_line(value):
    with pytest.raises(ValueError, match="--reference-every must be a whole number of frames >= 1") as err:
        check_reference_every(value)
    assert "\n" not in str(err.value)


@given(st.integers(1, 10_000), st.sampled_from([int, float, str, lambda n: f" {n} "]))
def test_a_whole_interval_is_taken_in_any_spelling(n, spell):
    assert check_reference_every(spell(n)) == n


@given(st.integers(1, 60), st.integers(1, 40))
def test_positions_bracket_every_group_of_frames(frames, every):
    refs = reference_positions(frames, every)
    assert refs[0] == 0 and refs[-1] == frames + len(refs) - 1 and len(refs) == reference_count(frames, every)
    gaps = np.diff(refs) - 1  # pattern frames between two reference frames
    assert gaps.sum() == frames and gaps.max() == min(every, frames) and gaps.min() >= 1
