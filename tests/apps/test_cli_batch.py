"""specgpu batch: Dask re-processing of recorded raw frames, equal to `specgpu recover`, resumable, one-line refusals.

A small twin recording (320 x 240, K = 9) is streamed once with its raw frames; every batch result is compared with
`specgpu recover SEQ --sequence i` on a sequence folder holding the same frames.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_line_error, run
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from stream_helpers import shared_stream_setup

from specgpu import io
from specgpu.apps.cli import main
from specgpu.calibration.bundle import save_calibration
from specgpu.io.recording import ZarrRecorder, open_recording
from specgpu.pipeline import Stream
from specgpu.pipeline.batch import run_batch
from specgpu.planning import save_plan

N = 6  # sequences in the recording
#: the extension of the cubes `specgpu recover` writes to be compared here: ENVI, raw float32 (every format holds
#: the cube exactly, as test_recover_writes_an_envi_cube_equal_to_npz checks); compressing an npz cube was a fifth
#: of this file's time
CUBE_EXT = "hdr"

# every batch here without a scheduler of its own runs on the session's one-worker cluster (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("dask_scheduler")


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A recording with raw frames (N sequences), its plan and calibration files, and a sequence folder of the
    first 3 sequences' frames."""
    root = tmp_path_factory.mktemp("batch")
    setup = shared_stream_setup(320, 240, sequences=3, output_step_nm=10.0)
    rec = ZarrRecorder(root / "rec.zarr", setup.plan, frames=True)
    report = Stream(setup.driver(loops=2), setup.plan, setup.bundle, outputs=("XYZ",), policy="block",
                    sinks=[rec]).run()
    assert report.sequences_out == N and rec.committed == N
    save_plan(root / "plan.npz", setup.plan)
    save_calibration(root / "calib.npz", setup.bundle)
    shutil.copyfile(root / "calib.npz", root / "rec.zarr" / "calibration.npz")
    recording = open_recording(root / "rec.zarr")
    frames = recording.read("frames", slice(0, 3))
    ids = recording.read("frame_id", slice(0, 3))
    K = setup.plan.K
    records = [{"frame_id": int(ids[s, k]), "pattern_index": k, "exposure_s": setup.plan.exposure_s,
                "timestamp_s": float(ids[s, k]) * 0.005} for s in range(3) for k in range(K)]
    io.write_sequence(root / "seq", frames.reshape(-1, *frames.shape[2:]), records, setup.plan.hash)
    shutil.copyfile(root / "plan.npz", root / "seq" / "plan.npz")
    shutil.copyfile(root / "calib.npz", root / "seq" / "calibration.npz")
    return setup, root


def recovered(root, tmp_path, sequence: int, frames=None, ext: str = CUBE_EXT) -> np.ndarray:
    """`specgpu recover` of one sequence: of the sequence folder, or of ``frames`` written into a new one, into a
    cube file of extension ``ext``."""
    seq = root / "seq"
    if frames is not None:
        seq = tmp_path / f"one-{sequence}"
        K = frames.shape[0]
        io.write_sequence(seq, frames, [{"frame_id": k, "pattern_index": k, "exposure_s": 0.004,
                                         "timestamp_s": k * 0.005} for k in range(K)],
                          __import__("specgpu.planning.plans",
                                     fromlist=["load_plan"]).load_plan(root / "plan.npz").hash)
        shutil.copyfile(root / "plan.npz", seq / "plan.npz")
        shutil.copyfile(root / "calib.npz", seq / "calibration.npz")
    out = tmp_path / f"r{sequence}.{ext}"
    args = ["recover", str(seq), "--out", str(out)] + (["--sequence", str(sequence)] if frames is None else [])
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return io.read_cube(out)[0]


