"""Motion-compensated decoding through the command line: `specgpu batch --motion` checked in one line, `specgpu
stream --motion`, and the stream bench putting the motion rate beside the static one."""


import numpy as np
import pytest
from cli_helpers import one_line_error, run
from moving_helpers import moving_capture


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """A sequence folder of 2 sequences of a 7-band narrowband plan on a twin whose scene drifts 2 px per frame
    in x and 1 in y, with its plan and calibration files."""
    return moving_capture(tmp_path_factory.mktemp("moving-decode"))



def test_batch_motion_is_checked_in_one_line(moving, tmp_path):
    root, _, _, plan_path, calib_path = moving
    args = ["batch", root / "seq", "--plan", plan_path, "--calib", calib_path, "--out", tmp_path / "o.zarr"]
    one_line_error(run(*args, "--motion", "optical", ok=False), "--motion", code=2)
    one_line_error(run(*args, "--motion", "global", "--white-reflectance", "0.9", ok=False),
                   "--white-reflectance needs --white-roi", code=2)
    one_line_error(run(*args, "--motion", "global", "--white-roi", "0,0,8,8", "--white-roi-moves", "up", ok=False),
                   "--white-roi-moves", code=2)
    one_line_error(run(*args, "--motion", "global", "--white-roi", "9000,0,8,8", ok=False), "--white-roi 9000,0,8,8")
    assert not (tmp_path / "o.zarr").exists()


def test_stream_motion_on_the_command_line(moving, tmp_path):
    import zarr

    root, _, _, plan_path, calib_path = moving
    (tmp_path / "rig.toml").write_text("[camera]\nroi_width = 320\nroi_height = 240\nframe_rate_hz = 200.0\n"
                                       "exposure_s = 0.0049\n[motion]\nvelocity_px_per_frame = [2.0, 1.0]\n")
    args = ["stream", "--rig", tmp_path / "rig.toml", "--plan", plan_path, "--calib", calib_path, "--scene",
            "natural", "--pacing", "free", "--seconds", "0.3"]
    one_line_error(run(*args, "--motion", "optical", ok=False), "--motion", code=2)
    one_line_error(run(*args, "--motion", "affine", "--outputs", "cube", "--accumulate", "3", ok=False),
                   "--accumulate needs the cube and sigma")
    one_line_error(run(*args, "--motion", "global", "--white-roi", "0,0,8,8", "--white-roi-moves", "sideways",
                       "--outputs", "cube", ok=False), "--white-roi-moves", code=2)
    done = run(*args, "--motion", "global", "--outputs", "cube,XYZ", "--out", tmp_path / "rec.zarr")
    rec = zarr.open_group(str(tmp_path / "rec.zarr"), mode="r")
    assert "global" in str(rec.attrs["metadata"].get("motion")), (done.output, dict(rec.attrs))
    cube = np.asarray(rec["cube"][0], np.float32)
    assert 0 < np.isnan(cube[..., 0]).mean() < 0.2  # the field's moving border: NaN, never a made-up value
    run(*args, "--motion", "global", "--outputs", "cube,sigma_rms", "--accumulate", "3", "--out", tmp_path / "acc.zarr")
    acc = zarr.open_group(str(tmp_path / "acc.zarr"), mode="r")
    assert "moved with the scene" in str(acc.attrs["metadata"].get("accumulate"))
    assert np.isfinite(np.asarray(acc["sigma_rms"][0], np.float32)).mean() > 0.8


def test_the_stream_bench_puts_the_motion_rate_beside_the_static_one(tmp_path, bench_on_the_shared_recording):
    import json

    out = tmp_path / "bench.json"
    result = run("bench", "--stream", "--stream-size", "320x240", "--stream-seconds", "0.5", "--stream-cases",
                 "motion", "--json", out)
    rows = {row["case"]: row for row in json.loads(out.read_text())["cases"]}
    assert set(rows) == {"coefficients+XYZ", "coefficients+XYZ with --motion global", "motion global / static"}
    ratio = rows["motion global / static"]
    assert ratio["static_frames_per_s"] == rows["coefficients+XYZ"]["frames_per_s"] > 0
    assert ratio["motion_frames_per_s"] == rows["coefficients+XYZ with --motion global"]["frames_per_s"] > 0
    assert ratio["ratio"] == pytest.approx(ratio["motion_frames_per_s"] / ratio["static_frames_per_s"])
    steps = ratio["ms_per_sequence"]
    assert set(steps) == {"estimate", "warp", "check", "colour"} and all(v > 0 for v in steps.values())
    assert f"ratio {ratio['ratio']:.3f}" in result.output
