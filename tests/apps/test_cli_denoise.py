"""``specgpu stream --denoise``: runs with the linear outputs and with Lab, records that it denoised, and refuses
the outputs it cannot carry in one line."""

import json

from cli_helpers import hadamard_rig, one_line_error, run


def test_stream_denoise(tmp_path):
    rig, cal, plan = hadamard_rig(tmp_path)
    base = ["stream", "--rig", rig, "--plan", plan, "--calib", cal, "--scene", "natural",
            "--seconds", "0.3", "--pacing", "free", "--denoise"]
    out = run(*base, "--outputs", "coefficients,XYZ", "--out", tmp_path / "rec.zarr").output
    assert "sequences" in out
    attrs = json.loads((tmp_path / "rec.zarr" / "zarr.json").read_text())["attributes"]
    assert "guided filter" in json.dumps(attrs)
    out = run(*base, "--outputs", "XYZ,Lab", "--out", tmp_path / "lab.zarr").output  # Lab of the filtered XYZ
    assert "sequences" in out
    one_line_error(run(*base, "--outputs", "cube,sigma", ok=False), "sigma cannot be denoised")


def test_stream_accumulate(tmp_path):
    rig, cal, plan = hadamard_rig(tmp_path)
    base = ["stream", "--rig", rig, "--plan", plan, "--calib", cal, "--scene", "colorchecker",
            "--seconds", "0.5", "--pacing", "free", "--accumulate", "4"]
    out = run(*base, "--outputs", "cube,sigma_rms", "--out", tmp_path / "rec.zarr").output
    assert "sequences" in out
    attrs = json.loads((tmp_path / "rec.zarr" / "zarr.json").read_text())["attributes"]
    assert "running estimate over up to 4" in json.dumps(attrs)
    one_line_error(run(*base, "--outputs", "cube,XYZ", ok=False), "needs the cube and sigma")
