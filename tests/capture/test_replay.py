"""Replay of recorded twin frames: same interface, same ring buffer and assembler, faster than rendering."""

import numpy as np
import pytest

from specgpu.capture import capture_sequences, open_driver
from specgpu.capture.replay import RecordedLight, ReplayDriver, record
from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.twin import FaultSchedule, TwinRig

K = 3


@pytest.fixture(scope="module")
def recording():
    rig = TwinRig(RigDescription(camera=CameraParameters(roi_width=320, roi_height=240)), scene="colorchecker")
    rig.load_sequence(np.stack([np.full(1024, lv, np.int32) for lv in (0, 30, 60)]))
    return rig, record(TwinDriver(rig), 4 * K)


def test_replay_reproduces_the_recording_and_loops_with_increasing_ids(recording):
    rig, (frames, infos, light) = recording
    assert frames.shape == (12, 240, 320) and [i.frame_id for i in infos] == list(range(12))
    np.testing.assert_array_equal(light.sequence, rig.light.sequence)
    np.testing.assert_allclose(light.emitted_spectrum(1), rig.light.emitted_spectrum(1))
    driver = open_driver("replay", frames=frames, infos=infos, light=light, loops=3)
    out = np.empty(driver.frame_shape, np.uint16)
    driver.start()
    got = []
    while (info := driver.fill(out)) is not None:
        np.testing.assert_array_equal(out, frames[len(got) % 12])
        assert driver.light.pattern_index == info.pattern_index
        got.append(info)
    assert [i.frame_id for i in got] == list(range(36))
    assert [i.pattern_index for i in got] == [i % K for i in range(36)]
    np.testing.assert_allclose(np.diff([i.timestamp_s for i in got]), 1 / 90.0)
    assert driver.stop().last_frame_id == 35


def test_replay_goes_through_ring_and_assembler(recording):
    _, (frames, infos, light) = recording
    result = capture_sequences(ReplayDriver(frames, infos, light, loops=5), K, n_slots=2)
    assert len(result.sequences) == 20 and result.assembly.dropped == 0
    assert result.assembly.missed_triggers == 0 and result.assembly.sequences_discarded == 0


def test_replayed_faults_are_counted_again(recording):
    rig, _ = recording
    frames, infos, light = record(TwinDriver(rig, faults=FaultSchedule(dropped={4}, duplicated={7})), 11)
    result = capture_sequences(ReplayDriver(frames, infos, light, loops=2), K)
    assert result.assembly.dropped == 2 and result.assembly.duplicates == 2


def test_replay_validation(recording):
    _, (frames, infos, light) = recording
    with pytest.raises(ValueError, match="infos must hold one FrameInfo per frame: 11 for 12"):
        ReplayDriver(frames, infos[:-1], light)
    with pytest.raises(ValueError, match="frame ids must not decrease"):
        ReplayDriver(frames[:2], infos[1::-1], light)
    with pytest.raises(ValueError, match=r"frames must have shape \(N, H, W\)"):
        ReplayDriver(frames[0], infos, light)
    with pytest.raises(RuntimeError, match="cannot load a new sequence"):
        light.load_sequence(np.zeros((1, 1024), int))
    with pytest.raises(ValueError, match=r"spectra must have shape \(K, grid\) = \(2, 3\)"):
        RecordedLight(np.zeros((2, 4)), np.zeros((2, 5)), np.arange(3.0), 8e-5)
