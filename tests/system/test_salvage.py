"""Nothing a capture recorded is lost: a capture stopped by Ctrl-C, SIGTERM or an error keeps its complete
sequences, and one killed outright leaves a journal that ``specgpu salvage`` turns back into a sequence folder.

Each test writes only under its own ``tmp_path``; the module fixture (a calibration and a plan) is read only.
"""

from __future__ import annotations

import errno
import json
import shutil
import tempfile
from pathlib import Path

import pytest
from cli_helpers import one_line_error, run, tristimulus_rig
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.io import sequence as io_sequence
from specgpu.pipeline.capture_folder import INCOMPLETE_MARKER

SEQUENCES = 5


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tristimulus_rig(tmp_path_factory.mktemp("salvage"))
    return d


def capture_args(base, out):
    return ("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
            "--scene", "colorchecker", "--out", out, "--sequences", SEQUENCES, "--seed", "7")


def stop_after(monkeypatch, n, error):
    """capture_plan raises ``error`` once ``n`` sequences have been handed to the writer."""
    import specgpu.pipeline.twin_capture as pipeline

    real = pipeline.capture_plan

    def stopping(*args, on_sequence, **kwargs):
        count = [0]

        def seen(sequence):
            on_sequence(sequence)
            count[0] += 1
            if count[0] == n:
                raise error
        return real(*args, on_sequence=seen, **kwargs)

    monkeypatch.setattr(pipeline, "capture_plan", stopping)


def K_of(base):
    from specgpu.planning import load_plan

    return load_plan(base / "tri.npz").K


def frame_files(folder):
    return sorted(p.name for p in folder.glob("frame_*.tif"))


def test_interrupted_capture_keeps_its_complete_sequences(base, tmp_path, monkeypatch):
    out = tmp_path / "seq"
    stop_after(monkeypatch, 2, KeyboardInterrupt())
    result = run(*capture_args(base, out), ok=False)
    assert result.exit_code == 130, result.output
    assert f"kept 2 of {SEQUENCES} sequences in {out}" in result.output
    frames, _, meta = io.read_sequence(out)
    K = K_of(base)
    assert frames.shape[0] == 2 * K
    assert meta["metadata"]["interrupted"] == "interrupted"
    assert meta["metadata"]["sequences"] == 2 and meta["metadata"]["sequences_requested"] == SEQUENCES
    assert not (out / INCOMPLETE_MARKER).exists() and not (out / io.JOURNAL_FILE).exists()
    run("recover", out, "--out", tmp_path / "r.exr", "--sequence", "1")


def test_disk_full_mid_sequence_keeps_the_complete_ones_and_drops_the_partial(base, tmp_path, monkeypatch):
    out = tmp_path / "seq"
    K = K_of(base)
    real = io_sequence._write_tiff
    calls = [0]

    def filling(path, frame, *rest):
        calls[0] += 1
        if calls[0] == 2 * K + 2:  # the third sequence's second frame: the disk is full
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, frame, *rest)

    monkeypatch.setattr(io_sequence, "_write_tiff", filling)
    result = run(*capture_args(base, out), ok=False)
    one_line_error(result, "No space left")
    assert f"kept 2 of {SEQUENCES} sequences" in result.output
    assert len(frame_files(out)) == 2 * K  # the third sequence's first frame is gone with it
    frames, _, meta = io.read_sequence(out)
    assert frames.shape[0] == 2 * K and "No space left" in meta["metadata"]["interrupted"]


def test_a_capture_with_no_complete_sequence_leaves_nothing(base, tmp_path, monkeypatch):
    out = tmp_path / "seq"
    import specgpu.pipeline.twin_capture as pipeline

    def failing(*args, **kwargs):
        raise RuntimeError("camera lost")

    monkeypatch.setattr(pipeline, "capture_plan", failing)
    one_line_error(run(*capture_args(base, out), ok=False), "camera lost")
    assert not out.exists() or frame_files(out) == []


def killed_capture(base, folder: Path, monkeypatch, sequences: int = 3, extra_frames: int = 1) -> Path:
    """The state ``kill -9`` leaves: ``sequences`` journaled sequences, ``extra_frames`` frames of the next one,
    no sequence.json (the cleanup the kill prevented is switched off). The kill itself is drilled in
    test_crash_drills.py."""
    from specgpu.pipeline import acquire

    K = K_of(base)
    real = io_sequence._write_tiff
    calls = [0]

    def dying(path, frame, *rest):
        if calls[0] == sequences * K + extra_frames:
            raise KeyboardInterrupt  # the process stops here
        calls[0] += 1
        return real(path, frame, *rest)

    with monkeypatch.context() as m:
        m.setattr(io_sequence, "_write_tiff", dying)
        m.setattr(acquire, "keep_or_abort", lambda *a, **k: None)
        run(*capture_args(base, folder), ok=False)
    assert not (folder / io.SEQUENCE_FILE).exists() and (folder / io.JOURNAL_FILE).exists()
    return folder