def test_cli_batch_of_a_recording_equals_recover_and_resumes(made, tmp_path):
    import xarray as xr

    setup, root = made
    out = tmp_path / "out.zarr"
    args = ["batch", str(root / "rec.zarr"), "--plan", str(root / "plan.npz"), "--out", str(out)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert f"{N} sequences computed on 1 worker(s)" in result.output and "OpenCL contexts built 1" in result.output
    ds = xr.open_zarr(out)
    assert ds["cube"].dims == ("time", "y", "x", "wavelength") and ds.sizes["time"] == N
    np.testing.assert_array_equal(ds["wavelength"].values, setup.plan.output_wavelengths)
    assert ds["done"].values.tolist() == [1] * N and ds.attrs["status"] == "complete"
    frames = open_recording(root / "rec.zarr").read("frames", slice(None))
    for i in (0, 4):
        want = recovered(root, tmp_path, i, frames[i])
        np.testing.assert_array_equal(ds["cube"].values[i], want)  # the same kernels on the same frames
    # run again: nothing left to do, nothing rewritten
    before = {p: p.stat().st_mtime_ns for p in (out / "cube" / "c").rglob("*") if p.is_file()}
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0 and "0 sequences computed" in again.output and f"{N} already done" in again.output
    assert {p: p.stat().st_mtime_ns for p in (out / "cube" / "c").rglob("*") if p.is_file()} == before


def test_batch_of_a_sequence_folder_equals_recover_per_sequence(made, tmp_path):
    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning import load_plan

    setup, root = made
    report = run_batch(root / "seq", load_plan(root / "plan.npz"), load_calibration(root / "calib.npz"),
                       tmp_path / "out.zarr", outputs=("cube", "XYZ", "Lab", "dE"), reference=[50.0, 0.0, 0.0],
                       workers=1, progress=False)
    assert report.computed == 3 and report.skipped == 0
    out = open_recording_like(tmp_path / "out.zarr")
    for i in range(3):
        np.testing.assert_array_equal(out["cube"][i], recovered(root, tmp_path, i))
    from specgpu.engine.colorimetry import delta_E
    from specgpu.pipeline.recovery import to_Lab, to_XYZ

    XYZ = to_XYZ(out["cube"][1], setup.plan)
    np.testing.assert_allclose(out["XYZ"][1], XYZ, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(out["dE"][1], delta_E(np.array([50.0, 0, 0], np.float32), to_Lab(XYZ, setup.plan)),
                               atol=1e-4)


def open_recording_like(path):
    import zarr

    return zarr.open_group(str(path), mode="r")


def test_an_interrupted_batch_resumes_without_recomputing_finished_chunks(made, tmp_path):
    import dask

    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning import load_plan

    _, root = made
    plan, bundle = load_plan(root / "plan.npz"), load_calibration(root / "calib.npz")
    out = tmp_path / "out.zarr"
    seen = []

    def stop_after_two(record):
        seen.append(record["index"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    # a cluster of the batch's own, closed by the interrupt: on a long-lived scheduler the task running when it
    # came would go on writing while this test looks
    with pytest.raises(KeyboardInterrupt), dask.config.set({"scheduler-address": None}):
        run_batch(root / "rec.zarr", plan, bundle, out, workers=1, progress=False, on_done=stop_after_two)
    done = open_recording_like(out)["done"][:]
    finished = np.flatnonzero(done)
    assert 2 <= len(finished) < N
    stamps = {i: (out / "cube" / "c" / str(i) / "0" / "0" / "0").stat().st_mtime_ns for i in finished}
    computed = []
    report = run_batch(root / "rec.zarr", plan, bundle, out, workers=1, progress=False,
                       on_done=lambda r: computed.append(r["index"]))
    assert report.skipped == len(finished) and report.computed == N - len(finished)
    assert sorted(computed) == sorted(set(range(N)) - set(finished.tolist()))
    assert {i: (out / "cube" / "c" / str(i) / "0" / "0" / "0").stat().st_mtime_ns for i in finished} == stamps
    assert open_recording_like(out)["done"][:].tolist() == [1] * N


@pytest.mark.slow  # a cluster of its own, two workers, one killed and replaced: the drill must take its time
def test_two_workers_each_build_one_context_and_a_killed_worker_loses_nothing(made, tmp_path):
    """Two worker processes: each builds its OpenCL state once. One worker is killed (SIGKILL) after the first
    result: the scheduler hands its unfinished chunks to the survivor (or the nanny's restarted process); every
    chunk is reported once, and the output is complete and equal to the undisturbed run."""
    from distributed import Client, LocalCluster

    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning import load_plan

    _, root = made
    plan, bundle = load_plan(root / "plan.npz"), load_calibration(root / "calib.npz")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        report = run_batch(root / "rec.zarr", plan, bundle, tmp_path / "two.zarr", client=client, progress=False)
        assert report.workers == 2 and report.computed == N
        assert report.contexts_built == len(report.pids) <= 2
        pids = sorted(client.run(os.getpid).values())
        killed = []

        def kill_one(record):  # kill -9 of a worker process once the first result is in
            if not killed:
                killed.append(pids[0])
                os.kill(pids[0], signal.SIGKILL)

        indices = []
        lost = run_batch(root / "rec.zarr", plan, bundle, tmp_path / "lost.zarr", client=client, progress=False,
                         on_done=lambda r: (indices.append(r["index"]), kill_one(r)))
    assert killed and lost.computed == N and sorted(indices) == list(range(N))
    a, b = open_recording_like(tmp_path / "two.zarr"), open_recording_like(tmp_path / "lost.zarr")
    assert b["done"][:].tolist() == [1] * N
    np.testing.assert_array_equal(a["cube"][:], b["cube"][:])


def test_bad_input_is_one_line(made, tmp_path):
    import zarr

    setup, root = made
    def run(source, *extra, out="o.zarr"):
        result = CliRunner().invoke(main, ["batch", str(source), "--plan", str(root / "plan.npz"), "--out",
                                           str(tmp_path / out), *extra])
        assert result.exit_code != 0
        return result.output.strip()

    # another plan: different patterns
    from dataclasses import replace

    from specgpu.planning import save_plan as save

    other = replace(setup.plan, patterns=setup.plan.patterns[::-1].copy())
    other.__dict__.pop("hash", None)
    save(tmp_path / "other.npz", other)
    out = CliRunner().invoke(main, ["batch", str(root / "rec.zarr"), "--plan", str(tmp_path / "other.npz"),
                                    "--out", str(tmp_path / "o.zarr")]).output.strip()
    assert re.search(r"rec.zarr: recorded with plan \w+ \(9 patterns\), whose illumination sequence is not", out)
    assert "\n" not in out
    # no raw frames
    rec = ZarrRecorder(tmp_path / "noframes.zarr", setup.plan)
    Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=("XYZ",), policy="block", sinks=[rec]).run()
    msg = run(tmp_path / "noframes.zarr", "--calib", str(root / "calib.npz"))
    assert "noframes.zarr: the recording has no raw frames" in msg and "\n" not in msg
    # a corrupt chunk
    shutil.copytree(root / "rec.zarr", tmp_path / "bad.zarr")
    chunk = tmp_path / "bad.zarr" / "frames" / "c" / "2" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[1000] ^= 0x40
    chunk.write_bytes(bytes(data))
    msg = run(tmp_path / "bad.zarr", out="bad-out.zarr")
    assert "bad.zarr/frames: corrupt or unreadable chunk at sequence 2" in msg and "\n" not in msg
    # an output from another batch
    msg = run(root / "rec.zarr", out="bad-out.zarr")
    assert f"bad-out.zarr: holds a batch made with SOURCE {tmp_path / 'bad.zarr'}, this run gives " \
           f"{root / 'rec.zarr'}; resume only the same batch" in msg
    zarr.open_group(str(tmp_path / "bad-out.zarr"), mode="r+").attrs["plan_hash"] = "0" * 64
    msg = run(tmp_path / "bad.zarr", out="bad-out.zarr")
    assert f"bad-out.zarr: holds a batch made with --plan {'0' * 12}, this run gives {setup.plan.hash[:12]}" in msg
    assert "\n" not in msg


def test_recover_writes_an_envi_cube_equal_to_npz(made, tmp_path):
    import spectral.io.envi as envi

    setup, root = made
    want = recovered(root, tmp_path, 1, ext="npz")
    result = CliRunner().invoke(main, ["recover", str(root / "seq"), "--sequence", "1", "--out",
                                       str(tmp_path / "r.hdr"), "--interleave", "bip"])
    assert result.exit_code == 0, result.output
    img = envi.open(str(tmp_path / "r.hdr"))
    assert img.metadata["interleave"] == "bip"
    np.testing.assert_array_equal(np.array(img.bands.centers), setup.plan.output_wavelengths)
    np.testing.assert_array_equal(np.asarray(img.load()), want)
    back, wl, meta = io.read_cube(tmp_path / "r.hdr")
    np.testing.assert_array_equal(back, want)
    assert meta["plan_hash"] == setup.plan.hash
    half = CliRunner().invoke(main, ["recover", str(root / "seq"), "--out", str(tmp_path / "h.hdr"), "--half"])
    assert half.exit_code == 1 and "ENVI has no half-float data type" in half.output


def test_capture_into_zarr_then_batch_equals_recover_of_a_capture_folder(made, tmp_path):
    """`capture --out SEQ.zarr` records the raw frames; the same capture (same seed) as a folder, recovered per
    sequence, equals the batch of the zarr recording."""
    setup, root = made
    cam = setup.description.camera
    (tmp_path / "rig.toml").write_text(f"[camera]\nroi_width = {cam.roi_width}\nroi_height = {cam.roi_height}\n"
                                       f"exposure_s = {cam.exposure_s!r}\nframe_rate_hz = {cam.frame_rate_hz!r}\n")
    common = ["capture", "--rig", str(tmp_path / "rig.toml"), "--plan", str(root / "plan.npz"), "--calib",
              str(root / "calib.npz"), "--scene", "colorchecker", "--sequences", "2", "--seed", "3"]
    result = CliRunner().invoke(main, [*common, "--out", str(tmp_path / "cap.zarr")])
    assert result.exit_code == 0, result.output
    assert "2 sequences of 9 frames" in result.output
    assert open_recording(tmp_path / "cap.zarr").sequences == 2
    assert CliRunner().invoke(main, [*common, "--out", str(tmp_path / "cap")]).exit_code == 0
    out = CliRunner().invoke(main, ["batch", str(tmp_path / "cap.zarr"), "--plan", str(root / "plan.npz"),
                                    "--out", str(tmp_path / "b.zarr")])
    assert out.exit_code == 0, out.output
    cube = open_recording_like(tmp_path / "b.zarr")["cube"]
    for i in range(2):
        got = CliRunner().invoke(main, ["recover", str(tmp_path / "cap"), "--sequence", str(i), "--out",
                                        str(tmp_path / f"c{i}.{CUBE_EXT}")])
        assert got.exit_code == 0, got.output
        np.testing.assert_array_equal(cube[i], io.read_cube(tmp_path / f"c{i}.{CUBE_EXT}")[0])
    again = CliRunner().invoke(main, [*common, "--out", str(tmp_path / "cap.zarr")])
    assert again.exit_code == 1 and "already exists" in again.output


def test_cli_batch_on_a_given_scheduler(made, tmp_path, dask_cluster):
    """--scheduler ADDRESS: the batch runs on that cluster's workers (here the session's LocalCluster, with Dask's
    own scheduler setting cleared: only the option names it)."""
    import dask

    _, root = made
    cluster = dask_cluster
    with dask.config.set({"scheduler-address": None}):
        result = CliRunner().invoke(main, ["batch", str(root / "seq"), "--plan", str(root / "plan.npz"), "--out",
                                           str(tmp_path / "s.zarr"), "--scheduler", cluster.scheduler_address])
    assert result.exit_code == 0, result.output
    assert "3 sequences computed on 1 worker(s)" in result.output
    assert len(cluster.scheduler.workers) == 1  # the cluster outlives the batch: only the client was closed
    np.testing.assert_array_equal(open_recording_like(tmp_path / "s.zarr")["cube"][2], recovered(root, tmp_path, 2))


def test_a_batch_without_a_scheduler_runs_on_the_one_dask_is_set_to(made, tmp_path, dask_cluster):
    """Dask's scheduler-address setting (DASK_SCHEDULER_ADDRESS) is the batch's default scheduler: the sequences
    are computed by that cluster's worker, no cluster of the batch's own is started."""
    from distributed import Client

    _, root = made
    plan, bundle = plan_and_calibration(root)
    report = run_batch(root / "seq", plan, bundle, tmp_path / "o.zarr", progress=False)
    with Client(dask_cluster) as client:
        worker_pids = set(client.run(os.getpid).values())
    assert report.computed == 3 and set(report.pids) == worker_pids


# ---- the batch's identity, its source's content, damaged and half-made outputs ------------------------------------


def record(setup, path, loops=2):
    """A new recording with raw frames of the module's plan at ``path`` (3 sequences per loop)."""
    rec = ZarrRecorder(path, setup.plan, frames=True)
    Stream(setup.driver(loops=loops), setup.plan, setup.bundle, outputs=("XYZ",), policy="block", sinks=[rec]).run()
    return path


def plan_and_calibration(root):
    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning import load_plan

    return load_plan(root / "plan.npz"), load_calibration(root / "calib.npz")


def test_a_resumed_batch_refuses_every_changed_result_option(made, tmp_path):
    """An output left by a killed batch (nothing or part done) is resumed only by the same batch: a changed dE
    reference, method, illuminant or output list would mix two batches' results in one output."""
    from specgpu.pipeline.batch import prepare_batch

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"
    prepare_batch(root / "rec.zarr", plan, bundle, out, outputs=("cube", "dE"),
                  reference=np.array([50, 0, 0], np.float32))  # what a batch killed before its first chunk leaves
    args = ["batch", root / "rec.zarr", "--plan", root / "plan.npz", "--out", out, "--outputs", "cube,dE"]
    one_line_error(run(*args, "--delta-e-ref", "90,40,-40", ok=False),
                   "b.zarr: holds a batch made with --delta-e-ref 50,0,0, this run gives 90,40,-40; resume only "
                   "the same batch")
    one_line_error(run(*args, "--delta-e-ref", "50,0,0", "--method", "CIE 1976", ok=False),
                   "made with --method CIE 2000, this run gives CIE 1976")
    one_line_error(run(*args, "--delta-e-ref", "50,0,0", "--illuminant", "A", ok=False),
                   "made with --illuminant D65, this run gives A")
    one_line_error(run(*args[:-2], ok=False), "made with --outputs cube,dE, this run gives cube;")
    # the same batch resumes
    _, todo = prepare_batch(root / "rec.zarr", plan, bundle, out, outputs=("cube", "dE"),
                            reference=np.array([50, 0, 0], np.float32))
    assert todo.tolist() == list(range(N))


def test_a_source_replaced_at_the_same_path_is_not_resumed(made, tmp_path):
    """The source is identified by its content: another recording put at its path, a frames chunk replaced, or
    another capture in a sequence folder's place is another source, and its output is not resumed with it."""
    from specgpu.pipeline.batch import prepare_batch

    setup, root = made
    plan, bundle = plan_and_calibration(root)
    src = tmp_path / "src.zarr"
    shutil.copytree(root / "rec.zarr", src)
    prepare_batch(src, plan, bundle, tmp_path / "a.zarr")
    prepare_batch(src, plan, bundle, tmp_path / "a.zarr")  # the same source: resumed
    shutil.rmtree(src)
    record(setup, src)  # same plan, same sequence count, another recording
    assert open_recording(src).sequences == N
    with pytest.raises(ValueError, match=r"a\.zarr: holds a batch made with SOURCE's content \(recording id and "
                                         r"frame checksums\) \w{12}, this run gives \w{12}; resume only"):
        prepare_batch(src, plan, bundle, tmp_path / "a.zarr")
    # one frames chunk replaced by another sequence's (the recording id unchanged)
    prepare_batch(src, plan, bundle, tmp_path / "b.zarr")
    chunk = src / "frames" / "c" / "0" / "0" / "0" / "0"
    chunk.write_bytes((src / "frames" / "c" / "1" / "0" / "0" / "0").read_bytes())
    with pytest.raises(ValueError, match=r"b\.zarr: holds a batch made with SOURCE's content"):
        prepare_batch(src, plan, bundle, tmp_path / "b.zarr")
    # a sequence folder replaced by a capture of other frames
    seq = tmp_path / "seq"
    shutil.copytree(root / "seq", seq)
    prepare_batch(seq, plan, bundle, tmp_path / "c.zarr")
    frames, records, meta = io.read_sequence(seq)
    shutil.rmtree(seq)
    io.write_sequence(seq, frames[::-1].copy(), records, meta["plan_hash"])
    for name in ("plan.npz", "calibration.npz"):
        shutil.copyfile(root / "seq" / name, seq / name)
    with pytest.raises(ValueError, match=r"c\.zarr: holds a batch made with SOURCE's content"):
        prepare_batch(seq, plan, bundle, tmp_path / "c.zarr")


def test_a_missing_chunk_of_a_committed_sequence_is_an_error(made, tmp_path):
    """zarr reads a chunk that is not on disk as fill values: a committed sequence without its chunk is damage,
    an error in open_recording().read and in batch (before the output is made), never zeros decoded."""
    from specgpu.io.recording import missing_sequences

    _, root = made
    src = tmp_path / "cap.zarr"
    shutil.copytree(root / "rec.zarr", src)
    (src / "frames" / "c" / "3" / "0" / "0" / "0").unlink()
    rec = open_recording(src)
    assert rec.read("frames", 2).shape[0] == rec.K  # its neighbours read
    for index in (3, slice(0, N), slice(None)):
        with pytest.raises(ValueError, match=r"cap\.zarr/frames: sequence 3 is committed but its chunk c/3/0/0/0 "
                                             r"is missing; the recording is damaged"):
            rec.read("frames", index)
    assert missing_sequences(src, "frames") == [3] and missing_sequences(src, "XYZ") == []
    (src / "XYZ" / "c" / "5" / "0" / "0" / "0").unlink()
    assert missing_sequences(src, "XYZ") == [5]
    result = run("batch", src, "--plan", root / "plan.npz", "--out", tmp_path / "b5.zarr", ok=False)
    one_line_error(result, "cap.zarr/frames: sequence 3 is committed but its chunk c/3/0/0/0 is missing")
    assert not (tmp_path / "b5.zarr").exists()


def test_a_sequence_folder_source_holds_one_sequence_at_a_time(made, tmp_path):
    """A sequence folder is read a sequence at a time: opening it keeps no frame, reading one sequence
    allocates about one sequence, whatever the capture's length (each frame still checked against its
    checksum)."""
    import tracemalloc

    from specgpu.pipeline.batch_source import open_source

    setup, root = made
    frames, _, _ = io.read_sequence(root / "seq")
    one = frames.nbytes // 3  # one sequence of K frames
    tracemalloc.start()
    try:
        base = tracemalloc.take_snapshot()
        source = open_source(root / "seq")
        kept = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(base, "filename"))
        assert kept < one / 2, f"opening the folder kept {kept} bytes (one sequence is {one})"
        peak = 0
        for i in range(source.sequences):
            tracemalloc.reset_peak()
            start = tracemalloc.get_traced_memory()[0]
            got = source.frames(i)
            peak = max(peak, tracemalloc.get_traced_memory()[1] - start)
            np.testing.assert_array_equal(got, frames[i * source.K:(i + 1) * source.K])
            del got
    finally:
        tracemalloc.stop()
    assert source.sequences == 3 and peak < 1.6 * one, f"reading peaked at {peak} bytes, one sequence is {one}"
    shutil.copytree(root / "seq", tmp_path / "seq")
    damaged = tmp_path / "seq" / sorted(p.name for p in (root / "seq").glob("frame_*.tif"))[source.K + 3]
    data = bytearray(damaged.read_bytes())
    data[-10] ^= 0x01
    damaged.write_bytes(bytes(data))
    copy = open_source(tmp_path / "seq")
    copy.frames(0)
    with pytest.raises(ValueError, match="corrupt frame: SHA-256 differs"):
        copy.frames(1)


def test_a_failing_sequence_stops_the_batch_in_one_line_without_a_worker_traceback(made, tmp_path, capfd):
    """A sequence that fails on a worker (here a corrupt chunk) is one line, with no Dask "Compute Failed" block
    or traceback printed by the worker processes; the output stays resumable. The batch starts its own cluster
    (no Dask scheduler set), so that its workers print, if at all, where this test reads."""
    import dask

    _, root = made
    shutil.copytree(root / "rec.zarr", tmp_path / "bad.zarr")
    chunk = tmp_path / "bad.zarr" / "frames" / "c" / "4" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[2000] ^= 0x10
    chunk.write_bytes(bytes(data))
    capfd.readouterr()
    with dask.config.set({"scheduler-address": None}):
        result = run("batch", tmp_path / "bad.zarr", "--plan", root / "plan.npz", "--out", tmp_path / "b.zarr",
                     ok=False)
    one_line_error(result, "bad.zarr/frames: corrupt or unreadable chunk at sequence 4", "sequences done in",
                   "run the batch again to resume")
    printed = capfd.readouterr()
    for text in (result.output, printed.err, printed.out):
        assert "Compute Failed" not in text and "Traceback" not in text, text
    assert zarr_attrs(tmp_path / "b.zarr")["status"] == "running"


def zarr_attrs(path):
    import zarr

    return dict(zarr.open_group(str(path), mode="r").attrs)


def test_frames_of_another_size_are_refused_before_the_output_exists(made, tmp_path):
    """An edited frames shape (or a calibration of another frame size) is found before any output is made or
    any worker started."""
    import json

    from specgpu.io.recording import consolidate

    _, root = made
    src = tmp_path / "edited.zarr"
    shutil.copytree(root / "rec.zarr", src)
    meta = json.loads((src / "frames" / "zarr.json").read_text())
    meta["shape"][-1] = 300
    meta["chunk_grid"]["configuration"]["chunk_shape"][-1] = 300
    (src / "frames" / "zarr.json").write_text(json.dumps(meta))
    consolidate(src)
    result = run("batch", src, "--plan", root / "plan.npz", "--out", tmp_path / "b.zarr", ok=False)
    one_line_error(result, "edited.zarr/frames: frames are 240 x 300 but the recording says 240 x 320")
    assert not (tmp_path / "b.zarr").exists()


def test_an_output_killed_while_being_created_is_resumed(made, tmp_path, monkeypatch):
    """A batch killed right after its output appeared: the output is made under a temporary name and renamed
    whole, so a kill leaves nothing at --out (and the next run removes the dead run's temporary); an output left
    half-made by an older specgpu (no ``done`` array yet, so nothing computed) is made again."""
    import subprocess
    import sys

    import zarr

    from specgpu.pipeline import batch_source
    from specgpu.pipeline.batch import BATCH_FORMAT, prepare_batch

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"

    def killed(self):
        raise KeyboardInterrupt  # as a kill in the middle of making the output

    with monkeypatch.context() as m:
        m.setattr(batch_source._RecordingSource, "times", killed)
        with pytest.raises(KeyboardInterrupt):
            prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert not out.exists() and not list(tmp_path.glob(".b.zarr.*"))
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    leftover = tmp_path / f".b.zarr.{int(dead.stdout)}.creating"
    (leftover / "cube").mkdir(parents=True)  # what a kill -9 during the creation leaves
    _, todo = prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert todo.tolist() == list(range(N)) and not leftover.exists()
    # an output an older specgpu left half-made: its attributes, no done array
    shutil.rmtree(out)
    group = zarr.open_group(str(out), mode="w-", zarr_format=3)
    group.attrs.update({"format": BATCH_FORMAT, "version": 1, "status": "running"})
    group.create_array("cube", shape=(N, 2), chunks=(1, 2), dtype="float32")
    _, todo = prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert todo.tolist() == list(range(N)) and zarr_attrs(out)["plan_hash"] == plan.hash


def test_resuming_removes_the_partial_chunks_a_killed_run_left(made, tmp_path):
    """zarr writes each chunk to ``*.partial`` and renames it: a kill -9 mid-write leaves that file; resuming the
    batch removes it (nothing else ever would)."""
    from specgpu.pipeline.batch import prepare_batch

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"
    prepare_batch(root / "rec.zarr", plan, bundle, out)
    partial = out / "cube" / "c" / "2" / "0" / "0" / "0.3f9c2b.partial"
    partial.parent.mkdir(parents=True, exist_ok=True)
    partial.write_bytes(bytes(5000))
    prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert not partial.exists() and not list(out.rglob("*.partial"))
    # a source recording whose writer was killed: its leftovers go once no live writer holds its lock
    from specgpu.core.locks import output_lock

    src = tmp_path / "src.zarr"
    shutil.copytree(root / "rec.zarr", src)
    leftover = src / "frames" / "c" / "4" / "0" / "0" / "0.77aa01.partial"
    leftover.write_bytes(bytes(5000))
    with output_lock(src):  # a live writer (flock: another open lock file, even in this process): left alone
        prepare_batch(src, plan, bundle, tmp_path / "c.zarr")
        assert leftover.exists()
    prepare_batch(src, plan, bundle, tmp_path / "d.zarr")
    assert not leftover.exists() and not list(src.rglob("*.partial"))


def test_a_recording_replaced_on_a_long_lived_scheduler_is_read_afresh(made, tmp_path, dask_cluster):
    """--scheduler: the workers outlive a batch and keep its state; a recording replaced at the same path (here
    by one with more sequences) is another source, so the workers open it again instead of reading it through
    the old one's handles (which made every later sequence a false "corrupt chunk")."""
    setup, root = made
    src, out = tmp_path / "src.zarr", tmp_path / "b.zarr"
    record(setup, src, loops=1)
    assert open_recording(src).sequences == 3
    args = ["batch", src, "--plan", root / "plan.npz", "--calib", root / "calib.npz", "--out", out,
            "--scheduler", dask_cluster.scheduler_address]
    assert "3 sequences computed" in run(*args).output
    shutil.rmtree(src)
    shutil.rmtree(out)
    shutil.copytree(root / "rec.zarr", src)
    assert f"{N} sequences computed" in run(*args).output
    frames = open_recording(src).read("frames", slice(None))
    cube = open_recording_like(out)["cube"]
    for i in (0, N - 1):
        np.testing.assert_array_equal(cube[i], recovered(root, tmp_path, i, frames[i]))


def test_a_full_disk_on_a_worker_is_one_line_naming_the_output(made, tmp_path, monkeypatch):
    """A worker's write that fails (a full disk) comes back as one line naming the output array and the sequence,
    never zarr's temporary chunk file, and the sequence is not marked done."""
    import errno

    from specgpu.pipeline import batch
    from specgpu.pipeline.batch import prepare_batch, process_sequence

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"
    job, _ = prepare_batch(root / "rec.zarr", plan, bundle, out)

    real_write = batch.write_sequence_chunk

    def full_disk(array, index, value, **kwargs):
        if array.basename == "cube":
            raise OSError(errno.ENOSPC, "No space left on device", str(out / "cube" / "c" / "1" / "0" / "0" / "0"))
        return real_write(array, index, value, **kwargs)

    monkeypatch.setattr(batch, "write_sequence_chunk", full_disk)
    record = process_sequence(job, 1)
    assert record["error"] == f"{out}/cube: writing sequence 1 failed (No space left on device)"
    assert open_recording_like(out)["done"][:].tolist() == [0] * N


@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_any_changed_identity_entry_is_named_with_both_values(data):
    """The resume check: the same identity resumes; any one entry changed is refused naming its option and both
    values (the dE reference by its label, decided by its checksum)."""
    from specgpu.pipeline.batch_source import _IDENTITY_NAMES, _identity_mismatch

    text = st.text(st.characters(min_codepoint=48, max_codepoint=122), min_size=1, max_size=12)
    identity = {key: data.draw(text, key) for key in _IDENTITY_NAMES}
    identity["outputs"] = data.draw(st.lists(st.sampled_from(["cube", "XYZ", "Lab", "dE"]), min_size=1,
                                             unique=True), "outputs")
    identity["delta_e_ref"] = data.draw(text, "label")
    out = Path("/x/b.zarr")
    assert _identity_mismatch(out, dict(identity), identity) is None
    key = data.draw(st.sampled_from(sorted(_IDENTITY_NAMES)), "changed")
    attrs = dict(identity)
    attrs[key] = data.draw(text.filter(lambda v: v != identity[key]), "old") if key != "outputs" else ["Lab"]
    if key == "outputs" and identity["outputs"] == ["Lab"]:
        attrs[key] = ["cube"]
    if key == "reference_sha256":
        attrs["delta_e_ref"] = "old-label"
    message = _identity_mismatch(out, attrs, identity)
    name, show = _IDENTITY_NAMES[key]
    assert message.startswith(f"{out}: holds a batch made with {name} ") and "\n" not in message
    if key == "reference_sha256":
        assert f"--delta-e-ref old-label, this run gives {identity['delta_e_ref']};" in message
    else:
        assert f"{name} {show(attrs[key])}, this run gives {show(identity[key])};" in message


def test_the_one_pass_batch_equals_recover_and_its_colour_steps_saturated_pixels_included(made, tmp_path):
    """The batch computes a sequence in one device pass (the cube from the frames, XYZ, Lab and dE fused from the
    same frames, as the stream does): each output equals `specgpu recover SEQ --sequence i` and the offline colour
    steps applied to its cube (to_XYZ, to_Lab, delta_E) to float rounding, and a pixel with a saturated sample is
    NaN in every output, as recover makes it."""
    from specgpu.engine.colorimetry import delta_E
    from specgpu.pipeline.recovery import to_Lab, to_XYZ

    setup, root = made
    plan, bundle = plan_and_calibration(root)
    frames = open_recording(root / "rec.zarr").read("frames", slice(0, 2))
    frames[1, 3, 10, 20] = bundle.max_code  # one saturated sample in the second sequence
    K = plan.K
    seq = tmp_path / "seq"
    io.write_sequence(seq, frames.reshape(-1, *frames.shape[2:]),
                      [{"frame_id": s * K + k, "pattern_index": k, "exposure_s": plan.exposure_s,
                        "timestamp_s": (s * K + k) * 0.005} for s in range(2) for k in range(K)], plan.hash)
    shutil.copyfile(root / "plan.npz", seq / "plan.npz")
    shutil.copyfile(root / "calib.npz", seq / "calibration.npz")
    ref = np.array([50.0, 0.0, 0.0], np.float32)
    run_batch(seq, plan, bundle, tmp_path / "out.zarr", outputs=("cube", "XYZ", "Lab", "dE"), reference=ref,
              workers=1, progress=False)
    out = open_recording_like(tmp_path / "out.zarr")
    for i in range(2):
        r = CliRunner().invoke(main, ["recover", str(seq), "--sequence", str(i), "--out",
                                      str(tmp_path / f"r.{CUBE_EXT}")])
        assert r.exit_code == 0, r.output
        cube = io.read_cube(tmp_path / f"r.{CUBE_EXT}")[0]
        XYZ = to_XYZ(cube, plan)
        Lab = to_Lab(XYZ, plan)
        dE = delta_E(ref, Lab)
        for name, want in (("cube", cube), ("XYZ", XYZ), ("Lab", Lab), ("dE", dE)):
            got = out[name][i]
            assert got.shape == want.shape and np.array_equal(np.isnan(got), np.isnan(want)), name
            # a* is 500 (f(X) - f(Y)): a float32 rounding of either, fused or not, is up to 1.2e-4 of it
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=2e-4 if name in ("Lab", "dE") else 1e-6,
                                       err_msg=name)
    for name in ("cube", "XYZ", "Lab", "dE"):
        assert np.all(np.isnan(out[name][1][10, 20])) and not np.any(np.isnan(out[name][0][10, 20])), name


def test_several_sequences_per_task_are_each_marked_done_and_a_failure_ends_the_task(made, tmp_path):
    """One Dask task computes several sequences (its own cost amortised): each is written and marked done on its
    own, in order; a sequence that fails ends the task with its one-line error, the sequences before it stay done
    and those after it are left to a resumed run."""
    from specgpu.pipeline.batch import _task_groups, prepare_batch, process_sequences

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"
    job, todo = prepare_batch(root / "rec.zarr", plan, bundle, out)
    records = process_sequences(job, [0, 1])
    assert [r["index"] for r in records] == [0, 1] and not any(r.get("error") for r in records)
    assert open_recording_like(out)["done"][:].tolist() == [1, 1, 0, 0, 0, 0]
    records = process_sequences(job, [2, 99, 3])
    assert [r["index"] for r in records] == [2, 99] and "sequence 99" in records[-1]["error"]
    assert "\n" not in records[-1]["error"]
    assert open_recording_like(out)["done"][:].tolist() == [1, 1, 1, 0, 0, 0]
    frames = open_recording(root / "rec.zarr").read("frames", slice(0, 3))
    for i in range(3):
        np.testing.assert_array_equal(open_recording_like(out)["cube"][i], recovered(root, tmp_path, i, frames[i]))
    # tasks: consecutive groups of at most 8, at least 4 per worker
    assert _task_groups(range(6), 1) == [[0], [1], [2], [3], [4], [5]]
    assert _task_groups(range(100), 1) == [list(range(k, min(k + 8, 100))) for k in range(0, 100, 8)]
    assert _task_groups(range(40), 2) == [list(range(k, k + 5)) for k in range(0, 40, 5)]


def test_the_batch_applies_recovers_frame_corrections(made, tmp_path):
    """With a calibration that measured a sensor compression and a wavelength-dependent flat field, the frames are
    corrected on the host before the one device pass exactly as recover corrects them: the batch's cube and XYZ
    equal recover's (and its to_XYZ) to float rounding, and differ from an uncorrected decode."""
    from dataclasses import replace

    from specgpu.pipeline.capture_folder import read_capture
    from specgpu.pipeline.recovery import recover, to_XYZ

    setup, root = made
    plan, b = plan_and_calibration(root)
    tilt = np.linspace(-1.0, 1.0, b.frame_shape[1], dtype=np.float32)[None, :]
    flats = np.stack([b.flat_field * (1 + 0.04 * s * tilt) for s in (-1.0, 1.0)])
    bundle = replace(b, flat_fields=flats, flat_wavelengths=np.array([450.0, 650.0]),
                     reports={**b.reports, "linearity_c_per_dn2": 4e-8})
    plan = replace(plan, calibration=bundle.hash)
    assert bundle.flat_ratio(plan.patterns) is not None
    frames = open_recording(root / "rec.zarr").read("frames", slice(0, 2))
    K = plan.K
    seq = tmp_path / "seq"
    io.write_sequence(seq, frames.reshape(-1, *frames.shape[2:]),
                      [{"frame_id": s * K + k, "pattern_index": k, "exposure_s": plan.exposure_s,
                        "timestamp_s": (s * K + k) * 0.005} for s in range(2) for k in range(K)], plan.hash)
    save_plan(seq / "plan.npz", plan)
    save_calibration(seq / "calibration.npz", bundle)
    run_batch(seq, plan, bundle, tmp_path / "out.zarr", outputs=("cube", "XYZ"), workers=1, progress=False)
    out = open_recording_like(tmp_path / "out.zarr")
    folder = read_capture(seq)
    for i in range(2):
        cube = recover(folder, sequence=i)
        np.testing.assert_allclose(out["cube"][i], cube, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out["XYZ"][i], to_XYZ(cube, plan), rtol=1e-5, atol=1e-6)
    bare = open_recording_like(tmp_path / "out.zarr")["cube"][0]
    plain = recover(replace(folder, calibration=b, plan=replace(plan, calibration=b.hash)), sequence=0)
    assert np.nanmax(np.abs(bare - plain)) > 0.01  # the corrections matter


def test_the_copying_path_of_a_discrete_device_gives_the_same_chunks(made, tmp_path):
    """On a discrete device the frames are copied to the device and the results back (no mapping): forced here on
    the CPU device, the chunks equal those of the zero-copy path."""
    from specgpu.pipeline.batch import _decoder, _worker_state, prepare_batch, process_sequence

    _, root = made
    plan, bundle = plan_and_calibration(root)
    outs = []
    for copy in (False, True):
        out = tmp_path / f"b{int(copy)}.zarr"
        job, _ = prepare_batch(root / "rec.zarr", plan, bundle, out, outputs=("cube", "XYZ", "Lab", "dE"),
                               reference=[50.0, 0.0, 0.0])
        state, _ = _worker_state(job)
        _decoder(job, state)
        state._zero_copy = not copy
        assert not process_sequence(job, 1).get("error")
        outs.append(open_recording_like(out))
    for name in ("cube", "XYZ", "Lab", "dE"):
        np.testing.assert_array_equal(outs[0][name][1], outs[1][name][1])
    assert outs[1]["done"][:].tolist() == [0, 1, 0, 0, 0, 0]


def test_a_done_mark_cut_by_a_crash_is_computed_again_not_refused(made, tmp_path):
    """A kill while a ``done`` mark is written leaves its sequence to compute again: the output stays resumable
    (the marks go through a temporary renamed into place; one found empty counts as not done)."""
    from specgpu.pipeline.batch import prepare_batch, process_sequence

    _, root = made
    plan, bundle = plan_and_calibration(root)
    out = tmp_path / "b.zarr"
    job, todo = prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert process_sequence(job, 0).get("error") is None
    assert process_sequence(job, 1).get("error") is None
    mark = out / "done" / "c" / "1"
    assert mark.is_file() and not list((out / "done").rglob("*.partial"))
    mark.write_bytes(b"")  # what a kill between creating the file and writing it leaves
    _, todo = prepare_batch(root / "rec.zarr", plan, bundle, out)
    assert todo.tolist() == list(range(1, N))


def test_a_recording_still_being_written_is_read_as_the_batch_saw_it(made, tmp_path):
    """A worker opening a source recording that has committed more sequences since the batch started takes it
    as the batch saw it (its first ``sequences``), not as another recording."""
    import dataclasses

    from specgpu.pipeline import batch
    from specgpu.pipeline.batch import open_source, prepare_batch

    _, root = made
    plan, bundle = plan_and_calibration(root)
    job, _ = prepare_batch(root / "rec.zarr", plan, bundle, tmp_path / "b.zarr")
    earlier = open_source(root / "rec.zarr")
    earlier.sequences = N - 2  # the recording as a batch started two sequences earlier saw it
    seen = dataclasses.replace(job, sequences=N - 2, source_id=earlier.content_id)
    assert seen.source_id != job.source_id
    state, built = batch._worker_state(seen)
    assert built and state.source.sequences == N - 2
    batch._STATE.pop(seen.key, None)
