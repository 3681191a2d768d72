"""The digital twin as an acquisition backend (driver name ``"twin"``).

It goes through the same :class:`~specgpu.capture.driver.CameraDriver` interface as hardware: the capture loop
hands it a ring-buffer slot, it exposes the next frame into that slot in place and returns the metadata. The
camera is the master: before every exposure after the first, the previous exposure's strobe triggers the light,
which advances to the next pattern of its pre-loaded sequence unless the fault schedule says the trigger is
missed. Faults (drops, duplicates, missed triggers, jitter) come from a :class:`~specgpu.rig.twin.FaultSchedule`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from specgpu.capture.driver import CameraDriver, FrameInfo, LightSource, StreamEnd
from specgpu.core.validate import check_number
from specgpu.rig.config import RigDescription, load_rig
from specgpu.rig.light import ProgrammableLight
from specgpu.rig.twin import FaultSchedule, TwinRig

# The rig model never imports capture/: its light implements the LightSource interface and is registered here.
LightSource.register(ProgrammableLight)

__all__ = ["TwinDriver"]


class TwinDriver(CameraDriver):
    """Camera-master acquisition from the simulated rig.

    Parameters
    ----------
    rig
        A :class:`~specgpu.rig.twin.TwinRig`, a :class:`~specgpu.rig.config.RigDescription`, a rig TOML path, or
        ``None`` for the paper's rig.
    patterns
        Optional (K, columns) pattern sequence to load into the light now (else the rig's loaded sequence).
    scene
        Optional scene for a rig built here (name, path or :class:`~specgpu.rig.scene.SpectralScene`).
    faults
        Fault schedule; by default the description's ``[faults]`` rates (all off unless set).
    n_frames
        Number of exposures after which the stream ends (``fill`` returns ``None``); ``None`` runs until stopped.
    pacing
        ``"free"`` (as fast as frames render) or ``"paced"`` (each frame returned no earlier than its timestamp);
        the description's by default.
    """

    def __init__(self, rig=None, *, patterns=None, scene=None, faults: FaultSchedule | None = None,
                 n_frames: int | None = None, pacing: str | None = None):
        if isinstance(rig, TwinRig):
            if scene is not None:
                rig.set_scene(scene)
            self.rig = rig
        else:
            desc = rig if isinstance(rig, RigDescription) else load_rig(rig) if isinstance(rig, (str, Path)) else None
            if rig is not None and desc is None:
                raise ValueError(f"rig must be a TwinRig, a RigDescription or a TOML path, got {type(rig).__name__}")
            self.rig = TwinRig(desc, scene=scene)
        if patterns is not None:
            self.rig.load_sequence(patterns)
        d = self.rig.description
        self.faults = faults if faults is not None else (
            FaultSchedule.from_rates(d.faults, seed=self.rig.seed) if d.faults.any else FaultSchedule())
        if self.faults.jitter_s > 0 and 4 * self.faults.jitter_s > self.rig.slack_s:
            raise ValueError(
                f"faults.jitter_s = {self.faults.jitter_s:g} s: 4 sigma exceeds the {self.rig.slack_s * 1e6:.1f} us "
                "left between the light settling and the next exposure; shorten the exposure or lower the jitter")
        self.n_frames = None if n_frames is None else check_number("n_frames", n_frames, low=0, integer=True)
        self.pacing = d.pacing if pacing is None else pacing
        if self.pacing not in ("free", "paced"):
            raise ValueError(f"pacing must be one of free, paced, got {self.pacing!r}")
        h, w = self.rig.camera.shape
        self._scratch = (np.empty((h, w), np.float32), np.empty((h, w), np.float32))
        self._running = False
        self._next_id = 0
        self._last = (-1, -1)
        self._pending_duplicate: FrameInfo | None = None
        self._t0 = 0.0
        self.frames_exposed = 0
        self.frames_delivered = 0

    # ---- interface ------------------------------------------------------------------------------------------
    @property
    def frame_shape(self) -> tuple[int, int]:
        return self.rig.camera.shape

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint16)

    @property
    def light(self) -> LightSource:
        return self.rig.light

    @property
    def running(self) -> bool:
        return self._running

    def start(self) -> None:
        self.rig.light.reset()
        self.rig._ensure_maps()  # render every pattern's noise-free frame once, before the clock starts
        self._next_id = 0
        self._last = (-1, -1)
        self._pending_duplicate = None
        self.frames_exposed = 0
        self.frames_delivered = 0
        self._t0 = time.perf_counter()
        self._running = True

    def stop(self) -> StreamEnd:
        self._running = False
        return StreamEnd(*self._last)

    def fill(self, out: np.ndarray | None) -> FrameInfo | None:
        if not self._running:
            raise RuntimeError("twin driver: fill() called before start() or after stop()")
        if out is not None and (out.shape != self.frame_shape or out.dtype != np.uint16):
            raise ValueError(f"slot must be a {self.frame_shape} uint16 array, got {out.shape} {out.dtype}")
        if self._pending_duplicate is not None:
            info, self._pending_duplicate = self._pending_duplicate, None
            if out is not None:
                self.rig.render(info.pattern_index, info.frame_id, info.timestamp_s, out, self._scratch)
            self.frames_delivered += 1
            return info
        period = self.rig.frame_period_s
        while True:
            k = self._next_id
            if self.n_frames is not None and k >= self.n_frames:
                return None
            dropped, duplicated, missed, jitter = self.faults.faults(k)
            if k > 0 and not missed:
                self.rig.light.trigger()
            p = self.rig.light.pattern_index
            self._next_id += 1
            self.frames_exposed += 1
            self._last = (k, p)
            if not dropped:
                break
        ts = k * period + jitter
        info = FrameInfo(k, p, ts, self.rig.exposure_s)
        if out is not None:
            self.rig.render(p, k, ts, out, self._scratch)
        if duplicated:
            self._pending_duplicate = info
        if self.pacing == "paced":
            wait = self._t0 + ts + self.rig.exposure_s - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        self.frames_delivered += 1
        return info

    def describe(self) -> dict:
        """Metadata for a capture record: the rig description and the loaded sequence."""
        return {"driver": "twin", "rig": self.rig.description.to_dict(),
                "patterns": self.rig.light.sequence.tolist()}
