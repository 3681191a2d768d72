"""The napari viewer with Qt offscreen: the readers' layers in napari's viewer model (named axes), the spectrum
widget (a real Qt widget, through pytest-qt) with its pixel and region spectra against NumPy, the truth and sigma it
finds, the illuminant choice re-rendering the sRGB layer, and the npe2 manifest. Skipped without the viewer extra
(pip install 'specgpu[viewer]'). napari's model is the viewer without its OpenGL canvas, which Qt's offscreen
platform cannot give; the widget reads nothing else of the viewer."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

napari = pytest.importorskip("napari", reason="napari is not installed (the optional extra specgpu[viewer])")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed (the test extra)")

from zarr_helpers import damaged_copy  # noqa: E402

from specgpu import io  # noqa: E402
from specgpu.apps.viewer_layers import read_layers, sRGB_of_cube  # noqa: E402
from specgpu.apps.viewer_widget import SpectrumWidget, add_layers, unreadable_note  # noqa: E402


@pytest.fixture
def make_viewer(qtbot):
    """napari's viewer model, the widgets made on it kept alive by pytest-qt until the test ends."""
    from napari.components import ViewerModel

    made = []

    def make():
        made.append(ViewerModel())
        return made[-1]

    yield make


def widget_for(qtbot, viewer):
    widget = SpectrumWidget(viewer)
    qtbot.addWidget(widget)
    return widget


@pytest.fixture
def cube_file(tmp_path):
    rng = np.random.default_rng(0)
    wl = np.arange(400.0, 701.0, 10.0)
    cube = rng.uniform(0.05, 0.9, (24, 32, wl.size)).astype(np.float32)
    return io.write_cube(tmp_path / "c.npz", cube, wl), cube, wl


def test_widget_shows_the_spectrum_of_the_pixel_under_the_cursor(make_viewer, qtbot, cube_file):
    path, cube, wl = cube_file
    viewer = make_viewer()
    add_layers(viewer, read_layers(path))
    assert viewer.dims.axis_labels == ("wavelength", "y", "x")
    widget = widget_for(qtbot, viewer)
    world = (550.0, 7.0, 19.0)  # wavelength (nm), y, x
    result = widget.probe.pixel(world)
    np.testing.assert_array_equal(result["values"], cube[7, 19])
    np.testing.assert_array_equal(result["wavelengths"], wl)
    assert result["sigma"] is None and result["truth"] is None
    viewer.cursor.position = world
    widget.on_move()
    line = widget.figure.axes[0].lines[-1]
    np.testing.assert_allclose(line.get_ydata(), cube[7, 19])
    assert "x 19, y 7" in widget.status.text()


