"""The recorder's chunk writer: zarr's own bytes, direct I/O with a buffered fallback, compression chosen by
measurement, the commit order, the up-front disk-rate check, and a preview that never holds up the recording.

Hand-built results (no device); chunks of a few MiB so the direct-I/O path (1 MiB and more) is the one taken.
"""

from __future__ import annotations

import errno
import json
import os
import time
import types

import numpy as np
import pytest

from specgpu.io import chunks, recording
from specgpu.io.recording import ZarrRecorder, check_write_rate, open_recording, probe_write_rate
from specgpu.pipeline import PreviewSink, StreamResult

# 1 MiB and more per chunk (frames 1.1 MB, cube 6.7 MB), sizes that are not a multiple of the 4 KiB direct-I/O block
H, W, K, B = 241, 333, 7, 21


def fake_plan():
    return types.SimpleNamespace(hash="ab" * 32, method="symmetric", calibration="cd" * 32,
                                 patterns=np.arange(K * 3).reshape(K, 3), K=K, output="reflectance",
                                 output_wavelengths=np.linspace(400.0, 700.0, B),
                                 output_labels=tuple(str(x) for x in np.linspace(400.0, 700.0, B)))


def result(i, rng, *, offset=False):
    """A sequence's maps; ``offset``: views starting 8 bytes into their buffer (not aligned for direct I/O)."""
    ids = np.arange(i * K, (i + 1) * K)

    def unaligned(a):
        if not offset:
            return a
        raw = np.empty(a.nbytes + 8, np.uint8)
        view = raw[8:].view(a.dtype).reshape(a.shape)
        view[...] = a
        return view

    cube = unaligned(rng.random((H, W, B), dtype=np.float32))
    XYZ = unaligned(rng.random((H, W, 3), dtype=np.float32))
    frames = unaligned(500 + rng.integers(0, 16, (K, H, W), dtype=np.uint16))  # a dark 10-bit frame: compressible
    return StreamResult(i, i, ids, ids * 0.005 + 1.0, {"cube": cube, "XYZ": XYZ}, 0.01, frames=frames)


def test_chunks_are_the_bytes_zarr_writes_and_read_back_exactly(tmp_path):
    """Each chunk file is byte for byte what zarr itself writes for the same array (checksum included), through
    direct I/O from aligned and unaligned memory; xarray reads every value back."""
    import xarray as xr
    import zarr

    rng = np.random.default_rng(1)
    rec = ZarrRecorder(tmp_path / "rec.zarr", fake_plan(), frames=True, grow=2)
    results = [result(i, rng, offset=i % 2 == 1) for i in range(3)]
    for r in results:
        rec.write(r)
    rec.close()
    if hasattr(os, "O_DIRECT"):
        assert rec._direct.state in (True, False)  # decided by the first large chunk
    ref = zarr.open_group(str(tmp_path / "ref.zarr"), mode="w", zarr_format=3)
    for name in ("cube", "XYZ", "frames"):
        src = rec.group[name]
        arr = ref.create_array(name, shape=src.shape, chunks=src.chunks, dtype=src.dtype,
                               compressors=list(src.compressors), fill_value=src.fill_value)
        for i, r in enumerate(results):
            arr[i] = r.frames if name == "frames" else r.arrays[name]
            key = f"{name}/c/{i}/0/0/0"
            assert (tmp_path / "rec.zarr" / key).read_bytes() == (tmp_path / "ref.zarr" / key).read_bytes(), key
    ds = xr.open_zarr(tmp_path / "rec.zarr")
    for i, r in enumerate(results):
        np.testing.assert_array_equal(ds["cube"][i].values, r.arrays["cube"])
        np.testing.assert_array_equal(ds["frames"][i].values, r.frames)
    assert not list((tmp_path / "rec.zarr").rglob("*.partial"))


def test_a_file_system_without_direct_io_gets_buffered_writes(tmp_path, monkeypatch):
    if not hasattr(os, "O_DIRECT"):
        pytest.skip("no O_DIRECT on this platform")
    real_open = os.open
    refused = []

    def no_direct(path, flags, *args, **kwargs):
        if flags & os.O_DIRECT:
            refused.append(path)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", no_direct)
    rng = np.random.default_rng(2)
    rec = ZarrRecorder(tmp_path / "rec.zarr", fake_plan(), frames=True)
    results = [result(i, rng) for i in range(2)]
    for r in results:
        rec.write(r)
    rec.close()
    monkeypatch.undo()
    assert rec._direct.state is False and len(refused) == 1  # tried once, then buffered for good
    opened = open_recording(tmp_path / "rec.zarr")
    for i, r in enumerate(results):
        np.testing.assert_array_equal(opened.read("cube", i), r.arrays["cube"])


