"""Motion of the photographed world during a capture: the rig TOML's ``[motion]`` table and its trajectory.

A sequence takes K frame periods; whatever moves in that time lands on different pixels in different frames. The
twin renders each frame at its own exposure time from this model (``TwinRig.render``)::

    [motion]
    velocity_px_per_frame = [3.0, 1.0]     # the scene (or the camera) translates, x and y, pixels per frame period
    rotation_deg_per_frame = 0.0           # and turns about the centre of the field
    vibration_rms_px = 0.5                 # a tripod's shake: RMS of the 2-D displacement, pixels
    vibration_hz = 20.0                    # its band limit: a random walk (amplitude ~ 1/f) below this frequency
    object = "chart.npz"                   # a second scene moving over the background, occluding it
    object_size_px = [120, 160]            # its height and width on the sensor (centred at time 0)
    object_velocity_px_per_frame = [3.0, 0.0]
    blur = true                            # integrate each frame over its exposure

Time is counted in frame periods from frame 0's exposure start. The background's displacement at time ``t`` is
``p(t) = v t + vibration(t)`` and its rotation ``omega t``: a point of the scene at ``s`` is seen at
``x = R(omega t) (s - c) + c + p(t)`` (``c`` the centre of the field). Images are resampled bilinearly; what
comes into view from beyond the edge of the scene repeats its border pixels. The object, a rectangle of its own
scene, is seen at ``s_o + q(t)`` with ``q(t) = v_o t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from specgpu.core.validate import check_number
from specgpu.rig.tables import build_table

__all__ = ["MotionParameters", "MOTION_KEYS", "motion_from_table", "MovingScene", "Trajectory", "magnify_image",
           "warp_image"]

#: Largest speed accepted, px per frame period: beyond it a frame is smeared over a good part of the field.
MAX_SPEED = 200.0


@dataclass(frozen=True)
class MotionParameters:
    """The ``[motion]`` table; every default is a still world (the twin's frames then do not depend on it).

    Attributes
    ----------
    velocity_px_per_frame : tuple of float
        (x, y) translation of the scene on the sensor per frame period, px.
    rotation_deg_per_frame : float
        Rotation of the scene about the centre of the field per frame period, degrees (counter-clockwise on screen).
    vibration_rms_px : float
        RMS of the 2-D displacement of a band-limited random walk (a tripod's shake), px.
    vibration_hz : float
        Band limit of the vibration, Hz.
    object : str
        A second scene (built-in name or cube path) moving over the background, or "" for none.
    object_size_px : tuple of int
        (height, width) of the object on the sensor, px; (0, 0): a third of the field each way.
    object_velocity_px_per_frame : tuple of float
        (x, y) translation of the object per frame period, px.
    blur : bool
        Integrate each frame over its exposure (motion blur) instead of sampling it at mid-exposure.
    seed : int
        Seed of the vibration's random phases and frequencies.
    """

    velocity_px_per_frame: tuple = (0.0, 0.0)
    rotation_deg_per_frame: float = 0.0
    vibration_rms_px: float = 0.0
    vibration_hz: float = 20.0
    object: str = ""
    object_size_px: tuple = (0, 0)
    object_velocity_px_per_frame: tuple = (0.0, 0.0)
    blur: bool = False
    seed: int = 0

    def __post_init__(self):
        for name in ("velocity_px_per_frame", "object_velocity_px_per_frame"):
            v = getattr(self, name)
            if not isinstance(v, (tuple, list)) or len(v) != 2:
                raise ValueError(f"motion.{name} must be a list of 2 numbers [x, y], got {v!r}")
            v = tuple(check_number(f"motion.{name}", c, low=-MAX_SPEED, high=MAX_SPEED) for c in v)
            object.__setattr__(self, name, v)
        object.__setattr__(self, "rotation_deg_per_frame",
                           check_number("motion.rotation_deg_per_frame", self.rotation_deg_per_frame, low=-10, high=10))
        object.__setattr__(self, "vibration_rms_px",
                           check_number("motion.vibration_rms_px", self.vibration_rms_px, low=0, high=100))
        object.__setattr__(self, "vibration_hz",
                           check_number("motion.vibration_hz", self.vibration_hz, low=0, low_open=True, high=1e5))
        if not isinstance(self.object, str):
            raise ValueError(f"motion.object must be a string (a scene name or cube path), got {self.object!r}")
        size = self.object_size_px
        if not isinstance(size, (tuple, list)) or len(size) != 2:
            raise ValueError(f"motion.object_size_px must be a list of 2 integers [height, width], got {size!r}")
        object.__setattr__(self, "object_size_px",
                           tuple(check_number("motion.object_size_px", c, low=0, high=1 << 16, integer=True)
                                 for c in size))
        if not isinstance(self.blur, bool):
            raise ValueError(f"motion.blur must be true or false, got {self.blur!r}")
        object.__setattr__(self, "seed", check_number("motion.seed", self.seed, low=0, high=2**63 - 1, integer=True))

    @property
    def any(self) -> bool:
        """True when anything moves."""
        return bool(any(self.velocity_px_per_frame) or self.rotation_deg_per_frame or self.vibration_rms_px
                    or self.object)

    def to_dict(self) -> dict:
        return {f.name: (list(getattr(self, f.name)) if isinstance(getattr(self, f.name), tuple)
                         else getattr(self, f.name)) for f in fields(self)}


MOTION_KEYS = tuple(f.name for f in fields(MotionParameters))


def motion_from_table(table, source: str = "<dict>") -> MotionParameters:
    """The ``[motion]`` table of a rig TOML as :class:`MotionParameters`; every error is one line naming the
    file and the key."""
    return build_table(MotionParameters, table, "motion", source)


def _shift_axis(image: np.ndarray, d: float, axis: int, out: np.ndarray | None = None) -> np.ndarray:
    """``image`` moved by ``d`` px along ``axis``, linearly interpolated, the edge values repeated beyond the
    border: ``out[x] = (1 - f) image[clip(x + k)] + f image[clip(x + k + 1)]`` with ``k + f = -d`` (``k`` whole,
    ``0 <= f < 1``). A translation has one ``f`` for every pixel, so this is slicing and one blend, with no gather;
    no move (``d == 0``) is a copy.
    """
    if out is None:
        out = np.empty_like(image)
    if d == 0:
        np.copyto(out, image)
        return out
    n = image.shape[axis]
    k = math.floor(-d)
    f = image.dtype.type(-d - k)

    def span(start: int, stop: int) -> tuple:
        index = [slice(None)] * image.ndim
        index[axis] = slice(start, stop)
        return tuple(index)

    lo, hi = max(0, -k), min(n, n - 1 - k)  # both neighbours x + k and x + k + 1 inside the image
    if lo < hi:
        a0 = image[span(lo + k, hi + k)]
        blend = out[span(lo, hi)]
        np.subtract(image[span(lo + k + 1, hi + k + 1)], a0, out=blend)
        blend *= f
        blend += a0
    first = min(lo, n)  # x + k + 1 <= 0: the first value
    out[span(0, first)] = image[span(0, 1)]
    last = max(first, hi)  # x + k >= n - 1: the last value
    out[span(last, n)] = image[span(n - 1, n)]
    return out


def magnify_image(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` (..., H, W) magnified by ``scale`` about the centre of its last two axes, resampled bilinearly
    (border pixels repeated): ``out(x) = image(c + (x - c) / scale)``. The same as scipy's ``ndimage.affine_transform``
    with the diagonal matrix ``1 / scale`` at order 1 and ``mode="nearest"`` (to the float's rounding): a scaling
    moves each axis on its own, so it is two linear interpolations, one per axis, on every leading plane at once."""
    out = image
    for axis in (-2, -1):
        n = image.shape[axis]
        centre = (n - 1) / 2.0
        source = centre + (np.arange(n, dtype=np.float64) - centre) / float(scale)
        below = np.floor(source)
        weight = (source - below).astype(image.dtype)
        low = below.astype(np.intp)
        high = np.clip(low + 1, 0, n - 1)
        np.clip(low, 0, n - 1, out=low)
        a0 = np.take(out, low, axis=axis)
        blend = np.take(out, high, axis=axis)
        blend -= a0
        blend *= weight if axis == -1 else weight[:, None]
        blend += a0
        out = blend
    return out


def warp_image(image: np.ndarray, shift, angle_deg: float = 0.0, out: np.ndarray | None = None) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) moved by ``shift`` = (x, y) px and turned by ``angle_deg`` about the field's
    centre, resampled bilinearly (border pixels repeated): ``out(x) = image(R(-angle) (x - c - shift) + c)``; the
    channels of a (H, W, C) image move together.

    A translation is two linear interpolations, one per axis: the same as scipy's ``ndimage.shift`` at order 1 with
    ``mode="nearest"`` (to the float's rounding) and several times faster, on a whole cube at once."""
    from scipy import ndimage

    h, w = image.shape[:2]
    dx, dy = float(shift[0]), float(shift[1])
    if not angle_deg:
        if not np.issubdtype(image.dtype, np.floating):
            return ndimage.shift(image, (dy, dx) + (0,) * (image.ndim - 2), order=1, mode="nearest", output=out,
                                 prefilter=False)
        rows = image if dy == 0 else _shift_axis(image, dy, 0)  # the column pass never writes into its input
        return _shift_axis(rows, dx, 1, out)
    if image.ndim == 3:
        if out is None:
            out = np.empty_like(image)
        for c in range(image.shape[2]):
            out[..., c] = warp_image(np.ascontiguousarray(image[..., c]), shift, angle_deg)
        return out
    a = math.radians(angle_deg)
    # (row, col) -> source: R(-a) in image coordinates (x right, y down; counter-clockwise on screen is -a in y-down)
    c, s = math.cos(a), math.sin(a)
    matrix = np.array([[c, s], [-s, c]])  # rows (y, x) of R(-a) for y pointing down, counter-clockwise on screen
    centre = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    offset = centre - matrix @ (centre + np.array([dy, dx]))
    return ndimage.affine_transform(image, matrix, offset=offset, order=1, mode="nearest", output=out,
                                    prefilter=False)


class Trajectory:
    """Where the background and the object are at any time (in frame periods), for one :class:`MotionParameters`
    and frame rate; deterministic for the parameters' seed."""

    _PARTIALS = 24  # sinusoids per axis of the vibration

    def __init__(self, params: MotionParameters, frame_rate_hz: float, field_radius_px: float = 400.0):
        self.params = params
        self.field_radius_px = float(field_radius_px)  # centre to corner: how far a rotation moves the field most
        self.frame_rate_hz = float(frame_rate_hz)
        p = params
        if p.vibration_rms_px:
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([p.seed, 0x51B])))
            n = self._PARTIALS
            # frequencies spread over (hz / n, hz], amplitudes ~ 1/f (a random walk's spectrum), random phases;
            # each axis carries half the variance, so the 2-D RMS is vibration_rms_px
            f = p.vibration_hz * rng.uniform(1.0 / n, 1.0, (2, n))
            amp = 1.0 / f
            amp *= (p.vibration_rms_px / math.sqrt(2.0)) / np.sqrt(0.5 * np.sum(amp**2, axis=1, keepdims=True))
            self._vib = (f / self.frame_rate_hz, amp, rng.uniform(0, 2 * math.pi, (2, n)))
        else:
            self._vib = None

    def displacement(self, t_frames) -> np.ndarray:
        """(..., 2) displacement (x, y) of the background at times ``t_frames`` (frame periods), px."""
        t = np.asarray(t_frames, np.float64)
        d = t[..., None] * np.asarray(self.params.velocity_px_per_frame, np.float64)
        if self._vib is not None:
            f, amp, ph = self._vib
            arg = 2 * math.pi * t[..., None, None] * f + ph  # (..., 2, n)
            d = d + np.sum(amp * (np.sin(arg) - np.sin(ph)), axis=-1)  # zero at t = 0
        return d

    def angle(self, t_frames) -> np.ndarray:
        """Rotation of the background at ``t_frames`` (frame periods), degrees."""
        return np.asarray(t_frames, np.float64) * self.params.rotation_deg_per_frame

    def maps(self, t_frames, t_ref: float, shape) -> np.ndarray:
        """(N, 2, 3) affine maps taking a background point's position (x, y) at ``t_ref`` to its position at each
        of ``t_frames`` (frame periods), for a field of ``shape`` (height, width)."""
        h, w = shape
        c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        t = np.atleast_1d(np.asarray(t_frames, np.float64))
        d = self.displacement(t)
        d_ref = self.displacement(float(t_ref))
        out = np.empty((t.size, 2, 3))
        for i, a in enumerate(np.radians(self.angle(t) - self.angle(float(t_ref)))):
            # a turn by +a counter-clockwise on screen (y down) is (cos a, sin a; -sin a, cos a) in (x, y)
            rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
            out[i, :, :2] = rot
            out[i, :, 2] = c + d[i] - rot @ (c + d_ref)
        return out

    def object_displacement(self, t_frames) -> np.ndarray:
        """(..., 2) displacement (x, y) of the object at ``t_frames``, px."""
        t = np.asarray(t_frames, np.float64)
        return t[..., None] * np.asarray(self.params.object_velocity_px_per_frame, np.float64)

    def sample_times(self, start_frames: float, exposure_frames: float) -> np.ndarray:
        """Times (frame periods) at which one frame's exposure is sampled: its middle, or with ``blur`` enough
        points over the exposure that the image moves at most a quarter pixel between them (at most 16)."""
        mid = start_frames + exposure_frames / 2.0
        if not self.params.blur:
            return np.array([mid])
        t = np.array([start_frames, start_frames + exposure_frames])
        travel = float(np.max(np.abs(np.diff(self.displacement(t), axis=0))))
        travel = max(travel, float(np.max(np.abs(np.diff(self.object_displacement(t), axis=0)))))
        travel += abs(self.params.rotation_deg_per_frame) * exposure_frames * math.pi / 180 * self.field_radius_px
        n = int(min(16, max(1, math.ceil(travel / 0.25))))
        return start_frames + (np.arange(n) + 0.5) * exposure_frames / n


