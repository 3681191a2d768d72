"""`specgpu recover --denoise` and `specgpu batch --denoise` on a capture: the guided filter through the command
line, the batch equal to recover."""

import numpy as np
import pytest
from cli_helpers import hadamard_rig, one_line_error, run

from specgpu.calibration.bundle import oracle_calibration
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E
from specgpu.io import read_cube, read_map
from specgpu.pipeline.denoise import denoise_recovery
from specgpu.pipeline.recovery import recover, to_XYZ
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)



def test_cli_recover_denoise(tmp_path, bundle):
    rig, cal, _ = hadamard_rig(tmp_path, bundle)
    run("capture", "--rig", rig, "--calib", cal, "--plan", tmp_path / "p.npz", "--scene", "natural", "--out",
        tmp_path / "seq")
    run("recover", tmp_path / "seq", "--out", tmp_path / "raw.npz", "--sigma", tmp_path / "raw-s.exr")
    out = run("recover", tmp_path / "seq", "--out", tmp_path / "d.npz", "--sigma", tmp_path / "d-s.exr",
              "--denoise").output
    assert "wrote" in out
    raw, den = read_cube(tmp_path / "raw.npz"), read_cube(tmp_path / "d.npz")
    y_raw = raw[0] if isinstance(raw, tuple) else raw.reflectance
    y_den = den[0] if isinstance(den, tuple) else den.reflectance
    assert y_den.shape == y_raw.shape and not np.allclose(y_den, y_raw)
    s_raw = read_map(tmp_path / "raw-s.exr")
    s_den = read_map(tmp_path / "d-s.exr")
    s_raw = s_raw[0] if isinstance(s_raw, tuple) else s_raw
    s_den = s_den[0] if isinstance(s_den, tuple) else s_den
    assert np.nanmedian(np.asarray(s_den)) < np.nanmedian(np.asarray(s_raw))
    # the XYZ covariance is carried through the filter too: dE_sigma at the filtered XYZ, lower than the raw one
    run("recover", tmp_path / "seq", "--out", tmp_path / "x.npz", "--delta-e-sigma", tmp_path / "x.exr")
    run("recover", tmp_path / "seq", "--out", tmp_path / "y.npz", "--denoise", "--delta-e-sigma", tmp_path / "y.exr")
    des_raw, des_den = (np.asarray(read_map(tmp_path / name)[0]) for name in ("x.exr", "y.exr"))
    assert 0 < np.nanmedian(des_den) < np.nanmedian(des_raw)
    one_line_error(run("recover", tmp_path / "seq", "--out", tmp_path / "x.npz", "--denoise", "--denoise-eps", "-1",
                       ok=False), "--denoise-eps")


@pytest.mark.usefixtures("dask_scheduler")  # the session's Dask cluster
def test_batch_denoise_equals_recover_denoise(tmp_path, bundle):
    """``specgpu batch --denoise`` of a sequence folder: each sequence's cube equals recover --denoise of it; a
    resumed batch asking otherwise is refused in one line; Lab and dE come from the filtered XYZ (as its help
    says)."""
    import zarr

    from specgpu.pipeline.capture_folder import read_capture

    rig, cal, _ = hadamard_rig(tmp_path, bundle)
    run("capture", "--rig", rig, "--calib", cal, "--plan", tmp_path / "p.npz", "--scene", "natural", "--out",
        tmp_path / "seq", "--sequences", "2")
    run("batch", tmp_path / "seq", "--plan", tmp_path / "p.npz", "--out", tmp_path / "b.zarr", "--outputs",
        "cube", "--denoise")
    folder = read_capture(tmp_path / "seq")
    cube = zarr.open_group(str(tmp_path / "b.zarr"), mode="r")["cube"]
    for i in range(2):
        want = denoise_recovery(folder, recover(folder, sequence=i), sequence=i)
        np.testing.assert_allclose(cube[i], want, atol=1e-4 * np.max(np.abs(want)))
    one_line_error(run("batch", tmp_path / "seq", "--plan", tmp_path / "p.npz", "--out", tmp_path / "b.zarr",
                       "--outputs", "cube", ok=False), "--denoise")
    # Lab from the filtered XYZ, as recover --denoise computes it from the filtered cube: the filtered XYZ equal
    # to within the float32 filter's rounding, and Lab and dE those of the batch's own filtered XYZ (near black a
    # rounding of 1e-5 in XYZ moves a* by hundredths, so Lab is compared to the XYZ it was computed from)
    run("batch", tmp_path / "seq", "--plan", tmp_path / "p.npz", "--out", tmp_path / "c.zarr", "--outputs",
        "XYZ,Lab,dE", "--delta-e-ref", "50,10,-10", "--denoise")
    group = zarr.open_group(str(tmp_path / "c.zarr"), mode="r")
    for i in range(2):
        want = to_XYZ(denoise_recovery(folder, recover(folder, sequence=i), sequence=i), folder.plan)
        xyz = np.asarray(group["XYZ"][i], np.float64)
        np.testing.assert_allclose(xyz, want, atol=1e-4 * np.max(np.abs(want)))
        lab = XYZ_to_Lab(xyz, folder.plan.white_XYZ("D65"))
        np.testing.assert_allclose(group["Lab"][i], lab, atol=2e-3)
        reference = np.broadcast_to(np.float32([50.0, 10.0, -10.0]), lab.shape)
        np.testing.assert_allclose(group["dE"][i], delta_E(reference, lab), atol=2e-3)
    assert "not with Lab or dE" not in " ".join(run("batch", "--help").output.split())