@pytest.fixture(scope="module")
def killed(base, tmp_path_factory):
    mp = pytest.MonkeyPatch()
    try:
        return killed_capture(base, tmp_path_factory.mktemp("killed") / "seq", mp)
    finally:
        mp.undo()


def copy_of(folder: Path, tmp: Path) -> Path:
    shutil.copytree(folder, tmp / "seq")
    return tmp / "seq"


def test_killed_capture_is_refused_with_the_way_out_then_salvaged(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    one_line_error(run("recover", out, "--out", tmp_path / "r.exr", ok=False), "interrupted capture",
                   "specgpu salvage")
    result = run("salvage", out)
    K = K_of(base)
    assert f"salvaged 3 sequences ({3 * K} of {3 * K} journaled frames)" in result.output
    assert "1 frame file(s) outside the index left in place" in result.output  # the partial sequence's frame
    frames, _, meta = io.read_sequence(out)  # checksums verified on read
    assert frames.shape[0] == 3 * K
    assert meta["metadata"]["salvaged"]["sequences"] == 3 and meta["metadata"]["K"] == K
    assert not (out / INCOMPLETE_MARKER).exists() and not (out / io.JOURNAL_FILE).exists()
    assert len(frame_files(out)) == 3 * K + 1  # nothing deleted: the partial sequence's frame stays, unindexed
    run("recover", out, "--out", tmp_path / "r.exr", "--sequence", "2")
    one_line_error(run("salvage", out, ok=False), "already holds")


def test_a_damaged_frame_leaves_out_only_its_sequence(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    K = K_of(base)
    victim = out / frame_files(out)[K + 1]  # a frame of the second sequence
    victim.write_bytes(victim.read_bytes()[:-10])
    result = run("salvage", out)
    assert f"salvaged 2 sequences ({2 * K} of {3 * K} journaled frames)" in result.output
    assert f"specgpu: sequence 1 (frame_{K:06d}.tif to frame_{2 * K - 1:06d}.tif) left out: {victim.name}" \
        in result.output
    frames, records, meta = io.read_sequence(out)  # checksums verified on read
    assert frames.shape[0] == 2 * K
    assert [r["file"] for r in records] == [f"frame_{i:06d}.tif" for i in (*range(K), *range(2 * K, 3 * K))]
    left = meta["metadata"]["salvaged"]["left_out"]
    assert [x["sequence"] for x in left] == [1] and victim.name in left[0]["reason"]
    assert not (out / io.JOURNAL_FILE).exists()
    run("recover", out, "--out", tmp_path / "r.exr", "--sequence", "1")  # the third captured sequence


def journal_lines(folder):
    return (folder / io.JOURNAL_FILE).read_bytes().split(b"\n")


def set_journal(folder, lines):
    (folder / io.JOURNAL_FILE).write_bytes(b"\n".join(lines))


def test_a_flipped_byte_in_a_journal_line_leaves_out_only_its_sequence(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    K = K_of(base)
    lines = journal_lines(out)
    line = bytearray(lines[1 + K + 1])  # a record of the second sequence: its timestamp's first digit
    at = line.index(b'"timestamp_s": ') + len(b'"timestamp_s": ')
    line[at] = ord("7") if line[at] != ord("7") else ord("6")  # still valid JSON: only its checksum tells
    lines[1 + K + 1] = bytes(line)
    set_journal(out, lines)
    result = run("salvage", out)
    assert "salvaged 2 sequences" in result.output
    assert f"sequence 1 (frame_{K:06d}.tif to frame_{2 * K - 1:06d}.tif) left out" in result.output
    assert f"line {K + 3} (its checksum does not match its content)" in result.output
    assert io.read_sequence(out)[0].shape[0] == 2 * K


def test_an_edited_height_leaves_out_its_sequence_even_without_line_checksums(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    K = K_of(base)
    lines = journal_lines(out)
    records = [json.loads(x) for x in lines if x.strip()]
    for r in records:
        r.pop("check")  # a journal written before lines carried checksums
    records[1 + 2 * K]["height"] += 1  # the third sequence's first frame
    set_journal(out, [json.dumps(r).encode() for r in records] + [b""])
    result = run("salvage", out)
    assert "salvaged 2 sequences" in result.output
    assert "sequence 2" in result.output and "journal record says" in result.output
    assert io.read_sequence(out)[0].shape[0] == 2 * K


def test_a_refused_salvage_writes_nothing_and_can_be_run_again(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    journal = (out / io.JOURNAL_FILE).read_bytes()
    plan = (out / "plan.npz").read_bytes()
    run("plan", "tristimulus", "--rig", base / "rig.toml", "--calib", base / "calib.npz", "--out",
        tmp_path / "other.npz", "--estimator", "wiener")
    shutil.copy(tmp_path / "other.npz", out / "plan.npz")  # another plan copied over the capture's
    one_line_error(run("salvage", out, ok=False), "plan.npz", "captured with plan")
    assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).read_bytes() == journal
    (out / "plan.npz").write_bytes(plan)
    lines = journal_lines(out)
    header = json.loads(lines[0])
    header.pop("check")  # a journal from a writer before checksums: its records are checked against the frames
    lines[0] = json.dumps(header).encode()
    for i in range(1, len(lines) - 1):  # every record's height wrong: nothing intact
        r = json.loads(lines[i])
        r.pop("check")
        r["height"] = 7
        lines[i] = json.dumps(r).encode()
    set_journal(out, lines)
    one_line_error(run("salvage", out, ok=False), "no complete, intact sequence", "journal record says")
    assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).exists()
    (out / io.JOURNAL_FILE).write_bytes(journal)
    assert "salvaged 3 sequences" in run("salvage", out).output  # run again once fixed


def test_a_plan_of_another_length_is_named_not_taken_for_broken_sequences(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    run("plan", "narrowband", "--rig", base / "rig.toml", "--calib", base / "calib.npz", "--out", out / "plan.npz",
        "--step-nm", "60")
    one_line_error(run("salvage", out, ok=False), f"{out / 'plan.npz'}: is plan", "captured with plan")
    assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).exists()


def test_an_index_that_does_not_read_back_is_withdrawn(base, killed, tmp_path, monkeypatch):
    import specgpu.pipeline.salvage as pipeline

    out = copy_of(killed, tmp_path)
    journal = (out / io.JOURNAL_FILE).read_bytes()
    monkeypatch.setattr(pipeline, "read_capture", lambda d: (_ for _ in ()).throw(ValueError("unreadable")))
    one_line_error(run("salvage", out, ok=False), "unreadable")
    assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).read_bytes() == journal
    assert (out / INCOMPLETE_MARKER).exists()
    monkeypatch.undo()
    assert "salvaged 3 sequences" in run("salvage", out).output


def test_a_damaged_journal_header_is_refused_with_nothing_written(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    lines = journal_lines(out)
    lines[0] = lines[0].replace(b'"plan_hash": "', b'"plan_hash": "0', 1)
    set_journal(out, lines)
    one_line_error(run("salvage", out, ok=False), "corrupt at line 1", "header")
    assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).exists()


def test_salvage_refuses_a_folder_with_nothing_to_salvage(base, killed, tmp_path):
    out = copy_of(killed, tmp_path)
    (out / io.JOURNAL_FILE).unlink()
    one_line_error(run("salvage", out, ok=False), "no capture journal")
    (out / io.JOURNAL_FILE).write_text("not json\n{}\n")
    one_line_error(run("salvage", out, ok=False), "corrupt at line 1")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.floats(min_value=0.0, max_value=1.0))
def test_a_torn_journal_keeps_exactly_its_complete_sequences(base, killed, cut):
    K = K_of(base)
    with tempfile.TemporaryDirectory() as tmp:
        out = copy_of(killed, Path(tmp))
        raw = (out / io.JOURNAL_FILE).read_bytes()
        header_end = raw.index(b"\n") + 1
        torn = raw[:header_end + int(cut * (len(raw) - header_end))]
        (out / io.JOURNAL_FILE).write_bytes(torn)
        whole = 0  # entry lines that survived whole (a cut exactly after a record's closing brace leaves it whole)
        for line in torn[header_end:].split(b"\n"):
            try:
                json.loads(line)
                whole += 1
            except ValueError:
                pass
        result = run("salvage", out, ok=False)
        if whole // K == 0:
            one_line_error(result, "no complete, intact sequence")
            assert not (out / io.SEQUENCE_FILE).exists()
        else:
            assert result.exit_code == 0, result.output
            assert io.read_sequence(out)[0].shape[0] == (whole // K) * K


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(where=st.floats(min_value=0.0, max_value=1.0, exclude_max=True), bit=st.integers(min_value=0, max_value=7))
@example(where=0.767578125, bit=0)  # the key "check" of a frame's line becomes "checj": the line lost its checksum
def test_a_flipped_byte_keeps_exactly_the_sequences_whose_records_are_intact(base, killed, where, bit):
    K = K_of(base)
    with tempfile.TemporaryDirectory() as tmp:
        out = copy_of(killed, Path(tmp))
        raw = (out / io.JOURNAL_FILE).read_bytes()
        header_end = raw.index(b"\n") + 1
        at = header_end + int(where * (len(raw) - header_end))
        flipped = bytearray(raw)
        flipped[at] ^= 1 << bit
        (out / io.JOURNAL_FILE).write_bytes(bytes(flipped))
        seen = set()  # the records that still read as what was written
        for line in bytes(flipped[header_end:]).split(b"\n"):
            try:
                seen.add(json.dumps(json.loads(line), sort_keys=True))
            except ValueError:
                pass
        original = [json.dumps(json.loads(line), sort_keys=True) for line in raw[header_end:].split(b"\n") if line]
        intact = [s for s in range(len(original) // K) if all(r in seen for r in original[s * K:(s + 1) * K])]
        result = run("salvage", out, ok=False)
        if not intact:
            one_line_error(result, "no complete, intact sequence")
            assert not (out / io.SEQUENCE_FILE).exists() and (out / io.JOURNAL_FILE).exists()
        else:
            assert result.exit_code == 0, result.output
            _, records, meta = io.read_sequence(out)
            assert [r["file"] for r in records] == [f"frame_{i:06d}.tif" for s in intact
                                                   for i in range(s * K, (s + 1) * K)]
            left = [x["sequence"] for x in meta["metadata"]["salvaged"]["left_out"]]
            assert left == [s for s in range(len(original) // K) if s not in intact]


def test_salvage_renumbers_a_moving_captures_truth_with_its_sequences(tmp_path, monkeypatch):
    """A killed capture on a moving twin with a gap (a damaged sequence left out): after salvage, the truth file
    of each sequence is the one taken at that sequence's own reference time, and the others are kept aside. Three
    journaled sequences are enough for a gap with a sequence after it (rendering the moving twin is what costs)."""
    from cli_helpers import MOVING_RIG

    from specgpu.calibration.bundle import oracle_calibration, save_calibration
    from specgpu.io.npz import read_cube_npz
    from specgpu.rig.config import load_rig

    (tmp_path / "rig.toml").write_text(MOVING_RIG)
    save_calibration(tmp_path / "calib.npz", oracle_calibration(load_rig(tmp_path / "rig.toml")))
    run("plan", "tristimulus", "--calib", tmp_path / "calib.npz", "--out", tmp_path / "tri.npz")
    out = killed_capture(tmp_path, tmp_path / "seq", monkeypatch, sequences=3)
    K = K_of(tmp_path)
    truth = out / "motion_truth"
    assert sorted(p.name for p in truth.iterdir()) == [f"sequence_{s:04d}.npz" for s in range(4)]
    victim = out / frame_files(out)[K + 1]  # a frame of the second sequence: sequence 1 is left out
    victim.write_bytes(victim.read_bytes()[:-10])
    captured = {s: read_cube_npz(truth / f"sequence_{s:04d}.npz")[2]["reference_time_s"] for s in range(4)}
    run("salvage", out)
    _, records, meta = io.read_sequence(out)
    assert meta["metadata"]["salvaged"]["kept_sequences"] == [0, 2]
    exposure = records[0]["exposure_s"]
    assert sorted(p.name for p in truth.glob("sequence_*.npz")) == [f"sequence_{s:04d}.npz" for s in range(2)]
    for n in range(2):
        reference = float(read_cube_npz(truth / f"sequence_{n:04d}.npz")[2]["reference_time_s"])
        # the truth at the middle frame's mid-exposure of the sequence now numbered n
        assert reference == pytest.approx(records[n * K + K // 2]["timestamp_s"] + exposure / 2, abs=1e-9)
    now_1 = read_cube_npz(truth / "sequence_0001.npz")[2]["reference_time_s"]
    assert float(now_1) == pytest.approx(float(captured[2]))  # the third captured sequence is sequence 1 now
    kept_aside = sorted(p.name for p in (truth / "left_out").iterdir())
    assert kept_aside == ["sequence_0001.npz", "sequence_0003.npz"]  # the damaged and the unfinished sequence
    assert not any(p.name.startswith("motion_truth.") for p in out.iterdir())
