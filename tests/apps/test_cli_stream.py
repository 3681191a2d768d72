"""`specgpu stream` and `specgpu bench --stream` on a replayed twin recording: what the stream records and reports,
a full disk said with what was saved and lost, a recording that cannot fit or an existing folder refused, a disk too
slow refused before the stream starts."""

import json

import pytest
from cli_helpers import stream_cli_files
from click.testing import CliRunner
from stream_helpers import shared_stream_setup
from zarr_helpers import disk_full_after

from specgpu.apps.cli import main
from specgpu.io import recording
from specgpu.io.recording import open_recording


@pytest.fixture(scope="module")
def setup():
    """A calibrated 320 x 240 twin at 200 fps, a symmetric plan (K = 9, 31 bands) and 4 recorded sequences."""
    return shared_stream_setup(320, 240, sequences=4, output_step_nm=10.0)


def test_cli_stream_records_and_reports(setup, tmp_path):
    from specgpu.calibration.bundle import save_calibration
    from specgpu.planning import save_plan

    cam = setup.description.camera
    (tmp_path / "rig.toml").write_text(f"[camera]\nroi_width = {cam.roi_width}\nroi_height = {cam.roi_height}\n"
                                       f"exposure_s = {cam.exposure_s!r}\nframe_rate_hz = {cam.frame_rate_hz!r}\n")
    save_calibration(tmp_path / "calib.npz", setup.bundle)
    save_plan(tmp_path / "plan.npz", setup.plan)
    result = CliRunner().invoke(main, ["stream", "--rig", str(tmp_path / "rig.toml"), "--plan",
                                       str(tmp_path / "plan.npz"), "--calib", str(tmp_path / "calib.npz"),
                                       "--scene", "colorchecker", "--seconds", "1", "--out", str(tmp_path / "out"),
                                       "--policy", "block"])  # no drops however busy the machine
    assert result.exit_code == 0, result.output
    assert "frames in" in result.output and "dropped 0 (ring 0)" in result.output
    recording = open_recording(tmp_path / "out")
    assert recording.attrs["plan_hash"] == setup.plan.hash and recording.sequences >= 10
    assert f"wrote {tmp_path / 'out'} ({recording.sequences} sequences)" in result.output
    assert (tmp_path / "out" / "preview.png").is_file()
    bad = CliRunner().invoke(main, ["stream", "--rig", str(tmp_path / "rig.toml"), "--plan",
                                    str(tmp_path / "plan.npz"), "--calib", str(tmp_path / "calib.npz"),
                                    "--seconds", "1", "--outputs", "XYZ,spectrum"])
    assert bad.exit_code != 0 and "spectrum" in bad.output


def test_cli_bench_stream_reports_every_case(tmp_path, bench_on_the_shared_recording):
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(main, ["bench", "--stream", "--stream-size", "320x240", "--stream-seconds", "0.5",
                                       "--paced-seconds", "0.5", "--stream-cases", "fused,paced,overload,equality",
                                       "--json", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    rows = {row["case"].split(" ")[0]: row for row in report["cases"]}
    assert set(rows) == {"coefficients+XYZ+dE2000", "paced", "overload", "stream"}
    for row in report["cases"]:
        if row["case"] != "coefficients+XYZ+dE2000":  # a throughput target, not a correctness check
            assert row["passed"], row
    assert rows["overload"]["ring"]["dropped"] == rows["overload"]["assembly"]["dropped"] > 0
    assert "PASS" in result.output and "frames/s in" in result.output
    # the rate targets are stated for 640 x 480: at 320 x 240 the rate is printed without a verdict
    assert "passed" not in rows["coefficients+XYZ+dE2000"] and "target >=" not in result.output
    bad = CliRunner().invoke(main, ["bench", "--stream", "--stream-size", "640"])
    assert bad.exit_code == 2 and "--stream-size" in bad.output


def test_cli_stream_on_a_full_disk_says_what_was_saved_and_lost(setup, tmp_path, monkeypatch):
    args = stream_cli_files(setup, tmp_path)
    disk_full_after(monkeypatch, 2)
    result = CliRunner().invoke(main, [*args, "--seconds", "20", "--out", str(tmp_path / "rec.zarr")])
    assert result.exit_code == 1
    last = result.output.strip().splitlines()[-1]
    assert "wrote" not in result.output and "No space left on device" in last
    saved, lost = (int(x) for x in __import__("re").search(r"; (\d+) sequences saved in .*rec.zarr, (\d+) lost",
                                                         last).groups())
    assert saved == 2 and lost >= 1
    monkeypatch.undo()
    assert open_recording(tmp_path / "rec.zarr").sequences == 2


def test_cli_stream_refuses_a_recording_that_cannot_fit_or_an_existing_folder(setup, tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple

    args = stream_cli_files(setup, tmp_path)
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 10**6, 10**6))
    result = CliRunner().invoke(main, [*args, "--seconds", "60", "--out", str(tmp_path / "rec.zarr")])
    assert result.exit_code == 1 and not (tmp_path / "rec.zarr").exists()
    assert result.output.count("\n") == 1
    assert __import__("re").search(r"the recording \(\d+ sequences x [0-9.]+ MB\) needs about [0-9.]+ GB but only "
                                   r"0.00 GB are free", result.output)
    monkeypatch.undo()
    (tmp_path / "old.zarr").mkdir()
    (tmp_path / "old.zarr" / "XYZ-000001.npy").write_bytes(b"a killed run's chunk")
    result = CliRunner().invoke(main, [*args, "--seconds", "1", "--out", str(tmp_path / "old.zarr")])
    assert result.exit_code == 1 and result.output.count("\n") == 1 and "already exists" in result.output
    assert [p.name for p in (tmp_path / "old.zarr").iterdir()] == ["XYZ-000001.npy"]


def test_cli_stream_refuses_a_disk_too_slow_before_it_starts(setup, tmp_path, monkeypatch):
    from cli_helpers import one_line_error, stream_cli_files

    from specgpu.apps.cli import main

    args = stream_cli_files(setup, tmp_path)
    monkeypatch.setattr(recording, "probe_write_rate", lambda path, *a, **k: 1e3)  # a fake slow disk
    # 10 s at 1 kB/s: far more than the 2 s the frame ring holds can wait (refused before any frame is taken)
    result = CliRunner().invoke(main, [*args, "--seconds", "10", "--frames", "--out", str(tmp_path / "rec.zarr")])
    line = one_line_error(result, "rec.zarr: the disk cannot keep up", "measured 0 MB/s", "--no-disk-check")
    assert "sequences/s" in line and not (tmp_path / "rec.zarr").exists()
    result = CliRunner().invoke(main, [*args, "--seconds", "0.5", "--out", str(tmp_path / "rec.zarr"),
                                       "--no-disk-check"])
    assert result.exit_code == 0, result.output
    assert open_recording(tmp_path / "rec.zarr").sequences >= 1
