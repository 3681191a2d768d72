"""The driver interface: abstract, implementable by another backend, and that backend runs the same capture path."""

import numpy as np
import pytest

from specgpu.capture import DRIVERS, CameraDriver, FrameInfo, LightSource, StreamEnd, capture_sequences
from specgpu.capture.twin_driver import TwinDriver


class ReplayLight(LightSource):
    def __init__(self):
        self._seq = np.zeros((1, 4), np.int32)
        self._i = 0

    wavelengths = property(lambda self: np.array([500.0, 600.0]))
    minimum_exposure_s = property(lambda self: 80e-6)
    pattern_index = property(lambda self: self._i)

    def load_sequence(self, patterns):
        self._seq = np.asarray(patterns)
        self._i = 0

    def trigger(self):
        self._i = (self._i + 1) % len(self._seq)
        return self._i

    def emitted_spectrum(self, index=None):
        return np.full(2, float(self._seq[self._i if index is None else index].sum()))


class ReplayDriver(CameraDriver):
    """A minimal non-twin backend: replays pre-rendered frames (what the streaming work may do)."""

    def __init__(self, frames, k):
        self.frames, self.k = frames, k
        self._light = ReplayLight()
        self._light.load_sequence(np.arange(k)[:, None] * np.ones((1, 4), np.int32))
        self._n = 0
        self._running = False

    frame_shape = property(lambda self: self.frames.shape[1:])
    dtype = property(lambda self: self.frames.dtype)
    light = property(lambda self: self._light)
    running = property(lambda self: self._running)

    def start(self):
        self._n, self._running = 0, True
        self._light._i = 0

    def stop(self):
        self._running = False
        return StreamEnd(self._n - 1, self._light.pattern_index)

    def fill(self, out):
        if self._n >= len(self.frames):
            return None
        if self._n > 0:
            self._light.trigger()
        if out is not None:
            out[...] = self.frames[self._n]
        info = FrameInfo(self._n, self._light.pattern_index, self._n / 200.0, 1e-3)
        self._n += 1
        return info


def test_interfaces_are_abstract():
    with pytest.raises(TypeError):
        CameraDriver()
    with pytest.raises(TypeError):
        LightSource()


def test_another_backend_goes_through_the_same_capture_path():
    k = 3
    frames = np.stack([np.full((4, 5), 10 * (i % k), np.uint16) for i in range(31)])
    result = capture_sequences(ReplayDriver(frames, k), k, n_slots=2)
    assert len(result.sequences) == 10
    assert result.assembly.sequences_discarded == 1  # the trailing cycle with a single frame
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames[:, 0, 0], [0, 10, 20])
    assert result.end == StreamEnd(30, 0)


def test_twin_is_the_default_backend_and_a_real_subclass():
    assert DRIVERS["twin"] == "specgpu.capture.twin_driver:TwinDriver"
    assert issubclass(TwinDriver, CameraDriver)
