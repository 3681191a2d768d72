"""The driver interface every acquisition backend implements: the twin today, hardware later.

Two roles, as in the paper's rig (Section 2.D): a **camera** that is the master and delivers frames, and a
**light source** that holds a pre-loaded sequence of DMD patterns and shows the next one on each trigger.
The capture path (ring buffer, assembler, streaming) only ever talks to these interfaces, so the simulated
backend and a real DLPC900 / GenICam backend go through exactly the same code (tests on the twin exercise the
real path).

Backends register under a name; :func:`open_driver` picks one, and an unknown name is a ``ValueError``
listing the valid ones.
"""

from __future__ import annotations

import abc
import importlib
from dataclasses import dataclass

import numpy as np

__all__ = ["FrameInfo", "StreamEnd", "CameraDriver", "LightSource", "DRIVERS", "open_driver"]


@dataclass(frozen=True, slots=True)
class FrameInfo:
    """Metadata of one delivered frame.

    Attributes
    ----------
    frame_id : int
        Camera frame counter, 0 for the first exposure after :meth:`CameraDriver.start`, incremented by one per
        exposure whether or not the frame reaches the host (a gap means frames were lost).
    pattern_index : int
        Index, in the loaded sequence, of the light pattern that lit this frame, as reported by the light
        source (domain [0, K-1]).
    timestamp_s : float
        Start of the exposure in seconds since :meth:`CameraDriver.start`.
    exposure_s : float
        Exposure time in seconds.
    """

    frame_id: int
    pattern_index: int
    timestamp_s: float
    exposure_s: float


@dataclass(frozen=True, slots=True)
class StreamEnd:
    """What a driver knows when its stream stops, so trailing losses can be accounted exactly.

    Attributes
    ----------
    last_frame_id : int
        Id of the last exposure the camera made (-1 if none).
    last_pattern_index : int
        Pattern the light showed for that exposure (-1 if none).
    """

    last_frame_id: int
    last_pattern_index: int


class LightSource(abc.ABC):
    """A programmable light source with a pre-loaded pattern sequence advanced by a hardware trigger."""

    @property
    @abc.abstractmethod
    def wavelengths(self) -> np.ndarray:
        """Wavelength grid (nm) of :meth:`emitted_spectrum`."""

    @property
    @abc.abstractmethod
    def minimum_exposure_s(self) -> float:
        """Shortest camera exposure (s) the light can follow: pattern load plus mirror settling."""

    @abc.abstractmethod
    def load_sequence(self, patterns: np.ndarray) -> None:
        """Load a (K, columns) sequence of patterns; the light then shows pattern 0."""

    @abc.abstractmethod
    def trigger(self) -> int:
        """Advance to the next pattern of the sequence (cyclically); return the index now shown."""

    @property
    @abc.abstractmethod
    def pattern_index(self) -> int:
        """Index of the pattern shown now."""

    @abc.abstractmethod
    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        """Spectral irradiance (W m^-2 nm^-1) of a loaded pattern (the current one by default)."""


class CameraDriver(abc.ABC):
    """A camera-master acquisition backend: start, fill the slot it is handed, report metadata, stop."""

    @property
    @abc.abstractmethod
    def frame_shape(self) -> tuple[int, int]:
        """(height, width) of the frames, in pixels."""

    @property
    @abc.abstractmethod
    def dtype(self) -> np.dtype:
        """NumPy dtype of the frames."""

    @property
    @abc.abstractmethod
    def light(self) -> LightSource:
        """The light source this camera triggers."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start the stream (frame ids and timestamps restart at 0)."""

    @abc.abstractmethod
    def stop(self) -> StreamEnd:
        """Stop the stream; return what is known about its last exposure."""

    @abc.abstractmethod
    def fill(self, out: np.ndarray | None) -> FrameInfo | None:
        """Write the next delivered frame into ``out`` in place and return its metadata.

        ``out`` is ``None`` when the host has no slot for it: the frame is consumed and lost (its id will
        show as a gap). Returns ``None`` once the stream has ended.
        """

    @property
    @abc.abstractmethod
    def running(self) -> bool:
        """Whether the stream is running."""


#: Backend name -> "module:Class". Imported on demand, so a backend's dependencies load only when used.
DRIVERS: dict[str, str] = {
    "twin": "specgpu.capture.twin_driver:TwinDriver",
    "replay": "specgpu.capture.replay:ReplayDriver",
    "vision-dlpc900": "specgpu.hardware.rig:open_hardware",  # GenICam camera lit by a DLPC900 (specgpu.hardware)
}


def open_driver(name: str = "twin", /, **kwargs) -> CameraDriver:
    """Create the acquisition backend registered as ``name`` (default: the digital twin).

    Raises
    ------
    ValueError
        If ``name`` is not registered; the message lists the valid names.
    """
    try:
        target = DRIVERS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown driver {name!r}; valid drivers: {', '.join(sorted(DRIVERS))}") from None
    module_name, _, cls_name = target.partition(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls(**kwargs)