def test_compression_is_chosen_by_measurement(tmp_path):
    """On a slow disk the 10-bit frames are worth compressing (the time saved writing beats the encode time); on
    a disk far faster than any encoder nothing is compressed. The choice and its figures are recorded, and the
    compressed chunks read back exactly."""
    rng = np.random.default_rng(3)
    slow = ZarrRecorder(tmp_path / "slow.zarr", fake_plan(), frames=True, disk_rate=1e6)
    fast = ZarrRecorder(tmp_path / "fast.zarr", fake_plan(), frames=True, disk_rate=1e15)
    results = [result(i, rng) for i in range(2)]
    for rec in (slow, fast):
        for r in results:
            rec.write(r)
        rec.close()
    report = open_recording(tmp_path / "slow.zarr").attrs["compression"]
    assert report["frames"]["codec"] in recording.COMPRESSIONS and report["frames"]["blosc-lz4_ratio"] > 2
    assert {v["codec"] for v in open_recording(tmp_path / "fast.zarr").attrs["compression"].values()} == {"none"}
    framed = tmp_path / "slow.zarr" / "frames" / "c" / "1" / "0" / "0" / "0"
    assert framed.stat().st_size < results[1].frames.nbytes / 2
    for name in ("slow", "fast"):
        opened = open_recording(tmp_path / f"{name}.zarr")
        for i, r in enumerate(results):
            np.testing.assert_array_equal(opened.read("frames", i), r.frames)
            np.testing.assert_array_equal(opened.read("cube", i), r.arrays["cube"])
    with pytest.raises(ValueError, match="compression must be none or one of"):
        ZarrRecorder(tmp_path / "bad.zarr", fake_plan(), compression="gzip")


class Killed(BaseException):
    """The process dying mid-write (nothing after it runs: no error handling, no close)."""


