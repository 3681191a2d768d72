"""specgpu.io.files: every file format round trip, band order, oiiotool interop, bad input (one line each)."""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import colour
import matplotlib
import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.capture.assemble import Sequence
from specgpu.capture.driver import FrameInfo

# OpenImageIO's own command-line tool: the console script next to this interpreter (the wheel installs it), or PATH.
OIIOTOOL = next((str(p) for p in (Path(sys.executable).parent / "oiiotool",) if p.exists()), None) or \
    shutil.which("oiiotool")


def raises_one_line(exc_type, match):
    """pytest.raises that also checks the message is one line."""

    class _Ctx:
        def __enter__(self):
            self.ctx = pytest.raises(exc_type, match=match)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.ctx.__exit__(*exc)
            assert "\n" not in str(self.info.value), str(self.info.value)
            return out

    return _Ctx()


def cube_data(h=6, w=5, b=4, seed=0):
    return np.random.default_rng(seed).random((h, w, b)).astype(np.float32)


def write_exr_channels(path, names, data, attributes=None):
    """An EXR written straight through OpenImageIO with the given channel names (any order)."""
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    spec.channelnames = tuple(names)
    for k, v in (attributes or {}).items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data, np.float32))
    out.close()


def no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if ".tmp" in p.name]


# ---- channel names ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, nm", [
    ("T.550,000000nm", 550.0),          # the reference writer's form (six decimals, comma)
    ("T.405,5nm", 405.5),
    ("T.405.5nm", 405.5),               # "." separator from other tools, read leniently
    ("T.400nm", 400.0),
    ("T.0,5505um", 550.5),              # SI prefix u (micro)
    ("T.5,5e2nm", 550.0),               # exponent
    ("T.5505Am", None),                 # unknown prefix
    ("T.550e-9m", 550.0),               # metres, no prefix
    ("T.600THz", 299_792_458.0 / 600e12 * 1e9),  # frequency
    ("T.550,000000nm.600nm", None),     # bi-spectral (re-radiation) channel, not a band
    ("S0.550,000000nm", None),          # emissive
    ("R", None), ("T.nm", None), ("T.550", None), ("T550nm", None), ("T.-550nm", None),
])
def test_parse_channel_follows_the_jcgt_grammar(name, nm):
    got = io.parse_channel(name)
    if nm is None:
        assert got is None
    else:
        assert got == pytest.approx(nm, rel=1e-12)


def test_format_channel_writes_the_reference_form():
    assert io.format_channel(550) == "T.550,000000nm"
    assert io.format_channel(405.5) == "T.405,500000nm"
    assert io.format_channel(405.12345678) == "T.405,12345678nm"  # six decimals would lose it
    for bad in (0, -1, float("nan"), float("inf"), "x"):
        with raises_one_line(ValueError, "wavelength must be"):
            io.format_channel(bad)


@given(st.floats(min_value=1e-300, max_value=1e300, allow_nan=False, allow_infinity=False))
def test_channel_name_round_trip_is_exact(wl):
    name = io.format_channel(wl)
    assert name.startswith("T.") and name.endswith("nm") and "." not in name[2:]  # comma: no OpenEXR layer split
    assert io.parse_channel(name) == wl


_SI = {"": 0, "da": 1, "h": 2, "k": 3, "M": 6, "d": -1, "c": -2, "m": -3, "u": -6, "n": -9, "p": -12}


@given(st.floats(min_value=1e-3, max_value=1e6, allow_nan=False), st.sampled_from(sorted(_SI)),
       st.sampled_from([",", "."]))
def test_parse_channel_applies_si_prefixes_and_either_separator(value, prefix, sep):
    name = "T." + repr(value).replace(".", sep) + prefix + "m"
    assert io.parse_channel(name) == pytest.approx(value * 10.0 ** (_SI[prefix] + 9), rel=1e-12)
    hz = io.parse_channel("T." + repr(value).replace(".", sep) + prefix + "Hz")
    assert hz == pytest.approx(299_792_458.0 / (value * 10.0 ** _SI[prefix]) * 1e9, rel=1e-12)


@given(st.text(max_size=20))
def test_parse_channel_never_raises_and_rejects_non_reflective_names(text):
    got = io.parse_channel(text)
    if not text.startswith("T."):
        assert got is None
    else:
        assert got is None or got >= 0


