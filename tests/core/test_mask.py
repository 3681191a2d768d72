"""The mask's flags: one enumeration, the values files carry, the same bits from every kernel, defined nowhere else."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from specgpu.core.mask import UNSEEN, Mask, mask_macros
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.runtime import mask_options
from specgpu.engine.warp_map import apply_linear_warped

ROOT = Path(__file__).resolve().parents[2]


def test_the_values_files_carry():
    assert [(f.name, int(f)) for f in Mask] == [("SATURATED", 1), ("NONFINITE", 2), ("OUTSIDE", 4),
                                               ("INCONSISTENT", 8), ("LAYER", 16)]
    assert int(UNSEEN) == 7
    assert mask_macros() == {"MASK_SATURATED": 1, "MASK_NONFINITE": 2, "MASK_OUTSIDE": 4, "MASK_INCONSISTENT": 8,
                             "MASK_LAYER": 16}
    assert set(mask_options()) == {"-DMASK_SATURATED=1", "-DMASK_NONFINITE=2", "-DMASK_OUTSIDE=4",
                                   "-DMASK_INCONSISTENT=8", "-DMASK_LAYER=16"}


def test_the_kernels_flag_with_the_enumerations_bits(queue):
    """A saturated sample, a NaN sample and a sample point outside the field each give exactly their flag, in the
    linear pass and in the warped pass."""
    frames = np.full((2, 6, 20), 50.0, np.float32)
    frames[0, 3, 5] = 1000.0  # saturated at 1000
    frames[1, 2, 9] = np.nan
    linear = apply_linear(frames, np.eye(2), saturation=1000.0, return_mask=True, device=queue)
    assert linear.mask[3, 5] == Mask.SATURATED and linear.mask[2, 9] == Mask.NONFINITE
    assert np.count_nonzero(linear.mask) == 2
    warped = apply_linear_warped(frames, np.eye(2), [[0.0, 0.0], [1.0, 0.0]], saturation=1000.0, return_mask=True,
                                 device=queue)
    # frame 1 sampled at x + 1: pixel 8 reads the NaN, the last column reads outside the field
    assert warped.mask[3, 5] == Mask.SATURATED and warped.mask[2, 8] == Mask.NONFINITE
    assert np.all(warped.mask[:, -1] == Mask.OUTSIDE)
    assert np.count_nonzero(warped.mask) == 2 + 6


def test_no_flag_value_is_defined_anywhere_else():
    """The kernels take the flags as build options and the Python code from the enumeration: no ``#define MASK_``
    in a kernel source, no ``MASK_... = <number>`` in the package, the tools or the tests."""
    define = re.compile(r"#\s*define\s+MASK_[A-Z]+\s")
    kernels = [p for p in (ROOT / "kernels").iterdir() if p.suffix in (".cl", ".h")]
    assert kernels and not [p.name for p in kernels if define.search(p.read_text(encoding="utf-8"))]
    assign = re.compile(r"^\s*MASK_[A-Z_]+\s*(: *[A-Za-z]+ *)?=\s*(np\.uint8\()?\d", re.MULTILINE)
    python = [p for top in ("specgpu", "tools", "tests") for p in (ROOT / top).rglob("*.py")]
    assert not [str(p.relative_to(ROOT)) for p in python if assign.search(p.read_text(encoding="utf-8"))]
