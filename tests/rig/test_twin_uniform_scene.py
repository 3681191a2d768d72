"""A uniform scene (one spectrum broadcast over the field) rendered from its one spectrum, the same images as a
scene holding that spectrum at every pixel; a black field skips the lens's blur and aberration, which leave zero
as it is."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.ndimage

from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.realism import LAB
from specgpu.rig.scene import SpectralScene, white_plate_scene
from specgpu.rig.twin import TwinRig

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


def copied(scene):
    """The same scene with its spectrum written out at every pixel (no broadcast)."""
    return SpectralScene(scene.wavelengths, np.ascontiguousarray(scene.reflectance), scene.masks, scene.name)


def test_a_uniform_scenes_images_equal_those_of_its_spectrum_at_every_pixel():
    plate = white_plate_scene(24, 32, reflectance=0.8)
    assert plate.reflectance.strides[:2] == (0, 0)
    bw = np.random.default_rng(0).uniform(0, 1, (5, plate.wavelengths.size))
    fast, slow = plate.weighted_images(bw), copied(plate).weighted_images(bw)
    assert fast.shape == slow.shape == (5, 24, 32) and fast.dtype == slow.dtype == np.float32
    np.testing.assert_allclose(fast, slow, rtol=1e-5)
    fast[0, 0, 0] = -1.0  # the images are the caller's to change in place
    assert plate.weighted_images(bw)[0, 0, 0] != -1.0


def test_the_lab_twins_signal_on_a_plate_is_that_of_the_plate_written_out():
    lab = replace(DESC, realism=LAB)
    plate = white_plate_scene(240, 320, reflectance=0.99)
    spectra = np.random.default_rng(1).uniform(0.1, 1.0, (3, TwinRig(lab, scene=plate).light.wavelengths.size))
    fast = TwinRig(lab, scene=plate).signal_electrons(spectra)
    slow = TwinRig(lab, scene=copied(plate)).signal_electrons(spectra)
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-6 * float(slow.max()))


def test_a_black_field_is_not_blurred(monkeypatch):
    calls = []
    blur = scipy.ndimage.gaussian_filter
    monkeypatch.setattr(scipy.ndimage, "gaussian_filter", lambda *a, **k: calls.append(1) or blur(*a, **k))
    rig = TwinRig(replace(DESC, realism=replace(LAB, ambient_lux=0.0)), scene=white_plate_scene(240, 320,
                                                                                                reflectance=0.0))
    spectra = np.ones((2, rig.light.wavelengths.size))
    assert not rig.signal_electrons(spectra).any() and calls == []
    rig = TwinRig(replace(DESC, realism=LAB), scene=white_plate_scene(240, 320))
    assert rig.signal_electrons(spectra).any() and len(calls) == 2  # a lit one is, each pattern's image