# ---- cubes -------------------------------------------------------------------------------------------------------------
def test_cube_exr_float_round_trip_is_identical(tmp_path):
    cube = cube_data()
    wl = np.array([400.0, 450.0, 500.5, 600.0])
    meta = {"method": "biased-6", "illuminant": "D65", "gain": 0.1, "n": np.int64(6), "nested": {"a": [1, 2]}}
    io.write_cube(tmp_path / "c.exr", cube, wl, metadata=meta)
    back, wl_back, meta_back = io.read_cube(tmp_path / "c.exr")
    assert back.dtype == np.float32 and wl_back.dtype == np.float64
    np.testing.assert_array_equal(back, cube)
    np.testing.assert_array_equal(wl_back, wl)
    assert meta_back == {"method": "biased-6", "illuminant": "D65", "gain": 0.1, "n": 6, "nested": {"a": [1, 2]}}
    assert no_temp_files(tmp_path)


def test_cube_exr_half_round_trip_is_half_rounding(tmp_path):
    cube = cube_data() * 1.4
    wl = np.array([400.0, 450.0, 500.0, 600.0])
    io.write_cube(tmp_path / "h.exr", cube, wl, half=True)
    back, _, meta = io.read_cube(tmp_path / "h.exr")
    assert meta == {}
    # Exactly IEEE half round-to-nearest, i.e. within half an ulp of 11 significant bits.
    np.testing.assert_array_equal(back, cube.astype(np.float16).astype(np.float32))
    np.testing.assert_allclose(back, cube, rtol=2.0 ** -11, atol=0)
    assert oiio.ImageInput.open(str(tmp_path / "h.exr")).spec().format == "half"


def test_cube_npz_round_trip_and_band_order(tmp_path):
    cube = cube_data()
    wl = np.array([600.0, 400.0, 500.0, 450.0])  # written in this order; read back sorted
    io.write_cube(tmp_path / "c.npz", cube, wl, metadata={"k": 1})
    back, wl_back, meta = io.read_cube(tmp_path / "c.npz")
    order = np.argsort(wl)
    np.testing.assert_array_equal(wl_back, wl[order])
    np.testing.assert_array_equal(back, cube[..., order])
    assert meta == {"k": 1}
    np.savez(tmp_path / "plain.npz", wavelengths=wl, reflectance=cube)  # a hand-made npz, no metadata
    back, wl_back, meta = io.read_cube(tmp_path / "plain.npz")
    np.testing.assert_array_equal(back, cube[..., order])
    assert meta == {}


def test_exr_bands_are_ordered_by_wavelength_not_by_channel_order(tmp_path):
    rng = np.random.default_rng(1)
    names = ["T.700,000000nm", "T.400nm", "T.0,5505um", "T.405.5nm", "T.1000,000000nm"]
    nm = [700.0, 400.0, 550.5, 405.5, 1000.0]
    data = rng.random((4, 3, len(names))).astype(np.float32)
    extra = rng.random((4, 3, 3)).astype(np.float32)  # RGB preview and an emissive band: not part of the cube
    write_exr_channels(tmp_path / "s.exr", names + ["R", "G", "S0.500,000000nm"], np.concatenate([data, extra], 2))
    # OpenEXR stores channels sorted by name (OpenImageIO then moves R, G first): the order seen by a reader is
    # neither the one written nor the wavelengths'.
    seen = [io.parse_channel(n) for n in oiio.ImageInput.open(str(tmp_path / "s.exr")).spec().channelnames]
    seen = [v for v in seen if v is not None]
    assert seen != sorted(seen) and seen != nm
    cube, wl, _ = io.read_cube(tmp_path / "s.exr")
    order = np.argsort(nm)
    np.testing.assert_array_equal(wl, np.array(nm)[order])
    np.testing.assert_allclose(wl, [400.0, 405.5, 550.5, 700.0, 1000.0], rtol=1e-12)
    np.testing.assert_array_equal(cube, data[..., order])


@pytest.mark.skipif(OIIOTOOL is None, reason="oiiotool (OpenImageIO's command-line tool) is not installed here")
@pytest.mark.parametrize("half", [False, True])
def test_oiiotool_info_shows_the_jcgt_channels(tmp_path, half):
    wl = np.array([400.0, 405.5, 700.0])
    io.write_cube(tmp_path / "c.exr", cube_data(b=3), wl, half=half, metadata={"method": "narrowband"})
    res = subprocess.run([OIIOTOOL, "--info", "-v", str(tmp_path / "c.exr")], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    assert re.search(r"channel list: T\.400,000000nm, T\.405,500000nm, T\.700,000000nm", res.stdout), res.stdout
    assert f"3 channel, {'half' if half else 'float'} openexr" in res.stdout
    assert 'spectralLayoutVersion: "1.0"' in res.stdout
    assert "specgpu:metadata" in res.stdout and "narrowband" in res.stdout


# ---- cubes: bad input --------------------------------------------------------------------------------------------------
def test_missing_cube_file(tmp_path):
    for name in ("none.exr", "none.npz"):
        with raises_one_line(FileNotFoundError, rf"{name}: spectral cube not found"):
            io.read_cube(tmp_path / name)


@pytest.mark.parametrize("fraction", [0.2, 0.6, 0.95])
def test_truncated_exr(tmp_path, fraction):
    io.write_cube(tmp_path / "ok.exr", cube_data(32, 32, 8), np.arange(400.0, 480.0, 10.0))
    raw = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "trunc.exr").write_bytes(raw[: int(len(raw) * fraction)])
    with raises_one_line(ValueError, r"trunc\.exr: (truncated or corrupt EXR|cannot open EXR)"):
        io.read_cube(tmp_path / "trunc.exr")


