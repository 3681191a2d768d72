"""The plugin in napari's own viewer (the `make_napari_viewer` fixture, with its OpenGL canvas): napari finds
specgpu's reader through the manifest, opens a cube with its wavelength axis, and the spectrum dock widget shows the
spectrum of the pixel under the cursor. The canvas needs a display (Xvfb in CI: `xvfb-run`); without one, or
without the viewer extra (pip install 'specgpu[viewer]'), the tests are skipped with the reason."""

import os

import numpy as np
import pytest

if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
    pytest.skip("no display for napari's OpenGL canvas (run under xvfb-run)", allow_module_level=True)
pytest.importorskip("napari", reason="napari is not installed (the optional extra specgpu[viewer])")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed (the viewer extra)")

from specgpu import io  # noqa: E402
from specgpu.apps.viewer_widget import SpectrumWidget  # noqa: E402


@pytest.fixture
def cube_file(tmp_path):
    rng = np.random.default_rng(4)
    wl = np.arange(400.0, 701.0, 10.0)
    cube = rng.uniform(0.05, 0.9, (20, 28, wl.size)).astype(np.float32)
    return io.write_cube(tmp_path / "cube.npz", cube, wl), cube, wl


def test_napari_opens_a_cube_through_the_plugin_and_the_dock_shows_a_pixel(make_napari_viewer, cube_file):
    path, cube, wl = cube_file
    viewer = make_napari_viewer(show=False)
    layers = viewer.open(str(path), plugin="specgpu")
    assert layers and viewer.dims.axis_labels[-3:] == ("wavelength", "y", "x")
    assert [layer.name for layer in viewer.layers] == ["sRGB (D65)", "reflectance"]
    assert viewer.layers["reflectance"].data.shape == (wl.size, 20, 28) and viewer.layers["sRGB (D65)"].rgb
    widget = SpectrumWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Spectrum")
    viewer.cursor.position = (550.0, 11.0, 5.0)  # wavelength (nm), y, x
    widget.on_move()
    np.testing.assert_allclose(widget.figure.axes[0].lines[-1].get_ydata(), cube[11, 5])
    assert "x 5, y 11" in widget.status.text()


def test_napari_opens_a_default_recording_through_the_plugin(make_napari_viewer, default_zarr):
    """napari's own File > Open on what `specgpu stream --out` records by default: named axes, the sRGB of the
    reflectance made from the coefficients, and the dock's spectrum of that reflectance."""
    _, path, _ = default_zarr
    rec = io.open_recording(path)
    viewer = make_napari_viewer(show=False)
    viewer.open(str(path), plugin="specgpu")
    assert viewer.dims.axis_labels == ("wavelength", "time", "y", "x")
    assert [layer.name for layer in viewer.layers] == ["sRGB (D65)", "reflectance", "X", "Y", "Z", "dE"]
    t = viewer.dims.current_step[1]
    assert np.asarray(viewer.layers["sRGB (D65)"].data[t]).mean() > 20  # the chart, not a black canvas
    widget = SpectrumWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Spectrum")
    viewer.cursor.position = (550.0, float(t), 60.0, 80.0)  # wavelength (nm), time, y, x
    widget.on_move()
    np.testing.assert_allclose(widget.figure.axes[0].lines[-1].get_ydata(),
                               rec.read("coefficients", t)[60, 80] @ rec.array("basis")[:].T, rtol=1e-5, atol=1e-6)
    assert widget.status.text() == f"x 80, y 60, sequence {t}"


def test_specgpu_view_names_the_damaged_sequences_and_opens_on_a_whole_one(default_zarr, tmp_path, capsys):
    from zarr_helpers import damaged_copy

    from specgpu.apps.viewer_widget import open_viewer

    _, path, _ = default_zarr
    bad = damaged_copy(path, tmp_path / "bad.zarr", missing=[("coefficients", 1)])
    viewer = open_viewer(bad, show=False, run=False)
    try:
        note = (f"{bad}: sequence 1 is damaged (its coefficients chunk is missing); the viewer refuses what is "
                "missing there")
        assert capsys.readouterr().err.strip() == f"specgpu: {note}"
        assert viewer.status == note and viewer.dims.current_step[1] == 0
        assert viewer.dims.axis_labels == ("wavelength", "time", "y", "x")
    finally:
        viewer.close()
