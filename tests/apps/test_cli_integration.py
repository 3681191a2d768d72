"""`--integration` on the commands that make XYZ, Lab and dE from reflectance: ASTM E308's tables or the rectangle
rule, recorded with every output, the white of Lab and dE integrated the same way; what cannot be integrated so is
refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error, plan_and_capture, run, tristimulus_rig

from specgpu import io
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E, reflectance_to_XYZ
from specgpu.pipeline.evaluate import scene_XYZ
from specgpu.planning import load_plan
from specgpu.rig.scene import load_scene

ASTM = "ASTM E308"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """The small twin rig, its tristimulus plan, and a narrowband plan on 400-700 nm every 20 nm (``nb.npz``) with
    one capture of the chart (``seqnb``)."""
    d = tristimulus_rig(tmp_path_factory.mktemp("integration"))
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seqtri", "--seed", "1")
    return plan_and_capture(d, "nb.npz", "narrowband", "--step-nm", "20", seq="seqnb")


def chart_Lab(integration):
    scene = load_scene("colorchecker", 240, 320)
    XYZ = scene_XYZ(scene, "D65", integration=integration)
    return XYZ_to_Lab(XYZ, "D65", wavelengths=scene.wavelengths, integration=integration)


def test_recover_integrates_by_ASTM_E308_and_takes_its_white(bench, tmp_path):
    d = bench
    out = {name: tmp_path / f"{name}.exr" for name in ("xyz", "lab", "dE")}
    run("recover", d / "seqnb", "--out", tmp_path / "cube.npz", "--xyz", out["xyz"], "--lab", out["lab"],
        "--delta-e-ref", "colorchecker", "--delta-e", out["dE"], "--method", "CIE 1976", "--integration",
        "astm-e308")
    cube, wl, meta = io.read_cube(tmp_path / "cube.npz")
    assert meta["integration"] == ASTM
    assert all(io.read_map(path)[2]["integration"] == ASTM for path in out.values())
    XYZ = io.read_map(out["xyz"], "XYZ")[0]
    np.testing.assert_allclose(XYZ, reflectance_to_XYZ(cube, wl, integration=ASTM), atol=1e-5)
    assert not np.allclose(XYZ, reflectance_to_XYZ(cube, wl), atol=1e-4, equal_nan=True)  # not the rectangle rule
    Lab = io.read_map(out["lab"], "Lab")[0]
    np.testing.assert_allclose(Lab, XYZ_to_Lab(XYZ, wavelengths=wl, integration=ASTM), atol=1e-3)
    ref = chart_Lab(ASTM)  # the reference's white is the scene grid's, by ASTM E308 too
    np.testing.assert_allclose(io.read_map(out["dE"], "dE76")[0][..., 0], delta_E(ref, Lab, "CIE 1976"), atol=2e-3)
    # evaluate scores the cube as it records, unless asked (a cube holds under either)
    report = tmp_path / "report.json"
    run("evaluate", tmp_path / "cube.npz", "--truth", "colorchecker", "--json", report)
    assert json.loads(report.read_text())["integration"] == ASTM
    run("evaluate", tmp_path / "cube.npz", "--truth", "colorchecker", "--json", report, "--integration", "rectangle")
    assert "integration" not in json.loads(report.read_text())


def test_an_unknown_integration_is_a_usage_error_naming_the_option(bench, tmp_path):
    result = run("recover", bench / "seqnb", "--out", tmp_path / "c.npz", "--integration", "simpson", ok=False)
    one_line_error(result, "--integration", "'simpson'", code=2)


def test_a_grid_ASTM_E308_has_no_table_for_is_a_usage_error(tmp_path):
    cube = tmp_path / "c15.npz"
    io.write_cube(cube, np.full((24, 36, 21), 0.5, np.float32), np.arange(400.0, 701.0, 15.0))
    one_line_error(run("evaluate", cube, "--truth", "colorchecker", "--integration", "astm-e308", ok=False),
                   "ASTM E308", "every 15 nm", code=2)


def test_a_tristimulus_plan_and_its_XYZ_map_are_refused_another_integration(bench, tmp_path):
    d = bench
    one_line_error(run("recover", d / "seqtri", "--out", tmp_path / "t.exr", "--xyz", tmp_path / "x.exr",
                       "--integration", "astm-e308", ok=False), "rectangle rule on the light's grid", code=1)
    run("recover", d / "seqtri", "--out", tmp_path / "t.exr")
    one_line_error(run("evaluate", tmp_path / "t.exr", "--truth", "colorchecker", "--integration", "astm-e308",
                       ok=False), "t.exr", "integrated by rectangle, not ASTM E308", code=1)


@pytest.mark.usefixtures("dask_scheduler")  # the session's Dask cluster
def test_a_batch_records_its_integration_and_resumes_only_with_it(bench, tmp_path):
    import zarr

    d = bench
    args = ["batch", d / "seqnb", "--plan", d / "nb.npz", "--out", tmp_path / "b.zarr", "--outputs", "cube,Lab"]
    run(*args, "--integration", "astm-e308")
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r")
    assert group.attrs["integration"] == ASTM
    cube = np.asarray(group["cube"][0])
    plan = load_plan(d / "nb.npz")
    want = XYZ_to_Lab(reflectance_to_XYZ(cube, plan.output_wavelengths, integration=ASTM),
                      wavelengths=plan.output_wavelengths, integration=ASTM)
    np.testing.assert_allclose(group["Lab"][0], want, atol=2e-3)
    one_line_error(run(*args, ok=False), "--integration ASTM E308", "this run gives rectangle")


def test_a_stream_records_its_integration_and_its_Lab_takes_that_white(bench, tmp_path):
    from specgpu.io.recording import open_recording

    d = bench
    run("stream", "--rig", d / "rig.toml", "--plan", d / "nb.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--seconds", "0.3", "--pacing", "free", "--outputs", "XYZ,Lab", "--integration",
        "ASTM E308", "--out", tmp_path / "rec.zarr")
    rec = open_recording(tmp_path / "rec.zarr")
    assert rec.attrs["metadata"]["integration"] == ASTM and rec.sequences >= 1
    white = load_plan(d / "nb.npz").white_XYZ("D65", integration=ASTM)
    np.testing.assert_allclose(rec.read("Lab", slice(0, 1))[0], XYZ_to_Lab(rec.read("XYZ", slice(0, 1))[0], white),
                               atol=2e-3)
