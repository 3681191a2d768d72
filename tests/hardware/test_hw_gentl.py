"""The GenICam camera driver against a real GenICam stack: harvesters loading the virtual GenTL producer shipped with
the ``genicam`` package (``genicam/viky.cti``, a free-running 400 x 400 "bouncing ball" camera at 20 fps, frame ids
from 1, no device timestamps, no trigger or I/O-line features).

These are the only tests that use a GenTL producer; the trigger wiring, line modes, id wrap and fault drills run on
the fakes of ``hw_fakes`` (``test_hw_bench.py``, ``test_hw_capture.py``), as the virtual camera has no trigger or
lines. Skipped where harvesters or the producer is not installed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

harvesters_core = pytest.importorskip("harvesters.core")
genicam = pytest.importorskip("genicam")
VIKY = Path(genicam.__path__[0]) / "viky.cti"
if not VIKY.is_file():  # pragma: no cover - depends on the genicam wheel
    pytest.skip("the genicam package ships no virtual GenTL producer (viky.cti) here", allow_module_level=True)

from specgpu.capture import capture_sequences  # noqa: E402
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, DMDGeometry, DMDLayout, SimulatedDLPC900  # noqa: E402
from specgpu.hardware.errors import DeviceNotFound, HardwareError  # noqa: E402
from specgpu.hardware.genicam import GenICamCamera, _timestamp_ns, _writable, open_acquirer  # noqa: E402

DMD = DMDGeometry("test-dmd", 160, 48)


@pytest.fixture
def viky():
    """(harvester, acquirer) of the virtual camera with serial "1", released afterwards."""
    h, ia = open_acquirer(VIKY, serial="1")
    try:
        yield h, ia
    finally:
        try:
            ia.stop()
        finally:
            ia.destroy()
            h.reset()


def _light():
    sim = SimulatedDLPC900(DMD)
    light = DLPC900Light(DLPC900(sim, dmd=DMD), layout=DMDLayout(DMD, 16, 40), exposure_s=0.001)
    light.load_sequence(np.arange(3)[:, None] * np.ones((1, 16), int) * 10)
    return sim, light


def test_open_acquirer_finds_the_producer_camera_and_refuses_an_unknown_serial():
    with pytest.raises(DeviceNotFound, match=r"^GenICam camera nosuch cannot be opened through .*viky\.cti"):
        open_acquirer(VIKY, serial="nosuch")
    h, ia = open_acquirer(VIKY, serial="2")
    try:
        assert len(h.device_info_list) == 3 and ia.remote_device.node_map.Width.value == 400
    finally:
        ia.destroy()
        h.reset()


def test_real_node_maps_pixel_format_features_and_access_modes(viky):
    _, ia = viky
    nm = ia.remote_device.node_map
    nm.PixelFormat.value = "RGBa8"
    sim, light = _light()
    with pytest.raises(HardwareError, match="^camera pixel format RGBa8 is not supported; set one of Mono8"):
        GenICamCamera(light, acquirer=ia)
    nm.PixelFormat.value = "Mono8"
    camera = GenICamCamera(light, acquirer=ia)
    assert camera.frame_shape == (400, 400) and camera.dtype == np.uint8
    assert _writable(nm.PixelFormat) and not _writable(nm.PayloadSize)  # genapi access modes of real nodes
    # the virtual camera has no exposure or trigger features: one line naming the missing one
    with pytest.raises(HardwareError, match=r"^camera has no GenICam feature 'ExposureTime' \(needed to set it"):
        camera.configure()


def test_frames_from_a_real_producer_without_timestamps(viky, monkeypatch):
    """Real GenTL buffers: frame ids from the producer, and its NotAvailableException on the timestamp handled
    (the host's clock stamps the frames)."""
    _, ia = viky
    ia.remote_device.node_map.PixelFormat.value = "Mono8"
    sim, light = _light()
    camera = GenICamCamera(light, acquirer=ia, n_frames=6, first_frame_id=1, timeout_s=3.0)
    monkeypatch.setattr(camera, "configure", lambda: None)  # no trigger or line features to write
    seen = []

    def fetch(timeout=None, _fetch=ia.fetch):
        buffer = _fetch(timeout=timeout)
        seen.append(_timestamp_ns(buffer))
        return buffer

    monkeypatch.setattr(ia, "fetch", fetch)
    result = capture_sequences(camera, 3)
    assert seen and all(s is None for s in seen)  # the producer really has no timestamps
    assert camera.describe()["timestamps"] == "host"
    assert len(result.sequences) == 2 and result.assembly.dropped == 0
    ids = np.concatenate([s.frame_ids for s in result.sequences])
    np.testing.assert_array_equal(ids, np.arange(6))  # GenTL ids 1..6, exposure 0 at id 1
    dt = np.diff(np.concatenate([s.timestamps_s for s in result.sequences]))
    assert 0.02 < float(np.median(dt)) < 0.2  # the producer's 20 fps, on the host clock
    frames = np.concatenate([s.frames for s in result.sequences])
    assert frames.shape == (6, 400, 400) and frames.dtype == np.uint8 and frames.max() > frames.min()
    assert not sim.running  # the light stopped with the capture
