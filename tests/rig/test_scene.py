"""Spectral scenes: cube readers (EXR JCGT layout, npz), built-ins, bad input."""

import time

import colour
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.rig.scene import (
    RESIZE_MODES,
    SpectralScene,
    colorchecker_scene,
    load_scene,
    natural_scene,
    patch_scene,
    read_scene,
    resample_scene,
    validate_resize,
    white_plate_scene,
    white_tile_roi,
    write_scene,
)


def small_cube(h=6, w=5, wl=(400.0, 450.0, 500.0, 600.0), seed=0):
    rng = np.random.default_rng(seed)
    return SpectralScene(np.array(wl), rng.random((h, w, len(wl))).astype(np.float32), {}, "cube")


def _write_exr_channels(path, names, data):
    import OpenImageIO as oiio

    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    spec.channelnames = tuple(names)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data, np.float32))
    out.close()


@pytest.mark.parametrize("half", [False, True])
def test_exr_round_trip(tmp_path, half):
    scene = small_cube()
    path = write_scene(tmp_path / "c.exr", scene, half=half)
    back = read_scene(path)
    np.testing.assert_array_equal(back.wavelengths, scene.wavelengths)
    np.testing.assert_allclose(back.reflectance, scene.reflectance, atol=1e-3 if half else 0)
    assert back.reflectance.dtype == np.float32


def test_exr_bands_are_ordered_by_wavelength_not_channel_order(tmp_path):
    rng = np.random.default_rng(1)
    data = rng.random((4, 3, 4)).astype(np.float32)
    # Channel order scrambled, both decimal separators, plus non-spectral channels the reader must ignore.
    names = ["T.600,000000nm", "T.450nm", "T.500.5nm", "T.400,5nm"]
    extra = rng.random((4, 3, 2)).astype(np.float32)
    _write_exr_channels(tmp_path / "s.exr", names + ["S0.500,000000nm", "A"], np.concatenate([data, extra], axis=2))
    scene = read_scene(tmp_path / "s.exr")
    np.testing.assert_array_equal(scene.wavelengths, [400.5, 450.0, 500.5, 600.0])
    np.testing.assert_array_equal(scene.reflectance, data[..., [3, 1, 2, 0]])


def test_npz_round_trip_with_masks_and_band_order(tmp_path):
    scene = small_cube()
    scene.masks["left"] = np.zeros(scene.shape, bool)
    scene.masks["left"][:, :2] = True
    write_scene(tmp_path / "c.npz", scene)
    back = read_scene(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.reflectance, scene.reflectance)
    np.testing.assert_array_equal(back.masks["left"], scene.masks["left"])
    # Bands stored out of order are sorted on reading.
    np.savez(tmp_path / "rev.npz", wavelengths=scene.wavelengths[::-1], reflectance=scene.reflectance[..., ::-1])
    rev = read_scene(tmp_path / "rev.npz")
    np.testing.assert_array_equal(rev.wavelengths, scene.wavelengths)
    np.testing.assert_array_equal(rev.reflectance, scene.reflectance)


def test_bad_cube_files_name_the_file_and_problem(tmp_path):
    scene = small_cube()
    write_scene(tmp_path / "ok.exr", scene)
    raw = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "trunc.exr").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"trunc\.exr: (truncated or corrupt|cannot open)"):
        read_scene(tmp_path / "trunc.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(ValueError, match=r"junk\.exr: cannot open EXR"):
        read_scene(tmp_path / "junk.exr")
    _write_exr_channels(tmp_path / "rgb.exr", ["R", "G", "B"], np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match=r"rgb\.exr: no reflective spectral channels"):
        read_scene(tmp_path / "rgb.exr")
    _write_exr_channels(tmp_path / "dup.exr", ["T.500nm", "T.500,0nm"], np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match=r"dup\.exr: a wavelength appears in more than one"):
        read_scene(tmp_path / "dup.exr")

    write_scene(tmp_path / "ok.npz", scene)
    raw = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"trunc\.npz: truncated or corrupt"):
        read_scene(tmp_path / "trunc.npz")
    np.savez(tmp_path / "nowl.npz", reflectance=scene.reflectance)
    with pytest.raises(ValueError, match=r"nowl\.npz: missing array\(s\) \['wavelengths'\]"):
        read_scene(tmp_path / "nowl.npz")
    np.savez(tmp_path / "shape.npz", wavelengths=scene.wavelengths, reflectance=scene.reflectance[..., :2])
    with pytest.raises(ValueError, match=r"shape\.npz: reflectance must have shape \(H, W, 4\)"):
        read_scene(tmp_path / "shape.npz")
    bad = scene.reflectance.copy()
    bad[0, 0, 0] = np.nan
    np.savez(tmp_path / "nan.npz", wavelengths=scene.wavelengths, reflectance=bad)
    with pytest.raises(ValueError, match=r"nan\.npz: .*1 NaN or infinite"):
        read_scene(tmp_path / "nan.npz")
    np.savez(tmp_path / "dupwl.npz", wavelengths=np.array([400.0, 400.0, 500.0, 600.0]), reflectance=scene.reflectance)
    with pytest.raises(ValueError, match=r"dupwl\.npz: .*strictly increasing"):
        read_scene(tmp_path / "dupwl.npz")
    with pytest.raises(ValueError, match=r"missing\.exr: scene file not found"):
        read_scene(tmp_path / "missing.exr")
    (tmp_path / "x.png").write_bytes(b"")
    with pytest.raises(ValueError, match=r"x\.png: unknown scene format '\.png'"):
        read_scene(tmp_path / "x.png")