def test_widget_region_mean_and_std_against_numpy(make_viewer, qtbot, cube_file):
    path, cube, _ = cube_file
    viewer = make_viewer()
    add_layers(viewer, read_layers(path))
    de = np.abs(np.random.default_rng(2).normal(2, 1, (24, 32))).astype(np.float32)
    viewer.add_image(de, name="dE", metadata={"specgpu": {"role": "dE"}})
    viewer.add_shapes([np.array([[4, 6], [4, 15], [11, 15], [11, 6]])], shape_type="rectangle", name="region")
    widget = widget_for(qtbot, viewer)
    widget.on_region()
    result = widget.probe.region(viewer.layers["region"])
    got = np.asarray(viewer.layers["region"].to_masks(mask_shape=(24, 32))[0], bool)  # the mask the probe uses
    assert got[5:11, 7:15].all() and not got[:3].any() and not got[13:].any() and not got[:, :5].any()
    np.testing.assert_allclose(result["values"], cube[got].mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(result["std"], cube[got].std(axis=0), rtol=1e-5)
    assert result["dE"]["mean"] == pytest.approx(float(de[got].mean()), rel=1e-6)
    assert result["pixels"] == int(got.sum()) > 40
    assert "ΔE00 mean" in widget.status.text()


def test_widget_illuminant_choice_re_renders_the_sRGB_layer(make_viewer, qtbot, cube_file):
    path, cube, wl = cube_file
    viewer = make_viewer()
    add_layers(viewer, read_layers(path))
    widget = widget_for(qtbot, viewer)
    widget.illuminants.setCurrentText("A")
    rgb = viewer.layers["sRGB (A)"]
    np.testing.assert_array_equal(np.asarray(rgb.data), sRGB_of_cube(cube, wl, "A"))


def test_sequence_folder_in_the_viewer_with_truth_and_time_slider(make_viewer, qtbot, tmp_path):
    from specgpu.calibration import oracle_calibration, save_calibration
    from specgpu.pipeline import capture_plan, read_capture, recover, write_capture
    from specgpu.planning import make_plan, save_plan
    from specgpu.rig import CameraParameters, RigDescription, colorchecker_scene

    rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    bundle = oracle_calibration(rig)
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    scene = colorchecker_scene(240, 320)
    res = capture_plan(rig, plan, scene, sequences=2, noise_seed=9, calibration=bundle)
    save_plan(tmp_path / "plan.npz", plan)
    save_calibration(tmp_path / "calibration.npz", bundle)
    seq = write_capture(tmp_path / "seq", res.sequences, res.assembly, tmp_path / "plan.npz",
                        tmp_path / "calibration.npz", metadata={"scene": "colorchecker"})
    viewer = make_viewer()
    add_layers(viewer, read_layers(seq))
    assert viewer.dims.axis_labels == ("wavelength", "sequence", "y", "x")
    viewer.dims.set_point(1, 1)  # the second sequence
    widget = widget_for(qtbot, viewer)
    wl0 = float(plan.output_wavelengths[0])
    result = widget.probe.pixel((wl0, 1.0, 120.0, 100.0))
    assert result["t"] == 1
    np.testing.assert_allclose(result["values"], recover(read_capture(seq), sequence=1)[120, 100], rtol=1e-5,
                               atol=1e-6)
    truth_wl, truth = result["truth"]
    np.testing.assert_array_equal(truth, scene.reflectance[120, 100])


def test_sigma_layer_gives_the_band(make_viewer, qtbot, cube_file):
    path, cube, wl = cube_file
    viewer = make_viewer()
    add_layers(viewer, read_layers(path))
    sigma = np.full((wl.size, 24, 32), 0.02, np.float32)
    viewer.add_image(sigma, name="sigma", metadata={"specgpu": {"role": "sigma"}},
                     translate=(400.0, 0, 0), scale=(10.0, 1, 1))
    widget = widget_for(qtbot, viewer)
    viewer.cursor.position = (400.0, 3.0, 3.0)
    widget.on_move()
    band = widget.figure.axes[0].collections[0].get_paths()[0].vertices[:, 1]
    assert band.max() == pytest.approx(float(cube[3, 3].max()) + 0.02, abs=1e-6)


def test_manifest_is_valid_and_names_the_reader_and_widget():
    from pathlib import Path

    from npe2 import PluginManifest

    import specgpu.apps

    manifest = PluginManifest.from_file(Path(specgpu.apps.__file__).parent / "napari.yaml")
    assert manifest.name == "specgpu"
    commands = {c.id: c.python_name for c in manifest.contributions.commands}
    assert commands["specgpu.get_reader"] == "specgpu.apps.viewer_layers:napari_get_reader"
    assert commands["specgpu.spectrum_widget"] == "specgpu.apps.viewer_widget:SpectrumWidget"
    assert manifest.contributions.readers[0].accepts_directories


def test_a_default_recording_opens_on_named_axes_with_a_spectrum(make_viewer, qtbot, default_zarr):
    """`specgpu view REC.zarr` on what `specgpu stream --out` records by default: axes named, the sRGB shown, the
    dock showing the centre pixel's spectrum (from the coefficients), which follows the time slider."""
    _, path, _ = default_zarr
    rec = io.open_recording(path)
    basis = rec.array("basis")[:]
    viewer = make_viewer()
    add_layers(viewer, read_layers(path))
    assert viewer.dims.axis_labels == ("wavelength", "time", "y", "x")
    assert [layer.name for layer in viewer.layers if layer.visible] == ["sRGB (D65)"]
    widget = widget_for(qtbot, viewer)
    t = viewer.dims.current_step[1]
    np.testing.assert_allclose(widget.figure.axes[0].lines[-1].get_ydata(),
                               rec.read("coefficients", t)[119, 159] @ basis.T, rtol=1e-5, atol=1e-6)
    assert widget.status.text() == f"x 159, y 119, sequence {t}"
    viewer.dims.set_current_step(1, 2)
    np.testing.assert_allclose(widget.figure.axes[0].lines[-1].get_ydata(),
                               rec.read("coefficients", 2)[119, 159] @ basis.T, rtol=1e-5, atol=1e-6)
    assert widget.status.text() == "x 159, y 119, sequence 2"


def test_the_viewer_opens_on_a_whole_sequence_and_refuses_the_damaged_one(make_viewer, qtbot, default_zarr,
                                                                        tmp_path):
    _, path, _ = default_zarr
    # napari opens at the middle step: sequence 1 of 3, whose coefficients are gone
    bad = damaged_copy(path, tmp_path / "bad.zarr", missing=[("coefficients", 1)])
    viewer = make_viewer()
    added = add_layers(viewer, read_layers(bad))
    assert viewer.dims.current_step[1] == 0 and viewer.layers["sRGB (D65)"].visible
    assert unreadable_note(bad, added) == (f"{bad}: sequence 1 is damaged (its coefficients chunk is missing); the "
                                           "viewer refuses what is missing there")
    widget = widget_for(qtbot, viewer)
    with pytest.raises(ValueError, match=r"bad\.zarr/coefficients: sequence 1 is committed but its chunk"):
        viewer.dims.set_current_step(1, 1)
    viewer.cursor.position = tuple(viewer.dims.point[:-2]) + (5.0, 5.0)
    widget.on_move()  # the dock names the refusal there too
    assert widget.status.text().startswith(f"{bad}/coefficients: sequence 1 is committed but its chunk")


def test_a_corrupt_chunk_where_the_viewer_opens_moves_it_to_a_whole_sequence(make_viewer, default_zarr, tmp_path):
    _, path, _ = default_zarr
    bad = damaged_copy(path, tmp_path / "bad.zarr", corrupt=[("coefficients", 1)])  # found only by reading it
    viewer = make_viewer()
    added = add_layers(viewer, read_layers(bad))
    assert viewer.dims.current_step[1] == 0 and viewer.layers["sRGB (D65)"].visible
    assert unreadable_note(bad, added) == (f"{bad}: sequence 1 is damaged (its coefficients chunk cannot be read); "
                                           "the viewer refuses what is missing there")
    no_dE = damaged_copy(path, tmp_path / "no-dE.zarr", missing=[("dE", i) for i in range(3)])
    viewer = make_viewer()
    add_layers(viewer, read_layers(no_dE))  # the dE layer is hidden: every sequence's sRGB can be shown
    assert viewer.dims.current_step[1] == 1 and viewer.layers["sRGB (D65)"].visible
    gone = damaged_copy(path, tmp_path / "gone.zarr", missing=[("coefficients", i) for i in range(3)])
    with pytest.raises(ValueError) as refused:
        add_layers(make_viewer(), read_layers(gone))
    assert str(refused.value) == (f"{gone}: no sequence can be shown, every one is damaged (sequence 0: its "
                                  "coefficients chunk is missing, ...)")
