"""The observer of a colorimetric result travels with it, as its illuminant does: a tristimulus plan made for the
CIE 1964 10 degree observer gives Lab and dE against that observer's white (not the 2 degree observer's) in
recover, stream and batch, the dE reference is made for it too, every output records it, evaluate judges the XYZ
map under it, and another observer than the plan's is refused; a reflectance plan makes its XYZ for the observer
asked for (the 2 degree one by default) and records it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error, plan_and_capture, run, tristimulus_rig
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.core.spectra import DEFAULT_CMFS, OBSERVERS
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E
from specgpu.planning import Plan, load_plan

TEN = "CIE 1964 10 Degree Standard Observer"


@pytest.fixture(scope="module")
def bench_10(tmp_path_factory):
    """The small twin rig with a tristimulus plan for the 10 degree observer (``tri10.npz``) and two sequences of
    the white plate captured with it (``seq10``)."""
    return plan_and_capture(tristimulus_rig(tmp_path_factory.mktemp("observer")), "tri10.npz", "tristimulus",
                            "--observer", TEN, scene="white", seq="seq10", sequences=2)


#: the plate in the field as the white reference: each sequence's decoder rescaled so the plate reads 0.99 of the
#: plan's white (the twin's light differs from the calibration model by a few per cent)
ROI = ("--white-roi", "100,80,120,80")


def median_Lab(Lab):
    return np.nanmedian(np.asarray(Lab, np.float64).reshape(-1, 3), axis=0)


def chart_Lab(observer, shape=(240, 320)):
    """Lab per pixel of the colour chart under D65 for ``observer``: what --delta-e-ref colorchecker gives."""
    from specgpu.pipeline.evaluate import scene_XYZ
    from specgpu.rig.scene import load_scene

    scene = load_scene("colorchecker", *shape)
    return XYZ_to_Lab(scene_XYZ(scene, "D65", observer), "D65", observer=observer, wavelengths=scene.wavelengths)


def test_recover_of_a_plan_for_the_10_degree_observer_makes_Lab_and_dE_against_its_white(bench_10, tmp_path):
    d = bench_10
    out = {name: tmp_path / f"{name}.exr" for name in ("tri", "xyz", "lab", "dE")}
    run("recover", d / "seq10", "--out", out["tri"], "--xyz", out["xyz"], "--lab", out["lab"], "--delta-e-ref",
        "colorchecker", "--delta-e", out["dE"], "--method", "CIE 1976", *ROI)
    for path in out.values():
        meta = io.read_map(path)[2]
        assert meta["observer"] == TEN and meta["illuminant"] == "D65", path
    XYZ = io.read_map(out["xyz"], "XYZ")[0]
    Lab = io.read_map(out["lab"], "Lab")[0]
    # the 10 degree white, integrated on the plan's grid
    np.testing.assert_allclose(Lab, XYZ_to_Lab(XYZ, load_plan(d / "tri10.npz").white_XYZ("D65", TEN)), atol=1e-3)
    L, a, b = median_Lab(Lab)
    assert 99 < L < 100.5 and abs(a) < 0.3 and abs(b) < 0.3, (L, a, b)  # the white plate is neutral
    # against the 2 degree observer's D65 white (what was computed before) the same white is measurably yellow
    old = median_Lab(XYZ_to_Lab(XYZ, "D65"))
    assert old[2] > 0.7 and old[1] < -0.3, old
    # the reference is made for the 10 degree observer too (the chart's colours differ between the two observers)
    ref = chart_Lab(TEN)
    assert float(np.max(np.abs(ref - chart_Lab(DEFAULT_CMFS)))) > 1
    np.testing.assert_allclose(io.read_map(out["dE"], "dE76")[0][..., 0], delta_E(ref, Lab, "CIE 1976"), atol=2e-3)


def test_evaluate_judges_the_XYZ_map_under_the_observer_it_records(bench_10, tmp_path):
    run("recover", bench_10 / "seq10", "--out", tmp_path / "tri10.exr", *ROI)
    report = tmp_path / "report.json"
    run("evaluate", tmp_path / "tri10.exr", "--truth", "white", "--json", report)
    figures = json.loads(report.read_text())
    assert figures["observer"] == TEN and figures["illuminant"] == "D65"
    assert figures["dE76_mean"] < 0.3 and figures["dE2000_mean"] < 0.3, figures  # the plate's mean colour


def test_recover_refuses_another_observer_than_the_plan_measures_for(bench_10, tmp_path):
    result = run("recover", bench_10 / "seq10", "--out", tmp_path / "t.exr", "--observer", DEFAULT_CMFS, ok=False)
    one_line_error(result, f"the plan of {bench_10 / 'seq10'}", f"for the {TEN}, not the {DEFAULT_CMFS}", code=1)
    assert not (tmp_path / "t.exr").exists()
    # the plan's own, in any case, is taken
    run("recover", bench_10 / "seq10", "--out", tmp_path / "t.exr", "--observer", TEN.lower())
    assert io.read_map(tmp_path / "t.exr")[2]["observer"] == TEN
    result = run("recover", bench_10 / "seq10", "--out", tmp_path / "u.exr", "--observer", "CIE 2 deg", ok=False)
    one_line_error(result, "observer 'CIE 2 deg' is not one of", DEFAULT_CMFS, TEN, code=2)  # a typo: usage


def test_a_stream_of_a_plan_for_the_10_degree_observer_records_it_and_agrees_with_recover(bench_10, tmp_path):
    from specgpu.io.recording import open_recording

    d = bench_10
    args = ["stream", "--rig", d / "rig.toml", "--plan", d / "tri10.npz", "--calib", d / "calib.npz", "--scene",
            "white", "--seconds", "0.3", "--pacing", "free", "--outputs", "XYZ,Lab,dE", "--method", "CIE 1976",
            "--delta-e-ref", "colorchecker", *ROI]
    run(*args, "--out", tmp_path / "rec.zarr")
    rec = open_recording(tmp_path / "rec.zarr")
    assert rec.attrs["metadata"]["observer"] == TEN and rec.sequences >= 1
    XYZ = rec.read("XYZ", slice(0, 1))[0]
    Lab = rec.read("Lab", slice(0, 1))[0]
    np.testing.assert_allclose(Lab, XYZ_to_Lab(XYZ, load_plan(d / "tri10.npz").white_XYZ("D65", TEN)), atol=2e-3)
    np.testing.assert_allclose(rec.read("dE", slice(0, 1))[0], delta_E(chart_Lab(TEN), Lab, "CIE 1976"), atol=2e-2)
    # the same white as recover makes of it (another noise draw: close, not equal), neutral
    run("recover", d / "seq10", "--out", tmp_path / "tri.exr", "--lab", tmp_path / "lab.exr", *ROI)
    np.testing.assert_allclose(median_Lab(Lab), median_Lab(io.read_map(tmp_path / "lab.exr", "Lab")[0]), atol=0.3)
    assert np.all(np.abs(median_Lab(Lab)[1:]) < 0.3), median_Lab(Lab)
    one_line_error(run(*args, "--observer", DEFAULT_CMFS, ok=False), "tri10.npz", f"not the {DEFAULT_CMFS}")


@pytest.mark.usefixtures("dask_scheduler")  # the session's Dask cluster
def test_a_batch_of_a_plan_for_the_10_degree_observer_equals_recover_and_records_it(bench_10, tmp_path):
    import zarr

    d = bench_10
    run("batch", d / "seq10", "--plan", d / "tri10.npz", "--out", tmp_path / "b.zarr", "--outputs",
        "cube,XYZ,Lab,dE", "--delta-e-ref", "colorchecker", "--method", "CIE 1976")
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r")
    assert group.attrs["observer"] == TEN and group.attrs["illuminant"] == "D65"
    run("recover", d / "seq10", "--sequence", "1", "--out", tmp_path / "t.exr", "--lab", tmp_path / "lab.exr",
        "--delta-e-ref", "colorchecker", "--delta-e", tmp_path / "dE.exr", "--method", "CIE 1976")
    np.testing.assert_allclose(group["Lab"][1], io.read_map(tmp_path / "lab.exr", "Lab")[0], atol=1e-3)
    np.testing.assert_allclose(group["dE"][1], io.read_map(tmp_path / "dE.exr", "dE76")[0][..., 0], atol=1e-3)
    white = load_plan(d / "tri10.npz").white_XYZ("D65", TEN)
    np.testing.assert_allclose(group["Lab"][1], XYZ_to_Lab(group["XYZ"][1], white), atol=2e-3)
    one_line_error(run("batch", d / "seq10", "--plan", d / "tri10.npz", "--out", tmp_path / "c.zarr", "--outputs",
                       "XYZ", "--observer", DEFAULT_CMFS, ok=False), "tri10.npz", f"not the {DEFAULT_CMFS}")


@pytest.fixture(scope="module")
def narrowband(bench_10):
    """A reflectance plan (``nb.npz``) and one capture of the chart with it (``seqnb``)."""
    return plan_and_capture(bench_10, "nb.npz", "narrowband", "--step-nm", "50", seq="seqnb")


def test_a_reflectance_plan_makes_and_records_XYZ_for_the_observer_asked_for(narrowband, tmp_path):
    from specgpu.engine.colorimetry import reflectance_to_XYZ

    d = narrowband
    for name, extra in (("default", ()), ("ten", ("--observer", TEN))):
        run("recover", d / "seqnb", "--out", tmp_path / f"{name}.npz", "--xyz", tmp_path / f"{name}.exr",
            "--lab", tmp_path / f"{name}-lab.exr", *extra)
    cube, wl, meta = io.read_cube(tmp_path / "ten.npz")
    assert meta["observer"] == TEN and io.read_cube(tmp_path / "default.npz")[2]["observer"] == DEFAULT_CMFS
    XYZ = io.read_map(tmp_path / "ten.exr", "XYZ")[0]
    np.testing.assert_allclose(XYZ, reflectance_to_XYZ(cube, wl, "D65", TEN), atol=1e-5)
    np.testing.assert_allclose(io.read_map(tmp_path / "ten-lab.exr", "Lab")[0],
                               XYZ_to_Lab(XYZ, "D65", observer=TEN, wavelengths=wl), atol=1e-3)
    assert not np.allclose(XYZ, io.read_map(tmp_path / "default.exr", "XYZ")[0], atol=1e-3, equal_nan=True)


@pytest.mark.usefixtures("dask_scheduler")  # the session's Dask cluster
def test_a_batch_is_resumed_only_with_the_observer_it_was_made_for(narrowband, tmp_path):
    import zarr

    d = narrowband
    args = ["batch", d / "seqnb", "--plan", d / "nb.npz", "--out", tmp_path / "b.zarr", "--outputs", "XYZ"]
    run(*args, "--observer", TEN)
    assert zarr.open_group(str(tmp_path / "b.zarr"), mode="r").attrs["observer"] == TEN
    one_line_error(run(*args, ok=False), f"made with --observer {TEN}, this run gives {DEFAULT_CMFS}")
    # an output made before the observer was recorded holds colours of the 2 degree observer
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r+")
    del group.attrs["observer"]
    one_line_error(run(*args, "--observer", TEN, ok=False), f"made with --observer {DEFAULT_CMFS}, this run gives")
    run(*args)


def bare_plan(output, observer):
    """A one-frame plan of the given output, made for ``observer`` (the fields the observer rule reads)."""
    n = 3 if output in ("XYZ", "RGB") else 1
    return Plan(method="m", patterns=np.zeros((1, 4), np.int64), target_spectra=np.zeros((1, 3)),
                light_wavelengths=[1.0, 2.0, 3.0], exposure_s=1e-3, A=np.ones((n, 1)), output=output,
                output_wavelengths=[500.0] if output == "reflectance" else [],
                output_labels=tuple("XYZ"[:n]) if n == 3 else ("r",), illuminant="D65", observer=observer,
                calibration="x", rows=768, min_exposure_s=80e-6, expected_level=[0.5])


@settings(max_examples=80, deadline=None)
@given(output=st.sampled_from(["XYZ", "RGB", "reflectance", "relative"]), own=st.sampled_from(OBSERVERS),
       asked=st.one_of(st.none(), st.sampled_from(OBSERVERS), st.sampled_from(["", "CIE 2 deg", "cie_2_1931"])),
       upper=st.booleans())
def test_a_plan_resolves_the_observer_of_its_colours(output, own, asked, upper):
    plan = bare_plan(output, own)
    measured = output in ("XYZ", "RGB")
    request = None if asked is None else (asked.upper() if upper else asked)
    if asked is not None and asked not in OBSERVERS:
        with pytest.raises(ValueError, match=f"^observer '{request}' is not one of {OBSERVERS[0]}, {OBSERVERS[1]}$"):
            plan.resolve_observer(request)
        return
    if measured and asked is not None and asked != own:
        with pytest.raises(ValueError, match=f"^the plan measures {output} for the {own}, not the {asked}: "):
            plan.resolve_observer(request)
        return
    assert plan.resolve_observer(request) == (own if measured else (asked or DEFAULT_CMFS))


@pytest.mark.parametrize("k", [0.05, 0.5, 1.0])
def test_delta_E_sigma_is_relative_to_the_observers_white(k):
    """A grey at ``k`` of an observer's white, with a covariance in proportion to that white, is the same colour
    with the same spread for either observer: its dE2000 sigma is the same only when each is taken relative to
    its own observer's white."""
    from specgpu.core.spectra import white_point_XYZ
    from specgpu.planning import delta_E_sigma

    S = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 5.0]]) * 1e-6
    got = {}
    for observer in OBSERVERS:
        w = white_point_XYZ("D65", observer)
        got[observer] = delta_E_sigma(k * w, np.diag(w) @ S @ np.diag(w), "D65", observer)
    assert got[TEN] == pytest.approx(got[DEFAULT_CMFS], rel=1e-6)
    w = white_point_XYZ("D65", TEN)  # the 10 degree grey against the 2 degree white: another figure
    assert abs(delta_E_sigma(k * w, np.diag(w) @ S @ np.diag(w), "D65") - got[TEN]) > 1e-3 * got[TEN]