def test_the_commit_follows_every_chunk_of_its_sequence(tmp_path, monkeypatch):
    """Whenever the commit count is raised, every chunk of every committed sequence is already in its file; a
    process cut mid-chunk (here: half a chunk written, then the writer dies) leaves the committed sequences
    whole and readable."""
    real = recording.write_chunk
    folder = tmp_path / "rec.zarr"
    seen = []

    def watching(path, parts, **kwargs):
        committed = json.loads((folder / "zarr.json").read_text())["attributes"]["sequences_committed"]
        index = int(path.split(f"{os.sep}c{os.sep}")[1].split(os.sep)[0])
        seen.append((index, committed))
        if index == 3 and f"{os.sep}cube{os.sep}" in path:  # a crash in the middle of sequence 3's cube
            data, _ = parts
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "wb") as f:
                f.write(data[: data.size // 2].tobytes())
            raise Killed
        return real(path, parts, **kwargs)

    monkeypatch.setattr(recording, "write_chunk", watching)
    rng = np.random.default_rng(4)
    rec = ZarrRecorder(folder, fake_plan(), frames=True, grow=8)
    results = [result(i, rng) for i in range(4)]
    for r in results[:3]:
        rec.write(r)
    with pytest.raises(Killed):
        rec.write(results[3])
    assert all(committed == index for index, committed in seen)  # chunks of sequence i while i are committed
    monkeypatch.undo()
    opened = open_recording(folder)  # never closed: as a killed process leaves it
    assert opened.sequences == 3 and opened.attrs["status"] == "recording"
    for i in range(3):
        np.testing.assert_array_equal(opened.read("cube", i), results[i].arrays["cube"])
    with pytest.raises(ValueError, match="corrupt or unreadable chunk at sequence 3"):
        opened.read("cube", 3)  # the torn chunk past the commit is never taken for data


# ---- the up-front check ------------------------------------------------------------------------------------------


def test_probe_measures_a_slow_writer_and_leaves_nothing(tmp_path, monkeypatch):
    fast = probe_write_rate(tmp_path / "rec.zarr", 8 << 20, repeats=1)
    real = chunks._write_all

    def slow(fd, view):  # a disk taking 8 MiB in 0.2 s: about 42 MB/s
        time.sleep(0.2)
        real(fd, view)

    monkeypatch.setattr(chunks, "_write_all", slow)
    rate = probe_write_rate(tmp_path / "rec.zarr", 16 << 20, repeats=1)
    assert rate < 45e6 < fast
    assert list(tmp_path.iterdir()) == []


def test_check_write_rate_refuses_with_the_figures():
    need = 520e6  # the default rig's four outputs and raw frames, about 10 sequences/s
    with pytest.raises(OSError) as err:
        check_write_rate("REC.zarr", need, 30, rate=200e6, buffer_bytes=2e9, what="the recording (52 MB x 10/s)")
    message = str(err.value)
    assert "\n" not in message and message.startswith("REC.zarr: the disk cannot keep up")
    assert "needs 520 MB/s" in message and "measured 200 MB/s" in message
    assert "9.60 GB would pile up" in message and "2.00 GB can wait" in message
    # what the system buffers covers a short recording; a disk faster than the need always passes
    assert check_write_rate("REC.zarr", need, 5, rate=200e6, buffer_bytes=2e9) == 200e6
    assert check_write_rate("REC.zarr", need, 3600, rate=600e6, buffer_bytes=0) == 600e6


# ---- the preview ---------------------------------------------------------------------------------------------------


def test_a_slow_preview_never_holds_up_the_sinks(tmp_path, monkeypatch):
    """Rendering the preview takes 0.3 s here: write() returns at once (the rendering is on the preview's
    thread), and close() leaves the preview of the last result handed over."""
    sink = PreviewSink(tmp_path / "preview.png", interval_s=0.0)
    real = PreviewSink._render

    def slow(self, XYZ):
        time.sleep(0.3)
        real(self, XYZ)

    monkeypatch.setattr(PreviewSink, "_render", slow)
    rng = np.random.default_rng(5)
    XYZs = [rng.random((12, 16, 3), dtype=np.float32) for _ in range(6)]
    t0 = time.perf_counter()
    for i, XYZ in enumerate(XYZs):
        sink.write(StreamResult(i, i, np.arange(K), np.zeros(K), {"XYZ": XYZ}, 0.0))
    assert time.perf_counter() - t0 < 0.25
    sink.close()
    last = PreviewSink(None, interval_s=0.0, background=False)
    monkeypatch.undo()
    last.write(StreamResult(0, 0, np.arange(K), np.zeros(K), {"XYZ": XYZs[-1]}, 0.0))
    np.testing.assert_array_equal(sink.image, last.image)
    assert 1 <= sink.updates < 6 and (tmp_path / "preview.png").is_file()
    with pytest.raises(ValueError, match="give a .png path"):
        PreviewSink(tmp_path / "preview.jpg")


@pytest.mark.parametrize("compressors", [["crc32c"], ["blosc-lz4", "crc32c"], ["zstd", "crc32c"]])
def test_write_sequence_chunk_writes_what_zarr_writes(tmp_path, compressors):
    """Batch outputs are written chunk by chunk like the recorder's: the same file bytes as zarr's own setitem
    (arrays with a codec the writer does not do, zstd here, go through zarr)."""
    import zarr
    from zarr.codecs import Crc32cCodec, ZstdCodec

    from specgpu.io.chunks import _blosc, write_sequence_chunk

    made = {"crc32c": lambda: Crc32cCodec(), "zstd": lambda: ZstdCodec(level=1),
            "blosc-lz4": lambda: _blosc("blosc-lz4", 4)[1]}
    rng = np.random.default_rng(6)
    values = [rng.random((300, 410, 3), dtype=np.float32) for _ in range(2)]  # 1.5 MB: the direct-I/O path
    groups = {}
    for name in ("ours", "zarr"):
        g = zarr.open_group(str(tmp_path / f"{name}.zarr"), mode="w", zarr_format=3)
        groups[name] = g.create_array("XYZ", shape=(2, 300, 410, 3), chunks=(1, 300, 410, 3), dtype="float32",
                                      compressors=[made[c]() for c in compressors], fill_value=np.nan)
    for i, v in enumerate(values):
        write_sequence_chunk(groups["ours"], i, v)
        groups["zarr"][i] = v
    for i, v in enumerate(values):
        key = f"XYZ/c/{i}/0/0/0"
        assert (tmp_path / "ours.zarr" / key).read_bytes() == (tmp_path / "zarr.zarr" / key).read_bytes()
        np.testing.assert_array_equal(zarr.open_array(str(tmp_path / "ours.zarr" / "XYZ"))[i], v)


def test_the_preview_is_colour_sciences_srgb_within_one_code():
    import colour

    rng = np.random.default_rng(7)
    XYZ = rng.random((40, 50, 3), dtype=np.float32) * 1.1
    XYZ[0, 0] = np.nan
    XYZ[1, 1] = [-0.2, 0.5, 0.3]
    sink = PreviewSink(interval_s=0.0, background=False)
    sink.write(StreamResult(0, 0, np.arange(K), np.zeros(K), {"XYZ": XYZ}, 0.0))
    want = colour.XYZ_to_sRGB(np.nan_to_num(np.clip(XYZ, 0, None)).astype(np.float64), apply_cctf_encoding=True)
    want = (np.clip(want, 0, 1) * 255 + 0.5).astype(np.uint8)
    assert np.abs(sink.image.astype(int) - want).max() <= 1 and sink.image.dtype == np.uint8
    assert tuple(sink.image[0, 0]) == (0, 0, 0)


def test_a_folder_name_with_braces_is_taken_as_it_is(tmp_path):
    """Chunk paths are joined per write: braces in the recording's folder name are neither a format field nor
    an escape (``{}`` failed, ``{{`` wrote the chunks into another folder)."""
    rng = np.random.default_rng(3)
    for name in ("run{}", "run{{0}}"):
        path = tmp_path / name / "rec.zarr"
        rec = ZarrRecorder(path, fake_plan(), frames=False, grow=2)
        rec.write(result(0, rng))
        rec.close()
        assert (path / "cube" / "c" / "0" / "0" / "0" / "0").is_file()
        assert open_recording(path).read("XYZ", 0).shape == (H, W, 3)