def test_corrupt_exr_and_wrong_file_type(tmp_path):
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all" * 10)
    with raises_one_line(ValueError, r"junk\.exr: cannot open EXR"):
        io.read_cube(tmp_path / "junk.exr")
    io.write_sRGB_preview(tmp_path / "p.png", np.full((2, 2, 3), 0.5))
    shutil.copy(tmp_path / "p.png", tmp_path / "png.exr")
    with raises_one_line(ValueError, r"png\.exr: not an OpenEXR file"):
        io.read_cube(tmp_path / "png.exr")
    with raises_one_line(ValueError, r"c\.tif: unknown spectral cube format '\.tif'; expected \.exr or \.npz"):
        io.read_cube(tmp_path / "c.tif")


def test_exr_without_spectral_channels(tmp_path):
    write_exr_channels(tmp_path / "rgb.exr", ["R", "G", "B"], np.zeros((2, 2, 3)))
    with raises_one_line(ValueError, r"rgb\.exr: no reflective spectral channels named 'T\.<wavelength>nm' "
                                     r"\(found R, G, B\)"):
        io.read_cube(tmp_path / "rgb.exr")


def test_exr_with_duplicate_wavelengths(tmp_path):
    write_exr_channels(tmp_path / "dup.exr", ["T.500nm", "T.500,0nm", "T.600nm"], np.zeros((2, 2, 3)))
    with raises_one_line(ValueError, r"dup\.exr: a wavelength appears in more than one 'T\.' channel"):
        io.read_cube(tmp_path / "dup.exr")


def test_exr_with_degenerate_wavelength(tmp_path):
    write_exr_channels(tmp_path / "zero.exr", ["T.0nm", "T.600nm"], np.zeros((2, 2, 2)))
    with raises_one_line(ValueError, r"zero\.exr: channel 'T\.0nm' gives wavelength 0\.0 nm; must be finite and > 0"):
        io.read_cube(tmp_path / "zero.exr")


def test_exr_with_corrupt_metadata(tmp_path):
    write_exr_channels(tmp_path / "meta.exr", ["T.500nm"], np.zeros((2, 2, 1)), {"specgpu:metadata": "{broken"})
    with raises_one_line(ValueError, r"meta\.exr: header attribute 'specgpu:metadata' is not valid JSON"):
        io.read_cube(tmp_path / "meta.exr")


def test_nan_and_duplicate_wavelengths_on_write_and_in_npz(tmp_path):
    cube = cube_data(b=3)
    for suffix in (".exr", ".npz"):
        with raises_one_line(ValueError, rf"nan{suffix}: wavelengths must be finite and > 0 nm"):
            io.write_cube(tmp_path / f"nan{suffix}", cube, [400.0, np.nan, 500.0])
        with raises_one_line(ValueError, rf"dup{suffix}: duplicate wavelength\(s\) \[400\.0\] nm"):
            io.write_cube(tmp_path / f"dup{suffix}", cube, [400.0, 400.0, 500.0])
    assert not list(tmp_path.iterdir())  # nothing written, not even a temporary
    np.savez(tmp_path / "nan.npz", wavelengths=np.array([400.0, np.nan, 500.0]), reflectance=cube)
    with raises_one_line(ValueError, r"nan\.npz: wavelengths must be finite and > 0 nm"):
        io.read_cube(tmp_path / "nan.npz")
    np.savez(tmp_path / "dup.npz", wavelengths=np.array([500.0, 400.0, 500.0]), reflectance=cube)
    with raises_one_line(ValueError, r"dup\.npz: duplicate wavelength\(s\) \[500\.0\] nm"):
        io.read_cube(tmp_path / "dup.npz")


def test_cube_shape_mismatches(tmp_path):
    with raises_one_line(ValueError, r"c\.exr: cube must have shape \(H, W, 4\) with H, W >= 1, got \(6, 5, 3\)"):
        io.write_cube(tmp_path / "c.exr", cube_data(b=3), [400.0, 450.0, 500.0, 550.0])
    with raises_one_line(ValueError, r"c\.exr: cube must have shape \(H, W, 2\)"):
        io.write_cube(tmp_path / "c.exr", np.zeros((4, 2)), [400.0, 450.0])
    np.savez(tmp_path / "shape.npz", wavelengths=np.array([400.0, 500.0]), reflectance=np.zeros((2, 2, 3)))
    with raises_one_line(ValueError, r"shape\.npz: reflectance must have shape \(H, W, 2\), got \(2, 2, 3\)"):
        io.read_cube(tmp_path / "shape.npz")
    np.savez(tmp_path / "nowl.npz", reflectance=np.zeros((2, 2, 3)))
    with raises_one_line(ValueError, r"nowl\.npz: missing array\(s\) \['wavelengths'\]"):
        io.read_cube(tmp_path / "nowl.npz")


