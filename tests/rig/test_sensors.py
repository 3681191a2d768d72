"""Camera presets (specgpu.rig.sensors): data-sheet figures, the rig TOML's preset key, any sensor size."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from specgpu.rig import sensors
from specgpu.rig.camera import Camera, CameraParameters
from specgpu.rig.config import dump_rig, rig_from_dict
from specgpu.rig.light import LightParameters, ProgrammableLight


@pytest.mark.parametrize("name, size, bits, full_well, read_noise, fps", [
    ("paper", (640, 480), 10, 35500.0, 14.0, 200.0),
    ("cmv4000", (2048, 2048), 10, 13500.0, 13.0, 180.0),  # ams DS000728: 180 fps at 10 bit, full resolution
    ("imx250", (2448, 2048), 12, 10700.0, 1.8, 57.8),  # Genie Nano M2450: 8.333 us x (2048 + 28) lines
    ("imx304", (4096, 3000), 12, 10700.0, 1.8, 23.8),
])
def test_presets_carry_their_data_sheet_figures(name, size, bits, full_well, read_noise, fps):
    p = sensors.camera_preset(name)
    assert (p.sensor_width, p.sensor_height) == size == (p.roi_width, p.roi_height)
    assert p.bit_depth == bits and p.full_well_e == full_well and p.read_noise_e == read_noise
    assert p.max_frame_rate_hz == pytest.approx(fps, abs=0.05)
    assert p.frame_rate_hz <= p.max_frame_rate_hz and p.exposure_s <= 1 / p.frame_rate_hz


def test_paper_camera_stays_the_default():
    assert sensors.camera_preset("paper") == CameraParameters()
    assert rig_from_dict({}).camera == CameraParameters()


def test_toml_preset_with_overrides_round_trips():
    desc = rig_from_dict({"camera": {"preset": "CMV4000", "roi_width": 1024, "roi_height": 768}}, source="rig.toml")
    cam = desc.camera
    assert (cam.sensor_width, cam.sensor_height, cam.roi_width, cam.roi_height) == (2048, 2048, 1024, 768)
    assert cam.full_well_e == 13500.0 and cam.pixel_pitch_um == 5.5
    assert cam.max_frame_rate_hz > 180.0  # a smaller ROI reads faster
    import tomllib

    again = rig_from_dict(tomllib.loads(dump_rig(desc)))
    assert again.camera == cam


def test_bad_preset_and_roi_beyond_the_sensor_are_one_line_errors():
    with pytest.raises(ValueError, match=r"^rig\.toml: camera\.preset 'imx999' is unknown \(choose from paper, "
                                         r"cmv4000, imx250, imx304\)$"):
        rig_from_dict({"camera": {"preset": "imx999"}}, source="rig.toml")
    with pytest.raises(ValueError, match=r"camera\.preset must be a name"):
        rig_from_dict({"camera": {"preset": 3}}, source="rig.toml")
    with pytest.raises(ValueError, match=r"camera\.roi must be between 320 x 240 and 2048 x 2048 pixels .*got "
                                         r"2448 x 2048") as info:
        sensors.camera_preset("cmv4000", roi_width=2448)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"camera\.frame_rate_hz = 90 exceeds the 23\.8 fps"):
        sensors.camera_preset("imx304", frame_rate_hz=90.0)


@pytest.mark.parametrize("size, sensor", [((640, 480), (640, 480)), ((320, 240), (640, 480)),
                                          ((2048, 2048), (2048, 2048)), ((2448, 2048), (2448, 2048)),
                                          ((1920, 1080), (2048, 2048)), ((4096, 3000), (4096, 3000)),
                                          ((4096, 4096), (4096, 4096))])
def test_camera_for_any_size(size, sensor):
    cam = sensors.camera_for_size(*size)
    assert (cam.roi_width, cam.roi_height) == size and (cam.sensor_width, cam.sensor_height) == sensor
    assert cam.frame_rate_hz <= cam.max_frame_rate_hz * (1 + 1e-9)


@given(w=st.integers(320, 5000), h=st.integers(240, 5000))
def test_camera_for_size_property(w, h):
    cam = sensors.camera_for_size(w, h)
    assert (cam.roi_width, cam.roi_height) == (w, h)
    assert w <= cam.sensor_width and h <= cam.sensor_height
    assert 0 < cam.exposure_s <= 1 / cam.frame_rate_hz


def test_a_preset_camera_exposes_frames_of_its_roi():
    params = sensors.camera_preset("imx250", roi_width=640, roi_height=480)
    cam = Camera(params, seed=3)
    assert cam.shape == (480, 640) and cam.prnu.shape == (480, 640)
    frame = cam.expose(np.full(cam.shape, 5000.0, np.float32), np.random.default_rng(0))
    assert frame.dtype == np.uint16 and frame.max() <= params.max_code
    # mean DN of a 5000 e- signal: (signal + pedestal + dark) / gain, within the noise of 307200 pixels
    expected = (5000.0 + params.pedestal_e + params.dark_current_e_per_s * params.exposure_s) / params.gain_e_per_dn
    assert frame.mean() == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize("name", [n for n in sensors.PRESETS if n != "paper"])
def test_every_preset_frames_the_paper_object_field_inside_the_light_spot(name):
    cam = sensors.PRESETS[name]
    paper = CameraParameters()
    longer = max(cam.sensor_width, cam.sensor_height)
    assert longer * cam.object_pixel_um == pytest.approx(paper.sensor_width * paper.object_pixel_um)
    # the paper's light spot then lights the sensor's corners as it lights the paper's (over half the centre's)
    light = ProgrammableLight(LightParameters())
    corner = light.field_profile(cam.sensor_height, cam.sensor_width, cam.object_pixel_um * 1e-3)[0, 0]
    assert corner > 0.5


@pytest.mark.parametrize("size", [(5000, 400), (400, 5000), (4500, 4500)])
def test_a_camera_for_a_size_beyond_every_preset_frames_the_same_field(size):
    cam = sensors.camera_for_size(*size)
    assert max(size) * cam.object_pixel_um == pytest.approx(sensors.OBJECT_FIELD_MM * 1e3)
    light = ProgrammableLight(LightParameters())  # a tall sensor is framed by its height: its corners are lit
    assert light.field_profile(size[1], size[0], cam.object_pixel_um * 1e-3)[0, 0] > 0.5
