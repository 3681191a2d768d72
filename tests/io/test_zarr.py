"""zarr recordings (specgpu.io.recording): opened by xarray and Dask with no specgpu code, commit rule, bad input.

The recorder is fed hand-built results here (no device needed); tests/pipeline/test_stream.py records real streams.
"""

from __future__ import annotations

import json
import types
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.io.recording import (
    ZarrRecorder,
    check_free_space,
    open_recording,
    patterns_hash,
    refuse_existing,
    sequence_bytes,
)
from specgpu.pipeline import StreamResult

H, W, K, B = 6, 8, 4, 5


def fake_plan(patterns=None):
    pat = np.arange(K * 3).reshape(K, 3) if patterns is None else patterns
    return types.SimpleNamespace(hash="ab" * 32, method="symmetric", calibration="cd" * 32, patterns=pat, K=K,
                                 output="reflectance", output_wavelengths=np.linspace(400.0, 700.0, B),
                                 output_labels=tuple(str(x) for x in np.linspace(400.0, 700.0, B)))


def result(i, rng):
    ids = np.arange(i * K, (i + 1) * K)
    arrays = {"cube": rng.random((H, W, B), dtype=np.float32), "XYZ": rng.random((H, W, 3), dtype=np.float32),
              "dE": rng.random((H, W), dtype=np.float32)}
    frames = rng.integers(0, 1024, (K, H, W), dtype=np.uint16)
    return StreamResult(i, i, ids, ids * 0.005 + 1.0, arrays, 0.01, frames=frames)


def record(path, n, *, close=True, frames=True, seed=0):
    rng = np.random.default_rng(seed)
    rec = ZarrRecorder(path, fake_plan(), frames=frames, metadata={"scene": "test"}, grow=3)
    results = [result(i, rng) for i in range(n)]
    for r in results:
        rec.write(r)
    if close:
        rec.close()
    return rec, results