def test_truncated_npz(tmp_path):
    io.write_cube(tmp_path / "ok.npz", cube_data(), [400.0, 450.0, 500.0, 550.0])
    raw = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with raises_one_line(ValueError, r"trunc\.npz: truncated or corrupt \.npz"):
        io.read_cube(tmp_path / "trunc.npz")


def test_metadata_must_be_json(tmp_path):
    with raises_one_line(ValueError, r"m\.exr: metadata must be JSON-serialisable with finite numbers"):
        io.write_cube(tmp_path / "m.exr", cube_data(b=2), [400.0, 500.0], metadata={"x": float("nan")})
    with raises_one_line(ValueError, r"m\.exr: metadata must be JSON-serialisable"):
        io.write_cube(tmp_path / "m.exr", cube_data(b=2), [400.0, 500.0], metadata={"x": object()})
    assert not (tmp_path / "m.exr").exists()


# ---- maps --------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind, channels", [("XYZ", 3), ("Lab", 3), ("dE2000", 1), (("RMSE",), 1)])
def test_map_round_trip(tmp_path, kind, channels):
    rng = np.random.default_rng(2)
    data = (rng.random((7, 9, channels)) * [100.0, 50.0, 50.0][:channels]).astype(np.float32)
    data[0, 0, 0] = np.nan  # NaN pixels are data, kept
    name = kind if isinstance(kind, str) else kind[0]
    io.write_map(tmp_path / f"{name}.exr", data[..., 0] if channels == 1 else data, kind, metadata={"kind": name})
    back, names, meta = io.read_map(tmp_path / f"{name}.exr")
    np.testing.assert_array_equal(back, data)
    assert names == (io.MAP_KINDS[kind] if isinstance(kind, str) else kind)
    assert meta == {"kind": name}
    back2, names2, _ = io.read_map(tmp_path / f"{name}.exr", kind)
    np.testing.assert_array_equal(back2, data)
    # half
    io.write_map(tmp_path / "h.exr", data, kind, half=True)
    np.testing.assert_array_equal(io.read_map(tmp_path / "h.exr", kind)[0], data.astype(np.float16).astype(np.float32))


def test_map_channels_come_back_in_the_kinds_order(tmp_path):
    data = np.random.default_rng(3).random((3, 4, 3)).astype(np.float32)
    write_exr_channels(tmp_path / "lab.exr", ["b", "L", "a"], data)  # written shuffled
    back, names, _ = io.read_map(tmp_path / "lab.exr")
    assert names == ("L", "a", "b")
    np.testing.assert_array_equal(back, data[..., [1, 2, 0]])


