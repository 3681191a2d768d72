"""An .npz whose arrays declare far more memory than the file holds (a "zip bomb" of constant data, or more than
this machine has) is refused from its headers, before any array is inflated."""

from __future__ import annotations

import io as pyio
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from specgpu.io import npz
from specgpu.io.tables import load_npz, save_npz
from specgpu.rig.scene import read_scene


def bomb(path, shape, *, extra=None):
    """An npz of ``wavelengths`` (shape[-1],) and an all-zero float64 ``reflectance`` of ``shape``, written
    without ever holding the array in memory (deflate packs zeros ~1000:1)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        buf = pyio.BytesIO()
        np.lib.format.write_array(buf, np.linspace(400.0, 700.0, shape[-1]))
        zf.writestr("wavelengths.npy", buf.getvalue())
        for name, value in (extra or {}).items():
            buf = pyio.BytesIO()
            np.lib.format.write_array(buf, value)
            zf.writestr(f"{name}.npy", buf.getvalue())
        with zf.open("reflectance.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": shape})
            left, zeros = int(np.prod(shape)) * 8, bytes(2**20)
            while left:
                fh.write(zeros[:min(left, len(zeros))])
                left -= min(left, len(zeros))
    return path


def test_a_zip_bomb_scene_is_refused_from_its_header(tmp_path):
    path = bomb(tmp_path / "zeros.npz", (1200, 1000, 12))  # 115 MB declared in a 0.1 MB file
    assert path.stat().st_size < 200_000
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=r"zeros\.npz: array 'reflectance' \(1200, 1000, 12\) would inflate "
                                             r"0\.\d\d MB to 115 MB \(\d+:1, constant data\); refused before "
                                             r"loading it"):
            read_scene(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5e6  # the check read headers, not arrays


def test_a_plan_file_bomb_is_refused_as_a_corrupt_file(tmp_path):
    path = bomb(tmp_path / "plan.npz", (1200, 1000, 12), extra={"__meta__": np.array("{}")})
    with pytest.raises(ValueError, match=r"plan\.npz: array 'reflectance' .* refused before loading it"):
        load_npz(path, "specgpu.plan", (1,))


def test_more_than_the_memory_available_is_refused(tmp_path, monkeypatch):
    path = bomb(tmp_path / "big.npz", (100, 100, 3))
    monkeypatch.setattr(npz, "available_memory_bytes", lambda: 100_000)
    with pytest.raises(ValueError, match=r"big\.npz: its arrays take 0\.00 GB once loaded but only 0\.00 GB of "
                                         r"memory are available"):
        read_scene(path)


def test_a_header_that_does_not_match_the_stored_bytes_is_corrupt(tmp_path):
    path = tmp_path / "lie.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        buf = pyio.BytesIO()
        np.lib.format.write_array(buf, np.zeros((4, 4, 3)))
        raw = buf.getvalue().replace(b"(4, 4, 3)", b"(9, 9, 3)")
        zf.writestr("reflectance.npy", raw)
        buf = pyio.BytesIO()
        np.lib.format.write_array(buf, np.array([400.0, 500.0, 600.0]))
        zf.writestr("wavelengths.npy", buf.getvalue())
    with pytest.raises(ValueError, match=r"lie\.npz: array 'reflectance' declares 1944 bytes but the archive "
                                         r"stores 384; truncated or corrupt"):
        read_scene(path)


def test_ordinary_files_load_as_before(tmp_path):
    from specgpu.rig.scene import SpectralScene, write_scene

    wl = np.linspace(400.0, 700.0, 31)
    refl = np.zeros((600, 800, 31), np.float32)  # a black scene: constant, but small
    write_scene(tmp_path / "black.npz", SpectralScene(wl, refl, {"all": np.ones((600, 800), bool)}, "black"))
    back = read_scene(tmp_path / "black.npz")
    assert back.reflectance.shape == (600, 800, 31) and float(back.reflectance.max()) == 0.0
    save_npz(tmp_path / "x.npz", "specgpu.test", 1, {"a": np.arange(10.0)}, {"k": 1})
    arrays, meta, _, _ = load_npz(tmp_path / "x.npz", "specgpu.test", (1,))
    assert arrays["a"].tolist() == list(np.arange(10.0)) and meta == {"k": 1}


def test_a_large_constant_cube_specgpu_writes_is_read_back_not_refused(tmp_path):
    """specgpu's own writer deflates at a level whose ratio on constant data (about 230:1) stays under the bomb
    refusal's 500:1: a recorded black or flat cube past the size the check looks at is read back, not lost."""
    from specgpu.io.npz import NPZ_MAX_RATIO, NPZ_UNIFORM_BYTES, read_cube_npz, write_cube_npz

    wl = np.linspace(400.0, 700.0, 16)
    h = int(np.ceil(NPZ_UNIFORM_BYTES / (1024 * 16 * 4)))
    write_cube_npz(tmp_path / "flat.npz", np.full((h, 1024, 16), 0.5, np.float32), wl)
    with zipfile.ZipFile(tmp_path / "flat.npz") as zf:
        info = zf.getinfo("reflectance.npy")
    assert info.file_size >= NPZ_UNIFORM_BYTES and info.compress_type == zipfile.ZIP_DEFLATED
    assert info.file_size < NPZ_MAX_RATIO * info.compress_size
    cube, back_wl, _ = read_cube_npz(tmp_path / "flat.npz")
    assert cube.shape == (h, 1024, 16) and float(cube.min()) == float(cube.max()) == 0.5
    np.testing.assert_array_equal(back_wl, wl)


_ARRAYS = st.dictionaries(
    st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True),
    hnp.arrays(st.sampled_from([np.float32, np.float64, np.int16, np.uint8, np.bool_]),
               hnp.array_shapes(min_dims=0, max_dims=3, max_side=6)),
    min_size=1, max_size=4)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(arrays=_ARRAYS)
def test_the_deflated_writer_writes_what_numpy_loads(tmp_path, arrays):
    with open(tmp_path / "w.npz", "wb") as fh:
        npz.savez_deflated(fh, arrays)
    assert npz.npz_members(tmp_path / "w.npz") == {k: (v.shape, v.dtype) for k, v in arrays.items()}
    with np.load(tmp_path / "w.npz", allow_pickle=False) as back:
        assert sorted(back.files) == sorted(arrays)
        for k, v in arrays.items():
            np.testing.assert_array_equal(back[k], v)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(arrays=_ARRAYS, compressed=st.booleans())
def test_npz_members_reads_every_header_as_numpy_wrote_it(tmp_path, arrays, compressed):
    path = tmp_path / "a.npz"
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    members = npz.npz_members(path)
    assert members == {k: (v.shape, v.dtype) for k, v in arrays.items()}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_damaged_npz_is_refused_in_one_line_or_read_as_declared(tmp_path, data):
    """Any byte flipped or cut: npz_members either reads the headers (whose sizes then match what the archive
    stores) or refuses in one line naming the file; never another exception."""
    path = tmp_path / "a.npz"
    np.savez_compressed(path, wavelengths=np.linspace(400, 700, 4), reflectance=np.full((3, 5, 4), 0.25))
    raw = bytearray(path.read_bytes())
    if data.draw(st.booleans(), "cut"):
        raw = raw[:data.draw(st.integers(0, len(raw) - 1), "at")]
    else:
        i = data.draw(st.integers(0, len(raw) - 1), "byte")
        raw[i] ^= data.draw(st.integers(1, 255), "mask")
    path.write_bytes(bytes(raw))
    try:
        members = npz.npz_members(path)
    except ValueError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)
    else:
        assert set(members) <= {"wavelengths", "reflectance"}