def test_xarray_opens_a_recording_with_named_dims_and_coordinates(tmp_path):
    import xarray as xr

    _, results = record(tmp_path / "rec.zarr", 5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consolidated metadata: no fallback warning
        ds = xr.open_zarr(tmp_path / "rec.zarr")
    assert ds.sizes["time"] == 5 and ds.sizes["wavelength"] == B and ds.sizes["pattern"] == K
    assert ds["cube"].dims == ("time", "y", "x", "wavelength")
    assert ds["frames"].dims == ("time", "pattern", "y", "x") and ds["frames"].dtype == np.uint16
    assert ds["XYZ"].attrs["channels"] == ["X", "Y", "Z"] and ds["dE"].dims == ("time", "y", "x")
    np.testing.assert_array_equal(ds["wavelength"].values, np.linspace(400.0, 700.0, B))
    assert ds["wavelength"].attrs["units"] == "nm" and ds["time"].attrs["units"] == "s"
    np.testing.assert_array_equal(ds["time"].values, [r.timestamps_s[0] for r in results])
    np.testing.assert_array_equal(ds["frame_id"].values, np.arange(5 * K).reshape(5, K))
    assert ds.attrs["plan_hash"] == "ab" * 32 and ds.attrs["sequences_committed"] == 5
    assert ds.attrs["patterns_hash"] == patterns_hash(fake_plan()) and ds.attrs["status"] == "complete"
    # label-based selection by wavelength works with no specgpu code
    np.testing.assert_array_equal(ds["cube"].sel(wavelength=550.0).isel(time=3).values,
                                  results[3].arrays["cube"][..., 2])
    for i, r in enumerate(results):
        np.testing.assert_array_equal(ds["frames"][i].values, r.frames)
        np.testing.assert_array_equal(ds["XYZ"][i].values, r.arrays["XYZ"])


def test_dask_reads_one_chunk_per_sequence(tmp_path):
    import dask.array as da

    _, results = record(tmp_path / "rec.zarr", 4)
    cube = da.from_zarr(str(tmp_path / "rec.zarr"), component="cube")
    assert cube.shape == (4, H, W, B) and cube.chunks[0] == (1, 1, 1, 1)
    np.testing.assert_allclose(cube.mean(axis=(1, 2)).compute(),
                               [r.arrays["cube"].mean(axis=(0, 1)) for r in results], rtol=1e-6)


@pytest.mark.parametrize("output", ["reflectance", "XYZ"])
def test_coefficients_keep_their_basis_and_its_wavelengths(tmp_path, output):
    import xarray as xr

    rng = np.random.default_rng(2)
    basis = np.linalg.qr(rng.normal(size=(B, 3)))[0]
    plan = types.SimpleNamespace(**{**vars(fake_plan()), "output": output})
    rec = ZarrRecorder(tmp_path / "rec.zarr", plan, basis=basis)
    coefficients = rng.random((H, W, 3), dtype=np.float32)
    ids = np.arange(K)
    rec.write(StreamResult(0, 0, ids, ids * 0.005, {"coefficients": coefficients}, 0.01))
    rec.close()
    ds = xr.open_zarr(tmp_path / "rec.zarr")
    cube = xr.dot(ds["coefficients"], ds["basis"], dim="component").isel(time=0)
    np.testing.assert_allclose(cube.values, coefficients @ basis.T, rtol=1e-5, atol=1e-6)
    if output == "reflectance":  # the cube is labelled by wavelength with no plan at hand
        np.testing.assert_array_equal(ds["basis_wavelength"].values, np.linspace(400.0, 700.0, B))
        assert ds["basis_wavelength"].attrs["units"] == "nm"
        np.testing.assert_allclose(cube.sel(basis_wavelength=550.0).values, (coefficients @ basis.T)[..., 2],
                                   rtol=1e-5, atol=1e-6)
    else:  # a basis of other outputs than reflectance has no wavelengths
        assert "basis_wavelength" not in ds.variables


def test_an_unclosed_recording_keeps_every_committed_sequence(tmp_path):
    """A recording never closed (the process killed): arrays hold a block past the commit; the committed
    sequences read back exactly and the commit count says where they end."""
    rec, results = record(tmp_path / "rec.zarr", 4, close=False)
    opened = open_recording(tmp_path / "rec.zarr")
    assert opened.sequences == 4 and opened.attrs["status"] == "recording"
    assert opened.array("dE").shape[0] == 6  # grown by blocks of 3
    for i, r in enumerate(results):
        np.testing.assert_array_equal(opened.read("dE", i), r.arrays["dE"])
    assert np.isnan(opened.read("dE", 5)).all()  # beyond the commit: fill values only


def test_a_failed_write_is_not_committed_and_the_recording_stays_readable(tmp_path, monkeypatch):
    import os

    from specgpu.io import recording

    rec, results = record(tmp_path / "rec.zarr", 2, close=False)
    real = recording.write_chunk

    def full(path, parts, **kwargs):
        if f"{os.sep}XYZ{os.sep}" in path:
            raise OSError(28, "No space left on device")
        return real(path, parts, **kwargs)

    monkeypatch.setattr(recording, "write_chunk", full)
    with pytest.raises(OSError, match="No space"):
        rec.write(result(2, np.random.default_rng(9)))
    with pytest.raises(OSError, match="stopped on an earlier error"):
        rec.write(result(3, np.random.default_rng(9)))
    monkeypatch.setattr(recording, "write_chunk", real)
    rec.close()
    opened = open_recording(tmp_path / "rec.zarr")
    assert opened.sequences == 2 and opened.attrs["status"] == "failed"
    assert opened.array("cube").shape[0] == 2  # cut to the commit on close
    np.testing.assert_array_equal(opened.read("cube", 1), results[1].arrays["cube"])


def test_a_corrupt_chunk_is_a_one_line_error(tmp_path):
    record(tmp_path / "rec.zarr", 3)
    chunk = tmp_path / "rec.zarr" / "frames" / "c" / "1" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[100] ^= 0xFF
    chunk.write_bytes(bytes(data))
    opened = open_recording(tmp_path / "rec.zarr")
    opened.read("frames", 0)
    with pytest.raises(ValueError, match=r"rec.zarr/frames: corrupt or unreadable chunk at sequence 1") as err:
        opened.read("frames", 1)
    assert "\n" not in str(err.value)
    assert str(err.value).endswith("(its CRC32C checksum does not match its bytes)")  # not zarr's raw bytes


def test_bad_recordings_are_one_line_errors(tmp_path):
    import zarr

    with pytest.raises(FileNotFoundError, match="recording not found"):
        open_recording(tmp_path / "none.zarr")
    (tmp_path / "plain").mkdir()
    with pytest.raises(ValueError, match="plain: not a"):
        open_recording(tmp_path / "plain")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "someone-else"
    with pytest.raises(ValueError, match="not a specgpu recording"):
        open_recording(tmp_path / "other.zarr")
    record(tmp_path / "rec.zarr", 2)
    zarr.open_group(str(tmp_path / "rec.zarr"), mode="r+").attrs["sequences_committed"] = 9
    with pytest.raises(ValueError, match="holds 2 sequences but 9 are committed"):
        open_recording(tmp_path / "rec.zarr")
    with pytest.raises(ValueError, match="has no 'Lab' array"):
        record(tmp_path / "r2.zarr", 1)
        open_recording(tmp_path / "r2.zarr").array("Lab")


def test_a_new_recording_never_mixes_with_an_existing_folder(tmp_path):
    record(tmp_path / "rec.zarr", 2)
    with pytest.raises(FileExistsError, match="rec.zarr: already exists; a recording is never appended"):
        ZarrRecorder(tmp_path / "rec.zarr", fake_plan())
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileExistsError):
        refuse_existing(tmp_path / "empty")
    assert open_recording(tmp_path / "rec.zarr").sequences == 2


