"""``specgpu stream --denoise``: runs with the linear outputs, with Lab and with the sigmas, and records that it
denoised."""

import json

import numpy as np
from cli_helpers import hadamard_rig, one_line_error, run

from specgpu.io.recording import open_recording


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
    out = run(*base, "--outputs", "cube,sigma,dE_sigma", "--out", tmp_path / "sigma.zarr").output  # carried through
    assert "sequences" in out
    rec = open_recording(tmp_path / "sigma.zarr")
    sigma, des = rec.read("sigma", 0), rec.read("dE_sigma", 0)
    assert np.isfinite(sigma).mean() > 0.9 and np.nanmedian(des) > 0


def test_stream_accumulate(tmp_path):
    rig, cal, plan = hadamard_rig(tmp_path)
    base = ["stream", "--rig", rig, "--plan", plan, "--calib", cal, "--scene", "colorchecker",
            "--seconds", "0.5", "--pacing", "free", "--accumulate", "4"]
    out = run(*base, "--outputs", "cube,sigma_rms", "--out", tmp_path / "rec.zarr").output
    assert "sequences" in out
    attrs = json.loads((tmp_path / "rec.zarr" / "zarr.json").read_text())["attributes"]
    assert "running estimate over up to 4" in json.dumps(attrs)
    one_line_error(run(*base, "--outputs", "cube,XYZ", ok=False), "needs the cube and sigma")
