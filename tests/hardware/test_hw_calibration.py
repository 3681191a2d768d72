"""`calibrate` on the hardware path, in CI without hardware.

The rig is the real driver stack: the DLPC900 light over the simulated controller (USB reports, LUT, uploaded
images decoded back), a GenICam camera driver through ring buffer and assembler, and an Ocean spectrometer driver.
Only the optics are faked, from the twin's physics and from what the controller really displays: the fake camera
(a harvesters-like acquirer) strobes the controller on each exposure and renders the twin's frame of the LUT entry
on display, at the exposure written to its ExposureTime feature; the fake seabreeze device reads the twin light's
spectrum of the mirrors on display (plus a dark offset the spectrometer's dark reading must remove).
"""

from __future__ import annotations

import numpy as np
import pytest

from hw_fakes import Buffer, NodeMap, TimeoutException
from specgpu.calibration import CalibrationRig, calibrate, oracle_calibration
from specgpu.calibration.rigs import twin_at_exposure
from specgpu.hardware.dlpc900 import DMDLayout, SimulatedDLPC900
from specgpu.hardware.errors import BackendMissing
from specgpu.hardware.rig import open_calibration_rig, open_hardware
from specgpu.planning.plans import make_plan
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.light import ProgrammableLight
from specgpu.rig.scene import white_plate_scene

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
WHITE = 0.99
DARK_COUNTS = 800.0


class TwinCamera:
    """A free-running GenICam camera (strobe-master) whose frames are the twin's, lit by the controller's display.

    At start it reads the exposure from its ExposureTime feature and the controller's LUT (each entry's mirrors
    decoded back to mirror counts); each exposure's strobe is a TRIG_IN_1 edge, and the frame is the twin's
    rendering of the entry now on display. Frame ids start at 1 (GigE Vision); ``lost`` exposures are made but
    never delivered.
    """

    def __init__(self, sim, description=DESC, *, lost=()):
        cam = description.camera
        self.sim, self.description = sim, description
        self.layout = DMDLayout(sim.geometry, description.light.columns, description.light.rows)
        self.scene = white_plate_scene(cam.roi_height, cam.roi_width, reflectance=WHITE)
        self.remote_device = type("Remote", (), {"node_map": NodeMap(cam.roi_height, cam.roi_width,
                                                                     f"Mono{cam.bit_depth}")})()
        self.lost = set(lost)
        self.starts = 0
        self.started = False
        self._twins = {}
        self.exposures = []

    def start(self):
        nm = self.remote_device.node_map
        assert (nm.TriggerMode.value, nm.LineSource.value) == ("Off", "ExposureActive")  # strobe-master wiring
        t = float(nm.ExposureTime.value) * 1e-6
        if t not in self._twins:
            self._twins[t] = twin_at_exposure(self.description, self.scene, t)
        self.twin = self._twins[t]
        lut = [self.layout.mask_to_pattern(self.sim.entry_mask(j)) for j in range(self.sim.lut_entries)]
        assert all(self.sim.lut[j]["exposure_us"] == round(t * 1e6) for j in range(len(lut)))  # light follows
        self.twin.load_sequence(np.stack(lut))
        self.twin.seed = 1000 + self.starts  # fresh temporal noise for every capture, as a real sensor
        self.starts += 1
        self.exposures.append(t)
        self.n, self.started = 0, True
        self.out = np.empty(self.twin.camera.shape, np.uint16)

    def stop(self):
        self.started = False

    def fetch(self, timeout=None):
        while True:
            if not self.started:
                raise TimeoutException("no buffer")
            n = self.n
            self.n += 1
            position = self.sim.trigger_in()  # the exposure's strobe edge shows the next entry
            if position < 0:
                raise TimeoutException("sequencer stopped")
            self.twin.render(position, n, n * 0.011, self.out)
            if n not in self.lost:
                return Buffer(self.out.copy(), 1 + n, 1_000_000 + n * 11_000_000)