def test_free_space_check_names_the_figures(tmp_path):
    shapes = {"cube": ((480, 640, 31), np.float32), "dE": ((480, 640), np.float32), "mask": ((480, 640), np.uint8)}
    per = sequence_bytes(shapes, frames_shape=(9, 480, 640))
    assert per == 480 * 640 * (31 * 4 + 4 + 9 * 2) + 4096
    assert check_free_space(tmp_path / "new" / "rec.zarr", per) > per
    with pytest.raises(OSError, match=r"rec.zarr: the recording needs about [0-9.]+ GB but only [0-9.]+ GB are free"):
        check_free_space(tmp_path / "rec.zarr", 10**18)


_json = st.recursive(st.none() | st.booleans() | st.integers(-3, 10**12) | st.floats(allow_nan=False)
                     | st.text(max_size=8),
                     lambda inner: st.lists(inner, max_size=3)
                     | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                     max_leaves=8)


@pytest.fixture(scope="module")
def fuzz_bases(tmp_path_factory):
    """A real recording of 2 sequences and an empty group, made once: each example edits a copy of one."""
    import zarr

    root = tmp_path_factory.mktemp("fz-bases")
    record(root / "recorded.zarr", 2)
    zarr.open_group(str(root / "empty.zarr"), mode="w")
    return root


@settings(max_examples=120)
@given(st.dictionaries(st.sampled_from(["format", "version", "sequences_committed", "outputs", "frames", "K"]), _json,
                       max_size=6), st.booleans())
def test_fuzzed_recording_attributes_give_a_recording_or_one_line(tmp_path_factory, fuzz_bases, attrs, based):
    """Random attribute values over a real recording (or an empty group): open_recording returns a recording
    whose committed sequences all read, or refuses in one line naming the folder."""
    import json
    import shutil

    folder = tmp_path_factory.mktemp("fz") / "rec.zarr"
    shutil.copytree(fuzz_bases / ("recorded.zarr" if based else "empty.zarr"), folder)
    doc = json.loads((folder / "zarr.json").read_text())
    doc.pop("consolidated_metadata", None)
    doc.setdefault("attributes", {}).update(attrs)
    (folder / "zarr.json").write_text(json.dumps(doc))
    try:
        rec = open_recording(folder)
    except (ValueError, FileNotFoundError) as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(folder))
    else:
        for name in rec.attrs.get("outputs") or []:
            assert rec.read(name, slice(0, rec.sequences)).shape[0] == rec.sequences


def test_every_write_of_the_recordings_attributes_is_whole(tmp_path, monkeypatch):
    """A crash can stop the recorder between any two writes of the group's zarr.json: every version it writes holds
    every attribute a reader needs (zarr's attrs.update wrote one key per write, and a kill -9 between two of them
    left a recording without sequences_committed)."""
    from zarr.storage import LocalStore

    versions = []
    set_ = LocalStore.set

    async def keep(self, key, value, *args, **kwargs):
        if key == "zarr.json" and str(tmp_path) in str(self.root):
            versions.append(json.loads(value.to_bytes()))
        return await set_(self, key, value, *args, **kwargs)

    monkeypatch.setattr(LocalStore, "set", keep)
    record(tmp_path / "rec.zarr", 4)
    assert len(versions) >= 3  # created, laid out at the first result, a commit per sequence, closed
    for attrs in (v["attributes"] for v in versions):
        assert {"format", "version", "K", "sequences_committed", "status", "outputs"} <= set(attrs), sorted(attrs)
    assert versions[-1]["attributes"]["status"] == "complete" and versions[-1]["attributes"]["sequences_committed"] == 4
