"""The stream's sinks on hand-made results, without a stream: the callback, the results ring's copies and drops,
EXR snapshots every n-th result, the sRGB preview. Their work inside a running stream (backpressure, a recording)
is tested in test_stream.py."""

from __future__ import annotations

import numpy as np
import pytest

from specgpu import io
from specgpu.pipeline.sinks import CallbackSink, ExrSequenceWriter, PreviewSink, ResultsRing, StreamResult


def result(index: int, h: int = 4, w: int = 6) -> StreamResult:
    XYZ = np.full((h, w, 3), 0.2 + 0.01 * index, np.float32)
    dE = np.full((h, w), float(index), np.float32)
    return StreamResult(index, cycle=index, frame_ids=np.arange(3) + 3 * index, timestamps_s=np.zeros(3),
                        arrays={"XYZ": XYZ, "dE": dE}, latency_s=1e-3)


def test_callback_sink_calls_and_refuses_what_is_not_callable():
    seen = []
    CallbackSink(seen.append).write(result(0))
    assert [r.index for r in seen] == [0]
    with pytest.raises(TypeError, match="needs a callable, got int"):
        CallbackSink(3)


def test_results_ring_keeps_copies_of_the_newest_and_counts_the_dropped():
    ring = ResultsRing(capacity=2, outputs=("dE",))
    for i in range(5):
        r = result(i)
        ring.write(r)
        r.arrays["dE"][:] = -1  # the stream reuses its buffers once the sinks return
    assert len(ring) == 2 and ring.written == 5 and ring.dropped == 3
    got = ring.get(0)
    assert got.index == 3 and set(got.arrays) == {"dE"} and np.all(got.arrays["dE"] == 3)
    assert ring.get(0).index == 4 and ring.get(0) is None
    ring.close()
    assert ring.get() is None  # closed and empty: no wait
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        ResultsRing(capacity=0)
    with pytest.raises(ValueError, match="unknown results ring policy"):
        ResultsRing(policy="wait")


def test_results_ring_drop_newest_skips_without_copying_while_full():
    ring = ResultsRing(capacity=1, outputs=("dE",), policy="drop_newest")
    copies = []

    class Counting(np.ndarray):
        def copy(self, *args, **kwargs):
            copies.append(1)
            return np.ndarray.copy(self, *args, **kwargs)

    for i in range(4):
        r = result(i)
        r.arrays["dE"] = r.arrays["dE"].view(Counting)
        ring.write(r)
    assert ring.written == 1 and ring.dropped == 3 and len(copies) == 1  # the skipped ones were never copied
    assert ring.get(0).index == 0 and ring.get(0) is None
    ring.write(result(7))  # taken: the next one is kept again
    assert ring.get(0).index == 7


def test_exr_writer_writes_every_nth_result_readably(tmp_path):
    writer = ExrSequenceWriter(tmp_path / "exr", every=2, metadata={"run": "unit"})
    for i in range(4):
        writer.write(result(i))
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [
        f"{n}-{i:06d}.exr" for n in ("XYZ", "dE") for i in (0, 2)]
    data, _, meta = io.read_map(tmp_path / "exr" / "dE-000002.exr")
    assert meta["frame_ids"] == [6, 7, 8] and meta["run"] == "unit"
    np.testing.assert_array_equal(data[..., 0], 2.0)
    with pytest.raises(ValueError, match="every must be >= 1"):
        ExrSequenceWriter(tmp_path / "other", every=0)
    cube = StreamResult(0, 0, np.arange(3), np.zeros(3), {"cube": np.zeros((4, 6, 5), np.float32)}, 0.0)
    with pytest.raises(ValueError, match="needs its wavelengths"):
        writer.write(cube)


def test_exr_writer_names_every_output_s_channels(tmp_path):
    """A map of one channel (H, W) is written as one channel named after its output, the sigma map's channels
    after the plan's outputs, the coefficients c0...; each reads back equal."""
    h, w = 5, 320  # as wide as a stream's frames: a (H, W) map once came out as W channels
    rng = np.random.default_rng(0)
    arrays = {"sigma_rms": rng.random((h, w), np.float32), "dE_sigma": rng.random((h, w), np.float32),
              "sigma": rng.random((h, w, 4), np.float32), "coefficients": rng.random((h, w, 2), np.float32)}
    writer = ExrSequenceWriter(tmp_path, output_labels=("450", "550", "650"))
    writer.write(StreamResult(0, 0, np.arange(3), np.zeros(3), arrays, 0.0))
    want = {"sigma_rms": ("sigma_rms",), "dE_sigma": ("dE_sigma",),
            "sigma": ("sigma_450", "sigma_550", "sigma_650", "sigma_rms"), "coefficients": ("c0", "c1")}
    for name, channels in want.items():
        data, got, _ = io.read_map(tmp_path / f"{name}-000000.exr", channels)
        assert got == channels
        np.testing.assert_array_equal(data, arrays[name].reshape(h, w, -1))
    unlabelled = ExrSequenceWriter(tmp_path / "u")  # no labels: numbered
    assert unlabelled.channels("sigma", arrays["sigma"]) == ("sigma_0", "sigma_1", "sigma_2", "sigma_rms")
    assert writer.optional and writer.label == "EXR snapshots"


def test_a_map_of_many_channels_refused_in_one_short_line(tmp_path):
    names = [f"c{i}" for i in range(320)]
    with pytest.raises(ValueError) as info:
        io.write_map(tmp_path / "m.exr", np.zeros((4, 320), np.float32), names)
    message = str(info.value)
    assert "c0/c1/c2/.../c319 (320) map must have shape (H, W, 320), got (4, 320)" in message
    assert len(message) < 200 and "\n" not in message


def test_preview_renders_srgb_and_refuses_what_it_cannot_show(tmp_path):
    preview = PreviewSink(tmp_path / "p.png", interval_s=0.0, background=False)
    preview.write(result(0))
    assert preview.image.shape == (4, 6, 3) and preview.image.dtype == np.uint8 and preview.updates == 1
    assert (tmp_path / "p.png").is_file()
    with pytest.raises(ValueError, match="needs the XYZ output"):
        preview.write(StreamResult(1, 1, np.arange(3), np.zeros(3), {"dE": np.zeros((4, 6), np.float32)}, 0.0))
    with pytest.raises(ValueError, match="the preview is a PNG"):
        PreviewSink(tmp_path / "p.jpg")


@pytest.mark.parametrize("illuminant", ["D65", "A", "FL2"])
def test_the_preview_of_a_perfect_white_is_255_with_the_streams_white(illuminant):
    """Given the stream decoder's white (of the plan's grid), a perfect white previews as (255, 255, 255)."""
    from types import SimpleNamespace

    from specgpu.core.spectra import XYZ_weights

    white = XYZ_weights(np.arange(400.0, 701.0, 10.0), illuminant).sum(axis=1)
    sink = PreviewSink(None, interval_s=0.0, illuminant=illuminant, background=False, white=white)
    sink.write(SimpleNamespace(arrays={"XYZ": np.broadcast_to(white, (2, 3, 3)).astype(np.float32)}))
    np.testing.assert_array_equal(sink.image[..., :3], np.full((2, 3, 3), 255))