def test_scene_validation():
    with pytest.raises(ValueError, match=r"reflectance must be <= 1\.5"):
        SpectralScene(np.array([400.0, 500.0]), np.full((2, 2, 2), 2.0))
    with pytest.raises(ValueError, match=r"reflectance must be >= 0"):
        SpectralScene(np.array([400.0, 500.0]), np.full((2, 2, 2), -0.1))
    with pytest.raises(ValueError, match=r"mask 'm' must have shape \(2, 2\)"):
        SpectralScene(np.array([400.0, 500.0]), np.zeros((2, 2, 2)), {"m": np.zeros((3, 3))})


def test_colorchecker_scene_uses_measured_spectra_and_masks():
    scene = colorchecker_scene(240, 320)
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    names = list(sds.keys())
    assert list(scene.masks) == names and len(names) == 24
    for name in (names[0], names[12], names[18]):
        m = scene.masks[name]
        assert m.sum() > 200
        spectra = scene.reflectance[m]
        np.testing.assert_allclose(spectra, np.broadcast_to(
            np.interp(scene.wavelengths, sds[name].wavelengths, sds[name].values), spectra.shape), atol=1e-6)
    # Masks do not overlap, and each is surrounded by its own patch (no surround pixels inside a mask).
    total = sum(m.astype(int) for m in scene.masks.values())
    assert total.max() == 1
    # Row-major chart order: patch 0 (dark skin) top left, patch 23 (black) bottom right.
    ys0, xs0 = np.nonzero(scene.masks[names[0]])
    ys23, xs23 = np.nonzero(scene.masks[names[23]])
    assert ys0.mean() < 120 and xs0.mean() < 160 and ys23.mean() > 120 and xs23.mean() > 160
    with pytest.raises(ValueError, match="unknown chart 'nope'; valid charts"):
        colorchecker_scene(chart="nope")


def test_white_plate():
    scene = white_plate_scene(10, 12, reflectance=0.9)
    assert scene.shape == (10, 12) and np.all(scene.reflectance == np.float32(0.9))
    assert scene.masks["plate"].all()


