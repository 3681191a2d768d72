"""The stream's decoder (and recover's colour maps) on a perfect white: the XYZ it decodes is integrated with the
weights of the plan's grid, and its Lab and dE take the white of the same weights, so a white scene decodes to
L* = 100, a* = b* = 0 for any illuminant, observer and integration."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from specgpu import engine
from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.recovery import to_Lab, to_XYZ
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
TEN = "CIE 1964 10 Degree Standard Observer"
TWO = "CIE 1931 2 Degree Standard Observer"


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def narrowband(bundle):
    """A reflectance plan on 400-700 nm every 20 nm: the coarse grid where a tabulated white was furthest off."""
    return make_plan("narrowband", bundle, step_nm=20.0)


def white_frames(plan, bundle) -> np.ndarray:
    """(K, H, W) float32 frames of the perfect diffuser as the plan's model sees them (the dark level added, the
    flat field divided in), which every plan decodes to the white exactly."""
    signal = bundle.forward_matrix(plan.patterns, plan.light_wavelengths, plan.exposure_s).sum(axis=1)
    dark = np.asarray(bundle.dark_at(plan.exposure_s), np.float64)
    gain = np.asarray(bundle.flat_field, np.float64)
    return (dark[None] + signal[:, None, None] / gain[None]).astype(np.float32)


def decoded(plan, bundle, queue, **colours) -> dict:
    dec = SequenceDecoder(plan, bundle, ("XYZ", "Lab", "dE"), frame_shape=bundle.frame_shape, device=queue,
                          reference=np.array([100.0, 0.0, 0.0]), **colours)
    assert not dec.precorrect  # the oracle's frames go to the kernels as they are
    out = dec.enqueue(engine.to_device(queue, white_frames(plan, bundle).reshape(-1)))
    maps = {}
    for name, (shape, dtype) in dec.shapes().items():
        maps[name] = np.empty(shape, dtype)
        cl.enqueue_copy(queue, maps[name], out[name])
    queue.finish()
    return maps


@pytest.mark.parametrize("illuminant, observer, integration", [
    ("D65", TWO, "rectangle"), ("A", TEN, "rectangle"), ("FL2", TWO, "ASTM E308"), ("D50", TEN, "ASTM E308"),
])
def test_the_stream_decoder_decodes_a_white_scene_to_Lab_100_0_0(bundle, narrowband, queue, illuminant, observer,
                                                                  integration):
    colours = dict(illuminant=illuminant, observer=observer, integration=integration)
    maps = decoded(narrowband, bundle, queue, **colours)
    np.testing.assert_allclose(maps["XYZ"].reshape(-1, 3), [narrowband.white_XYZ(illuminant, observer, integration)]
                               * maps["XYZ"][..., 0].size, rtol=1e-5)
    np.testing.assert_allclose(maps["Lab"].reshape(-1, 3), [[100, 0, 0]] * maps["Lab"][..., 0].size, atol=1e-3)
    assert float(maps["dE"].max()) < 1e-3


def test_a_tristimulus_plans_white_is_its_own_light_grids(bundle, queue):
    """A tristimulus plan's frames integrate on the light's grid: the white its decoder divides by is that grid's,
    and another integration than the one its frames were made for is refused in one line."""
    plan = make_plan("tristimulus", bundle, illuminant="A")
    maps = decoded(plan, bundle, queue)
    np.testing.assert_allclose(maps["Lab"].reshape(-1, 3), [[100, 0, 0]] * maps["Lab"][..., 0].size, atol=1e-3)
    with pytest.raises(ValueError, match="integrated by the rectangle rule on the light's grid, not by ASTM E308"):
        plan.white_XYZ("A", integration="ASTM E308")


@pytest.mark.parametrize("integration", ["rectangle", "ASTM E308"])
def test_recovers_maps_of_a_white_cube_are_Lab_100_0_0(narrowband, queue, integration):
    """recover's XYZ and Lab maps (to_XYZ then to_Lab) of a cube of ones on the plan's grid."""
    cube = np.ones((4, 5, narrowband.output_wavelengths.size), np.float32)
    XYZ = to_XYZ(cube, narrowband, "D65", integration=integration, device=queue)
    Lab = to_Lab(XYZ, narrowband, "D65", integration=integration, device=queue)
    np.testing.assert_allclose(Lab.reshape(-1, 3), [[100, 0, 0]] * 20, atol=1e-3)
