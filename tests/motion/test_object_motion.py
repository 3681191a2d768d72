"""An object's own motion: the regions tried as objects and the background an object covers."""

from __future__ import annotations

import numpy as np

from specgpu.motion.object_motion import flagged_regions, occluded_by


def test_occluded_by_is_the_footprint_swept_by_the_relative_motion_less_itself():
    F = np.zeros((20, 30), bool)
    F[5:15, 10:20] = True
    hidden = occluded_by(F, [[-3.0, 0.0], [0.0, 0.0], [3.0, 0.0]])
    expected = np.zeros_like(F)
    expected[5:15, 7:10] = expected[5:15, 20:23] = True
    np.testing.assert_array_equal(hidden, expected)
    # a sub-pixel shift covers the next column partly: it counts as hidden
    assert occluded_by(F, [[0.5, 0.0]])[5:15, 20].all()


def test_flagged_regions_joins_nearby_flags_and_drops_small_ones():
    flagged = np.zeros((200, 300), bool)
    flagged[50:60, 50:60] = flagged[50:60, 70:80] = True  # 20 px apart: one region at join_px 12
    flagged[150:152, 250:252] = True  # 4 px: too small
    regions = flagged_regions(flagged, min_share=0.002)
    assert len(regions) == 1 and regions[0][55, 65] and not regions[0][151, 251]
    assert flagged_regions(np.zeros((10, 10), bool)) == []
