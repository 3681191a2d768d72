"""flagged_regions joins flags within JOIN_PX city-block steps in one distance transform: the regions, their order
and the ones dropped equal, bit for bit, those of the iterated dilation it stands for."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from specgpu.motion.object_motion import JOIN_PX, flagged_regions


def regions_by_definition(flagged, min_share, max_regions=2):
    joined = ndimage.binary_dilation(flagged, iterations=JOIN_PX)
    labels, n = ndimage.label(joined)
    counts = ndimage.sum_labels(flagged, labels, index=np.arange(1, n + 1))
    order = np.argsort(counts)[::-1]
    return [labels == (i + 1) for i in order[:max_regions] if counts[i] >= min_share * flagged.size]


@pytest.mark.parametrize("seed", range(4))
def test_regions_equal_the_iterated_dilations(seed):
    rng = np.random.default_rng(seed)
    flagged = rng.random((120, 160)) < 0.002 * (seed + 1)
    flagged[20:40, 30:45] = True  # a block, and a second one just within and one just beyond reach of it
    flagged[20:40, 45 + JOIN_PX:50 + JOIN_PX] = True
    flagged[70:80, 100:110] = True
    flagged[80 + JOIN_PX + 1:95 + JOIN_PX, 100:110] = True
    flagged[0, :4] = flagged[-1, -3:] = True  # on the field's edges
    for share in (0.0, 0.002, 0.01):
        got, expected = flagged_regions(flagged, min_share=share), regions_by_definition(flagged, share)
        assert len(got) == len(expected) and len(got) >= 1
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)


def test_two_flags_join_at_the_reach_and_not_beyond():
    flagged = np.zeros((40, 80), bool)
    # the two reaches touch (neighbouring pixels) up to 2 JOIN_PX + 1 apart
    flagged[20, 10] = flagged[20, 11 + 2 * JOIN_PX] = True
    assert len(flagged_regions(flagged, min_share=0.0, max_regions=5)) == 1
    flagged[20, 11 + 2 * JOIN_PX] = False
    flagged[20, 12 + 2 * JOIN_PX] = True
    assert len(flagged_regions(flagged, min_share=0.0, max_regions=5)) == 2
