"""specgpu batch: Dask re-processing of recorded raw frames, equal to `specgpu recover`, resumable, one-line refusals.

A small twin recording (320 x 240, K = 9) is streamed once with its raw frames; every batch result is compared with
`specgpu recover SEQ --sequence i` on a sequence folder holding the same frames.
"""

from __future__ import annotations

import os
import re
import shutil
import signal

import numpy as np
import pytest
from click.testing import CliRunner

from specgpu import io
from specgpu.batch import run_batch
from specgpu.bench import stream_setup
from specgpu.calibration import save_calibration
from specgpu.cli import main
from specgpu.plans import save_plan
from specgpu.recording import ZarrRecorder, open_recording
from specgpu.stream import Stream

N = 6  # sequences in the recording


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A recording with raw frames (N sequences), its plan and calibration files, and a sequence folder of the
    first 3 sequences' frames."""
    root = tmp_path_factory.mktemp("batch")
    setup = stream_setup(320, 240, sequences=3, output_step_nm=10.0)
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


def recovered(root, tmp_path, sequence: int, frames=None) -> np.ndarray:
    """`specgpu recover` of one sequence: of the sequence folder, or of ``frames`` written into a new one."""
    seq = root / "seq"
    if frames is not None:
        seq = tmp_path / f"one-{sequence}"
        K = frames.shape[0]
        io.write_sequence(seq, frames, [{"frame_id": k, "pattern_index": k, "exposure_s": 0.004,
                                         "timestamp_s": k * 0.005} for k in range(K)],
                          __import__("specgpu.plans", fromlist=["load_plan"]).load_plan(root / "plan.npz").hash)
        shutil.copyfile(root / "plan.npz", seq / "plan.npz")
        shutil.copyfile(root / "calib.npz", seq / "calibration.npz")
    out = tmp_path / f"r{sequence}.npz"
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
    from specgpu.calibration import load_calibration
    from specgpu.plans import load_plan

    setup, root = made
    report = run_batch(root / "seq", load_plan(root / "plan.npz"), load_calibration(root / "calib.npz"),
                       tmp_path / "out.zarr", outputs=("cube", "XYZ", "Lab", "dE"), reference=[50.0, 0.0, 0.0],
                       workers=1, progress=False)
    assert report.computed == 3 and report.skipped == 0
    out = open_recording_like(tmp_path / "out.zarr")
    for i in range(3):
        np.testing.assert_array_equal(out["cube"][i], recovered(root, tmp_path, i))
    from specgpu.colorimetry import delta_E
    from specgpu.pipeline import to_Lab, to_XYZ

    XYZ = to_XYZ(out["cube"][1], setup.plan)
    np.testing.assert_allclose(out["XYZ"][1], XYZ, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(out["dE"][1], delta_E(np.array([50.0, 0, 0], np.float32), to_Lab(XYZ)), atol=1e-4)


def open_recording_like(path):
    import zarr

    return zarr.open_group(str(path), mode="r")


def test_an_interrupted_batch_resumes_without_recomputing_finished_chunks(made, tmp_path):
    from specgpu.calibration import load_calibration
    from specgpu.plans import load_plan

    _, root = made
    plan, bundle = load_plan(root / "plan.npz"), load_calibration(root / "calib.npz")
    out = tmp_path / "out.zarr"
    seen = []

    def stop_after_two(record):
        seen.append(record["index"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
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


def test_two_workers_each_build_one_context_and_a_killed_worker_loses_nothing(made, tmp_path):
    """Two worker processes: each builds its OpenCL state once. One worker is killed (SIGKILL) after the first
    result: the scheduler hands its unfinished chunks to the survivor (or the nanny's restarted process); every
    chunk is reported once, and the output is complete and equal to the undisturbed run."""
    from distributed import Client, LocalCluster

    from specgpu.calibration import load_calibration
    from specgpu.plans import load_plan

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

    from specgpu.plans import save_plan as save

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
    assert "bad-out.zarr: holds a batch of another source; resume only the same batch" in msg
    zarr.open_group(str(tmp_path / "bad-out.zarr"), mode="r+").attrs["plan_hash"] = "0" * 64
    msg = run(tmp_path / "bad.zarr", out="bad-out.zarr")
    assert "bad-out.zarr: holds a batch of another plan_hash" in msg and "\n" not in msg


def test_recover_writes_an_envi_cube_equal_to_npz(made, tmp_path):
    import spectral.io.envi as envi

    setup, root = made
    want = recovered(root, tmp_path, 1)
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
                                        str(tmp_path / f"c{i}.npz")])
        assert got.exit_code == 0, got.output
        np.testing.assert_array_equal(cube[i], io.read_cube(tmp_path / f"c{i}.npz")[0])
    again = CliRunner().invoke(main, [*common, "--out", str(tmp_path / "cap.zarr")])
    assert again.exit_code == 1 and "already exists" in again.output


def test_cli_batch_on_a_given_scheduler(made, tmp_path):
    """--scheduler ADDRESS: the batch runs on that cluster's workers (here a LocalCluster started by the test)."""
    from distributed import LocalCluster

    _, root = made
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        result = CliRunner().invoke(main, ["batch", str(root / "seq"), "--plan", str(root / "plan.npz"), "--out",
                                           str(tmp_path / "s.zarr"), "--scheduler", cluster.scheduler_address])
        assert result.exit_code == 0, result.output
        assert "3 sequences computed on 1 worker(s)" in result.output
        assert len(cluster.scheduler.workers) == 1  # the cluster outlives the batch: only the client was closed
    np.testing.assert_array_equal(open_recording_like(tmp_path / "s.zarr")["cube"][2], recovered(root, tmp_path, 2))
