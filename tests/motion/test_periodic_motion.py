"""A scene that repeats itself, moving: the host estimate chooses among a correlation's rival peaks the ones on the
sequence's steady motion, never the peak a period off (a silent wrong answer where the patches look alike)."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup

from specgpu.motion.candidates import choose_candidates, peak_candidates
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.rig.motion import MotionParameters, warp_image
from specgpu.rig.scene import colorchecker_scene

PITCH = 50  # the twin's chart at 320 x 240: 6 x 4 patches 50 px apart


@pytest.fixture(scope="module")
def setup():
    return moving_setup()


@pytest.mark.parametrize("velocity, seed", [((3.0, 0.0), 1), ((3.0, 1.0), 2), ((-3.0, 0.0), 3), ((0.0, 3.0), 2),
                                            ((5.0, 0.0), 2)])
def test_the_twins_moving_chart_is_not_snapped_by_a_period(setup, velocity, seed):
    """The twin's chart (patches 50 px apart, a white tile above) moving a few px a frame under a 7-band plan: the
    dim blue bands' frames correlate with the reference frame better a period off than at their displacement (a
    tenth of its height in the worst pair), and the highest peaks put two or three frames 50 px off. The pairs'
    candidates on one steady motion put every frame within 0.1 px of the truth."""
    desc, bundle, plan, _ = setup
    scene = colorchecker_scene(240, 320, white_tile=0.99)
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=velocity), seed=seed)
    est = estimate_global_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    assert est.registered.all()
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)


def _grid_frames(velocity, K=9, h=120, w=160, pitch=20, seed=0):
    """K frames of a grid of equal bright squares (``pitch`` px apart, every one alike: only the field's edge and
    the noise break the period) moving ``velocity`` px a frame, and each frame's true displacement from the middle
    frame's position."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:h, :w]
    base = np.where(((y % pitch) < 0.6 * pitch) & ((x % pitch) < 0.6 * pitch), 200.0, 40.0)
    base[:, : w // 4] = 40.0  # a plain band at the left: a grid does not fill the field
    times = np.arange(K) - (K - 1) / 2
    shifts = np.outer(times, velocity)
    frames = np.stack([warp_image(base, s) + rng.normal(0.0, 2.0, base.shape) for s in shifts])
    return frames.astype(np.float32), shifts


@pytest.mark.parametrize("velocity", [(3.0, 0.0), (-3.0, 2.0), (5.0, -1.0)])
def test_a_grid_moving_steadily_registers_on_its_motion(velocity):
    """A grid of identical squares 20 px apart: every pair's correlation has equal peaks a period apart, within
    reach of the motion. The estimate is within 0.1 px of the truth in every frame."""
    frames, truth = _grid_frames(velocity)
    est = estimate_global_motion(frames)
    assert est.registered.all()
    np.testing.assert_allclose(est.shifts, truth, atol=0.1)


def test_a_still_grid_stays_still_however_far_the_motion_could_reach():
    """A period within reach of every pair (a reach of 60 px a frame) and nothing moving: zero, not a period."""
    frames, truth = _grid_frames((0.0, 0.0))
    np.testing.assert_allclose(estimate_global_motion(frames, max_speed=60.0).shifts, truth, atol=0.1)


def test_the_candidates_are_the_surfaces_peaks_within_reach():
    h, w = 64, 96
    yy, xx = np.mgrid[:h, :w]
    surface = np.zeros((h, w))
    for (cx, cy), top in (((5.3, -2.0), 1.0), ((-15.0, 3.0), 0.8), ((30.0, 0.0), 0.9), ((10.0, 10.0), 0.02)):
        dx = (xx - cx + w / 2) % w - w / 2
        dy = (yy - cy + h / 2) % h - h / 2
        surface += top * np.exp(-(dx ** 2 + dy ** 2) / (2 * 1.3 ** 2))
    peaks, heights = peak_candidates(surface, radius=2, within=20)
    np.testing.assert_allclose(peaks, [[5.3, -2.0], [-15.0, 3.0]], atol=0.05)  # (30, 0) beyond reach; (10, 10) low
    assert heights[0] > heights[1]
    everywhere, _ = peak_candidates(surface, radius=2)
    np.testing.assert_allclose(everywhere, [[5.3, -2.0], [30.0, 0.0], [-15.0, 3.0]], atol=0.05)


def _pairs_to(ref, K):
    return [(ref, k) for k in range(K) if k != ref]


def test_the_choice_is_the_candidate_on_the_steady_motion():
    """Frames against the middle one at 3 px a frame, a rival 50 px off in three of them, the higher in two:
    each pair takes the candidate on the motion most pairs share."""
    K, ref, v = 7, 3, np.array([3.0, 0.5])
    pairs = _pairs_to(ref, K)
    cands, heights = [], []
    for a, b in pairs:
        true = v * (b - a)
        if abs(b - a) >= 2:
            cands.append([true + [50.0, 0.0], true])
            heights.append([1.0, 0.4])
        else:
            cands.append([true])
            heights.append([1.0])
    choice = choose_candidates(np.arange(K), pairs, cands, heights)
    np.testing.assert_allclose(choice.displacements, [v * (b - a) for a, b in pairs])
    assert choice.resolved.all() and choice.on_line.all()
    np.testing.assert_allclose(choice.velocity, v)


def test_equal_rivals_go_to_the_prior_and_rivals_off_the_motion_are_not_guessed():
    """Three frames whose every candidate has an equal rival: the motion nearest the prior (zero, or the one given)
    wins; a pair whose candidates are all off the chosen motion, and rival each other, is unresolved."""
    pairs = [(1, 0), (1, 2)]
    cands = [[[-3.0, 0.0], [47.0, 0.0]], [[3.0, 0.0], [-47.0, 0.0]]]
    heights = [[1.0, 1.0], [1.0, 1.0]]
    still = choose_candidates(np.arange(3), pairs, cands, heights)
    np.testing.assert_allclose(still.displacements, [[-3.0, 0.0], [3.0, 0.0]])
    fast = choose_candidates(np.arange(3), pairs, cands, heights, prior_velocity=(-40.0, 0.0))
    np.testing.assert_allclose(fast.displacements, [[47.0, 0.0], [-47.0, 0.0]])
    lost = choose_candidates(np.arange(4), [(1, 0), (1, 2), (1, 3)],
                             [[[-3.0, 0.0]], [[3.0, 0.0]], [[20.0, 0.0], [-30.0, 0.0]]],
                             [[1.0], [1.0], [1.0, 0.9]])
    assert lost.resolved.tolist() == [True, True, False]
    assert np.isnan(lost.displacements[2]).all()


def test_a_clear_peak_off_the_motion_is_kept():
    """A shake is not a steady motion: a pair with one clear peak keeps it, off the motion or not."""
    pairs = _pairs_to(2, 5)
    cands = [[[-6.0, 0.0]], [[-3.0, 0.0]], [[3.0, 0.0]], [[9.0, 0.0], [-41.0, 0.0]]]
    heights = [[1.0], [1.0], [1.0], [1.0, 0.1]]
    choice = choose_candidates(np.arange(5), pairs, cands, heights)
    np.testing.assert_allclose(choice.displacements[3], [9.0, 0.0])
    assert choice.resolved.all() and not choice.on_line[3]


def test_bad_candidates_are_refused():
    with pytest.raises(ValueError, match="a height per candidate"):
        choose_candidates(np.arange(2), [(0, 1)], [[[1.0, 0.0]]], [[1.0, 0.5]])
    with pytest.raises(ValueError, match="different times"):
        choose_candidates(np.zeros(2), [(0, 1)], [[[1.0, 0.0]]], [[1.0]])
