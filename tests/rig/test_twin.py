"""The synchronous twin: camera master -> trigger -> light; one pattern per frame; faults; determinism."""

import time

import numpy as np
import pytest

from specgpu.capture.driver import FrameInfo, StreamEnd
from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import FaultRates, RigDescription
from specgpu.rig.light import LightParameters
from specgpu.rig.twin import FaultSchedule, TwinRig

SMALL = CameraParameters(roi_width=320, roi_height=240)
K = 4


def level_patterns(columns=1024, k=K):
    """K patterns with clearly different levels on white: dark, and about 1/8, 1/4 and 1/2 of the full well."""
    levels = [0, 24, 48, 96][:k]
    return np.stack([np.full(columns, lv, np.int32) for lv in levels])


@pytest.fixture(scope="module")
def rig():
    r = TwinRig(RigDescription(camera=SMALL, light=LightParameters(fluctuation_rms=0.0)), scene="white")
    r.load_sequence(level_patterns())
    return r


def run(driver, n=None):
    frames, infos = [], []
    out = np.empty(driver.frame_shape, np.uint16)
    driver.start()
    while (n is None or len(infos) < n) and (info := driver.fill(out)) is not None:
        frames.append(out.copy())
        infos.append(info)
    end = driver.stop()
    return np.array(frames), infos, end


def lit_by(rig, frame):
    """Which loaded pattern a frame's mean level matches (the levels are far apart compared with the noise)."""
    means = np.array([rig.expected_frame(k).mean() for k in range(rig.light.sequence.shape[0])])
    return int(np.argmin(np.abs(means - frame.mean())))


def test_each_frame_is_lit_by_the_pattern_it_reports(rig):
    frames, infos, end = run(TwinDriver(rig, n_frames=12))
    assert [i.frame_id for i in infos] == list(range(12))
    assert [i.pattern_index for i in infos] == [k % K for k in range(12)]
    assert [lit_by(rig, f) for f in frames] == [k % K for k in range(12)]
    assert end == StreamEnd(11, 3)
    period = 1 / 90.0
    np.testing.assert_allclose([i.timestamp_s for i in infos], np.arange(12) * period)
    assert all(i.exposure_s == SMALL.exposure_s for i in infos)


def test_deterministic_for_a_seed():
    def frames(seed):
        r = TwinRig(RigDescription(camera=SMALL, seed=seed), scene="colorchecker")
        r.load_sequence(level_patterns())
        return run(TwinDriver(r, n_frames=6))[0]

    a, b, c = frames(3), frames(3), frames(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_missed_trigger_repeats_the_previous_pattern_and_shifts_the_rest(rig):
    faults = FaultSchedule(missed_triggers={2, 7})
    frames, infos, end = run(TwinDriver(rig, n_frames=10, faults=faults))
    expected = [0, 1, 1, 2, 3, 0, 1, 1, 2, 3]
    assert [i.pattern_index for i in infos] == expected
    assert [lit_by(rig, f) for f in frames] == expected
    assert end == StreamEnd(9, 3)


def test_dropped_frames_leave_id_gaps_and_the_light_still_advances(rig):
    faults = FaultSchedule(dropped={1, 2, 6})
    frames, infos, end = run(TwinDriver(rig, n_frames=8, faults=faults))
    assert [i.frame_id for i in infos] == [0, 3, 4, 5, 7]
    assert [i.pattern_index for i in infos] == [0, 3, 0, 1, 3]
    assert [lit_by(rig, f) for f in frames] == [0, 3, 0, 1, 3]
    assert end == StreamEnd(7, 3)


def test_duplicated_frames_are_bit_identical(rig):
    faults = FaultSchedule(duplicated={2})
    frames, infos, _ = run(TwinDriver(rig, n_frames=4, faults=faults))
    assert [i.frame_id for i in infos] == [0, 1, 2, 2, 3]
    assert infos[2] == infos[3]
    np.testing.assert_array_equal(frames[2], frames[3])
    assert not np.array_equal(frames[1], frames[2])


def test_fill_without_a_slot_consumes_the_frame(rig):
    driver = TwinDriver(rig, n_frames=3)
    driver.start()
    assert driver.fill(None) == FrameInfo(0, 0, 0.0, SMALL.exposure_s)
    out = np.empty(driver.frame_shape, np.uint16)
    assert driver.fill(out).frame_id == 1
    assert lit_by(rig, out) == 1


def test_jitter_is_bounded_and_too_much_is_refused(rig):
    faults = FaultSchedule(jitter_s=5e-6, seed=2)
    _, infos, _ = run(TwinDriver(rig, n_frames=400, faults=faults))
    dev = np.array([i.timestamp_s - i.frame_id / 90.0 for i in infos])
    assert np.abs(dev).max() <= 1e-5 + 1e-12
    assert dev.std() == pytest.approx(5e-6 * 0.88, rel=0.15)  # a Gaussian truncated at 2 sigma
    with pytest.raises(ValueError, match=r"faults.jitter_s = 1e-05 s: 4 sigma exceeds the 31.1 us left"):
        TwinDriver(rig, faults=FaultSchedule(jitter_s=1e-5))


def test_random_fault_rates_are_deterministic_and_near_their_rates():
    rates = FaultRates(drop_rate=0.05, duplicate_rate=0.05, missed_trigger_rate=0.05)
    a, b = FaultSchedule.from_rates(rates, seed=1), FaultSchedule.from_rates(rates, seed=1)
    fa = np.array([a.faults(k)[:3] for k in range(20000)])
    fb = np.array([b.faults(k)[:3] for k in range(20000)])
    np.testing.assert_array_equal(fa, fb)
    assert np.all(np.abs(fa.mean(axis=0) - [0.05, 0.05 * 0.95, 0.05]) < 0.006)
    assert not np.any(fa[:, 0] & fa[:, 1])  # a dropped frame is never also duplicated
    assert not fa[0, 2]  # frame 0 has no trigger to miss


def test_fault_schedule_validation():
    with pytest.raises(ValueError, match="frame 3 is both dropped and duplicated"):
        FaultSchedule(dropped={3}, duplicated={3})
    with pytest.raises(ValueError, match="cannot hold frame 0"):
        FaultSchedule(missed_triggers={0})
    with pytest.raises(ValueError, match=r"faults.dropped must hold frame ids >= 0"):
        FaultSchedule(dropped={-1})


def test_paced_mode_runs_at_the_frame_rate():
    cam = CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0, exposure_s=0.004)
    r = TwinRig(RigDescription(camera=cam, pacing="paced"), scene="white")
    t0 = time.perf_counter()
    _, infos, _ = run(TwinDriver(r, n_frames=20))
    assert time.perf_counter() - t0 >= 19 / 200.0
    assert len(infos) == 20