class TwinSeaBreeze:
    """A seabreeze-like spectrometer: the twin light's spectral irradiance of the mirrors the controller displays,
    sampled on the instrument's pixels, in counts (through the inverse of ``CAL``) plus a dark offset."""

    def __init__(self, sim, description=DESC, cal=1.0):
        self.sim = sim
        self.layout = DMDLayout(sim.geometry, description.light.columns, description.light.rows)
        self.model = ProgrammableLight(description.light, seed=description.seed)
        self.pixels = np.linspace(340.0, 830.0, 1961)
        self.cal = cal
        self.t = 0.1
        self.rng = np.random.default_rng(7)
        self.closed = False

    def wavelengths(self):
        return self.pixels

    def integration_time_micros(self, us):
        self.t = us * 1e-6

    def intensities(self, correct_dark_counts=True, correct_nonlinearity=True):
        mask = self.sim.displayed_mask()
        spd = (self.model.pattern_to_spectrum(self.layout.mask_to_pattern(mask)) if mask.any()
               else np.zeros(self.model.wavelengths.shape))
        irr = np.interp(self.pixels, self.model.wavelengths, spd, left=0.0, right=0.0)
        counts = irr * self.t / self.cal + DARK_COUNTS
        return counts + self.rng.normal(0.0, 0.5, counts.shape)

    def close(self):
        self.closed = True


def _cal():
    """An irradiance calibration scale putting the all-on spectrum at about 30000 counts in 0.1 s."""
    return float(ProgrammableLight(DESC.light).max_spectrum.max()) * 0.1 / 30000.0


def _table(tmp_path, **extra):
    csv = tmp_path / "irradiance_cal.csv"
    csv.write_text("\n".join(f"{wl:g},{_cal():.9g}" for wl in (330.0, 850.0)) + "\n")
    return {"light": "dlpc900-simulated", "spectrometer": "ocean", "spectrometer_calibration": str(csv),
            "camera_first_frame_id": 1, "exposure_s": DESC.camera.exposure_s, **extra}


def _open(tmp_path, **camera):
    sim = SimulatedDLPC900("lightcrafter-6500")
    rig = open_calibration_rig(DESC, hardware=_table(tmp_path), acquirer=TwinCamera(sim, **camera), transport=sim,
                               spectrometer=TwinSeaBreeze(sim, cal=_cal()))
    return sim, rig


@pytest.fixture(scope="module")
def hardware_bundle(tmp_path_factory):
    sim, rig = _open(tmp_path_factory.mktemp("hw"), lost={5, 300, 2000})
    with rig:
        bundle = calibrate(DESC, rig=rig, repeats=4, white_reflectance=WHITE, perturbation=0.3, seed=3)
    return bundle, sim, rig


def test_hardware_rig_is_a_calibration_rig(tmp_path):
    sim, rig = _open(tmp_path)
    with rig:
        assert isinstance(rig, CalibrationRig) and rig.max_code == 1023 and rig.frame_shape == (240, 320)
        assert rig.exposure_s == DESC.camera.exposure_s and rig.max_spectrum is None
        frames = rig.capture_mean(np.zeros((2, DESC.light.columns), np.int32), 2, exposure_s=0.004)
        assert frames.shape == (2, 240, 320)
        nm = rig.camera.acquirer.remote_device.node_map
        assert nm.ExposureTime.value == pytest.approx(4000.0) and sim.lut[0]["exposure_us"] == 4000
        rig.zero_spectrometer()
        np.testing.assert_allclose(rig.spectroradiometer.dark_counts, DARK_COUNTS, atol=3)
    assert rig.spectroradiometer.device.closed and not sim.running


def test_calibration_converges_through_the_hardware_drivers(hardware_bundle):
    bundle, sim, rig = hardware_bundle
    rep = bundle.reports
    assert rep["loop_a"]["history"][0] > 0.05  # the start was off
    assert rep["loop_a"]["converged"] and rep["loop_a"]["residual"] <= 0.01
    assert rep["loop_b"]["converged"]
    assert rig.sequences_lost >= 1  # a lost frame discarded its sequence, the mean went on without it
    # exposures were set on the camera: the calibration one, the short dark one and loop (a)'s
    t = {round(x, 9) for x in rig.camera.acquirer.exposures}
    assert {round(x, 9) for x in (DESC.camera.exposure_s, DESC.camera.exposure_s / 4, rep["loop_a_exposure_s"])} <= t
    assert bundle.max_code == 1023 and bundle.frame_shape == (240, 320)
    assert not sim.running  # closing the rig stopped the light


def test_hardware_bundle_matches_the_twin(hardware_bundle):
    bundle = hardware_bundle[0]
    oracle = oracle_calibration(DESC)
    np.testing.assert_allclose(bundle.column_wavelengths, oracle.column_wavelengths, atol=0.5)
    sel = (bundle.wavelengths >= 410) & (bundle.wavelengths <= 690)
    est = bundle.system_matrix.sum(axis=1)[sel]
    true = oracle.system_matrix.sum(axis=1)[sel]
    assert np.median(np.abs(est / true - 1)) < 0.05
    np.testing.assert_allclose(bundle.dark.mean(), oracle.dark.mean(), rtol=0.02)


