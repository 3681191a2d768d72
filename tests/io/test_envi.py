"""ENVI cubes (specgpu.io.envi): written for and checked by Spectral Python, read from it, refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import spectral.io.envi as envi
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io

WL = np.array([400.0, 410.5, 420.25, 700.0 / 3.0 + 400.0, 700.0])


def cube(h=7, w=5, seed=0):
    rng = np.random.default_rng(seed)
    c = rng.random((h, w, WL.size), dtype=np.float32)
    c[2, 3, 1] = np.nan
    c[0, 0, 0] = np.float32(1e-38)  # a subnormal-adjacent value survives
    return c


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
def test_spectral_python_reads_our_cube_bit_exactly(tmp_path, interleave):
    data = cube()
    path = io.write_cube(tmp_path / "c.hdr", data, WL, interleave=interleave, metadata={"plan": "x", "k": 9})
    assert (tmp_path / "c.img").stat().st_size == data.size * 4
    img = envi.open(str(path))
    assert img.metadata["interleave"] == interleave and img.shape == data.shape
    assert img.metadata["wavelength units"] == "Nanometers"
    np.testing.assert_array_equal(np.array(img.bands.centers, np.float64), WL)
    loaded = img.load()
    assert loaded.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(loaded), data)  # NaN in the same place, every bit equal
    back, wl, meta = io.read_cube(path)
    np.testing.assert_array_equal(back, data)
    np.testing.assert_array_equal(wl, WL)
    assert meta == {"plan": "x", "k": 9}


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16, np.int16])
@pytest.mark.parametrize("byteorder", [0, 1])
def test_we_read_cubes_spectral_python_wrote(tmp_path, interleave, dtype, byteorder):
    rng = np.random.default_rng(1)
    data = (rng.random((6, 4, 3)) * 1000).astype(dtype)
    wl_um = [0.7, 0.45, 0.55]  # micrometres, out of order
    envi.save_image(str(tmp_path / "s.hdr"), data, dtype=dtype, interleave=interleave, byteorder=byteorder,
                    metadata={"wavelength": wl_um, "wavelength units": "Micrometers"}, ext=".img")
    back, wl, meta = io.read_cube(tmp_path / "s.hdr")
    np.testing.assert_allclose(wl, [450.0, 550.0, 700.0])
    np.testing.assert_array_equal(back, data[..., [1, 2, 0]].astype(np.float32))
    assert back.dtype == np.float32 and meta == {}


def test_header_size_disagreeing_with_the_data_is_one_line(tmp_path):
    io.write_cube(tmp_path / "c.hdr", cube(), WL)
    with open(tmp_path / "c.img", "ab") as fh:
        fh.write(b"\0" * 4)
    with pytest.raises(ValueError) as err:
        io.read_cube(tmp_path / "c.hdr")
    msg = str(err.value)
    assert msg == (f"{tmp_path / 'c.hdr'}: data file c.img holds {7 * 5 * 5 * 4 + 4} bytes but the header describes "
                   f"{7 * 5 * 5 * 4} (7 lines x 5 samples x 5 bands of 4-byte data type 4)")
    (tmp_path / "c.img").unlink()
    with pytest.raises(FileNotFoundError, match="c.hdr: the ENVI data file c.img is missing"):
        io.read_cube(tmp_path / "c.hdr")


def test_bad_headers_and_arguments_are_one_line(tmp_path):
    io.write_cube(tmp_path / "c.hdr", cube(), WL)
    text = (tmp_path / "c.hdr").read_text()
    cases = {
        "data type = 4": ("data type = 6", "unsupported ENVI data type 6"),
        "interleave = bsq": ("interleave = bxx", "unknown ENVI interleave 'bxx'"),
        "samples = 5": ("samples = five", "'samples' must be an integer"),
        "wavelength units = Nanometers": ("wavelength units = Furlongs", "unknown ENVI 'wavelength units'"),
        "ENVI\n": ("NOPE\n", "not an ENVI header"),
    }
    for old, (new, message) in cases.items():
        (tmp_path / "b.hdr").write_text(text.replace(old, new, 1))
        (tmp_path / "b.img").write_bytes((tmp_path / "c.img").read_bytes())
        with pytest.raises(ValueError, match=message) as err:
            io.read_cube(tmp_path / "b.hdr")
        assert "\n" not in str(err.value) and str(err.value).startswith(str(tmp_path / "b.hdr"))
    kept = [line for line in text.splitlines() if not line.startswith("wavelength =")]
    (tmp_path / "b.hdr").write_text("\n".join(kept))
    with pytest.raises(ValueError, match="no 'wavelength' list"):
        io.read_cube(tmp_path / "b.hdr")
    with pytest.raises(ValueError, match="ENVI has no half-float"):
        io.write_cube(tmp_path / "h.hdr", cube(), WL, half=True)
    with pytest.raises(ValueError, match="unknown ENVI interleave 'tiles'"):
        io.write_cube(tmp_path / "h.hdr", cube(), WL, interleave="tiles")
    assert not (tmp_path / "h.hdr").exists() and not (tmp_path / "h.img").exists()


@settings(max_examples=150)
@given(st.binary(max_size=400), st.sampled_from(["ENVI\n", "ENVI\nsamples = 2\nlines = 1\nbands = 1\n", ""]))
def test_fuzzed_headers_give_a_cube_or_one_line(tmp_path_factory, body, prefix):
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "f.hdr").write_bytes(prefix.encode() + body)
    (folder / "f.img").write_bytes(b"\0" * 8)
    try:
        data, wl, _ = io.read_cube(folder / "f.hdr")
    except (ValueError, FileNotFoundError) as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(folder / "f.hdr"))
    else:
        assert data.ndim == 3 and data.shape[2] == wl.size and np.all(np.diff(wl) > 0)