def test_driver_misuse(rig):
    driver = TwinDriver(rig, n_frames=2)
    with pytest.raises(RuntimeError, match="before start"):
        driver.fill(np.empty(driver.frame_shape, np.uint16))
    driver.start()
    with pytest.raises(ValueError, match=r"slot must be a \(240, 320\) uint16 array"):
        driver.fill(np.empty((10, 10), np.uint16))
    with pytest.raises(ValueError, match="rig must be a TwinRig"):
        TwinDriver(3.5)


def test_the_light_source_interface_is_the_rigs_light(rig):
    driver = TwinDriver(rig)
    assert driver.light is rig.light
    assert driver.light.minimum_exposure_s == pytest.approx(80e-6)
    assert driver.describe()["patterns"][1][0] == 24


def test_pool_noise_has_the_same_temporal_statistics(rig):
    fresh = run(TwinDriver(rig, n_frames=200))[0].astype(float)
    rig.set_noise("pool")
    try:
        pooled = run(TwinDriver(rig, n_frames=200))[0].astype(float)
    finally:
        rig.set_noise("fresh")
    for k in (1, 3):
        vf = fresh[k::K].var(axis=0, ddof=1).mean()
        vp = pooled[k::K].var(axis=0, ddof=1).mean()
        assert vp == pytest.approx(vf, rel=0.05)
        assert pooled[k::K].mean() == pytest.approx(fresh[k::K].mean(), abs=0.05)
    with pytest.raises(ValueError, match="noise must be one of fresh, pool"):
        rig.set_noise("cheap")


def test_render_refuses_non_contiguous_slots(rig):
    wide = np.empty((240, 640), np.uint16)
    with pytest.raises(ValueError, match=r"out must be a C-contiguous \(240, 320\) uint16 array"):
        rig.render(0, 0, 0.0, wide[:, ::2])


def test_temporal_std_matches_rendered_frames(rig):
    frames = run(TwinDriver(rig, n_frames=400))[0].astype(float)
    for k in (0, 3):
        measured = frames[k::K].var(axis=0, ddof=1).mean()
        predicted = (rig.temporal_std(k) ** 2).mean() + 1 / 12
        assert measured == pytest.approx(predicted, rel=0.05)


def test_plan_exposure_places_the_brightest_pattern_at_the_level(rig):
    t, reached = rig.plan_exposure(0.5)
    assert reached == pytest.approx(0.5)
    e = rig.signal_electrons() * rig.camera.prnu[None]
    brightest = np.percentile(e[3], 99.9) * t / rig.exposure_s
    assert brightest == pytest.approx(0.5 * rig.camera.params.full_well_e, rel=1e-4)
    t, reached = rig.plan_exposure(1.0)  # would need longer than the 90 fps frame allows: capped
    assert t == pytest.approx(1 / 90 - 80e-6) and reached < 1.0


def test_loading_through_the_driver_interface_updates_the_frames():
    r = TwinRig(RigDescription(camera=SMALL, light=LightParameters(fluctuation_rms=0.0)), scene="white")
    r.load_sequence(level_patterns())
    driver = TwinDriver(r, n_frames=4)
    first, _, _ = run(driver)
    driver.light.load_sequence(level_patterns()[::-1])  # the generic LightSource call, bypassing TwinRig
    second, infos, _ = run(driver)
    assert [lit_by(r, f) for f in second] == [0, 1, 2, 3]
    assert second[0].mean() == pytest.approx(first[3].mean(), rel=0.01)  # now pattern 0 is the brightest