def test_hardware_bundle_plans_and_reads_the_white_back(hardware_bundle):
    """The bundle is the planner's model: a narrowband plan made from it, captured through the same drivers with
    the bundle's column map, reads the white's reflectance back."""
    bundle = hardware_bundle[0]
    plan = make_plan("narrowband", bundle)
    assert plan.calibration == bundle.hash
    sim = SimulatedDLPC900("lightcrafter-6500")
    camera = open_hardware(DESC, hardware={"light": "dlpc900-simulated", "camera_first_frame_id": 1,
                                           "exposure_s": plan.exposure_s},
                           patterns=plan.patterns, calibration=bundle, n_frames=2 * plan.K,
                           acquirer=TwinCamera(sim), transport=sim)
    from specgpu.capture.session import capture_sequences

    result = capture_sequences(camera, plan.K)
    frames = np.mean([s.frames for s in result.sequences], axis=0)
    o = (frames - bundle.dark_at(plan.exposure_s)) * bundle.flat_field
    h, w = bundle.frame_shape
    centre = o[:, h // 2 - 20:h // 2 + 20, w // 2 - 20:w // 2 + 20].mean(axis=(1, 2))
    y = plan.A @ centre
    inside = (plan.output_wavelengths >= 420) & (plan.output_wavelengths <= 680)
    assert np.median(np.abs(y[inside] - WHITE)) < 0.03


def test_calibration_needs_a_spectrometer_with_its_calibration(tmp_path):
    with pytest.raises(ValueError, match="calibration needs a spectrometer"):
        open_calibration_rig(DESC, hardware={"light": "dlpc900-simulated"})
    with pytest.raises(ValueError, match="spectrometer_calibration"):
        open_calibration_rig(DESC, hardware={"light": "dlpc900-simulated", "spectrometer": "ocean"})


def test_missing_camera_backend_is_one_clear_error(tmp_path):
    try:
        import harvesters  # noqa: F401
    except ImportError:
        with pytest.raises(BackendMissing, match="harvesters"):
            open_calibration_rig(DESC, hardware=_table(tmp_path), transport=SimulatedDLPC900())
    else:
        pytest.skip("harvesters is installed")


def test_missing_spectrometer_backend_is_one_clear_error(tmp_path):
    try:
        import seabreeze  # noqa: F401
    except ImportError:
        sim = SimulatedDLPC900("lightcrafter-6500")
        with pytest.raises(BackendMissing, match="seabreeze"):
            open_calibration_rig(DESC, hardware=_table(tmp_path), acquirer=TwinCamera(sim), transport=sim)
    else:
        pytest.skip("seabreeze is installed")


def test_twin_and_hardware_rigs_share_one_interface():
    from specgpu.calibration import TwinCalibrationRig

    assert isinstance(TwinCalibrationRig(DESC), CalibrationRig)  # the hardware rig's check is above


def test_cli_calibrate_takes_the_hardware_path(tmp_path, monkeypatch):
    """`specgpu calibrate --rig RIG.toml` with a [hardware] table runs the procedure on the devices it names (here
    the simulated controller, with the fake camera and spectrometer put in where the real ones would be opened)."""
    from click.testing import CliRunner

    import specgpu.hardware.rig as hw_rig
    from specgpu.calibration.bundle import load_calibration
    from specgpu.apps.cli import main
    from specgpu.rig.config import load_rig

    real = hw_rig.open_calibration_rig
    opened = []

    def with_fakes(description, *, hardware):
        sim = SimulatedDLPC900(hardware.dmd)
        opened.append(real(description, hardware=hardware, acquirer=TwinCamera(sim, description), transport=sim,
                           spectrometer=TwinSeaBreeze(sim, description, cal=_cal())))
        return opened[-1]

    monkeypatch.setattr(hw_rig, "open_calibration_rig", with_fakes)
    table = _table(tmp_path)
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text("[camera]\nroi_width = 320\nroi_height = 240\n[hardware]\n"
                        + "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in table.items()))
    result = CliRunner().invoke(main, ["calibrate", "--rig", str(rig_toml), "--out", str(tmp_path / "c.npz")])
    assert result.exit_code == 0, result.output
    assert "loop (a) camera + white" in result.output and "converged True" in result.output
    assert len(opened) == 1 and opened[0].spectroradiometer.device.closed  # devices released
    bundle = load_calibration(tmp_path / "c.npz", rig=load_rig(rig_toml))
    assert bundle.reports["loop_a"]["converged"] and make_plan("reciprocal", bundle).calibration == bundle.hash
