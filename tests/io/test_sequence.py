"""specgpu.io.sequence: frame sequence folders round trip, refusals in one line, sequence.json validation."""

from __future__ import annotations

import copy
import hashlib
import json
import math

import numpy as np
import OpenImageIO as oiio
import pytest
from file_helpers import (
    no_temp_files,
    raises_one_line,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.capture.assemble import Sequence
from specgpu.capture.driver import FrameInfo
from specgpu.io.sequence import validate_sequence_document


# ---- frame sequences -------------------------------------------------------------------------------------------------
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
    with raises_one_line(ValueError,
                         r"sequence\.json: frames\[0\]\.exposure_s must be a finite number > 0 \(s\), got 0\.0"):
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


@pytest.mark.parametrize("roi", ["0,0,41,32", "1,1,0,2", "a,b,c,d", "1,2,3", [0, 0, 2.5, 2], 7])
def test_a_recorded_white_roi_outside_the_frame_names_the_file_and_the_key(seq, roi):
    """The white ROI a capture records (what recover and the report use) is checked where the file is read."""
    doc = json.loads((seq / "sequence.json").read_text())
    doc["metadata"] = {"white_roi": roi}
    (seq / "sequence.json").write_text(json.dumps(doc))
    with raises_one_line(ValueError, r"seq/sequence\.json: metadata\.white_roi must be X,Y,W,H in whole pixels "
                                     r"inside the 40 x 32 frame, got "):
        io.read_sequence_header(seq)
    doc["metadata"] = {"white_roi": "1,1,39,31"}  # the largest inside, and the list form
    (seq / "sequence.json").write_text(json.dumps(doc))
    assert io.read_sequence_header(seq)[1]["metadata"]["white_roi"] == "1,1,39,31"
    doc["metadata"] = {"white_roi": [0, 0, 40, 32]}
    (seq / "sequence.json").write_text(json.dumps(doc))
    assert io.read_sequence_header(seq)[1]["metadata"]["white_roi"] == [0, 0, 40, 32]


def test_sequence_with_a_missing_frame(seq):
    (seq / "frame_000002.tif").unlink()
    with raises_one_line(ValueError,
                         r"frame_000002\.tif: frame 2 \(frame id 102\) listed in sequence\.json is missing"):
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
    out = validate_sequence_document(doc, "x/sequence.json")
    assert out == doc
    assert validate_sequence_document(json.loads(json.dumps(out)), "x/sequence.json") == doc


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
        validate_sequence_document(bad, "x/sequence.json")


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
        validate_sequence_document(bad, "x/sequence.json")
    with raises_one_line(ValueError, r"must hold a JSON object"):
        validate_sequence_document([doc], "x/sequence.json")
