"""specgpu.io.cube: spectral cubes (EXR, npz) and maps round trip, band order, oiiotool interop, bad input (one line
each)."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import OpenImageIO as oiio
import pytest
from file_helpers import (
    OIIOTOOL,
    cube_data,
    no_temp_files,
    raises_one_line,
    write_exr_channels,
)

from specgpu import io
from specgpu.io.exr import parse_channel


# ---- cubes -----------------------------------------------------------------------------------------------------------
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
    seen = [parse_channel(n) for n in oiio.ImageInput.open(str(tmp_path / "s.exr")).spec().channelnames]
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


# ---- cubes: bad input ------------------------------------------------------------------------------------------------
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


# ---- maps ------------------------------------------------------------------------------------------------------------
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
