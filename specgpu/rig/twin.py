"""The synchronous capture system, simulated: camera master -> strobe -> light trigger (paper Section 2.D).

Timing of frame ``k`` (``P`` the frame period, ``t_exp`` the exposure)::

    exposure starts at   t_k = k P + jitter_k          (jitter: truncated Gaussian, |jitter| <= 2 sigma)
    strobe at its end    t_k + t_exp  -> trigger -> the light loads the next pattern (62 us) and settles (18 us)
    frame k+1 exposes    only after the pattern has settled, so P >= t_exp + 80 us + 4 sigma_jitter is required

so each frame is lit by exactly one pattern. Frame 0 is lit by pattern 0 (loaded before the start). A missed
trigger leaves the light on its pattern, so that frame is lit by the previous frame's pattern and every later
frame lags one pattern behind (as a hardware sequencer would). A dropped frame was exposed (the light advanced)
but never reaches the host; a duplicated frame is delivered twice with the same id and content.

Rendering is built for speed: each pattern's noise-free frame (scene, spot field profile, PRNU, exposure and
gain folded into one DN map per pattern, plus one offset map with pedestal, dark current and DSNU) is computed once
per loaded sequence; a frame then costs one table-driven Gaussian draw and a few vectorized passes over
cache-sized chunks, with the noise's variance derived from the signal itself so that shot noise follows the
light's power exactly (``tools/benchmarks/twin_speed.py`` measures frames/s).
Everything random is keyed by (seed, frame id), so a frame's content does not depend on which other frames
were rendered: a run is deterministic for a seed, and a duplicate is re-rendered bit-identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import check_number
from specgpu.rig.camera import _NORMAL_TABLE, Camera, standard_normal_fill
from specgpu.rig.config import FaultRates, RigDescription
from specgpu.rig.light import K_M, ProgrammableLight, lamp_change, photopic_y
from specgpu.rig.lights import make_light
from specgpu.rig.motion import MovingScene, Trajectory, magnify_image
from specgpu.rig.scene import SpectralScene, interpolation_matrix, load_scene, white_plate_scene
from specgpu.rig.spectroradiometer import Spectroradiometer

__all__ = ["FaultSchedule", "TwinRig", "SNRReport", "measure_snr", "band_patterns"]

_BLOCK = 4096
_CHUNK = 1 << 16


@dataclass(frozen=True)
class FaultSchedule:
    """Which frames suffer which fault: explicit frame ids, plus optional random rates (deterministic per seed).

    Attributes
    ----------
    dropped : frozenset of int
        Frame ids exposed but never delivered.
    duplicated : frozenset of int
        Frame ids delivered twice (same id, same content). Disjoint from ``dropped``.
    missed_triggers : frozenset of int
        Frame ids (>= 1: frame 0 has no trigger) whose trigger the light misses.
    jitter_s : float
        Standard deviation (s) of the exposure start times around the nominal grid (truncated at 2 sigma).
    rates : FaultRates or None
        Per-frame probabilities applied on top of the explicit sets, drawn from ``seed``.
    seed : int
        Seed of the random faults and of the jitter.
    """

    dropped: frozenset = frozenset()
    duplicated: frozenset = frozenset()
    missed_triggers: frozenset = frozenset()
    jitter_s: float = 0.0
    rates: FaultRates | None = None
    seed: int = 0

    def __post_init__(self):
        for name in ("dropped", "duplicated", "missed_triggers"):
            ids = frozenset(getattr(self, name))
            bad = [i for i in ids if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or i < 0]
            if bad:
                raise ValueError(f"faults.{name} must hold frame ids >= 0, got {bad[:3]}")
            object.__setattr__(self, name, frozenset(int(i) for i in ids))
        if 0 in self.missed_triggers:
            raise ValueError("faults.missed_triggers cannot hold frame 0: the first frame has no trigger")
        both = self.dropped & self.duplicated
        if both:
            raise ValueError(f"frame {min(both)} is both dropped and duplicated")
        check_number("faults.jitter_s", self.jitter_s, low=0, high=1)
        if self.rates is not None and self.rates.jitter_s > 0 and self.jitter_s == 0:
            object.__setattr__(self, "jitter_s", self.rates.jitter_s)

    @classmethod
    def from_rates(cls, rates: FaultRates, seed: int = 0) -> "FaultSchedule":
        """Random faults at the given per-frame rates."""
        return cls(rates=rates, seed=int(seed), jitter_s=rates.jitter_s)

    @lru_cache(maxsize=64)
    def _block(self, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 0xFA17, b])))
        u = rng.random((3, _BLOCK))
        jitter = np.clip(rng.standard_normal(_BLOCK), -2.0, 2.0) * self.jitter_s
        r = self.rates
        if r is None:
            z = np.zeros(_BLOCK, bool)
            return z, z, z, jitter
        drop = u[0] < r.drop_rate
        dup = (u[1] < r.duplicate_rate) & ~drop
        miss = u[2] < r.missed_trigger_rate
        if b == 0:
            miss[0] = False
        return drop, dup, miss, jitter

    def faults(self, frame_id: int) -> tuple[bool, bool, bool, float]:
        """(dropped, duplicated, missed trigger, jitter in s) for one frame."""
        k = int(frame_id)
        drop, dup, miss, jit = self._block(k // _BLOCK)
        i = k % _BLOCK
        dropped = k in self.dropped or bool(drop[i])
        duplicated = (k in self.duplicated or bool(dup[i])) and not dropped
        missed = k in self.missed_triggers or bool(miss[i])
        return dropped, duplicated, missed, float(jit[i])


class TwinRig:
    """The simulated rig: light, camera and scene, with the per-pattern noise-free frames cached.

    Parameters
    ----------
    description
        :class:`~specgpu.rig.config.RigDescription` (defaults: the paper's rig).
    scene
        A :class:`SpectralScene`, a built-in name or a cube path; the description's scene by default. Resampled to
        the camera's ROI.
    seed
        Overrides ``description.seed``: the camera's fixed pattern and all temporal noise derive from it.
    clock_start_s
        The rig's own clock (s since the lamp was started) at this rig's frame 0: the lamp's drifts per hour
        (``[realism]``) act on ``clock_start_s + timestamp``, so a capture that starts where a calibration ended
        sees the lamp as it has become (the colour temperature is taken at the clock when the light is built or
        :meth:`set_clock` is called; the output drift frame by frame, and so is the colour temperature's drift
        since then, to first order: each pattern's power on a white changes by its own relative slope per K, the
        shape inside a band held; at the lab's -20 K/h that is 0.006 K over a 1 s sequence, 3 K over a 10 min
        stream).

    Raises
    ------
    ValueError
        If the exposure is shorter than the light's switch time (80 us) or the frame period leaves no room for the
        light to switch between exposures.
    """

    def __init__(self, description: RigDescription | None = None, *, scene: SpectralScene | None = None,
                 seed: int | None = None,
                 clock_start_s: float = 0.0):
        self.description = description if description is not None else RigDescription()
        d = self.description
        self.seed = int(d.seed if seed is None else seed)
        self.realism = d.realism
        self.clock_start_s = check_number("clock_start_s", clock_start_s, low=0)
        self._cct_slope = None
        self.light = make_light(d.light, seed=self.seed, realism=d.realism, drift=d.drift,
                                clock_s=self.clock_start_s, exposure_s=d.camera.exposure_s)
        self.camera = Camera(d.camera, seed=self.seed, realism=d.realism if d.realism.any else None)
        self.spectroradiometer = Spectroradiometer(d.spectroradiometer, seed=self.seed)
        cam = d.camera
        where = "" if d.source.startswith("<") else f"{d.source}: "
        try:
            self.light.check_exposure(cam.exposure_s, "camera.exposure_s")
        except ValueError as exc:
            raise ValueError(f"{where}{exc}") from None
        if cam.exposure_s + d.light.switch_time_s > self.frame_period_s * (1 + 1e-12):
            raise ValueError(
                f"{where}camera.exposure_s = {cam.exposure_s:g} s plus the light's {d.light.switch_time_s * 1e6:.0f} "
                f"us switch time exceeds the frame period {self.frame_period_s:g} s at {cam.frame_rate_hz:g} fps")
        self.field = self.light.field_profile(*self.camera.shape, self.camera.pixel_mm)
        self._scene: SpectralScene | None = None
        self.set_scene(d.scene if scene is None else scene)

    # ---- configuration ------------------------------------------------------------------------------------
    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.description.camera.frame_rate_hz

    @property
    def exposure_s(self) -> float:
        return self.description.camera.exposure_s

    @property
    def slack_s(self) -> float:
        """Time between the light settling and the next exposure at nominal timing (s)."""
        return self.frame_period_s - self.exposure_s - self.description.light.switch_time_s

    @property
    def scene(self) -> SpectralScene:
        return self._scene

    def set_scene(self, scene: SpectralScene) -> None:
        """Photograph another scene (built-in name, path or :class:`SpectralScene`), resampled to the ROI."""
        self._scene = load_scene(scene, *self.camera.shape)
        self._maps = None
        self._moving = None

    def load_sequence(self, patterns: ArrayLike) -> None:
        """Load a (K, columns) pattern sequence into the light; the per-pattern frames are recomputed lazily."""
        self.light.load_sequence(patterns)
        self._maps = None

    def set_clock(self, clock_s: float) -> None:
        """Set the rig's clock at frame 0 (s); the lamp's colour is re-evaluated if it drifts on the clock."""
        self.clock_start_s = check_number("clock_s", clock_s, low=0)
        if self.realism.lamp_cct_drift_K_per_hour:
            seq = self.light.sequence
            d = self.description
            self.light = make_light(d.light, seed=self.seed, realism=d.realism, drift=d.drift,
                                    clock_s=self.clock_start_s, exposure_s=d.camera.exposure_s)
            self.light.load_sequence(seq)
            self._maps = None

    def _field_terms(self):
        """(vignetted spot profile, radial weight q in [0, 1]) of the field, or None on an ideal rig."""
        r = self.realism
        if not (r.vignetting or r.field_colour):
            return None
        cached = getattr(self, "_field_cache", None)
        if cached is None:
            h, w = self.camera.shape
            y = np.arange(h) - (h - 1) / 2.0
            x = np.arange(w) - (w - 1) / 2.0
            q = ((x[None, :] ** 2 + y[:, None] ** 2) / ((w - 1) ** 2 / 4.0 + (h - 1) ** 2 / 4.0)).astype(np.float32)
            cached = self._field_cache = (self.field * (1.0 - np.float32(r.vignetting) * q), q)
        return cached

    def _optics(self, e: np.ndarray, weights: np.ndarray, wl: np.ndarray) -> np.ndarray:
        """Lens blur and lateral chromatic aberration of each pattern's image, in place: each (H, W) map is
        magnified about the centre by ``1 + lateral_ca_px / r_corner * (lambda_k - 550) / 150`` at the pattern's
        centroid wavelength ``lambda_k`` (so the corner moves ``lateral_ca_px`` between 550 and 700 nm), then blurred
        by a Gaussian of ``blur_px``."""
        from scipy import ndimage

        r = self.realism
        h, w = self.camera.shape
        corner = math.hypot((h - 1) / 2.0, (w - 1) / 2.0)
        total = weights.sum(axis=1)
        lam = np.where(total > 0, (weights @ wl) / np.where(total > 0, total, 1.0), 550.0)
        for k in range(e.shape[0]):
            img = e[k]
            if not img.any():  # no light (a capped lens, a dark pattern): magnified and blurred, still zero
                continue
            if r.lateral_ca_px:
                img = magnify_image(img, 1.0 + r.lateral_ca_px / corner * (lam[k] - 550.0) / 150.0)
            if r.blur_px:
                img = ndimage.gaussian_filter(img, r.blur_px, mode="nearest")
            e[k] = img
        return e

    # ---- the physics ----------------------------------------------------------------------------------------
    def signal_electrons(self, spectra: ArrayLike | None = None) -> np.ndarray:
        """(K, H, W) mean photo-electrons per pattern (field profile included, PRNU not), float32.

        ``spectra``: (K, grid) irradiance on the light's grid; the loaded sequence's by default.
        """
        sp = self.light.sequence_spectra if spectra is None else np.atleast_2d(np.asarray(spectra, np.float64))
        wl = self.light.wavelengths
        resp = self.camera.responsivity(wl)
        weights = self.exposure_s * sp * resp[None, :]
        wb = self._scene.band_weights(wl, weights).astype(np.float32)  # (K, B)
        images = self._scene.weighted_images
        e = images(wb)
        r = self.realism
        terms = self._field_terms()
        if terms is None:
            e *= self.field[None]
        else:  # wavelength-dependent field: spot * vignetting * (1 + q(x) c(lambda)), c linear in lambda
            spot, q = terms
            if r.field_colour:
                c = r.field_colour * (wl - 550.0) / 150.0
                e1 = images(self._scene.band_weights(wl, weights * c[None, :]).astype(np.float32))
                e += q[None] * e1
            e *= spot[None]
        if r.ambient_lux:  # room light on the object, not shaped by the spot (vignetted by the lens)
            amb = self.exposure_s * ambient_spectrum(wl, r.ambient_lux) * resp
            ea = images(self._scene.band_weights(wl, amb[None, :]).astype(np.float32))[0]
            if terms is not None:
                ea = ea * (1.0 - np.float32(r.vignetting) * terms[1])
            e += ea[None]
        if r.blur_px or r.lateral_ca_px:
            e = self._optics(e, weights, wl)
        return e

    def _ensure_maps(self):
        # The light's sequence may also be loaded through the driver interface (driver.light.load_sequence).
        if self._maps is not None and self._maps_version == self.light.sequence_version:
            return self._maps
        self._maps_version = self.light.sequence_version
        cam = self.camera
        p = cam.params
        g = np.float32(p.gain_e_per_dn)
        sig = self.signal_electrons()  # (K, H, W) e-; worked on in place to keep the peak memory at one copy
        sig *= cam.prnu[None]
        np.maximum(sig, 0.0, out=sig)
        dark = cam.dark_electrons(self.exposure_s)
        mean_dn = sig
        mean_dn /= g
        offset_dn = (np.float32(p.pedestal_e + dark) + cam.dsnu_e) / g + np.float32(0.5)
        self._var_floor = np.float32((dark + p.read_noise_e**2) / p.gain_e_per_dn**2)
        self._maps = (mean_dn, offset_dn.astype(np.float32))
        self._chunk_scratch = np.empty(_CHUNK, np.float32)
        self._cct_slope = self._colour_slopes()
        self._moving = self._moving_scene() if self.description.motion.any else None
        return self._maps

    def _moving_scene(self) -> MovingScene:
        """The per-pattern images of the scene (and of the ``[motion]`` object) before the field, for frames of a
        moving world."""
        d, r = self.description, self.realism
        if self._field_terms() is not None or r.blur_px or r.lateral_ca_px:
            raise ValueError(f"{d.source}: [motion] needs a rig without realism.vignetting, field_colour, blur_px "
                             "and lateral_ca_px (they act on the sensor's image, not on the moving scene)")
        h, w = self.camera.shape
        wl = self.light.wavelengths
        resp = self.camera.responsivity(wl)
        weights = self.exposure_s * self.light.sequence_spectra * resp[None, :]
        amb = self.exposure_s * ambient_spectrum(wl, r.ambient_lux) * resp if r.ambient_lux else None

        def images(scene, wts):
            wb = scene.band_weights(wl, wts).astype(np.float32)
            return (wb @ scene.reflectance.reshape(-1, wb.shape[1]).T).reshape(-1, *scene.shape)

        bg = images(self._scene, weights)
        ambient = None if amb is None else images(self._scene, amb[None, :])[0]
        m = d.motion
        if not m.object:
            return MovingScene(Trajectory(m, d.camera.frame_rate_hz, math.hypot(h, w) / 2), bg, ambient)
        oh, ow = m.object_size_px if all(m.object_size_px) else (max(1, h // 3), max(1, w // 3))
        try:
            obj = load_scene(m.object, min(oh, h), min(ow, w), resize="stretch")
        except ValueError as exc:  # a built-in drawn too small for its layout, or an unreadable cube
            raise ValueError(f"{d.source}: [motion] object {m.object!r} at object_size_px = [{oh}, {ow}]: "
                             f"{exc}") from None
        y0, x0 = (h - obj.shape[0]) // 2, (w - obj.shape[1]) // 2
        where = (slice(None), slice(y0, y0 + obj.shape[0]), slice(x0, x0 + obj.shape[1]))
        canvas = np.zeros_like(bg)
        canvas[where] = images(obj, weights)
        alpha = np.zeros((h, w), np.float32)
        alpha[where[1:]] = 1.0
        cube = np.zeros((h, w, self._scene.wavelengths.size), np.float32)
        cube[where[1:]] = obj.reflectance @ interpolation_matrix(self._scene.wavelengths, obj.wavelengths).T
        self._object_cube = cube
        oamb = None
        if amb is not None:
            oamb = np.zeros((h, w), np.float32)
            oamb[where[1:]] = images(obj, amb[None, :])[0]
        return MovingScene(Trajectory(m, d.camera.frame_rate_hz, math.hypot(h, w) / 2), bg, ambient, canvas, oamb,
                           alpha)

    def moving_mean(self, pattern_index: int, timestamp_s: float) -> np.ndarray:
        """(H, W) noise-free signal (DN above the offset, float32) of a frame of a moving world exposed from
        ``timestamp_s``: what :meth:`render` draws its noise around (the still world's is a per-pattern map)."""
        mean_dn, _ = self._ensure_maps()
        if self._moving is None:
            return mean_dn[pattern_index]
        period = self.frame_period_s
        sig = self._moving.frame(pattern_index, timestamp_s / period, self.exposure_s / period, self.field)
        sig *= self.camera.prnu
        np.maximum(sig, 0.0, out=sig)
        sig /= np.float32(self.camera.params.gain_e_per_dn)
        return sig

    def motion_truth(self, timestamps_s: ArrayLike) -> dict:
        """The truth of one sequence at its reference time, the mean of its frames' mid-exposure times.

        Returns
        -------
        dict
            ``reflectance`` (H, W, B) the scene as it is at the reference time; ``displacement`` (K, 2) each
            frame's displacement (x, y) of the background from the reference time to its mid-exposure, px (a scene
            point at x at the reference time is at x + displacement in that frame, the rotation aside);
            ``maps`` (K, 2, 3) the affine maps of reference-time positions to each frame's (rotation included);
            ``reference_time_s``; ``object_mask`` (H, W) the object's footprint at the reference time (None
            without an object).
        """
        self._ensure_maps()
        period = self.frame_period_s
        mid = (np.asarray(timestamps_s, np.float64) + self.exposure_s / 2.0) / period
        t_ref = float(np.mean(mid))
        if self._moving is None:
            return {"reflectance": self._scene.reflectance, "displacement": np.zeros((mid.size, 2)),
                    "maps": np.tile(np.eye(2, 3), (mid.size, 1, 1)), "reference_time_s": t_ref * period,
                    "object_mask": None}
        tr = self._moving.trajectory
        obj = self._object_cube if self._moving.object_images is not None else None
        return {"reflectance": self._moving.reflectance(self._scene.reflectance, obj, t_ref),
                "displacement": tr.displacement(mid) - tr.displacement(t_ref),
                "maps": tr.maps(mid, t_ref, self.camera.shape),
                "reference_time_s": t_ref * period, "object_mask": self._moving.object_mask(t_ref)}

    def _colour_slopes(self) -> np.ndarray | None:
        """(K,) relative change of each loaded pattern's output on a white per K of lamp colour temperature (from
        the lamp's state at the clock start), or None when the colour does not drift on the clock."""
        rate = self.realism.lamp_cct_drift_K_per_hour
        if not rate or not self.light.lamp_colour_drifts:  # an LED has no lamp
            return None
        lp = self.light
        now = lp.drift.lamp_cct_K + rate * lp.clock_s / 3600.0
        wl = lp.wavelengths
        step = lamp_change(lp.params, wl, now + 1.0, 0.0) / lamp_change(lp.params, wl, now, 0.0) - 1.0
        w = lp.sequence_spectra * self.camera.responsivity(wl)[None, :]
        tot = w.sum(axis=1)
        return np.where(tot > 0, (w @ step) / np.where(tot > 0, tot, 1.0), 0.0)

    def expected_frame(self, pattern_index: int, power: float = 1.0) -> np.ndarray:
        """Noise-free mean output (DN, float32, before rounding) of a frame lit by a pattern at relative power."""
        mean_dn, offset_dn = self._ensure_maps()
        x = mean_dn[pattern_index] * np.float32(power)
        if self.realism.nonlinearity:
            x = x * (1.0 - np.float32(self.realism.nonlinearity) * (x / np.float32(self.camera.params.max_code)) ** 2)
        return x + (offset_dn - np.float32(0.5))

    def temporal_std(self, pattern_index: int, power: float = 1.0) -> np.ndarray:
        """Per-pixel temporal standard deviation (DN) of the camera noise (shot, dark, read; no quantization)
        for a frame lit by a pattern at a relative light power."""
        mean_dn, _ = self._ensure_maps()
        g = np.float32(self.camera.params.gain_e_per_dn)
        return np.sqrt(mean_dn[pattern_index] * np.float32(power) / g + self._var_floor)

    def measure_spectrum(self, pattern_index: int | None = None, power: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Measure a loaded pattern's emission with the rig's spectroradiometer (paper Fig. 8(b)).

        Returns (wavelengths nm, spectral irradiance W m^-2 nm^-1) at the spot centre, with the instrument's
        bandpass and noise; ``power`` scales the emission (e.g. a drifted lamp).
        """
        spd = self.light.emitted_spectrum(pattern_index) * check_number("power", power, low=0)
        return self.spectroradiometer.wavelengths, self.spectroradiometer.measure(spd, self.light.wavelengths)

    def plan_exposure(self, level: float = 0.8, *, percentile: float = 99.9) -> tuple[float, float]:
        """The exposure (s) that brings the brightest loaded pattern to ``level`` of the full well.

        The ``percentile`` of the pixels of the brightest pattern's noise-free signal is placed at ``level``; the
        exposure is capped by the frame period minus the light's switch time and floored at the light's minimum.

        Returns
        -------
        exposure_s, level_reached : float
            The exposure, and the fraction of the full well it reaches (below ``level`` when capped).
        """
        level = check_number("level", level, low=0, low_open=True, high=1)
        check_number("percentile", percentile, low=0, high=100)
        e = self.signal_electrons() * self.camera.prnu[None]
        per_s = max(float(np.percentile(e[k], percentile)) for k in range(e.shape[0])) / self.exposure_s
        if not per_s > 0:
            raise ValueError("plan_exposure: the loaded patterns give no signal on this scene")
        wanted = level * self.camera.params.full_well_e / per_s
        longest = self.frame_period_s - self.description.light.switch_time_s
        t = min(max(wanted, self.light.minimum_exposure_s), longest)
        return t, t * per_s / self.camera.params.full_well_e

    def frame_rng(self, frame_id: int) -> np.random.Generator:
        """The generator of one frame's randomness, keyed by (seed, frame id)."""
        return np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 0x7E3, int(frame_id)])))

    def render(self, pattern_index: int, frame_id: int, timestamp_s: float, out: np.ndarray | None = None,
               scratch: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, float]:
        """Render one noisy frame lit by a loaded pattern into uint16 ``out``; return (out, relative light power).

        ``scratch`` may hold two float32 (H, W) work arrays to avoid allocations in a streaming loop. The noise
        source is :attr:`noise`: ``"fresh"`` draws new Gaussian samples for every frame; ``"pool"`` takes a
        randomly placed window of a pre-drawn pool of 32 frames of samples (about 3x faster: per-pixel temporal
        statistics are unchanged, but a frame's noise is a shifted copy of pool content, so spatial noise
        patterns recur across frames; use it for throughput work, not for noise studies).
        """
        mean_dn, offset_dn = self._ensure_maps()
        rng = self.frame_rng(frame_id)
        f = float(self.light.power_factors(np.array([timestamp_s + self.clock_start_s]), self.exposure_s, rng)[0])
        if self._cct_slope is not None:  # the colour temperature's drift since the clock start, this pattern's share
            f *= 1.0 + float(self._cct_slope[pattern_index]) * self.realism.lamp_cct_drift_K_per_hour * (
                float(timestamp_s) / 3600.0)
        if scratch is None:
            x = np.empty(self.camera.shape, np.float32)
            z = np.empty(self.camera.shape, np.float32)
        else:
            x, z = scratch
        if out is None:
            out = np.empty(self.camera.shape, np.uint16)
        for name, arr, dtype in (("out", out, np.uint16), ("scratch", x, np.float32), ("scratch", z, np.float32)):
            if arr.shape != self.camera.shape or arr.dtype != dtype or not arr.flags.c_contiguous:
                raise ValueError(f"{name} must be a C-contiguous {self.camera.shape} {np.dtype(dtype).name} array, "
                                 f"got {arr.shape} {arr.dtype}")
        n = x.size
        xf, zf, of = x.reshape(-1), z.reshape(-1), out.reshape(-1)
        mean, offset = mean_dn[pattern_index].reshape(-1), offset_dn.reshape(-1)
        if self._moving is not None:  # the world moves: this frame's own noise-free image, at its exposure time
            mean = self.moving_mean(pattern_index, timestamp_s).reshape(-1)
        if self.noise == "pool":
            pool = self._noise_pool()
            base = int(rng.integers(0, pool.size - n + 1))
        else:
            idx = rng.bit_generator.random_raw((n + 3) // 4).view(np.uint16)
        fs = np.float32(f)
        inv_g = np.float32(1.0 / self.camera.params.gain_e_per_dn)
        top = np.float32(self.camera.params.max_code + 0.5)
        w = self._chunk_scratch
        nl = np.float32(self.realism.nonlinearity / float(self.camera.params.max_code) ** 2)
        # Per chunk small enough to stay in cache (the frame is memory-bound, so each map is read once):
        # signal x = f * mean; variance = x / g + (dark + read^2) / g^2 (shot noise follows the light's power
        # exactly); x + offset + sqrt(variance) * z, rounded half up and clipped.
        for a in range(0, n, _CHUNK):
            b = min(n, a + _CHUNK)
            m = b - a
            xs, zs, ws = xf[a:b], zf[a:b], w[:m]
            np.multiply(mean[a:b], fs, out=xs)
            np.multiply(xs, inv_g, out=zs)
            np.add(zs, self._var_floor, out=zs)
            np.sqrt(zs, out=zs)
            if self.noise == "pool":
                np.multiply(zs, pool[base + a:base + b], out=zs)
            else:
                np.take(_NORMAL_TABLE, idx[a:b], out=ws)
                np.multiply(zs, ws, out=zs)
            if nl:  # compression near full well acts on the signal (with its noise), not on the offset
                np.add(xs, zs, out=xs)
                np.multiply(xs, xs, out=zs)
                np.multiply(zs, nl, out=zs)
                np.subtract(np.float32(1.0), zs, out=zs)
                np.multiply(xs, zs, out=xs)
                np.add(xs, offset[a:b], out=xs)
            else:
                np.add(xs, offset[a:b], out=xs)  # offset_dn carries the +0.5 of round-half-up
                np.add(xs, zs, out=xs)
            np.clip(xs, np.float32(0.5), top, out=xs)
            np.copyto(of[a:b], xs, casting="unsafe")  # truncation of x + 0.5 >= 0.5: round half up
        return out, f

    noise = "fresh"
    _POOL_FRAMES = 32

    def set_noise(self, mode: str) -> None:
        """Choose the noise source of :meth:`render`: ``"fresh"`` (default) or ``"pool"``."""
        if mode not in ("fresh", "pool"):
            raise ValueError(f"noise must be one of fresh, pool, got {mode!r}")
        self.noise = mode

    def _noise_pool(self) -> np.ndarray:
        pool = getattr(self, "_pool", None)
        if pool is None:
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 0x9001])))
            pool = np.empty(self._POOL_FRAMES * self.camera.shape[0] * self.camera.shape[1], np.float32)
            standard_normal_fill(rng, pool)
            self._pool = pool
        return pool


