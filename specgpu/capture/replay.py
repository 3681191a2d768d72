"""Replay of pre-rendered or recorded frames as an acquisition backend (driver name ``"replay"``).

The twin renders about 600 frames/s at 640 x 480 with fresh noise on a 2-core machine; the camera can deliver
780 frames/s at reduced ROI. Work that must be fed faster than the twin renders (streaming throughput, kernel
benchmarks) records a block of frames once with :func:`record` and replays it through the very same interface,
ring buffer and assembler, at memory-copy speed or paced at a frame rate. Replaying a recording in a loop keeps
frame ids increasing (loop ``j`` adds ``j * (last id + 1)``) and timestamps continuous; record a whole number
of sequences (a multiple of K frames from frame 0) so the pattern indices also run on across the loop seam.
"""

from __future__ import annotations

import time

import numpy as np

from specgpu.capture.driver import CameraDriver, FrameInfo, LightSource, StreamEnd
from specgpu.core.validate import check_number

__all__ = ["ReplayDriver", "RecordedLight", "record"]


class RecordedLight(LightSource):
    """The light of a recording: its pattern sequence and spectra, advanced in step with the replayed frames.

    Parameters
    ----------
    patterns
        (K, columns) mirror counts that were loaded.
    spectra
        (K, grid) emitted spectral irradiance, W m^-2 nm^-1.
    wavelengths
        (grid,) nm.
    minimum_exposure_s
        The recorded light's minimum exposure, s.
    """

    def __init__(self, patterns, spectra, wavelengths, minimum_exposure_s: float):
        self._patterns = np.array(patterns)
        self._spectra = np.array(spectra, dtype=np.float64)
        self._wl = np.array(wavelengths, dtype=np.float64)
        if self._patterns.ndim != 2 or self._spectra.shape != (self._patterns.shape[0], self._wl.size):
            raise ValueError(f"spectra must have shape (K, grid) = ({self._patterns.shape[0]}, {self._wl.size}), "
                             f"got {self._spectra.shape}")
        self._min_exposure = check_number("minimum_exposure_s", minimum_exposure_s, low=0)
        self._index = 0

    @property
    def wavelengths(self) -> np.ndarray:
        return self._wl

    @property
    def minimum_exposure_s(self) -> float:
        return self._min_exposure

    def load_sequence(self, patterns) -> None:
        raise RuntimeError("a recorded light cannot load a new sequence: record again with the new patterns")

    def trigger(self) -> int:
        self._index = (self._index + 1) % self._patterns.shape[0]
        return self._index

    @property
    def pattern_index(self) -> int:
        return self._index

    def _show(self, index: int) -> None:
        self._index = int(index)

    @property
    def sequence(self) -> np.ndarray:
        return self._patterns

    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        k = self._index if index is None else int(index)
        if not 0 <= k < self._spectra.shape[0]:
            raise ValueError(f"index must lie in [0, {self._spectra.shape[0] - 1}], got {index}")
        return self._spectra[k]


def record(driver: CameraDriver, n_frames: int) -> tuple[np.ndarray, list[FrameInfo], RecordedLight]:
    """Pull ``n_frames`` delivered frames from a driver (started and stopped here).

    Returns the (n, H, W) frames, their metadata and the driver's light as a :class:`RecordedLight` (its pattern
    sequence and spectra). Fewer frames come back if the driver's stream ends first.
    """
    n = check_number("n_frames", n_frames, low=1, integer=True)
    frames = np.empty((n,) + tuple(driver.frame_shape), driver.dtype)
    infos = []
    driver.start()
    try:
        while len(infos) < n and (info := driver.fill(frames[len(infos)])) is not None:
            infos.append(info)
    finally:
        driver.stop()
    light = driver.light
    seq = getattr(light, "sequence", None)
    if seq is None:
        raise ValueError("record: the driver's light does not expose its loaded sequence")
    spectra = np.stack([light.emitted_spectrum(k) for k in range(len(seq))])
    return frames[:len(infos)], infos, RecordedLight(seq, spectra, light.wavelengths, light.minimum_exposure_s)


class ReplayDriver(CameraDriver):
    """Replay recorded frames and metadata through the driver interface.

    Parameters
    ----------
    frames
        (N, H, W) frames (not copied).
    infos
        N :class:`FrameInfo` with strictly increasing frame ids (duplicates allowed: a recorded fault).
    light
        The recording's :class:`RecordedLight`.
    loops
        How many times to play the recording (``None``: forever, until stopped).
    pacing
        ``"free"`` (as fast as slots are filled) or ``"paced"`` (each frame no earlier than its timestamp).
    """

    def __init__(self, frames, infos, light: RecordedLight, *, loops: int | None = 1, pacing: str = "free"):
        self.frames = np.asarray(frames)
        if self.frames.ndim != 3:
            raise ValueError(f"frames must have shape (N, H, W), got {self.frames.shape}")
        self.infos = list(infos)
        if len(self.infos) != self.frames.shape[0] or not self.infos:
            raise ValueError(f"infos must hold one FrameInfo per frame: {len(self.infos)} for {self.frames.shape[0]}")
        ids = np.array([i.frame_id for i in self.infos])
        if np.any(np.diff(ids) < 0):
            raise ValueError("infos: frame ids must not decrease")
        self.loops = None if loops is None else check_number("loops", loops, low=1, integer=True)
        if pacing not in ("free", "paced"):
            raise ValueError(f"pacing must be one of free, paced, got {pacing!r}")
        self.pacing = pacing
        self._light = light
        self._id_step = int(ids[-1]) + 1
        last = self.infos[-1]
        # One loop lasts until the frame after the last one recorded (a whole number of frame periods).
        period = (last.timestamp_s - self.infos[0].timestamp_s) / max(int(ids[-1] - ids[0]), 1)
        self._time_step = last.timestamp_s + period
        self._pos = 0
        self._loop = 0
        self._last = (-1, -1)
        self._running = False
        self._t0 = 0.0

    @property
    def frame_shape(self) -> tuple[int, int]:
        return tuple(self.frames.shape[1:])

    @property
    def dtype(self) -> np.dtype:
        return self.frames.dtype

    @property
    def light(self) -> LightSource:
        return self._light

    @property
    def running(self) -> bool:
        return self._running

    def start(self) -> None:
        self._pos, self._loop, self._last = 0, 0, (-1, -1)
        self._light._show(0)
        self._t0 = time.perf_counter()
        self._running = True

    def stop(self) -> StreamEnd:
        self._running = False
        return StreamEnd(*self._last)

    def fill(self, out: np.ndarray | None) -> FrameInfo | None:
        if not self._running:
            raise RuntimeError("replay driver: fill() called before start() or after stop()")
        if self._pos == len(self.infos):
            self._pos = 0
            self._loop += 1
        if self.loops is not None and self._loop >= self.loops:
            return None
        rec = self.infos[self._pos]
        info = FrameInfo(rec.frame_id + self._loop * self._id_step, rec.pattern_index,
                         rec.timestamp_s + self._loop * self._time_step, rec.exposure_s)
        if out is not None:
            np.copyto(out, self.frames[self._pos])
        self._light._show(rec.pattern_index)
        self._last = (info.frame_id, info.pattern_index)
        self._pos += 1
        if self.pacing == "paced":
            wait = self._t0 + info.timestamp_s + info.exposure_s - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        return info
