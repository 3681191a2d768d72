"""The viewer's layer data (no napari needed): cubes with the wavelength axis first in nm, maps with colour maps and
limits, sequence folders and recordings read lazily with one Dask chunk per sequence, and the reader hook; the
core install stays free of Qt."""

import tomllib
from pathlib import Path

import colour
import numpy as np
import pytest
from capture_helpers import write_chart_capture
from hypothesis import given, settings
from hypothesis import strategies as st
from zarr_helpers import damaged_copy

from specgpu import io
from specgpu.apps.viewer_layers import (
    ILLUMINANTS,
    napari_get_reader,
    read_layers,
    sRGB_of_cube,
    wavelength_axis,
)
from specgpu.core.spectra import XYZ_weights

ROOT = Path(__file__).resolve().parents[2]


def by_name(layers):
    return {(k["name"] if isinstance(k["name"], str) else "+".join(k["name"])): (d, k, t) for d, k, t in layers}


@pytest.fixture
def cube_file(tmp_path):
    rng = np.random.default_rng(0)
    wl = np.arange(400.0, 701.0, 10.0)
    cube = rng.uniform(0.05, 0.9, (12, 16, wl.size)).astype(np.float32)
    path = io.write_cube(tmp_path / "c.npz", cube, wl)
    return path, cube, wl


def test_cube_layers_put_the_wavelength_first_in_nm(cube_file):
    path, cube, wl = cube_file
    layers = by_name(read_layers(path))
    data, kw, kind = layers["reflectance"]
    assert kind == "image" and data.shape == (wl.size, 12, 16)
    np.testing.assert_array_equal(data[:, 3, 5], cube[3, 5])
    assert kw["translate"][0] == 400.0 and kw["scale"][0] == 10.0 and kw["units"][0] == "nm"
    assert kw["axis_labels"] == ("wavelength", "y", "x")
    assert kw["metadata"]["specgpu"]["wavelengths"] == list(wl)
    rgb, kw_rgb, _ = layers["sRGB (D65)"]
    assert kw_rgb["rgb"] and rgb.shape == (12, 16, 3) and rgb.dtype == np.uint8


def test_sRGB_of_cube_against_colour_science_numpy_and_dask():
    import dask.array as da

    wl = np.arange(400.0, 701.0, 10.0)
    rng = np.random.default_rng(1)
    cube = rng.uniform(0, 1, (4, 5, wl.size)).astype(np.float32)
    XYZ = cube.astype(np.float64) @ XYZ_weights(wl, "A").T
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    ref = np.round(np.clip(colour.XYZ_to_sRGB(XYZ, illuminant=xy), 0, 1) * 255)
    got = sRGB_of_cube(cube, wl, "A")
    assert np.abs(got.astype(int) - ref).max() <= 1
    lazy = sRGB_of_cube(da.from_array(np.moveaxis(cube, -1, 0), chunks=(wl.size, 2, 5)), wl, "A", axis=0)
    np.testing.assert_array_equal(lazy.compute(), got)
    assert "A" in ILLUMINANTS and "D65" in ILLUMINANTS
    with pytest.raises(ValueError, match="unknown illuminant 'nope'"):
        sRGB_of_cube(cube, wl, "nope")


def test_wavelength_axis_is_nm_only_on_an_even_grid():
    assert wavelength_axis([400, 410, 420]) == (400.0, 10.0)
    assert wavelength_axis([400, 410, 430]) == (0.0, 1.0)


def test_dE_map_layer_has_its_colour_map_and_limits(tmp_path):
    de = np.linspace(0, 20, 6 * 8, dtype=np.float32).reshape(6, 8)
    path = io.write_map(tmp_path / "de.exr", de, "dE2000")
    (data, kw, kind), = read_layers(path)
    assert kw["colormap"] == "magma" and kw["contrast_limits"] == (0.0, 10.0)
    np.testing.assert_array_equal(data, de)


