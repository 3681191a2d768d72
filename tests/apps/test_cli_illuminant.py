"""The illuminant of a colorimetric result travels with it: a tristimulus plan made for illuminant A gives XYZ,
Lab and dE under A in recover, stream and batch, every output records A, evaluate judges it under A by default
and refuses to judge it under another illuminant (that would compare colours taken under two lights)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error, plan_and_capture, run, tristimulus_rig
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.engine.colorimetry import XYZ_to_Lab
from specgpu.pipeline.evaluate import evaluation_illuminant
from specgpu.planning import Plan, load_plan

NAMES = ("D65", "A", "D50", "E", "FL2")


@pytest.fixture(scope="module")
def bench_a(tmp_path_factory):
    """The small twin rig with a tristimulus plan for illuminant A (``triA.npz``) and one capture of the chart
    with it (``seqA``)."""
    return plan_and_capture(tristimulus_rig(tmp_path_factory.mktemp("illuminant")), "triA.npz", "tristimulus",
                            "--illuminant", "A", seq="seqA")


@pytest.fixture(scope="module")
def tri_a(bench_a, tmp_path_factory):
    """``specgpu recover seqA --out triA.exr``: the capture's XYZ map under A, made once for the tests that only
    read it (in a folder of its own)."""
    path = tmp_path_factory.mktemp("triA") / "triA.exr"
    run("recover", bench_a / "seqA", "--out", path)
    return path


def test_recover_of_a_plan_for_A_makes_every_output_under_A(bench_a, tmp_path):
    d = bench_a
    out = {name: tmp_path / f"{name}.exr" for name in ("tri", "xyz", "lab", "dE")}
    run("recover", d / "seqA", "--out", out["tri"], "--xyz", out["xyz"], "--lab", out["lab"], "--delta-e-ref",
        "colorchecker", "--delta-e", out["dE"], "--method", "CIE 1976")
    for path in out.values():
        assert io.read_map(path)[2]["illuminant"] == "A", path
    XYZ = io.read_map(out["xyz"], "XYZ")[0]
    np.testing.assert_array_equal(XYZ, io.read_map(out["tri"], "XYZ")[0])  # the plan's XYZ as measured
    Lab = io.read_map(out["lab"], "Lab")[0]
    # relative to A's white (the plan's: the perfect diffuser on its light's grid), not D65's
    np.testing.assert_allclose(Lab, XYZ_to_Lab(XYZ, load_plan(d / "triA.npz").white_XYZ("A")), atol=1e-3)
    # the chart under A against its own XYZ under A: small differences (under D65's white they are ~40)
    assert float(np.nanmedian(io.read_map(out["dE"], "dE76")[0])) < 4


def test_evaluate_judges_an_XYZ_map_under_the_illuminant_it_records(tri_a, tmp_path):
    report = tmp_path / "report.json"
    result = run("evaluate", tri_a, "--truth", "colorchecker", "--json", report)
    assert "per patch under A:" in result.output
    figures = json.loads(report.read_text())
    assert figures["illuminant"] == "A" and figures["dE76_mean"] < 3 and figures["dE2000_mean"] < 3
    # the same name in another case is the same illuminant
    again = json.loads((run("evaluate", tri_a, "--truth", "colorchecker", "--illuminant", "a", "--json", report),
                        report.read_text())[1])
    assert again["dE76_mean"] == pytest.approx(figures["dE76_mean"], rel=1e-6)


def test_evaluate_refuses_another_illuminant_than_an_XYZ_map_records(tri_a):
    result = run("evaluate", tri_a, "--truth", "colorchecker", "--illuminant", "D65", ok=False)
    one_line_error(result, str(tri_a), "under illuminant A, not D65", code=1)


def test_recover_refuses_another_illuminant_than_the_plan_measures_under(bench_a, tmp_path):
    result = run("recover", bench_a / "seqA", "--out", tmp_path / "triA.exr", "--illuminant", "D65", ok=False)
    one_line_error(result, str(bench_a / "seqA"), "XYZ under illuminant A, not D65", code=1)
    assert not (tmp_path / "triA.exr").exists()


def test_a_reflectance_cube_colours_are_evaluated_under_the_illuminant_they_were_made_for(bench_a, tmp_path):
    d = bench_a
    run("plan", "narrowband", "--step-nm", "50", "--calib", d / "calib.npz", "--out", tmp_path / "nb.npz")
    run("capture", "--rig", d / "rig.toml", "--plan", tmp_path / "nb.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", tmp_path / "seq", "--seed", "1")
    run("recover", tmp_path / "seq", "--out", tmp_path / "cube.npz", "--xyz", tmp_path / "xyz.exr",
        "--illuminant", "A")
    assert io.read_cube(tmp_path / "cube.npz")[2]["illuminant"] == "A"
    reports = {}
    for name, extra in (("default", ()), ("A", ("--illuminant", "A"))):
        run("evaluate", tmp_path / "xyz.exr", "--truth", "colorchecker", "--json", tmp_path / f"{name}.json", *extra)
        reports[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert reports["default"]["illuminant"] == "A"
    assert reports["default"]["dE2000_mean"] == pytest.approx(reports["A"]["dE2000_mean"], rel=1e-6)
    one_line_error(run("evaluate", tmp_path / "xyz.exr", "--truth", "colorchecker", "--illuminant", "D50",
                       ok=False), "xyz.exr", "under illuminant A, not D50")
    # reflectance holds under any illuminant: the cube may be judged under another than its colours were made for
    run("evaluate", tmp_path / "cube.npz", "--truth", "colorchecker", "--illuminant", "D50", "--json",
        tmp_path / "d50.json")
    assert json.loads((tmp_path / "d50.json").read_text())["illuminant"] == "D50"


def test_a_stream_of_a_plan_for_A_records_A_and_its_colours_under_A(bench_a, tmp_path):
    from specgpu.io.recording import open_recording

    d = bench_a
    args = ["stream", "--rig", d / "rig.toml", "--plan", d / "triA.npz", "--calib", d / "calib.npz", "--scene",
            "colorchecker", "--seconds", "0.3", "--pacing", "free", "--outputs", "cube,XYZ,Lab,dE", "--method",
            "CIE 1976"]
    run(*args, "--out", tmp_path / "rec.zarr")
    rec = open_recording(tmp_path / "rec.zarr")
    assert rec.attrs["metadata"]["illuminant"] == "A" and rec.sequences >= 1
    XYZ = rec.read("XYZ", slice(0, 1))[0]
    white = load_plan(d / "triA.npz").white_XYZ("A")
    np.testing.assert_allclose(rec.read("Lab", slice(0, 1))[0], XYZ_to_Lab(XYZ, white), atol=2e-3)
    assert float(np.nanmedian(rec.read("dE", slice(0, 1))[0])) < 4
    one_line_error(run(*args, "--illuminant", "D65", ok=False), "triA.npz", "illuminant A, not D65")


@pytest.mark.usefixtures("dask_scheduler")  # the session's Dask cluster
def test_a_batch_of_a_plan_for_A_computes_and_records_its_colours_under_A(bench_a, tmp_path):
    import zarr

    d = bench_a
    run("capture", "--rig", d / "rig.toml", "--plan", d / "triA.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", tmp_path / "cap.zarr", "--sequences", "2", "--seed", "1")
    run("batch", tmp_path / "cap.zarr", "--plan", d / "triA.npz", "--out", tmp_path / "b.zarr", "--outputs",
        "cube,XYZ,Lab")
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r")
    assert group.attrs["illuminant"] == "A"
    XYZ = group["XYZ"][0]
    np.testing.assert_array_equal(XYZ, group["cube"][0])
    np.testing.assert_allclose(group["Lab"][0], XYZ_to_Lab(XYZ, load_plan(d / "triA.npz").white_XYZ("A")), atol=2e-3)


def test_the_stream_preview_shows_a_white_under_A_as_white(tmp_path):
    from types import SimpleNamespace

    from specgpu.core.spectra import white_point_XYZ
    from specgpu.pipeline import PreviewSink

    XYZ = np.broadcast_to(0.5 * white_point_XYZ("A"), (4, 4, 3)).astype(np.float32)
    sink = PreviewSink(tmp_path / "preview.png", interval_s=0.0, illuminant="A", background=False)
    sink.write(SimpleNamespace(arrays={"XYZ": XYZ}))
    for rgb in (sink.image, io.read_png(tmp_path / "preview.png")[0]):
        assert int(rgb[..., :3].max()) - int(rgb[..., :3].min()) <= 1, rgb[0, 0]  # neutral grey
    assert io.read_png(tmp_path / "preview.png")[1]["illuminant"] == "A"


def test_the_demo_files_of_a_plan_for_A_record_A(bench_a, tmp_path):
    from specgpu.apps.demo import _evaluate
    from specgpu.pipeline.capture_folder import read_capture
    from specgpu.pipeline.recovery import recover
    from specgpu.rig.scene import colorchecker_scene

    folder = read_capture(bench_a / "seqA")
    for sub in ("cubes", "maps", "png"):
        (tmp_path / sub).mkdir()
    _evaluate(tmp_path, "tristimulus-A", folder.plan, recover(folder), colorchecker_scene(240, 320), None)
    assert io.read_map(tmp_path / "cubes" / "tristimulus-A.exr")[2]["illuminant"] == "A"
    assert io.read_map(tmp_path / "maps" / "tristimulus-A-dE2000.exr")[2]["illuminant"] == "A"
    run("evaluate", tmp_path / "cubes" / "tristimulus-A.exr", "--truth", "colorchecker", "--json", tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text())["dE76_mean"] < 3


def spelled(name, flips):
    """``name`` with the letters whose flag is set in another case."""
    return "".join(c.swapcase() if f else c for c, f in zip(name, flips + [False] * len(name)))


def bare_plan(output, illuminant):
    """A one-frame plan of the given output, made for ``illuminant`` (the fields the illuminant rule reads)."""
    n = 3 if output in ("XYZ", "RGB") else 1
    return Plan(method="m", patterns=np.zeros((1, 4), np.int64), target_spectra=np.zeros((1, 3)),
                light_wavelengths=[1.0, 2.0, 3.0], exposure_s=1e-3, A=np.ones((n, 1)), output=output,
                output_wavelengths=[500.0] if output == "reflectance" else [],
                output_labels=tuple("XYZ"[:n]) if n == 3 else ("r",), illuminant=illuminant, observer="",
                calibration="x", rows=768, min_exposure_s=80e-6, expected_level=[0.5])


@settings(max_examples=80, deadline=None)
@given(output=st.sampled_from(["XYZ", "RGB", "reflectance", "relative"]), own=st.sampled_from(NAMES),
       asked=st.one_of(st.none(), st.sampled_from(NAMES)), flips=st.lists(st.booleans(), max_size=3))
def test_a_plan_resolves_the_illuminant_of_its_colours(output, own, asked, flips):
    plan = bare_plan(output, own)
    measured = output in ("XYZ", "RGB")
    request = None if asked is None else spelled(asked, flips)
    if measured and asked is not None and asked != own:
        with pytest.raises(ValueError, match=f"the plan measures {output} under illuminant {own}, not {request}"):
            plan.resolve_illuminant(request)
        return
    want = own if measured else (asked or "D65")
    got = plan.resolve_illuminant(request)
    assert got == want or (not measured and got == request)


@settings(max_examples=80, deadline=None)
@given(recorded=st.one_of(st.none(), st.sampled_from(NAMES)), asked=st.one_of(st.none(), st.sampled_from(NAMES)),
       colorimetric=st.booleans(), flips=st.lists(st.booleans(), max_size=3))
def test_evaluate_takes_the_recorded_illuminant_and_refuses_only_a_contradiction(recorded, asked, colorimetric,
                                                                               flips):
    request = None if asked is None else spelled(asked, flips)
    if colorimetric and recorded and asked and asked != recorded:
        with pytest.raises(ValueError, match=f"^f.exr holds XYZ under illuminant {recorded}, not {request}: "):
            evaluation_illuminant(recorded, request, colorimetric=True, name="f.exr")
        return
    got = evaluation_illuminant(recorded, request, colorimetric=colorimetric, name="f.exr")
    assert got.lower() == (asked or recorded or "D65").lower()


@pytest.mark.parametrize("recorded", [3, "", ["A"]])
def test_evaluate_refuses_a_recorded_illuminant_that_is_no_name(recorded):
    with pytest.raises(ValueError, match="f.exr: the recorded illuminant .* is not an illuminant name"):
        evaluation_illuminant(recorded, colorimetric=True, name="f.exr")