def ambient_spectrum(wavelengths, lux: float) -> np.ndarray:
    """Spectral irradiance (W m^-2 nm^-1) of room light at ``lux``: CIE FL2 (a cool-white fluorescent tube, the
    commonest lab ceiling light) scaled to that illuminance."""
    wl = np.asarray(wavelengths, np.float64)
    sd = colour.SDS_ILLUMINANTS["FL2"]
    spd = np.interp(wl, sd.wavelengths, sd.values, left=0.0, right=0.0)
    lux_per_unit = K_M * float(np.sum(spd * photopic_y(wl)) * (wl[1] - wl[0]))
    return spd * (lux / lux_per_unit) if lux_per_unit > 0 else spd * 0.0


def band_patterns(light: ProgrammableLight, bands_nm) -> np.ndarray:
    """(K, columns) patterns with every mirror on in the columns whose centre lies in each [low, high) band (nm)."""
    cw = light.column_wavelengths
    out = np.zeros((len(bands_nm), light.params.columns), np.int32)
    for k, (lo, hi) in enumerate(bands_nm):
        out[k, (cw >= lo) & (cw < hi)] = light.params.rows
    return out


@dataclass(frozen=True)
class SNRReport:
    """Result of :func:`measure_snr` (paper Section 2.F).

    Attributes
    ----------
    sensor_db : float
        Camera-only SNR, dB: the same measurement with the light's fluctuation, drift and flicker off.
    temporal_db : float
        SNR of the R, G, B sequence with the light's own fluctuation, dB (mean of the three channels).
    sensor_db_per_channel, temporal_db_per_channel : dict
        Per illuminant ("R", "G", "B").
    mean_dn : dict
        Dark-subtracted mean output per illuminant, DN.
    repeats, frame_rate_hz, exposure_s : as measured.
    """

    sensor_db: float
    temporal_db: float
    sensor_db_per_channel: dict
    temporal_db_per_channel: dict
    mean_dn: dict
    repeats: int
    frame_rate_hz: float
    exposure_s: float


