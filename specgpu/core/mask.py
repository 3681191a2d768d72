"""The flags of a recovery's per-pixel mask, defined once for Python and the kernels.

A mask is a uint8 map beside the decoded outputs; each bit says why a pixel's value is NaN or is to be read with
care. Files on disk (maps, recordings, batch outputs) carry these values, so they never change. The kernels
receive them as build macros (``-DMASK_SATURATED=1`` ...: :func:`mask_macros`, added to every program by
:func:`specgpu.engine.runtime.get_program`), so the device and the host cannot disagree.
"""

from __future__ import annotations

import enum

__all__ = ["Mask", "mask_macros", "UNSEEN"]


class Mask(enum.IntFlag):
    """The bits of a recovery's mask.

    Attributes
    ----------
    SATURATED
        A sample the pixel uses reached the camera's saturation level.
    NONFINITE
        A sample the pixel uses is NaN or infinite.
    OUTSIDE
        Some frame saw the pixel outside the field (a motion-compensated decoding).
    INCONSISTENT
        The pixel's compensated frames disagree (an object moving on its own, an occlusion).
    LAYER
        The pixel was decoded with an object's own motion (a second motion layer).

    Notes
    -----
    NumPy takes a member as a 64-bit integer, not as a Python scalar of the array's type: an in-place operation on
    a uint8 mask takes ``np.uint8(Mask.X)``.
    """

    SATURATED = 1
    NONFINITE = 2
    OUTSIDE = 4
    INCONSISTENT = 8
    LAYER = 16


#: The flags that make a pixel's samples unusable whatever the motion: saturated, not finite, outside the field.
UNSEEN = Mask.SATURATED | Mask.NONFINITE | Mask.OUTSIDE


def mask_macros() -> dict[str, int]:
    """The kernels' build macros of the mask flags: ``{"MASK_SATURATED": 1, ...}``, one per :class:`Mask` member."""
    return {f"MASK_{flag.name}": int(flag.value) for flag in Mask}
