"""``specgpu batch --outputs ...,sigma,sigma_rms,dE_sigma``: the uncertainty outputs named in the help, computed on
the Dask workers equal to the stream's with ``--motion global --denoise``, and a plan that cannot give them refused
in one line before any output (160 x 120 frames, :mod:`batch_sigma_helpers`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from batch_sigma_helpers import DENOISE, OUTPUTS, rendered, streamed, window_twin
from cli_helpers import one_line_error, run

from specgpu.calibration.bundle import save_calibration
from specgpu.io.recording import open_recording
from specgpu.pipeline.batch_output import open_batch_output
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS
from specgpu.planning import save_plan


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """A recording of the drifting scene streamed with ``--motion global --denoise`` (raw frames and the sigmas),
    its plan and calibration files, and the plan's file without its noise model."""
    root = tmp_path_factory.mktemp("cli-batch-sigma")
    twin = window_twin()
    _, plan, bundle, _ = twin
    frames, infos, light = rendered(twin, moving=True)
    rec = streamed(root / "rec.zarr", plan, bundle, frames, infos, light, motion="global", denoise=DENOISE,
                   white=None)
    save_plan(root / "plan.npz", plan)
    save_plan(root / "bare.npz", replace(plan, params={k: v for k, v in plan.params.items() if k != "noise"}))
    save_calibration(root / "calib.npz", bundle)
    return root, rec


def test_the_help_names_the_sigma_outputs():
    text = " ".join(run("batch", "--help").output.split())
    assert "sigma (each output's standard deviation and their RMS)" in text
    assert "sigma_rms (that RMS alone)" in text and "dE_sigma (first-order dE2000 standard deviation)" in text


@pytest.mark.usefixtures("dask_scheduler")
def test_the_workers_sigmas_equal_the_streams_with_motion_and_denoise(moving, tmp_path):
    assert (DENOISE_RADIUS, DENOISE_EPS) == DENOISE  # --denoise is the filter the stream ran
    root, rec = moving
    out = tmp_path / "out.zarr"
    result = run("batch", rec, "--plan", root / "plan.npz", "--calib", root / "calib.npz", "--out", out,
                 "--outputs", ",".join(OUTPUTS), "--motion", "global", "--denoise")
    assert "2 sequences computed" in result.output
    got, want = open_batch_output(out), open_recording(rec)
    for name in OUTPUTS:
        a, b = got.read(name, slice(None)), want.read(name, slice(None))
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), rtol=1e-5, atol=1e-7)
    assert np.isfinite(got.read("sigma_rms", 0)).mean() > 0.6 and got.attrs["status"] == "complete"


def test_a_plan_with_no_noise_model_is_refused_in_one_line_before_any_output(moving, tmp_path):
    root, rec = moving
    out = tmp_path / "out.zarr"
    for outputs in ("cube,sigma", "dE_sigma"):
        result = run("batch", rec, "--plan", root / "bare.npz", "--calib", root / "calib.npz", "--out", out,
                     "--outputs", outputs, "--motion", "global", ok=False)
        one_line_error(result, f"the {outputs.split(',')[-1]} output: the narrowband plan records no noise model",
                       "re-plan it with specgpu plan --rig RIG.toml", code=1)
        assert not out.exists()