def test_reader_hook_accepts_specgpu_paths_only(cube_file, tmp_path):
    path, _, _ = cube_file
    assert napari_get_reader(str(path)) is not None
    assert napari_get_reader([str(path)]) is not None
    assert napari_get_reader(str(tmp_path / "x.png")) is None
    assert napari_get_reader(str(tmp_path)) is None  # a plain folder
    assert napari_get_reader([str(path), str(path)]) is None
    with pytest.raises(ValueError, match="neither a sequence folder"):
        read_layers(tmp_path)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Two sequences of the chart (narrowband, 20 nm) on the small twin, recording the scene."""
    return write_chart_capture(tmp_path_factory.mktemp("seq"), "seq", sequences=2, noise_seed=5)


def test_sequence_folder_layers_are_lazy_and_recover_each_sequence(capture):
    from specgpu.pipeline import read_capture, recover

    layers = by_name(read_layers(capture))
    data, kw, _ = layers["reflectance"]
    folder = read_capture(capture)
    assert data.shape == (len(folder.plan.output_wavelengths), 2, 240, 320)
    assert data.chunks[1] == (1, 1)  # one chunk per sequence: recovered when the slider reaches it
    assert kw["axis_labels"] == ("wavelength", "sequence", "y", "x")
    assert kw["metadata"]["specgpu"]["scene"] == "colorchecker"
    expected = recover(folder, sequence=1)
    np.testing.assert_allclose(np.asarray(data[:, 1, 100, 150]), expected[100, 150], rtol=1e-5, atol=1e-6)
    frames = layers["frames"][0]
    assert frames.shape == (folder.plan.K, 2, 240, 320)
    np.testing.assert_array_equal(np.asarray(frames[:, 0, 10, 20]), folder.frames[0, :, 10, 20])
    assert layers["sRGB (D65)"][0].shape == (2, 240, 320, 3)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 1 s stream of the small twin with the cube, dE and sigma recorded."""
    from cli_helpers import calibrated_rig, run

    d = tmp_path_factory.mktemp("rec")
    calibrated_rig(d)
    run("plan", "narrowband", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", d / "nb.npz")
    run("stream", "--rig", d / "rig.toml", "--plan", d / "nb.npz", "--calib", d / "calib.npz", "--seconds", "1",
        "--scene", "colorchecker", "--outputs", "cube,XYZ,dE,sigma", "--out", d / "REC.zarr")
    return d / "REC.zarr"


def test_recording_layers_are_dask_with_a_time_axis(recording):
    rec = io.open_recording(recording)
    n = rec.sequences
    assert n >= 1
    layers = by_name(read_layers(recording))
    cube, kw, _ = layers["reflectance"]
    wl = np.asarray(rec.group["wavelength"][:])
    assert cube.shape == (wl.size, n, 240, 320) and kw["axis_labels"][1] == "time"
    np.testing.assert_array_equal(np.asarray(cube[:, n - 1, 50, 60]), rec.read("cube", n - 1)[50, 60])
    de, kw_de, _ = layers["dE"]
    assert de.shape == (n, 240, 320) and kw_de["colormap"] == "magma"
    assert layers["sigma"][0].shape == cube.shape
    xyz, kw_xyz, _ = layers["X+Y+Z"]
    assert kw_xyz["channel_axis"] == 0 and xyz.shape == (3, n, 240, 320)
    assert layers["sRGB (D65)"][0].shape == (n, 240, 320, 3)


def test_the_core_install_has_no_qt():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = " ".join(project["dependencies"]).lower()
    assert not any(qt in core for qt in ("napari", "pyqt", "pyside", "qtpy", "pytest-qt"))
    tests = " ".join(project["optional-dependencies"]["test"]).lower()
    assert not any(qt in tests for qt in ("napari", "pyqt", "pyside", "pytest-qt"))  # pytest starts without Qt
    viewer = " ".join(project["optional-dependencies"]["viewer"]).lower()
    assert "napari" in viewer and "pyqt6" in viewer
    assert project["entry-points"]["napari.manifest"]["specgpu"] == "specgpu.apps:napari.yaml"
    assert (ROOT / "specgpu" / "apps" / "napari.yaml").is_file()


def test_cli_view_refuses_a_file_that_is_not_specgpus_in_one_line(tmp_path, monkeypatch):
    from cli_helpers import one_line_error, run

    import specgpu.apps.cli.view as cli_view

    bad = tmp_path / "notes.txt"
    bad.write_text("x")
    monkeypatch.setattr(cli_view.importlib.util, "find_spec", lambda name: object())  # as if napari were there
    one_line_error(run("view", bad, ok=False), "notes.txt", "not a specgpu cube", code=1)
    opened = []
    monkeypatch.setattr(cli_view, "open_viewer", lambda path: opened.append(path))
    run("view", tmp_path)
    assert opened == [str(tmp_path)]
    monkeypatch.setattr(cli_view.importlib.util, "find_spec", lambda name: None)
    one_line_error(run("view", tmp_path, ok=False), "pip install 'specgpu[viewer]'", code=1)


def test_XYZ_map_layers_are_its_rendering_and_three_channels(tmp_path):
    XYZ = np.random.default_rng(3).uniform(0.05, 0.9, (6, 8, 3)).astype(np.float32)
    path = io.write_map(tmp_path / "xyz.exr", XYZ, "XYZ", metadata={"illuminant": "A"})
    layers = by_name(read_layers(path))
    rgb, kw, _ = layers["sRGB (A)"]
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    ref = np.round(np.clip(colour.XYZ_to_sRGB(XYZ.astype(np.float64), illuminant=xy), 0, 1) * 255)
    assert kw["rgb"] and np.abs(rgb.astype(int) - ref).max() <= 1
    data, kw_xyz, _ = layers["X+Y+Z"]
    assert kw_xyz["channel_axis"] == 0
    np.testing.assert_array_equal(data[1], XYZ[..., 1])


@given(st.text(min_size=1, max_size=40))
@settings(max_examples=200, deadline=None)
def test_reader_hook_never_raises_on_any_path(text):
    """napari asks every plugin about every path: the hook answers None or a reader, never an exception."""
    got = napari_get_reader(text)
    assert got is None or callable(got)


@pytest.mark.parametrize("step", [10.0, 20.0])
@pytest.mark.parametrize("illuminant", ["D65", "A", "FL2"])
def test_a_perfect_white_renders_as_255_under_any_illuminant(illuminant, step):
    """The rendering adapts from the white of the cube's own weights: a reflectance of 1 is (255, 255, 255) (from
    the tabulated chromaticity FL2's white on a 10 nm grid came out (255, 255, 232))."""
    wl = np.arange(400.0, 701.0, step)
    np.testing.assert_array_equal(sRGB_of_cube(np.ones((2, 3, wl.size), np.float32), wl, illuminant),
                                  np.full((2, 3, 3), 255))


@pytest.fixture(scope="module")
def moving_folder(tmp_path_factory):
    from capture_helpers import write_moving_capture

    return write_moving_capture(tmp_path_factory.mktemp("moving"), "seqm")


def test_a_capture_that_moved_is_decoded_compensated_with_each_sequences_truth(moving_folder):
    from specgpu.apps.viewer_layers import VIEW_MOTION, motion_note

    layers = by_name(read_layers(moving_folder))
    data, kw, _ = layers["reflectance"]
    meta = kw["metadata"]["specgpu"]
    assert meta["scene"] is None and meta["motion"] == VIEW_MOTION == "global"
    assert meta["truths"] == [str(moving_folder / "motion_truth" / f"sequence_{s:04d}.npz") for s in range(2)]
    cube = np.asarray(data[:, 1])
    # compensated: the pixels some frame saw outside the field are NaN along the edges the scene moved from
    edge = np.isnan(cube[0])
    assert edge[:, :2].all() and 0 < edge.mean() < 0.2
    note = motion_note(moving_folder)
    assert "\n" not in note and "captured while the scene moved" in note and "--motion global" in note
    assert motion_note(moving_folder / "plan.npz") is None


def test_a_still_capture_keeps_its_scene_and_no_motion_note(tmp_path):
    from specgpu.apps.viewer_layers import motion_note

    folder = write_chart_capture(tmp_path, "seq", noise_seed=1)
    meta = by_name(read_layers(folder))["reflectance"][1]["metadata"]["specgpu"]
    assert meta["scene"] == "colorchecker" and meta["truths"] is None and meta["motion"] == "none"
    assert motion_note(folder) is None


def test_the_spectrum_probe_takes_the_truth_of_the_sequence_shown(tmp_path):
    from types import SimpleNamespace

    from specgpu.apps.viewer_widget import SpectrumProbe

    wl = [500.0, 600.0]
    paths = [io.write_cube(tmp_path / f"t{s}.npz", np.full((4, 6, 2), 0.1 + s / 4, np.float32), wl)
             for s in range(2)]
    layer = SimpleNamespace(metadata={"specgpu": {"role": "spectrum", "scene": None,
                                                  "truths": [str(p) for p in paths]}})
    probe = SpectrumProbe(viewer=None)
    assert [float(probe.truth(layer, (4, 6), t).reflectance[1, 2, 0]) for t in (0, 1)] == pytest.approx([0.1, 0.35])
    assert probe.truth(layer, (4, 6), None) is None


def test_a_default_recording_shows_reflectance_from_its_coefficients(default_zarr):
    """What `specgpu stream --out` records by default (coefficients, XYZ, dE): the reflectance is made from the
    coefficients and their recorded basis, with its sRGB shown and every other layer hidden, on named axes."""
    setup, path, _ = default_zarr
    rec = io.open_recording(path)
    layers = by_name(read_layers(path))
    assert set(layers) == {"sRGB (D65)", "reflectance", "X+Y+Z", "dE"}
    cube, kw, _ = layers["reflectance"]
    wl = setup.plan.output_wavelengths
    assert cube.shape == (wl.size, 3, 240, 320) and cube.chunks[1] == (1, 1, 1)
    assert kw["metadata"]["specgpu"]["wavelengths"] == list(wl)
    assert kw["translate"][0] == 400.0 and kw["scale"][0] == 10.0
    basis = rec.array("basis")[:]
    expected = rec.read("coefficients", 1) @ basis.T
    np.testing.assert_allclose(np.moveaxis(np.asarray(cube[:, 1]), 0, -1), expected, rtol=1e-5, atol=1e-6)
    rgb, kw_rgb, _ = layers["sRGB (D65)"]
    assert np.abs(np.asarray(rgb[1]).astype(int) - sRGB_of_cube(expected, wl, "D65")).max() <= 1  # float32 rounding
    assert np.asarray(rgb[1]).mean() > 20  # the chart, not a black canvas
    for name, (_, kwargs, _) in layers.items():
        labels = kwargs["axis_labels"]
        assert (labels[0] if name == "X+Y+Z" else labels)[-3:] == ("time", "y", "x"), name
        assert kwargs.get("visible", True) is (name == "sRGB (D65)"), name


def test_a_recording_without_basis_wavelengths_takes_them_from_its_plan(default_zarr, tmp_path):
    import zarr

    from specgpu.io.recording import consolidate
    from specgpu.planning import load_plan, make_plan

    setup, path, _ = default_zarr
    old = damaged_copy(path, tmp_path / "old.zarr")
    del zarr.open_group(str(old), mode="r+")["basis_wavelength"]
    consolidate(old)
    cube, kw, _ = by_name(read_layers(old))["reflectance"]
    assert kw["metadata"]["specgpu"]["wavelengths"] == list(load_plan(old / "plan.npz").output_wavelengths)
    np.testing.assert_array_equal(np.asarray(cube[:, 0, 5, 7]), np.asarray(by_name(read_layers(path))["reflectance"]
                                                                           [0][:, 0, 5, 7]))
    # another plan's copy says nothing of this basis: no reflectance, the sRGB of the recorded XYZ instead
    from specgpu.planning import save_plan

    save_plan(old / "plan.npz", make_plan("narrowband", setup.bundle, step_nm=10.0))
    layers = by_name(read_layers(old))
    assert "reflectance" not in layers
    XYZ = io.open_recording(old).read("XYZ", 2)
    from specgpu.apps.report_figures import sRGB_rendering

    np.testing.assert_array_equal(np.asarray(layers["sRGB (D65)"][0][2]), sRGB_rendering(XYZ, "D65"))


def test_the_sRGB_of_a_recordings_XYZ_adapts_from_the_white_of_its_plan(default_zarr, tmp_path):
    """Without a reflectance to render, the recorded XYZ is rendered from the white the decoder divided by (the
    plan's weights'), not from the illuminant's tabulated chromaticity."""
    import colour
    import zarr

    from specgpu.apps.viewer_layers import recorded_white_xy
    from specgpu.io.previews import sRGB8
    from specgpu.io.recording import consolidate

    setup, path, _ = default_zarr
    old = damaged_copy(path, tmp_path / "xyz.zarr")
    group = zarr.open_group(str(old), mode="r+")
    del group["coefficients"]
    group.attrs["outputs"] = [name for name in group.attrs["outputs"] if name != "coefficients"]
    consolidate(old)
    rec = io.open_recording(old)
    meta = rec.attrs["metadata"]
    xy = recorded_white_xy(rec, old, "D65", meta)
    np.testing.assert_allclose(xy, colour.XYZ_to_xy(setup.plan.white_XYZ("D65", meta.get("observer"),
                                                                         meta.get("integration") or "rectangle")))
    layers = by_name(read_layers(old))
    assert "reflectance" not in layers
    np.testing.assert_array_equal(np.asarray(layers["sRGB (D65)"][0][1]), sRGB8(rec.read("XYZ", 1), xy))


def test_a_damaged_recording_is_refused_in_one_line_naming_the_sequence(default_zarr, tmp_path):
    _, path, _ = default_zarr
    bad = damaged_copy(path, tmp_path / "bad.zarr", missing=[("dE", 1)], corrupt=[("XYZ", 2)])
    layers = by_name(read_layers(bad))
    de = layers["dE"][0]
    np.testing.assert_array_equal(np.asarray(de[0]), io.open_recording(path).read("dE", 0))
    with pytest.raises(ValueError) as missing:  # zarr alone reads it as NaN
        np.asarray(de[1])
    assert str(missing.value).startswith(f"{bad}/dE: sequence 1 ") and "missing" in str(missing.value)
    with pytest.raises(ValueError) as corrupt:  # zarr alone names neither the recording nor the sequence
        np.asarray(layers["X+Y+Z"][0][:, 2])
    assert str(corrupt.value).startswith(f"{bad}/XYZ: corrupt or unreadable chunk at sequence 2 ")
    assert "\n" not in str(missing.value) + str(corrupt.value)
    assert layers["dE"][1]["metadata"]["specgpu"]["unreadable"] == {1: "its dE chunk is missing"}


def test_a_batch_output_opens_with_the_sequences_it_computed(default_zarr):
    _, path, out = default_zarr
    assert napari_get_reader(str(out)) is not None
    layers = by_name(read_layers(out))
    assert set(layers) == {"sRGB (D65)", "reflectance", "X+Y+Z", "dE"}
    cube, kw, _ = layers["reflectance"]
    assert kw["axis_labels"] == ("wavelength", "time", "y", "x") and cube.shape[1] == 3
    assert kw["metadata"]["specgpu"]["unreadable"] == {1: "not computed yet"}
    streamed = by_name(read_layers(path))
    # the batch decodes the recorded frames as the stream did
    np.testing.assert_allclose(np.asarray(cube[:, 2]), np.asarray(streamed["reflectance"][0][:, 2]), rtol=1e-4,
                               atol=1e-5)
    np.testing.assert_allclose(np.asarray(layers["X+Y+Z"][0][:, 0]), np.asarray(streamed["X+Y+Z"][0][:, 0]),
                               rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match=r"out\.zarr/dE: sequence 1 is not computed yet"):
        np.asarray(layers["dE"][0][1])
