"""A sequence's frames written with or without deflate: the same frames read back, the TIFF's own compression tag
saying which, and an unknown compression refused before anything is written."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest

from specgpu import io


def noisy_frames(n=3, h=40, w=50, seed=2):
    """Frames like a camera's: a level with its noise (deflate keeps most of their size)."""
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(20000.0, 300.0, (n, h, w)), 0, 65535).astype(np.uint16)


def records(n):
    return [{"frame_id": 10 + i, "pattern_index": i, "exposure_s": 0.01, "timestamp_s": 0.02 * i} for i in range(n)]


def write(directory, frames, **kwargs):
    writer = io.SequenceWriter(directory, "plan-x", **kwargs)
    for frame, record in zip(frames, records(len(frames))):
        writer.add(frame, record)
    return writer.close()


@pytest.mark.parametrize("compression", ["zip", "none"])
def test_frames_read_back_the_same_with_either_compression(tmp_path, compression):
    frames = noisy_frames()
    out = write(tmp_path / "seq", frames, compression=compression)
    back, recs, _ = io.read_sequence(out)
    np.testing.assert_array_equal(back, frames)
    spec = oiio.ImageInput.open(str(out / recs[0]["file"])).spec()
    assert spec.get_string_attribute("compression") == compression
    size = (out / recs[0]["file"]).stat().st_size
    raw = frames[0].nbytes
    assert (size >= raw) if compression == "none" else (size < raw)


def test_the_default_is_deflate(tmp_path):
    out = write(tmp_path / "seq", noisy_frames(n=1))
    spec = oiio.ImageInput.open(str(out / "frame_000000.tif")).spec()
    assert spec.get_string_attribute("compression") == "zip"


def test_an_unknown_compression_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"compression must be one of zip, none, got 'lzw'"):
        io.SequenceWriter(tmp_path / "seq", "plan-x", compression="lzw")
    assert not (tmp_path / "seq").exists()
