"""`specgpu stream` on a rig TOML with a [hardware] table streams from the devices it names: here the simulated
DLPC900 (the plan's patterns really uploaded and decoded back) and the bench camera of ``hw_fakes`` in strobe-master
wiring, whose frames are the twin's rendering of the LUT entry the controller displays at each strobe, put in where
the GenICam camera would be opened."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from hw_fakes import FakeCamera
from stream_helpers import shared_stream_setup

from specgpu.hardware.dlpc900 import DMDLayout, SimulatedDLPC900
from specgpu.pipeline.twin_replay import offline_maps
from specgpu.rig.twin import TwinRig


@pytest.fixture(scope="module")
def setup():
    return shared_stream_setup(320, 240, sequences=1, output_step_nm=10.0)


class TwinBench:
    """Renders, at each exposure of the bench camera, the twin frame of the LUT entry the controller shows."""

    def __init__(self, sim, description, plan, scene):
        self.sim = sim
        self.layout = DMDLayout(sim.geometry, description.light.columns, description.light.rows)
        self.twin = TwinRig(plan.rig_description(description), scene=scene)
        self.twin.seed = 5
        self.loaded = False
        self.n = 0
        self.out = np.empty(self.twin.camera.shape, np.uint16)

    def __call__(self, light):
        if not self.loaded:  # what the controller really holds, decoded from the uploaded images
            self.twin.load_sequence(np.stack([self.layout.mask_to_pattern(self.sim.entry_mask(j))
                                              for j in range(self.sim.lut_entries)]))
            self.loaded = True
        self.twin.render(self.sim.position, self.n, self.n * 0.005, self.out)
        self.n += 1
        return self.out.copy()


def test_cli_stream_on_the_simulated_hardware_rig(setup, tmp_path, monkeypatch):
    import specgpu.hardware.rig as hw_rig
    from specgpu.apps.cli import main
    from specgpu.calibration.bundle import save_calibration
    from specgpu.io.recording import open_recording
    from specgpu.planning import save_plan
    from specgpu.rig.scene import colorchecker_scene

    cam = setup.description.camera
    real = hw_rig.open_hardware
    opened = []

    def with_bench_camera(description, *, hardware, patterns, calibration, exposure_s):
        sim = SimulatedDLPC900(hardware.dmd)
        scene = colorchecker_scene(cam.roi_height, cam.roi_width)
        render = TwinBench(sim, description, setup.plan, scene)
        acquirer = FakeCamera(sim, render, 10 ** 9, shape=(cam.roi_height, cam.roi_width),
                              pixel_format=f"Mono{cam.bit_depth}")
        driver = real(description, hardware=hardware, patterns=patterns, calibration=calibration,
                      acquirer=acquirer, transport=sim, exposure_s=exposure_s)
        opened.append((sim, driver))
        return driver

    monkeypatch.setattr(hw_rig, "open_hardware", with_bench_camera)
    (tmp_path / "rig.toml").write_text(
        f"[camera]\nroi_width = {cam.roi_width}\nroi_height = {cam.roi_height}\nbit_depth = {cam.bit_depth}\n"
        f"exposure_s = {cam.exposure_s!r}\nframe_rate_hz = {cam.frame_rate_hz!r}\n"
        # hardware.exposure_s is not the plan's: the plan's exposure (its dark frame and decoder) is what runs
        f"[hardware]\nlight = \"dlpc900-simulated\"\nexposure_s = {2 * cam.exposure_s!r}\n"
        "camera_first_frame_id = 1\n")
    save_calibration(tmp_path / "calib.npz", setup.bundle)
    save_plan(tmp_path / "plan.npz", setup.plan)
    result = CliRunner().invoke(main, ["stream", "--rig", str(tmp_path / "rig.toml"), "--plan",
                                       str(tmp_path / "plan.npz"), "--calib", str(tmp_path / "calib.npz"),
                                       "--scene", "colorchecker", "--seconds", "1.5", "--outputs", "XYZ,dE",
                                       "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert len(opened) == 1
    sim, driver = opened[0]
    assert sim.lut_entries == setup.plan.K and not sim.running  # the plan was uploaded; the light stopped
    assert driver.exposure_s == pytest.approx(setup.plan.exposure_s)  # camera ExposureTime: the plan's
    assert all(sim.lut[i]["exposure_us"] == round(setup.plan.exposure_s * 1e6) for i in range(sim.lut_entries))
    assert not sim.is_open  # and its USB link released
    rec = open_recording(tmp_path / "out")
    assert rec.attrs["plan_hash"] == setup.plan.hash and rec.sequences >= 2
    dE = rec.read("dE", slice(0, rec.sequences))
    # the colorchecker read back through the devices as well as the twin's own stream reads it (same plan, same
    # noise level; a frame labelled with the wrong pattern would put the median far above)
    twin = float(np.nanmedian(offline_maps(setup, 0)["dE"]))
    assert np.nanmedian(dE) < twin + 1.5