def test_natural_scene_is_fast_and_reproduces_the_photo():
    natural_scene(60, 80)  # imports
    t0 = time.perf_counter()
    scene = natural_scene(480, 640, image="coffee")
    # Seconds, not minutes (a per-pixel colour-science call would take about 5 min); generous for loaded CI.
    assert time.perf_counter() - t0 < 30.0
    assert scene.shape == (480, 640) and scene.reflectance.dtype == np.float32
    assert 0.0 <= scene.reflectance.min() and scene.reflectance.max() <= 1.0
    # Mallett 2019: under D65 the spectra reproduce the (linear) sRGB of the photo they came from.
    import skimage.data
    from skimage.transform import resize

    small = natural_scene(48, 64, image="coffee")
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wl = small.wavelengths
    xbar = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, i]) for i in range(3)], axis=1)
    e = np.interp(wl, d65.wavelengths, d65.values)
    k = 1.0 / np.sum(e * xbar[:, 1])
    xyz = k * np.einsum("hwb,b,bc->hwc", small.reflectance.astype(np.float64), e, xbar)
    rgb = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False)
    photo = skimage.data.coffee()[..., :3] / 255.0
    ih, iw = photo.shape[:2]
    cw = int(round(ih * 64 / 48))
    photo = photo[:, (iw - cw) // 2:(iw - cw) // 2 + cw]
    photo = colour.cctf_decoding(np.clip(resize(photo, (48, 64), anti_aliasing=True, order=1), 0, 1), function="sRGB")
    assert np.abs(rgb - photo).mean() < 0.01


def test_load_scene_resamples_and_rejects_unknown_names(tmp_path):
    scene = load_scene("colorchecker", 240, 320)
    assert scene.shape == (240, 320)
    write_scene(tmp_path / "c.npz", small_cube())
    assert load_scene(str(tmp_path / "c.npz"), 12, 10).shape == (12, 10)
    with pytest.raises(ValueError, match=r"unknown scene 'moon'; give a \.exr, \.npz or \.hdr \(ENVI\) file or one of: "
                                         r"colorchecker"):
        load_scene("moon")
    assert load_scene("natural:rocket", 24, 32).name == "natural:rocket"
    with pytest.raises(ValueError, match="unknown image 'moon'; valid images: chelsea"):
        load_scene("natural:moon", 24, 32)


def test_band_weights_integrate_linearly_interpolated_reflectance():
    scene = small_cube(1, 1)
    grid = np.arange(380.0, 781.0)
    w = np.random.default_rng(3).random(grid.size)
    wb = scene.band_weights(grid, w)
    direct = np.sum(np.interp(grid, scene.wavelengths, scene.reflectance[0, 0]) * w)
    assert float(scene.reflectance[0, 0] @ wb) == pytest.approx(direct, rel=1e-6)


@settings(max_examples=25, deadline=None)
@given(wl=st.lists(st.integers(300, 1000), min_size=2, max_size=8, unique=True), seed=st.integers(0, 1000))
def test_npz_reader_orders_any_band_order(tmp_path_factory, wl, seed):
    rng = np.random.default_rng(seed)
    refl = rng.random((2, 3, len(wl))).astype(np.float32)
    path = tmp_path_factory.mktemp("npz") / "s.npz"
    np.savez(path, wavelengths=np.array(wl, float), reflectance=refl)
    scene = read_scene(path)
    order = np.argsort(wl)
    np.testing.assert_array_equal(scene.wavelengths, np.array(wl, float)[order])
    np.testing.assert_array_equal(scene.reflectance, refl[..., order])


def test_natural_scene_equals_colour_science_mallett2019_per_pixel():
    import skimage.data
    from skimage.transform import resize

    scene = natural_scene(24, 32, image="astronaut")
    photo = skimage.data.astronaut()[..., :3] / 255.0  # square: centre-crop rows to 4:3
    ch = int(round(photo.shape[1] / (32 / 24)))
    photo = photo[(photo.shape[0] - ch) // 2:(photo.shape[0] - ch) // 2 + ch]
    linear = colour.cctf_decoding(np.clip(resize(photo, (24, 32), anti_aliasing=True, order=1), 0, 1), function="sRGB")
    for y, x in [(0, 0), (12, 16), (23, 31), (5, 27)]:
        sd = colour.recovery.RGB_to_sd_Mallett2019(linear[y, x])
        np.testing.assert_allclose(scene.reflectance[y, x], np.clip(sd.values, 0, 1), atol=2e-6)
        np.testing.assert_array_equal(scene.wavelengths, sd.wavelengths)


# ---- fitting a scene of another size to the frame --------------------------------------------------------------
def test_a_file_of_another_aspect_ratio_is_refused_unless_a_mode_is_chosen(tmp_path):
    path = write_scene(tmp_path / "tall.npz", colorchecker_scene(120, 100))  # 100 x 120 (W x H), portrait
    with pytest.raises(ValueError, match=r"tall.npz is 100 x 120 pixels, the frame 640 x 480: another aspect "
                                         r"ratio \(0.8333 against 1.333\); choose how to fit it \(--resize stretch"):
        load_scene(str(path), 480, 640)
    with pytest.raises(ValueError, match=r"tall.npz is 100 x 120 pixels, the frame 200 x 240; give a scene of the "
                                         r"frame's size"):
        load_scene(str(path), 240, 200, resize="exact")
    stretched = load_scene(str(path), 480, 640, resize="stretch")
    assert stretched.shape == (480, 640)
    assert stretched.resampled == ("100 x 120 -> 640 x 480 pixels (stretch, nearest neighbour; aspect ratio "
                                   "0.8333 -> 1.333)")
    same = load_scene(str(path), 240, 200)  # the same aspect ratio: scaled, and said
    assert same.shape == (240, 200) and same.resampled == "100 x 120 -> 200 x 240 pixels (scale, nearest neighbour)"
    assert load_scene(str(path), 120, 100, resize="exact").resampled == ""  # the frame's size: untouched


def test_crop_and_pad_keep_the_aspect_ratio_and_say_what_they_did():
    scene = small_cube(12, 10, seed=4)
    scene.masks = {"all": np.ones((12, 10), bool)}
    scene = SpectralScene(scene.wavelengths, scene.reflectance, scene.masks, "cube")
    crop = resample_scene(scene, 12, 20, "crop")  # scale 2 covers 20 x 24, 12 rows overhang: 6 source rows cut
    np.testing.assert_array_equal(crop.reflectance, np.repeat(np.repeat(scene.reflectance[3:9], 2, 0), 2, 1))
    assert crop.resampled == "10 x 12 -> 20 x 12 pixels (crop, nearest neighbour; 0 source columns and 6 rows cropped)"
    pad = resample_scene(scene, 12, 20, "pad")  # scale 1 fits: the 10 columns centred, 5 black on each side
    np.testing.assert_array_equal(pad.reflectance[:, 5:15], scene.reflectance)
    assert not pad.reflectance[:, :5].any() and not pad.reflectance[:, 15:].any()
    assert pad.masks["all"].sum() == 120 and not pad.masks["all"][:, :5].any()
    assert pad.resampled == "10 x 12 -> 20 x 12 pixels (pad, nearest neighbour; 120 border pixels padded black)"


@settings(max_examples=60, deadline=None)
@given(mode=st.sampled_from(sorted(RESIZE_MODES)), upper=st.lists(st.booleans(), min_size=8, max_size=8),
       left=st.text(" \t", max_size=2), right=st.text(" \t", max_size=2))
def test_validate_resize_accepts_any_spelling_of_a_mode(mode, upper, left, right):
    spelled = "".join(c.upper() if u else c for c, u in zip(mode, upper + [False] * len(mode)))
    assert validate_resize(left + spelled + right) == mode


@settings(max_examples=100, deadline=None)
@given(text=st.one_of(st.text(max_size=12), st.integers(), st.none()))
def test_validate_resize_refuses_anything_else_naming_the_modes(text):
    if isinstance(text, str) and text.strip().lower() in RESIZE_MODES:
        return
    with pytest.raises(ValueError, match=r"resize mode .* is not one of scale, exact, stretch, crop, pad$"):
        validate_resize(text)


@settings(max_examples=80, deadline=None)
@given(h=st.integers(1, 9), w=st.integers(1, 9), fh=st.integers(1, 30), fw=st.integers(1, 30),
       mode=st.sampled_from(sorted(RESIZE_MODES)))
def test_every_mode_fills_the_frame_with_source_spectra_or_refuses(h, w, fh, fw, mode):
    scene = small_cube(h, w, seed=h * 10 + w)
    scene = SpectralScene(scene.wavelengths, scene.reflectance, {"m": np.ones((h, w), bool)}, "cube")
    uniform = max((fw - 0.5) / w, (fh - 0.5) / h) <= min((fw + 0.5) / w, (fh + 0.5) / h)
    refused = (mode == "exact" and (h, w) != (fh, fw)) or (mode == "scale" and not uniform)
    if refused:
        with pytest.raises(ValueError, match=f"is {w} x {h} pixels, the frame {fw} x {fh}"):
            resample_scene(scene, fh, fw, mode)
        return
    out = resample_scene(scene, fh, fw, mode)
    assert out.shape == (fh, fw) and out.masks["m"].shape == (fh, fw)
    assert bool(out.resampled) == ((h, w) != (fh, fw))
    source = {tuple(v) for v in scene.reflectance.reshape(-1, scene.wavelengths.size)}
    pixels = out.reflectance.reshape(-1, scene.wavelengths.size)
    inside = out.masks["m"].reshape(-1)
    assert all(tuple(v) in source for v in pixels[inside])  # nearest neighbour: no spectrum invented
    assert not pixels[~inside].any()  # outside the source (pad only): black
    assert inside.all() or mode == "pad"
    if mode == "crop" or mode == "pad":  # uniform: one scale factor on both axes
        assert out.resampled == "" or f"({mode}, nearest neighbour" in out.resampled


# ---- a chart of arbitrary patch spectra ----------------------------------------------------------------------

def test_patch_scene_white_tile():
    # 14 patches, as the held-out chart has
    names, wl = [f"patch {i}" for i in range(14)], np.arange(400.0, 701.0, 10.0)
    spec = np.random.default_rng(3).uniform(0.05, 0.9, (14, wl.size))
    plain = patch_scene(names, wl, spec, 240, 320)
    tiled = patch_scene(names, wl, spec, 240, 320, white_tile=0.97)
    x, y, w, h = white_tile_roi(240, 320)
    np.testing.assert_array_equal(tiled.reflectance[y:y + h, x:x + w], np.float32(0.97))
    assert set(tiled.masks) == set(plain.masks)
    outside = np.ones((240, 320), bool)
    outside[max(0, y - 3):y + h + 3, max(0, x - 3):x + w + 3] = False
    np.testing.assert_array_equal(tiled.reflectance[outside], plain.reflectance[outside])
    with pytest.raises(ValueError, match="white_tile") as err:
        patch_scene(names, wl, spec, 240, 320, white_tile=-1.0)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="no room"):
        many = [f"{n}-{i}" for i in range(10) for n in names]
        patch_scene(many, wl, np.vstack([spec] * 10), 240, 320, white_tile=0.99)
