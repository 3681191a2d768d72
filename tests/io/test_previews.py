"""specgpu.io.previews: the sRGB preview against colour-science and the colour-difference heat map PNG."""

from __future__ import annotations

import colour
import matplotlib
import numpy as np
import pytest
from file_helpers import (
    no_temp_files,
    raises_one_line,
)

from specgpu import io
from specgpu.io.previews import MIN_BAR_HEIGHT


# ---- previews --------------------------------------------------------------------------------------------------------
def test_sRGB_preview_adapts_from_the_given_illuminant(tmp_path):
    xy_a = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    white_a = np.broadcast_to(colour.xy_to_XYZ(xy_a) * 0.9, (2, 2, 3))
    io.write_sRGB_preview(tmp_path / "a.png", white_a, exposure=0.0, illuminant=xy_a)
    neutral = io.read_png(tmp_path / "a.png")[0]
    assert np.ptp(neutral.astype(int), axis=-1).max() <= 1  # the white of A renders neutral
    io.write_sRGB_preview(tmp_path / "b.png", white_a, exposure=0.0)
    warm = io.read_png(tmp_path / "b.png")[0][0, 0].astype(int)
    assert warm[0] - warm[2] > 50  # unadapted, A's white is orange


def test_sRGB_preview_matches_colour_science(tmp_path):
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    rng = np.random.default_rng(4)
    xyz = rng.random((6, 8, 3)) * 0.8
    xyz[0, 0] = d65            # the perfect diffuser: white
    xyz[0, 1] = d65 * 0.18     # 18 % grey
    xyz[0, 2] = np.nan         # NaN renders black
    io.write_sRGB_preview(tmp_path / "p.png", xyz, exposure=0.0, metadata={"scene": "chart"})
    rgb, meta = io.read_png(tmp_path / "p.png")
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint8
    expected = np.round(np.clip(colour.XYZ_to_sRGB(np.nan_to_num(xyz)), 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(rgb, expected)
    assert tuple(rgb[0, 0]) == (255, 255, 255) and tuple(rgb[0, 2]) == (0, 0, 0)
    assert abs(int(rgb[0, 1, 1]) - 118) <= 1  # sRGB code of 18 % grey
    assert float(meta["specgpu:exposure_EV"]) == 0.0 and meta["scene"] == "chart"
    # +1 EV doubles the linear values; "auto" brings the 99th percentile of Y to 1.
    io.write_sRGB_preview(tmp_path / "p1.png", xyz, exposure=1.0)
    np.testing.assert_array_equal(
        io.read_png(tmp_path / "p1.png")[0],
        np.round(np.clip(colour.XYZ_to_sRGB(np.nan_to_num(xyz) * 2), 0, 1) * 255).astype(np.uint8))
    io.write_sRGB_preview(tmp_path / "pa.png", xyz * 0.1)
    ev = float(io.read_png(tmp_path / "pa.png")[1]["specgpu:exposure_EV"])
    assert 2.0 ** ev * np.nanpercentile(xyz[..., 1] * 0.1, 99) == pytest.approx(1.0)
    with raises_one_line(ValueError, r"q\.png: exposure must be a number of stops or 'auto', got 'bright'"):
        io.write_sRGB_preview(tmp_path / "q.png", xyz, exposure="bright")
    with raises_one_line(ValueError, r"q\.png: XYZ must have shape \(H, W, 3\), got \(6, 8\)"):
        io.write_sRGB_preview(tmp_path / "q.png", xyz[..., 0])
    assert no_temp_files(tmp_path)


def test_delta_E_heat_map_png(tmp_path):
    dE = np.array([[0.0, 2.5, 5.0], [10.0, np.nan, 1.0]])
    io.write_delta_E_png(tmp_path / "d.png", dE, vmax=5.0, colormap="viridis")
    rgb, meta = io.read_png(tmp_path / "d.png")
    lut = np.round(matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    assert tuple(rgb[0, 0]) == tuple(lut[0]) and tuple(rgb[0, 2]) == tuple(lut[255])
    assert tuple(rgb[1, 0]) == tuple(lut[255])           # above vmax clips
    assert tuple(rgb[0, 1]) == tuple(lut[128])           # 2.5 / 5 -> middle (127.5 rounds to 128)
    assert tuple(rgb[1, 1]) == (128, 128, 128)           # NaN grey
    assert meta["specgpu:quantity"] == "dE2000" and meta["specgpu:colormap"] == "viridis"
    assert float(meta["specgpu:vmin"]) == 0.0 and float(meta["specgpu:vmax"]) == 5.0
    io.write_delta_E_png(tmp_path / "auto.png", dE, quantity="dE76")
    meta = io.read_png(tmp_path / "auto.png")[1]
    assert float(meta["specgpu:vmax"]) == 10.0 and meta["specgpu:quantity"] == "dE76"
    with raises_one_line(ValueError, r"j\.png: unknown colormap 'jet'; valid colormaps: magma, inferno"):
        io.write_delta_E_png(tmp_path / "j.png", dE, colormap="jet")
    with raises_one_line(ValueError, r"j\.png: vmax must be finite and > 0"):
        io.write_delta_E_png(tmp_path / "j.png", dE, vmax=0)


def test_delta_E_heat_map_carries_its_colour_bar_beside_the_map(tmp_path):
    dE = np.linspace(0.0, 12.0, 240 * 320).reshape(240, 320)
    dE[:10, :10] = np.nan
    io.write_delta_E_png(tmp_path / "d.png", dE, vmax=10.0, colormap="viridis")
    rgb, meta = io.read_png(tmp_path / "d.png")
    lut = np.round(matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    assert rgb.shape[0] == 240 and rgb.shape[1] > 320 + 40  # the map, then the bar to its right
    assert (int(meta["specgpu:map_width"]), int(meta["specgpu:map_height"])) == (320, 240)
    assert "colour bar" in meta["ImageDescription"]
    index = np.round(np.clip(np.nan_to_num(dE) / 10.0, 0, 1) * 255).astype(int)
    expected = np.where(np.isnan(dE)[..., None], np.uint8(128), lut[index])
    np.testing.assert_array_equal(rgb[:, :320], expected)  # the map's pixels are where they were, unscaled
    panel = rgb[:, 320:].astype(int)
    distance = np.abs(panel[:, :, None, :] - lut[None, None].astype(int)).sum(axis=-1)  # (H, w, 256)
    on_scale = distance.min(axis=-1) <= 6
    column = int(np.argmax(on_scale.sum(axis=0)))  # the bar: the column most of whose pixels are the colormap's
    rows = np.nonzero(on_scale[:, column])[0]
    level = distance[rows, column].argmin(axis=-1)
    assert rows.size > 0.6 * 240  # the bar spans most of the height
    assert level[0] > 240 and level[-1] < 16 and rows[0] < 0.2 * 240 and rows[-1] > 0.8 * 240  # vmax on top, 0 below
    assert (np.diff(level) <= 2).all()  # the scale runs down without a jump back
    assert (panel.sum(axis=-1) < 100).sum() > 100  # its numbers and its quantity, in black
    assert (np.abs(panel - 128).sum(axis=-1) == 0).sum() > 50  # the grey of NaN pixels is drawn in


def test_a_small_heat_map_gets_a_readable_bar_and_can_go_without(tmp_path):
    dE = np.array([[0.0, 2.5], [5.0, 1.0]])
    io.write_delta_E_png(tmp_path / "d.png", dE)
    rgb = io.read_png(tmp_path / "d.png")[0]
    assert rgb.shape[0] == MIN_BAR_HEIGHT and (rgb[2:, :2] == 255).all()  # the map at the top left, then white
    io.write_delta_E_png(tmp_path / "bare.png", dE, colorbar=False)
    assert io.read_png(tmp_path / "bare.png")[0].shape == (2, 2, 3)