RGB_BANDS_NM = {"R": (600.0, 700.0), "G": (500.0, 600.0), "B": (400.0, 500.0)}


def measure_snr(description: RigDescription | None = None, *, repeats: int = 100, frame_rate_hz: float = 90.0,
                level: float = 0.75, seed: int = 0) -> SNRReport:
    """Measure the paper's two SNR figures on the twin, the way the paper did.

    R (600-700 nm), G (500-600 nm) and B (400-500 nm) illuminants are projected in turn onto a reference white
    plate at ``frame_rate_hz`` (R1, G1, B1, R2, ...), ``repeats`` images of each are captured through the twin's
    driver path, and per pixel ``SNR = mean / std`` over the repeats is pooled over the frame as
    ``20 log10(mean of the dark-subtracted means / RMS of the standard deviations)``; the dark level comes from
    ``repeats`` frames with every mirror off. Each band's mirror count is set so the white plate gives ``level``
    of the full well, as the paper's calibration loop equalizes the sequence. The temporal figure includes the
    light's fluctuation; the sensor figure repeats the measurement with the light perfectly steady, so it is
    the camera's own noise (shot, dark current, read, quantization). (The paper says its 44.2 dB was "derived by
    measuring dark current" without naming the signal level; taking the camera-only figure at the same operating
    point as the temporal one makes the two comparable, and their difference is then the light's share.) Fault
    injection and pacing in the description are ignored: the measurement needs every frame, at full speed.

    Parameters
    ----------
    description
        The rig (defaults: the paper's). Its camera exposure is kept if it fits the frame rate, else shortened.
    repeats
        Images per illuminant, >= 2 (paper: 100).
    frame_rate_hz
        Frame rate (paper: 90 fps).
    level
        Target mean signal as a fraction of the full well, in (0, 1).
    seed
        Seed of the run.

    Raises
    ------
    ValueError
        If the light is too dim to reach ``level`` in the exposure the frame rate allows.
    """
    repeats = check_number("repeats", repeats, low=2, integer=True)
    level = check_number("level", level, low=0, low_open=True, high=1)
    d = description if description is not None else RigDescription()
    period = 1.0 / check_number("frame_rate_hz", frame_rate_hz, low=0, low_open=True)
    exposure = min(d.camera.exposure_s, period - d.light.switch_time_s)
    cam = replace(d.camera, frame_rate_hz=float(frame_rate_hz), exposure_s=exposure)
    steady = replace(d.light, fluctuation_rms=0.0, drift_per_hour=0.0, flicker_amplitude=0.0)
    results = {}
    for label, light in (("temporal", d.light), ("sensor", steady)):
        desc = replace(d, camera=cam, light=light, seed=seed)
        rig = TwinRig(desc, scene=white_plate_scene(cam.roi_height, cam.roi_width))
        full = band_patterns(rig.light, RGB_BANDS_NM.values())
        e_full = rig.signal_electrons(rig.light.pattern_to_spectrum(full)).mean(axis=(1, 2))
        target = level * cam.full_well_e
        if np.any(e_full * (1 + 3 * cam.prnu_rms) < target):
            weakest = list(RGB_BANDS_NM)[int(np.argmin(e_full))]
            raise ValueError(f"the light is too dim: band {weakest} gives {e_full.min():.0f} e- with every mirror on, "
                             f"below {level:g} of the full well at {frame_rate_hz:g} fps")
        patterns = np.rint(full * (target / e_full)[:, None]).astype(np.int32)
        dark_mean = _dark_mean(desc, repeats)
        rig.load_sequence(patterns)
        h, w = rig.camera.shape
        s1 = np.zeros((3, h, w))
        s2 = np.zeros((3, h, w))
        for k, frame in _fault_free_frames(rig, 3 * repeats):
            f = frame.astype(np.float64)
            s1[k % 3] += f
            s2[k % 3] += f * f
        mean = s1 / repeats
        var = (s2 - s1 * mean) / (repeats - 1)
        per = {}
        levels = {}
        for k, name in enumerate(RGB_BANDS_NM):
            mu = float(np.mean(mean[k] - dark_mean))
            per[name] = 20.0 * math.log10(mu / math.sqrt(float(np.mean(var[k]))))
            levels[name] = mu
        results[label] = (per, levels)
    t_per, levels = results["temporal"]
    s_per, _ = results["sensor"]
    return SNRReport(float(np.mean(list(s_per.values()))), float(np.mean(list(t_per.values()))), s_per, t_per,
                     levels, repeats, float(frame_rate_hz), exposure)


def _fault_free_frames(rig: TwinRig, n_frames: int):
    """Yield (frame id, frame) for ``n_frames`` fault-free frames of the loaded sequence, pattern ``k % K`` at
    ``k`` frame periods: what the capture path's twin driver delivers with no faults, without importing it (the
    rig model never imports capture/). The frame array is reused between yields."""
    n_patterns = rig.light.sequence.shape[0]
    frame = np.empty(rig.camera.shape, np.uint16)
    scratch = (np.empty(rig.camera.shape, np.float32), np.empty(rig.camera.shape, np.float32))
    for k in range(int(n_frames)):
        rig.render(k % n_patterns, k, k * rig.frame_period_s, frame, scratch)
        yield k, frame


def _dark_mean(desc: RigDescription, repeats: int) -> np.ndarray:
    rig = TwinRig(desc, scene=white_plate_scene(desc.camera.roi_height, desc.camera.roi_width))
    rig.load_sequence(np.zeros((1, desc.light.columns), np.int32))
    acc = np.zeros(rig.camera.shape)
    for _, frame in _fault_free_frames(rig, repeats):
        acc += frame
    return acc / repeats
