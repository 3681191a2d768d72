"""grow_flags, the ring and the enclosed islands the consistency flags take in, made with whole-array operations:
equal, bit for bit, to the binary dilation and the labelled sizes it is defined by, on masks with flags, layers and
pixels outside the field."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from specgpu.core.mask import UNSEEN, Mask
from specgpu.pipeline.moving_layers import ISLAND_PX, grow_flags


def grown_by_definition(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    flagged = (mask & np.uint8(Mask.INCONSISTENT)) != 0
    ring = ndimage.binary_dilation(flagged, structure=np.ones((3, 3), bool)) & ~flagged
    labels, n = ndimage.label(~(flagged | ring))
    if n:
        sizes = ndimage.sum_labels(np.ones(labels.shape), labels, index=np.arange(1, n + 1))
        ring |= np.isin(labels, 1 + np.flatnonzero(sizes < ISLAND_PX))
    ring &= (mask & np.uint8(UNSEEN)) == 0
    out[ring] = (out[ring] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_grown_flags_equal_their_definition(seed):
    rng = np.random.default_rng(seed)
    h, w = 60 + 7 * seed, 90 - 5 * seed
    mask = np.zeros((h, w), np.uint8)
    mask[rng.random((h, w)) < 0.02 * (seed + 1)] |= np.uint8(Mask.INCONSISTENT)
    mask[10:30, 20:50] |= np.uint8(Mask.INCONSISTENT)  # a block with a hole (an island) inside
    mask[15:19, 30:34] = 0
    mask[rng.random((h, w)) < 0.05] |= np.uint8(Mask.LAYER)
    mask[:, :3] |= np.uint8(Mask.SATURATED)  # outside what the ring may take
    mask[0, :] |= np.uint8(Mask.INCONSISTENT)  # flags on the field's edge
    expected = grown_by_definition(mask)
    grow_flags(mask)
    np.testing.assert_array_equal(mask, expected)
    assert (mask[16, 31] & Mask.INCONSISTENT) != 0  # the island flagged


def test_no_flag_leaves_the_mask_as_it_is():
    mask = np.zeros((40, 50), np.uint8)
    mask[5:8, 5:8] = np.uint8(Mask.LAYER)
    before = mask.copy()
    grow_flags(mask)
    np.testing.assert_array_equal(mask, before)