class MovingScene:
    """The per-pattern images of a moving world, composed at any time.

    The image of pattern ``k`` is linear in the reflectance of each pixel, so moving the scene moves the image:
    each pattern's noise-free image of the still background (``images``, electrons before the light's field and
    the sensor's PRNU, which stay on the sensor) is computed once, and a frame at time ``t`` is that image warped
    to the background's pose at ``t``, the object's image laid over it where its (warped) footprint is, and, with
    ``blur``, averaged over the exposure.

    Parameters
    ----------
    trajectory : Trajectory
    images : numpy.ndarray
        (K, H, W) per-pattern images of the background scene, float32.
    ambient : numpy.ndarray or None
        (H, W) image of the room light on the background (not shaped by the light's field).
    object_images, object_ambient : numpy.ndarray or None
        The same of the object, on a full (H, W) canvas with the object centred.
    object_alpha : numpy.ndarray or None
        (H, W) float32 footprint of the object on that canvas (1 inside).
    """

    def __init__(self, trajectory: Trajectory, images, ambient=None, object_images=None, object_ambient=None,
                 object_alpha=None):
        self.trajectory = trajectory
        self.images, self.ambient = images, ambient
        self.object_images, self.object_ambient, self.object_alpha = object_images, object_ambient, object_alpha

    def _pose(self, image: np.ndarray, t: float, obj: bool, out=None) -> np.ndarray:
        tr = self.trajectory
        if obj:
            return warp_image(image, tr.object_displacement(t), 0.0, out)
        return warp_image(image, tr.displacement(t), float(tr.angle(t)), out)

    def compose(self, layers, t: float) -> np.ndarray:
        """(H, W) or (H, W, B) background layer over which the object layer (if any) is laid, at time ``t`` (frame
        periods); ``layers`` = (background image, object image or None), both 2-D or both 3-D."""
        bg, ob = layers
        img = self._pose(bg, t, False)
        if ob is not None and self.object_alpha is not None:
            a = self._pose(self.object_alpha, t, True)
            if img.ndim == 3:
                a = a[..., None]
            img += a * (self._pose(ob, t, True) - img)
        return img

    def frame(self, k: int, start_frames: float, exposure_frames: float, field: np.ndarray) -> np.ndarray:
        """(H, W) float32 mean signal (electrons, PRNU not applied) of pattern ``k`` exposed from ``start_frames``
        for ``exposure_frames`` (frame periods), lit through ``field``."""
        times = self.trajectory.sample_times(start_frames, exposure_frames)
        obj = None if self.object_images is None else self.object_images[k]
        acc = None
        for t in times:
            img = self.compose((self.images[k], obj), float(t))
            img *= field
            if self.ambient is not None:
                img += self.compose((self.ambient, self.object_ambient), float(t))
            acc = img if acc is None else acc + img
        if len(times) > 1:
            acc /= np.float32(len(times))
        return acc.astype(np.float32, copy=False)

    def reflectance(self, cube: np.ndarray, object_cube: np.ndarray | None, t: float) -> np.ndarray:
        """(H, W, B) reflectance seen at time ``t``: the background cube posed, the object's laid over it (every
        band moved at once)."""
        return self.compose((cube, object_cube), t)

    def object_mask(self, t: float) -> np.ndarray | None:
        """(H, W) float32 footprint of the object at ``t`` (fractional at its resampled edges), or None."""
        if self.object_alpha is None:
            return None
        return self._pose(self.object_alpha, t, True)