def test_map_bad_input(tmp_path):
    xyz = np.zeros((3, 4, 3), np.float32)
    io.write_map(tmp_path / "xyz.exr", xyz, "XYZ")
    with raises_one_line(ValueError, r"xyz\.exr: not a Lab map: expected channels L, a, b, found X, Y, Z"):
        io.read_map(tmp_path / "xyz.exr", "Lab")
    with raises_one_line(ValueError, r"w\.exr: unknown map kind 'XYZW'; valid kinds: XYZ, Lab, dE76, dE94, dE2000"):
        io.write_map(tmp_path / "w.exr", xyz, "XYZW")
    with raises_one_line(ValueError, r"d\.exr: a dE2000 map must have shape \(H, W, 1\), got \(3, 4, 3\)"):
        io.write_map(tmp_path / "d.exr", xyz, "dE2000")
    with raises_one_line(FileNotFoundError, r"none\.exr: map not found"):
        io.read_map(tmp_path / "none.exr")
    raw = (tmp_path / "xyz.exr").read_bytes()
    (tmp_path / "trunc.exr").write_bytes(raw[: len(raw) // 3])
    with raises_one_line(ValueError, r"trunc\.exr: (truncated or corrupt EXR|cannot open EXR)"):
        io.read_map(tmp_path / "trunc.exr")
    with raises_one_line(ValueError, r"m\.png: unknown map format '\.png'; expected \.exr"):
        io.write_map(tmp_path / "m.png", xyz, "XYZ")


# ---- previews ----------------------------------------------------------------------------------------------------------
def test_sRGB_preview_adapts_from_the_given_illuminant(tmp_path):
    xy_a = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    white_a = np.broadcast_to(colour.xy_to_XYZ(xy_a) * 0.9, (2, 2, 3))
    io.write_sRGB_preview(tmp_path / "a.png", white_a, exposure=0.0, illuminant=xy_a)
    neutral = io.read_png(tmp_path / "a.png")[0]
    assert np.ptp(neutral.astype(int), axis=-1).max() <= 1  # the white of A renders neutral
    io.write_sRGB_preview(tmp_path / "b.png", white_a, exposure=0.0)
    warm = io.read_png(tmp_path / "b.png")[0][0, 0].astype(int)
    assert warm[0] - warm[2] > 50  # unadapted, A's white is orange


def test_sRGB_preview_matches_colour_science(tmp_path):
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    rng = np.random.default_rng(4)
    xyz = rng.random((6, 8, 3)) * 0.8
    xyz[0, 0] = d65            # the perfect diffuser: white
    xyz[0, 1] = d65 * 0.18     # 18 % grey
    xyz[0, 2] = np.nan         # NaN renders black
    io.write_sRGB_preview(tmp_path / "p.png", xyz, exposure=0.0, metadata={"scene": "chart"})
    rgb, meta = io.read_png(tmp_path / "p.png")
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint8
    expected = np.round(np.clip(colour.XYZ_to_sRGB(np.nan_to_num(xyz)), 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(rgb, expected)
    assert tuple(rgb[0, 0]) == (255, 255, 255) and tuple(rgb[0, 2]) == (0, 0, 0)
    assert abs(int(rgb[0, 1, 1]) - 118) <= 1  # sRGB code of 18 % grey
    assert float(meta["specgpu:exposure_EV"]) == 0.0 and meta["scene"] == "chart"
    # +1 EV doubles the linear values; "auto" brings the 99th percentile of Y to 1.
    io.write_sRGB_preview(tmp_path / "p1.png", xyz, exposure=1.0)
    np.testing.assert_array_equal(
        io.read_png(tmp_path / "p1.png")[0],
        np.round(np.clip(colour.XYZ_to_sRGB(np.nan_to_num(xyz) * 2), 0, 1) * 255).astype(np.uint8))
    io.write_sRGB_preview(tmp_path / "pa.png", xyz * 0.1)
    ev = float(io.read_png(tmp_path / "pa.png")[1]["specgpu:exposure_EV"])
    assert 2.0 ** ev * np.nanpercentile(xyz[..., 1] * 0.1, 99) == pytest.approx(1.0)
    with raises_one_line(ValueError, r"q\.png: exposure must be a number of stops or 'auto', got 'bright'"):
        io.write_sRGB_preview(tmp_path / "q.png", xyz, exposure="bright")
    with raises_one_line(ValueError, r"q\.png: XYZ must have shape \(H, W, 3\), got \(6, 8\)"):
        io.write_sRGB_preview(tmp_path / "q.png", xyz[..., 0])
    assert no_temp_files(tmp_path)


def test_delta_E_heat_map_png(tmp_path):
    dE = np.array([[0.0, 2.5, 5.0], [10.0, np.nan, 1.0]])
    io.write_delta_E_png(tmp_path / "d.png", dE, vmax=5.0, colormap="viridis")
    rgb, meta = io.read_png(tmp_path / "d.png")
    lut = np.round(matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    assert tuple(rgb[0, 0]) == tuple(lut[0]) and tuple(rgb[0, 2]) == tuple(lut[255])
    assert tuple(rgb[1, 0]) == tuple(lut[255])           # above vmax clips
    assert tuple(rgb[0, 1]) == tuple(lut[128])           # 2.5 / 5 -> middle (127.5 rounds to 128)
    assert tuple(rgb[1, 1]) == (128, 128, 128)           # NaN grey
    assert meta["specgpu:quantity"] == "dE2000" and meta["specgpu:colormap"] == "viridis"
    assert float(meta["specgpu:vmin"]) == 0.0 and float(meta["specgpu:vmax"]) == 5.0
    io.write_delta_E_png(tmp_path / "auto.png", dE, quantity="dE76")
    meta = io.read_png(tmp_path / "auto.png")[1]
    assert float(meta["specgpu:vmax"]) == 10.0 and meta["specgpu:quantity"] == "dE76"
    with raises_one_line(ValueError, r"j\.png: unknown colormap 'jet'; valid colormaps: magma, inferno"):
        io.write_delta_E_png(tmp_path / "j.png", dE, colormap="jet")
    with raises_one_line(ValueError, r"j\.png: vmax must be finite and > 0"):
        io.write_delta_E_png(tmp_path / "j.png", dE, vmax=0)


# ---- frame sequences ---------------------------------------------------------------------------------------------------
def frames_and_records(n=4, h=5, w=6, seed=5, first_id=100):
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 65536, (n, h, w), dtype=np.uint16)
    frames[0, 0, 0], frames[0, 0, 1] = 0, 65535
    records = [{"frame_id": first_id + i, "pattern_index": i % 3, "exposure_s": 0.0125, "timestamp_s": 0.04 * i}
               for i in range(n)]
    return frames, records


def test_sequence_round_trip_from_array(tmp_path):
    frames, records = frames_and_records()
    out = io.write_sequence(tmp_path / "seq", frames, records, "plan-abc", metadata={"scene": "colorchecker"})
    back, recs, meta = io.read_sequence(out)
    np.testing.assert_array_equal(back, frames)
    assert back.dtype == np.uint16
    assert [{k: r[k] for k in records[0]} for r in recs] == records
    assert meta["plan_hash"] == "plan-abc" and meta["n_frames"] == 4 and (meta["height"], meta["width"]) == (5, 6)
    assert meta["format"] == io.SEQUENCE_FORMAT and meta["version"] == io.SEQUENCE_VERSION
    assert meta["metadata"] == {"scene": "colorchecker"}
    # The frames are ordinary 16-bit TIFFs any tool reads.
    spec = oiio.ImageInput.open(str(out / recs[2]["file"])).spec()
    assert (spec.format, spec.nchannels, spec.width, spec.height) == ("uint16", 1, 6, 5)
    assert no_temp_files(tmp_path)


def test_sequence_from_an_iterable_of_frames_and_capture_objects(tmp_path):
    frames, records = frames_and_records()
    infos = [FrameInfo(r["frame_id"], r["pattern_index"], r["timestamp_s"], r["exposure_s"]) for r in records]
    io.write_sequence(tmp_path / "gen", (f for f in frames), infos, "p1")
    np.testing.assert_array_equal(io.read_sequence(tmp_path / "gen")[0], frames)
    seq = Sequence(frames=frames, frame_ids=np.arange(7, 11), timestamps_s=np.arange(4) * 0.05, exposure_s=0.02,
                   cycle=0)
    io.write_sequence(tmp_path / "asm", seq, plan_hash="p2")
    back, recs, _ = io.read_sequence(tmp_path / "asm")
    np.testing.assert_array_equal(back, frames)
    assert [r["frame_id"] for r in recs] == [7, 8, 9, 10] and [r["pattern_index"] for r in recs] == [0, 1, 2, 3]


def test_sequence_overwrite_and_refusal(tmp_path):
    frames, records = frames_and_records()
    io.write_sequence(tmp_path / "s", frames, records, "p")
    with raises_one_line(FileExistsError, r"s: already holds a frame sequence"):
        io.write_sequence(tmp_path / "s", frames, records, "p")
    io.write_sequence(tmp_path / "s", frames[:2], records[:2], "q", overwrite=True)
    back, recs, meta = io.read_sequence(tmp_path / "s")
    assert back.shape[0] == 2 and meta["plan_hash"] == "q"
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["frame_000000.tif", "frame_000001.tif",
                                                                  "sequence.json"]


def test_interrupted_sequence_write_leaves_nothing_that_looks_complete(tmp_path):
    frames, records = frames_and_records()

    def failing():
        yield frames[0]
        yield frames[1]
        raise RuntimeError("camera unplugged")

    with pytest.raises(RuntimeError, match="camera unplugged"):
        io.write_sequence(tmp_path / "s", failing(), records, "p")
    assert not (tmp_path / "s" / "sequence.json").exists()
    assert not list((tmp_path / "s").iterdir())  # the frames written so far were removed
    with raises_one_line(ValueError, r"sequence\.json: missing; .* is not a complete frame sequence"):
        io.read_sequence(tmp_path / "s")


def test_sequence_write_bad_input(tmp_path):
    frames, records = frames_and_records()
    with raises_one_line(ValueError, r"a: 2 frame\(s\) but 4 record\(s\)"):
        io.write_sequence(tmp_path / "a", frames[:2], records, "p")
    with raises_one_line(ValueError, r"b: more frames than records \(3\)"):
        io.write_sequence(tmp_path / "b", frames, records[:3], "p")
    with raises_one_line(ValueError, r"c: frame 0 must be uint16 \(16-bit DN\), got dtype float32"):
        io.write_sequence(tmp_path / "c", frames.astype(np.float32), records, "p")
    with raises_one_line(ValueError, r"d: frame 1 has shape \(4, 6\), the first frame \(5, 6\)"):
        io.write_sequence(tmp_path / "d", [frames[0], frames[1][:4]], records[:2], "p")
    seq = Sequence(frames=frames, frame_ids=np.arange(4), timestamps_s=np.zeros(4), exposure_s=0.0, cycle=0)
    with raises_one_line(ValueError, r"sequence\.json: frames\[0\]\.exposure_s must be a finite number > 0 \(s\), got 0\.0"):
        io.write_sequence(tmp_path / "h", seq, plan_hash="p")  # rejected before any frame is written
    with raises_one_line(ValueError, r"e: plan_hash must be a non-empty string"):
        io.write_sequence(tmp_path / "e", frames, records, "")
    with raises_one_line(ValueError, r"f: record 2 lacks exposure_s"):
        io.write_sequence(tmp_path / "f", frames, records[:2] + [{"frame_id": 3, "pattern_index": 0,
                                                                 "timestamp_s": 0.0}] + records[3:], "p")
    bad = copy.deepcopy(records)
    bad[2]["frame_id"] = bad[1]["frame_id"]
    with raises_one_line(ValueError, r"sequence\.json: frames\[2\]\.frame_id 101 must be greater than"):
        io.write_sequence(tmp_path / "g", frames, bad, "p")
    for name in "abcdefgh":  # no folder left looking like a sequence
        assert not (tmp_path / name / "sequence.json").exists()
        assert not (tmp_path / name).exists() or not list((tmp_path / name).iterdir())


@pytest.fixture
def seq(tmp_path):
    frames, records = frames_and_records(h=32, w=40)
    return io.write_sequence(tmp_path / "seq", frames, records, "plan")


def test_sequence_folder_missing(tmp_path):
    with raises_one_line(FileNotFoundError, r"nope: sequence folder not found"):
        io.read_sequence(tmp_path / "nope")


def test_sequence_without_json(seq):
    (seq / "sequence.json").unlink()
    with raises_one_line(ValueError, r"seq/sequence\.json: missing; .*seq is not a complete frame sequence"):
        io.read_sequence(seq)


@pytest.mark.parametrize("cut", [0, 1, 40, -3])
def test_sequence_with_corrupt_json(seq, cut):
    text = (seq / "sequence.json").read_text()
    (seq / "sequence.json").write_text(text[:cut] if cut >= 0 else text[:cut] + "}}")
    with raises_one_line(ValueError, r"seq/sequence\.json: corrupt JSON \(.* at line \d+ column \d+\)"):
        io.read_sequence(seq)
    (seq / "sequence.json").write_bytes(b"\xff\xfe\x00garbage")
    with raises_one_line(ValueError, r"seq/sequence\.json: corrupt \(not UTF-8 text\)"):
        io.read_sequence(seq)


def test_sequence_with_unknown_format_version(seq):
    doc = json.loads((seq / "sequence.json").read_text())
    doc["version"] = 2
    (seq / "sequence.json").write_text(json.dumps(doc))
    with raises_one_line(ValueError, r"sequence\.json: unknown format version 2 \(this specgpu reads version 1\)"):
        io.read_sequence(seq)
    doc["version"], doc["format"] = 1, "other.tool"
    (seq / "sequence.json").write_text(json.dumps(doc))
    with raises_one_line(ValueError, r"sequence\.json: not a specgpu frame sequence \(format 'other\.tool'"):
        io.read_sequence(seq)


def test_sequence_with_a_missing_frame(seq):
    (seq / "frame_000002.tif").unlink()
    with raises_one_line(ValueError, r"frame_000002\.tif: frame 2 \(frame id 102\) listed in sequence\.json is missing"):
        io.read_sequence(seq)


def test_sequence_with_a_truncated_frame(seq):
    path = seq / "frame_000001.tif"
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with raises_one_line(ValueError, r"frame_000001\.tif: truncated or altered frame: \d+ bytes, sequence\.json says"):
        io.read_sequence(seq)
    # Even when the record is edited to match, decoding catches the truncation.
    doc = json.loads((seq / "sequence.json").read_text())
    doc["frames"][1]["bytes"] = len(raw) // 2
    doc["frames"][1]["sha256"] = hashlib.sha256(raw[: len(raw) // 2]).hexdigest()
    (seq / "sequence.json").write_text(json.dumps(doc))
    with raises_one_line(ValueError, r"frame_000001\.tif: truncated or corrupt TIFF"):
        io.read_sequence(seq)


def test_sequence_with_a_corrupt_frame_of_the_right_size(seq):
    path = seq / "frame_000003.tif"
    raw = bytearray(path.read_bytes())
    raw[-20] ^= 0xFF
    path.write_bytes(bytes(raw))
    with raises_one_line(ValueError, r"frame_000003\.tif: corrupt frame: SHA-256 differs from sequence\.json"):
        io.read_sequence(seq)


def test_sequence_frame_of_the_wrong_shape(seq):
    doc = json.loads((seq / "sequence.json").read_text())
    doc["height"] = 31
    (seq / "sequence.json").write_text(json.dumps(doc))
    with raises_one_line(ValueError, r"frame_000000\.tif: frame is 32 x 40, sequence\.json says 31 x 40"):
        io.read_sequence(seq)


# ---- sequence.json validation (property tests) ---------------------------------------------------------------------
_hex = st.text(alphabet="0123456789abcdef", min_size=64, max_size=64)


@st.composite
def sequence_documents(draw):
    n = draw(st.integers(1, 6))
    ids = sorted(draw(st.sets(st.integers(0, 2**40), min_size=n, max_size=n)))
    frames = [{"file": f"frame_{i:06d}.tif", "frame_id": fid,
               "pattern_index": draw(st.integers(0, 60)),
               "exposure_s": draw(st.floats(1e-6, 10.0)),
               "timestamp_s": draw(st.floats(-1e6, 1e6)),
               "bytes": draw(st.integers(0, 2**31)), "sha256": draw(_hex)} for i, fid in enumerate(ids)]
    return {"format": io.SEQUENCE_FORMAT, "version": io.SEQUENCE_VERSION,
            "plan_hash": draw(st.text(min_size=1, max_size=16)),
            "height": draw(st.integers(1, 5000)), "width": draw(st.integers(1, 5000)), "dtype": "uint16",
            "n_frames": n, "frames": frames,
            "metadata": draw(st.dictionaries(st.text(max_size=5), st.integers() | st.text(max_size=5), max_size=3))}


@settings(max_examples=60, deadline=None)
@given(sequence_documents())
def test_valid_sequence_documents_pass_and_survive_json(doc):
    out = io.validate_sequence_document(doc, "x/sequence.json")
    assert out == doc
    assert io.validate_sequence_document(json.loads(json.dumps(out)), "x/sequence.json") == doc


# (where, key, bad value): each breaks one rule of the document.
_MUTATIONS = [
    (None, "format", "specgpu.cube"), (None, "format", None), (None, "version", 0), (None, "version", "1"),
    (None, "version", True), (None, "plan_hash", ""), (None, "plan_hash", 3), (None, "height", 0),
    (None, "width", 2.5), (None, "dtype", "float32"), (None, "frames", []), (None, "frames", {}),
    (None, "metadata", []), (None, "n_frames", 99), (None, "n_frames", "1"),
    ("frame", "frame_id", -1), ("frame", "frame_id", 1.0), ("frame", "frame_id", True),
    ("frame", "pattern_index", -2), ("frame", "pattern_index", "0"), ("frame", "exposure_s", 0.0),
    ("frame", "exposure_s", math.nan), ("frame", "exposure_s", math.inf), ("frame", "exposure_s", "1ms"),
    ("frame", "timestamp_s", math.nan), ("frame", "timestamp_s", None), ("frame", "bytes", -1),
    ("frame", "sha256", "xyz"), ("frame", "sha256", "A" * 64), ("frame", "file", "../escape.tif"),
    ("frame", "file", ""), ("frame", "file", "sub/frame.tif"), ("frame", "file", 7),
    ("frame", "__delete__", "frame_id"), ("frame", "__delete__", "sha256"), (None, "__delete__", "plan_hash"),
]


@settings(max_examples=150, deadline=None)
@given(sequence_documents(), st.sampled_from(_MUTATIONS), st.data())
def test_each_broken_rule_is_a_one_line_error_naming_the_file(doc, mutation, data):
    where, key, value = mutation
    bad = copy.deepcopy(doc)
    target = bad if where is None else bad["frames"][data.draw(st.integers(0, len(bad["frames"]) - 1))]
    if key == "__delete__":
        del target[value]
    else:
        target[key] = value
    with raises_one_line(ValueError, r"^x/sequence\.json: "):
        io.validate_sequence_document(bad, "x/sequence.json")


@settings(max_examples=40, deadline=None)
@given(sequence_documents(), st.data())
def test_frame_ids_out_of_capture_order_or_repeated_files_are_rejected(doc, data):
    if len(doc["frames"]) < 2:
        doc["frames"].append(dict(doc["frames"][0], file="frame_999999.tif", frame_id=doc["frames"][0]["frame_id"] + 1))
        doc["n_frames"] = 2
    bad = copy.deepcopy(doc)
    i = data.draw(st.integers(1, len(bad["frames"]) - 1))
    if data.draw(st.booleans()):
        bad["frames"][i]["frame_id"] = bad["frames"][i - 1]["frame_id"]
        match = r"frame_id .* must be greater than the previous frame's"
    else:
        bad["frames"][i]["file"] = bad["frames"][0]["file"]
        match = r"is listed twice"
    with raises_one_line(ValueError, match):
        io.validate_sequence_document(bad, "x/sequence.json")
    with raises_one_line(ValueError, r"must hold a JSON object"):
        io.validate_sequence_document([doc], "x/sequence.json")
