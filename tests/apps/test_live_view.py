"""``stream --view``'s live view on a twin stream: napari's viewer model receives results from the stream's
results ring while the stream drops nothing, its layers hold the latest result, and the spectrum widget reads the
pixel of the latest cube. Skipped without the viewer extra."""

import os
import threading
import time

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("napari", reason="napari is not installed (the optional extra specgpu[viewer])")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed (the viewer extra)")

from specgpu.apps.live_view import VIEW_OUTPUTS, LiveView  # noqa: E402
from specgpu.apps.viewer_widget import SpectrumWidget  # noqa: E402
from specgpu.pipeline.sinks import CallbackSink, ResultsRing  # noqa: E402


def test_live_view_shows_the_stream_while_it_drops_nothing(qtbot):
    from napari.components import ViewerModel

    from specgpu.calibration import oracle_calibration
    from specgpu.hardware.drivers import open_rig_driver
    from specgpu.pipeline.stream import Stream
    from specgpu.planning import make_plan
    from specgpu.rig import CameraParameters, RigDescription, colorchecker_scene

    rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    bundle = oracle_calibration(rig)
    plan = make_plan("narrowband", bundle, step_nm=40.0)
    driver = open_rig_driver(rig, plan, scene=colorchecker_scene(240, 320), calibration=bundle, seed=1, pacing="paced")
    stream = Stream(driver, plan, bundle, outputs=["cube", "XYZ"])
    ring = ResultsRing(capacity=1, outputs=VIEW_OUTPUTS, policy="drop_newest")
    kept = []
    stream.sinks += [ring, CallbackSink(lambda r: kept.append((r.index, r.arrays["cube"][100, 150].copy())))]
    viewer = ViewerModel()
    view = LiveView(viewer, stream, ring, wavelengths=plan.output_wavelengths)
    widget = SpectrumWidget(viewer)
    qtbot.addWidget(widget)
    out = {}
    thread = threading.Thread(target=lambda: out.update(report=stream.run(3.0)))
    thread.start()
    while thread.is_alive():
        view.poll()
        time.sleep(0.05)
    thread.join()
    view.poll(done=True)
    report = out["report"]
    assert not report.sink_errors
    assert report.assembly.dropped == 0 and report.ring.dropped == 0  # the view cost the stream no frame
    assert view.shown >= 2 and report.sequences_out >= view.shown, (view.shown, report.sequences_out, ring.dropped,
                                                                    ring.written, len(kept), report.frames_in)
    assert view.shown + ring.dropped == len(kept)  # every result was shown or skipped, none lost
    cube = viewer.layers["reflectance"].data
    assert cube.shape == (len(plan.output_wavelengths), 240, 320)
    assert viewer.layers["sRGB (D65)"].data.shape == (240, 320, 3)
    # the layer holds one of the stream's results, and the widget reads its pixel
    shown = widget.probe.pixel((float(plan.output_wavelengths[0]), 100.0, 150.0))["values"]
    assert any(np.allclose(shown, values, rtol=1e-6) for _, values in kept)
    assert "finished" in viewer.text_overlay.text and "drops 0" in viewer.text_overlay.text


def test_stream_cli_view_runs_the_stream_through_the_live_view(monkeypatch, tmp_path):
    """``specgpu stream --view`` hands the stream to the live view (faked here: no window) and prints its
    summary; without --view the view is never opened."""
    from cli_helpers import RIG, run

    import specgpu.apps.cli.stream as cli_stream

    calls = []

    def fake_view(stream, seconds, **kwargs):
        calls.append((seconds, kwargs))
        return stream.run(seconds)

    monkeypatch.setattr(cli_stream, "run_with_view", fake_view)
    (tmp_path / "rig.toml").write_text(RIG)
    run("calibrate", "--rig", tmp_path / "rig.toml", "--out", tmp_path / "calib.npz")
    run("plan", "narrowband", "--calib", tmp_path / "calib.npz", "--out", tmp_path / "nb.npz")
    args = ["stream", "--rig", tmp_path / "rig.toml", "--plan", tmp_path / "nb.npz", "--calib",
            tmp_path / "calib.npz", "--seconds", "1", "--outputs", "cube,XYZ"]
    result = run(*args, "--view")
    assert len(calls) == 1 and calls[0][0] == 1.0
    assert list(calls[0][1]["wavelengths"]) and calls[0][1]["illuminant"] == "D65"
    assert "sequences out" in result.output
    run(*args)
    assert len(calls) == 1


def test_live_view_of_the_default_outputs_makes_the_cube_from_the_coefficients(qtbot):
    """`stream --view` with the default outputs (coefficients, XYZ, dE): the spectrum widget reads the cube the
    coefficients and the plan's basis make, and every layer names its axes."""
    from types import SimpleNamespace

    from napari.components import ViewerModel

    rng = np.random.default_rng(5)
    wl = np.arange(400.0, 701.0, 10.0)
    basis = np.linalg.qr(rng.normal(size=(wl.size, 5)))[0]
    coefficients = rng.normal(size=(24, 32, 5)).astype(np.float32)
    viewer = ViewerModel()
    view = LiveView(viewer, None, None, wavelengths=wl, basis=basis)
    widget = SpectrumWidget(viewer)
    qtbot.addWidget(widget)
    view.show(SimpleNamespace(arrays={"coefficients": coefficients, "XYZ": rng.uniform(0, 1, (24, 32, 3)),
                                      "dE": rng.uniform(0, 5, (24, 32)).astype(np.float32)}))
    assert viewer.dims.axis_labels == ("wavelength", "y", "x")
    np.testing.assert_allclose(widget.probe.pixel((400.0, 7.0, 9.0))["values"], coefficients[7, 9] @ basis.T,
                               rtol=1e-5, atol=1e-6)
    assert {layer.name for layer in viewer.layers} == {"reflectance", "sRGB (D65)", "dE"}
