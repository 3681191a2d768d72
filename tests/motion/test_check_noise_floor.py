"""The consistency check's noise floor: a frame's local gradient energy counts as structure of its own only above
what its noise gives at that pixel's signal (a bright flat area's shot noise is far above the field's median energy,
which the dim areas set), while a wrong motion is still found."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from specgpu.engine.consistency import consistency_maps, consistency_maps_numpy
from specgpu.motion.consistency import CHECK_THRESHOLD, consistency, noise_floors
from specgpu.motion.images import gradient_image
from specgpu.planning.noise import NoiseModel

NOISE = NoiseModel(gain_e_per_dn=2.0, read_var_dn2=4.0)
K, H, W = 5, 96, 128
DARK = 16.0


def _frames(signal, seed=0):
    """K frames of ``signal`` (K, H, W) in DN above the dark level, with the NOISE model's noise, as float32."""
    rng = np.random.default_rng(seed)
    sd = np.sqrt(signal / NOISE.gain_e_per_dn + NOISE.read_var_dn2)
    return (DARK + signal + rng.normal(0.0, 1.0, signal.shape) * sd).astype(np.float32)


def _patch(level=3000.0):
    """A dim field (30 DN) with a bright flat square (``level`` DN), brighter in some frames than others."""
    s = np.full((K, H, W), 30.0)
    s[:, 24:72, 32:96] = level * np.linspace(0.6, 1.0, K)[:, None, None]
    return s


def _edge_patch():
    """A bright noisy area with a vertical edge inside it (3000 DN left of column 64, 1500 DN right)."""
    s = _patch()
    s[:, 24:72, 64:96] *= 0.5
    return s


def _textured(seed=1):
    """A random texture (bright, about 500 to 3000 DN), the same in every frame up to a gain."""
    rng = np.random.default_rng(seed)
    t = np.abs(ndimage.gaussian_filter(rng.normal(0, 1, (H, W)), 1.5))
    s = np.full((H, W), 30.0)  # on a dim field, so that the texture is above the field's median energy
    s[24:72, 32:96] = (500.0 + 3000.0 * t / t.max())[24:72, 32:96]
    return s[None] * np.linspace(0.7, 1.0, K)[:, None, None]


def _flagged(frames, shifts, noise):
    return consistency(frames, shifts, np.full((H, W), DARK, np.float32), None, noise=noise)[1] < CHECK_THRESHOLD


def test_the_noise_floor_is_the_expected_local_energy_of_the_noise_alone():
    frames = _frames(np.full((K, H, W), 1200.0))
    dark = np.full((H, W), DARK, np.float32)
    g = np.stack([gradient_image(f, dark) for f in frames])
    m = ndimage.uniform_filter(g, (1, 9, 9))
    va = ndimage.uniform_filter(g * g, (1, 9, 9)) - m * m
    floor = noise_floors(frames, NOISE, dark, factor=1.0)
    ratio = (va / floor)[:, 8:-8, 8:-8]
    assert float(np.median(ratio)) == pytest.approx(0.93, abs=0.07)  # a 9 x 9 box of correlated samples
    assert float(ratio.max()) < 3.0  # the default factor of 4 is never reached by noise


def test_a_still_bright_flat_patch_with_shot_noise_is_not_flagged():
    frames = _frames(_patch())
    still = np.zeros((K, 2))
    assert _flagged(frames, still, None)[24:72, 32:96].sum() > 100  # the median's test alone takes noise for structure
    assert _flagged(frames, still, NOISE).sum() == 0


def test_a_wrong_shift_on_a_textured_scene_is_still_flagged():
    frames = _frames(_textured())
    wrong = np.array([[3.0 * k, 0.0] for k in range(K)]) - 6.0  # the scene is still: every frame but one off
    right = _flagged(frames, np.zeros((K, 2)), NOISE)
    flagged = _flagged(frames, wrong, NOISE)
    assert right.mean() < 0.01
    assert flagged[30:66, 38:90].mean() > 0.5


def test_a_wrong_shift_at_an_edge_in_a_bright_noisy_patch_is_still_flagged():
    frames = _frames(_edge_patch())
    wrong = np.array([[0.0, 0.0], [0.0, 0.0], [6.0, 0.0], [0.0, 0.0], [-6.0, 0.0]])
    assert _flagged(frames, np.zeros((K, 2)), NOISE).sum() == 0
    flagged = _flagged(frames, wrong, NOISE)
    assert flagged[30:66, 52:76].mean() > 0.5  # about the edge, where two frames see it elsewhere


@pytest.mark.parametrize("kind", ["translation", "affine", "flow"])
def test_the_device_equals_the_numpy_reference_with_the_noise_floor(kind):
    frames = _frames(_edge_patch(), seed=3)
    dark = np.full((H, W), DARK, np.float32)
    g = np.stack([gradient_image(f, dark) for f in frames])
    floor = noise_floors(frames, NOISE, dark)
    rng = np.random.default_rng(4)
    d = rng.uniform(-3.0, 3.0, (K, 2))
    if kind == "translation":
        motion = d
    elif kind == "affine":
        motion = np.concatenate([np.tile(np.array([[1.0, 0.01], [-0.01, 1.0]]), (K, 1, 1)), d[:, :, None]], 2)
    else:
        motion = (d[:, :, None, None] + rng.normal(0, 0.3, (K, 2, H, W))).astype(np.float32)
    t_dev, w_dev = consistency_maps(g, motion, floor=floor)
    t_np, w_np = consistency_maps_numpy(g, motion, floor=floor)
    _, w_none = consistency_maps_numpy(g, motion)
    assert np.array_equal(t_dev, t_np)
    # float32 sums on the device, float64 in SciPy: the rare pixel near a threshold may differ
    assert np.mean(np.abs(w_dev - w_np) > 2e-3) < 0.01
    assert np.mean((w_dev < CHECK_THRESHOLD) != (w_np < CHECK_THRESHOLD)) < 0.002
    assert np.count_nonzero(w_np != w_none) > 0  # the floor decided some frames


def test_a_floor_of_the_wrong_shape_is_refused():
    g = np.zeros((K, H, W), np.float32)
    with pytest.raises(ValueError, match="floor must be"):
        consistency_maps_numpy(g, np.zeros((K, 2)), floor=np.zeros((K, H, W + 1)))
