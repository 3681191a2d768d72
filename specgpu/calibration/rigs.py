"""The rig as calibration sees it, and the capture helpers the procedure measures with.

:class:`CalibrationRig` is the little a calibration needs from a rig: capture a mean frame stack at an exposure,
measure a loaded pattern's spectrum, the light's model and the camera's limits. :class:`TwinCalibrationRig` is
the digital twin's (frames through the twin driver, ring buffer and assembler) and
:class:`specgpu.hardware.rig.HardwareCalibrationRig` a real rig's (DLPC900 light, GenICam camera, Ocean
spectrometer). :func:`distribute_counts` sets a band's power in steps of one mirror; :func:`capture_mean` averages
captured sequences of a twin rig.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from specgpu.capture.session import capture_sequences
from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import white_plate_scene
from specgpu.rig.twin import FaultSchedule, TwinRig

if TYPE_CHECKING:
    from specgpu.rig.scene import SpectralScene

__all__ = [
    "CalibrationRig",
    "NoiseSeeds",
    "TwinCalibrationRig",
    "as_calibration_rig",
    "capture_mean",
    "centre_window",
    "distribute_counts",
    "twin_at_exposure",
]


def distribute_counts(levels, masks, rows: int) -> np.ndarray:
    """Patterns with a total mirror count ``level * rows * (columns in mask)`` spread evenly over each mask's
    columns (the remainder one mirror at a time), so a band's power is set in steps of one mirror, not one row.

    Parameters
    ----------
    levels : (K,) float in [0, 1]
    masks : (K, C) bool
    rows : int

    Returns
    -------
    (K, C) int32 mirror counts in [0, rows].
    """
    levels = np.clip(np.asarray(levels, np.float64), 0.0, 1.0)
    masks = np.asarray(masks, bool)
    out = np.zeros(masks.shape, np.int32)
    for k in range(masks.shape[0]):
        cols = np.flatnonzero(masks[k])
        total = int(round(levels[k] * rows * cols.size))
        base, extra = divmod(total, max(cols.size, 1))
        out[k, cols] = base
        if extra:
            # Spread the extra mirrors evenly across the band rather than bunching them at one end.
            pick = cols[np.round(np.linspace(0, cols.size - 1, extra)).astype(int)]
            out[k, pick] += 1
    return np.minimum(out, rows)


class NoiseSeeds:
    """Fresh temporal noise for every capture on the same camera: the twin keys a frame's noise by (seed, frame
    id) and every capture restarts at frame 0, so repeated captures would otherwise repeat their noise."""

    def __init__(self, seed: int):
        self._seq = np.random.SeedSequence([int(seed), 0xCA11B])

    def next(self) -> int:
        return int(self._seq.spawn(1)[0].generate_state(1, np.uint64)[0] >> np.uint64(1))


def capture_mean(rig, patterns, repeats: int, *, noise_seed: int | None = None) -> np.ndarray:
    """(K, H, W) float64 mean of ``repeats`` captured sequences of ``patterns`` on a twin rig.

    Goes through the capture path (twin driver, ring buffer, assembler) without fault injection.
    ``noise_seed`` gives the frames fresh temporal noise (the camera's fixed pattern is unchanged).
    """
    patterns = np.atleast_2d(np.asarray(patterns, np.int32))
    k = patterns.shape[0]
    if noise_seed is not None:
        rig.seed = int(noise_seed)
    driver = TwinDriver(rig, patterns=patterns, n_frames=k * int(repeats), faults=FaultSchedule(), pacing="free")
    acc = np.zeros((k, *rig.camera.shape))
    count = 0

    def add(seq):
        nonlocal count
        acc[...] += seq.frames
        count += 1

    capture_sequences(driver, k, on_sequence=add)
    if count == 0:
        raise RuntimeError("capture_mean: no complete sequence was captured")
    return acc / count


def centre_window(shape, fraction: float = 0.25):
    """(rows, columns) slices of the central ``fraction`` of a frame of ``shape`` (at least one pixel each way)."""
    h, w = shape
    dh, dw = max(1, int(h * fraction / 2)), max(1, int(w * fraction / 2))
    return slice(h // 2 - dh, h // 2 + dh), slice(w // 2 - dw, w // 2 + dw)


def twin_at_exposure(description, scene, exposure_s=None, seed=None):
    """A twin rig on ``scene``; with ``exposure_s``, the frame rate is lowered if the exposure needs it."""
    d = description
    if exposure_s is not None:
        cam = d.camera
        rate = min(cam.frame_rate_hz, 1.0 / (float(exposure_s) + d.light.switch_time_s + 1e-6))
        d = replace(d, camera=replace(cam, exposure_s=float(exposure_s), frame_rate_hz=rate))
    return TwinRig(d, scene=scene, seed=seed)


@runtime_checkable
class CalibrationRig(Protocol):
    """What the calibration procedure reads from a rig (twin or hardware), and nothing more.

    Attributes
    ----------
    light
        The light source: ``params`` (columns, rows, ``line_fwhm_nm``, ``switch_time_s``), ``wavelengths`` (its
        uniform grid, nm), ``column_wavelengths``, ``minimum_exposure_s`` (s), ``load_sequence((K, C))`` and
        ``check_pattern``.
    spectroradiometer
        ``wavelengths`` (nm, the instrument's output grid) and ``params.bandwidth_nm``.
    exposure_s : float
        The calibration exposure (s): the dark level is measured at it; other exposures are asked for by value.
    frame_shape : tuple of int
        (H, W) of the camera's frames.
    max_code : int
        Top ADC code of the frames (DN).
    frame_period_s : float
        Frame period at the calibration exposure (s); the longest exposure is this less the light's switch time.
    max_spectrum : numpy.ndarray or None
        (G,) the light's spectral irradiance with every mirror on (W m^-2 nm^-1) when the rig knows it (the twin);
        ``None`` on hardware, where calibration uses the spectroradiometer's all-on reading instead.
    """

    light: object
    spectroradiometer: object
    exposure_s: float
    frame_shape: tuple
    max_code: int
    frame_period_s: float
    max_spectrum: np.ndarray | None

    def capture_mean(self, patterns: ArrayLike, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        """(K, H, W) float64 mean of ``repeats`` captured sequences of ``patterns`` (K, C) mirror counts, at
        ``exposure_s`` (the calibration exposure by default). ``noise_seed`` gives simulated frames fresh temporal
        noise; real frames always have it, so hardware ignores it."""

    def measure_spectrum(self, pattern_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Show loaded pattern ``pattern_index`` and read the spectroradiometer: (wavelengths nm, W m^-2 nm^-1)."""

    def zero_spectrometer(self) -> None:
        """Take the spectroradiometer's dark reading with the light off (a no-op where there is none)."""

    # Optional: ``capture_dark(repeats, *, exposure_s=None, noise_seed=None)`` -> (H, W) mean of frames with no
    # light reaching the sensor (lens capped, shutter closed). With it, calibration tells the camera's own dark
    # level from the light the object receives with every mirror off (room light, the DMD's off-state): see
    # :func:`~specgpu.calibration.procedure.calibrate` step (6). A rig without it is assumed to have such light
    # (plans then add an ambient frame).


class TwinCalibrationRig:
    """The digital twin as a :class:`CalibrationRig`: one :class:`~specgpu.rig.twin.TwinRig` per exposure, all
    looking at the same scene (the reference white), frames through the twin driver, ring buffer and assembler.

    Parameters
    ----------
    description : RigDescription, optional
        The rig (the paper's by default).
    scene
        What the camera sees (a white plate of reflectance 0.99 by default).
    rig : TwinRig, optional
        Use this twin (its description and scene) for the calibration exposure instead of building one.
    """

    def __init__(self, description: RigDescription | None = None, *, scene: SpectralScene | None = None, rig=None):
        if rig is not None:
            self.rig = rig
            self.description = rig.description
            self._scene = rig.scene
        else:
            d = description if description is not None else RigDescription()
            self.description = d
            self._scene = scene if scene is not None else white_plate_scene(d.camera.roi_height, d.camera.roi_width)
            self.rig = twin_at_exposure(d, self._scene)
        self._by_exposure: dict[float, object] = {}
        #: The rig's own clock (s): it runs on through every capture and spectrum reading of the calibration, so the
        #: lamp drifts during the procedure as on a bench; :func:`~specgpu.calibration.procedure.calibrate` records
        #: where it ended.
        self.clock_s = float(self.rig.clock_start_s)

    # the rig at each exposure; the calibration exposure's is ``rig`` itself (its spectroradiometer too)
    def _at(self, exposure_s):
        if exposure_s is None:
            return self.rig
        t = float(exposure_s)
        if t not in self._by_exposure:
            self._by_exposure[t] = twin_at_exposure(self.description, self._scene, t)
        return self._by_exposure[t]

    @property
    def light(self):
        return self.rig.light

    @property
    def spectroradiometer(self):
        return self.rig.spectroradiometer

    @property
    def exposure_s(self) -> float:
        return self.rig.exposure_s

    @property
    def frame_shape(self) -> tuple:
        return tuple(self.rig.camera.shape)

    @property
    def max_code(self) -> int:
        return int(self.rig.camera.params.max_code)

    @property
    def frame_period_s(self) -> float:
        return self.rig.frame_period_s

    @property
    def max_spectrum(self) -> np.ndarray:
        return self.rig.light.max_spectrum

    def capture_mean(self, patterns: ArrayLike, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        rig = self._at(exposure_s)
        if rig.clock_start_s != self.clock_s:
            rig.set_clock(self.clock_s)
        out = capture_mean(rig, patterns, repeats, noise_seed=noise_seed)
        self.clock_s += np.atleast_2d(patterns).shape[0] * int(repeats) * rig.frame_period_s
        return out

    #: Seconds one spectroradiometer reading takes on the rig's clock (integration and read-out).
    SPECTRUM_READ_S = 0.2

    def measure_spectrum(self, pattern_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        d = self.description
        power = 1.0 + (d.light.drift_per_hour + d.realism.lamp_output_drift_per_hour) * self.clock_s / 3600.0
        self.clock_s += self.SPECTRUM_READ_S
        return self.rig.measure_spectrum(pattern_index, power=max(power, 0.0))

    def zero_spectrometer(self) -> None:
        """The twin's spectroradiometer has no dark offset."""

    def capture_dark(self, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        """(H, W) float64 mean of ``repeats`` frames with no light reaching the sensor (the lens capped): the
        camera's own dark level (offset, dark current) at ``exposure_s``. The twin renders a black object."""
        t = self.exposure_s if exposure_s is None else float(exposure_s)
        capped = self.__dict__.setdefault("_capped", {})
        if t not in capped:
            h, w = self.frame_shape
            capped[t] = twin_at_exposure(self.description, white_plate_scene(h, w, reflectance=0.0), t)
        rig = capped[t]
        out = capture_mean(rig, np.zeros((1, rig.light.params.columns), np.int32), repeats, noise_seed=noise_seed)[0]
        self.clock_s += int(repeats) * rig.frame_period_s
        return out


def as_calibration_rig(rig) -> CalibrationRig:
    """``rig`` as a :class:`CalibrationRig`: a TwinRig is wrapped, a CalibrationRig passed through."""
    if isinstance(rig, TwinRig):
        return TwinCalibrationRig(rig=rig)
    if isinstance(rig, CalibrationRig):
        return rig
    raise TypeError(f"a calibration needs a TwinRig or a CalibrationRig, got {type(rig).__name__}")
