"""The calibration procedure: both loops and the camera's measurements on a rig, into a bundle.

:func:`calibrate` runs the whole procedure on a rig through the capture path (driver, ring buffer, assembler) and
returns a :class:`~specgpu.calibration.bundle.CalibrationBundle`. It is written once against
:class:`~specgpu.calibration.rigs.CalibrationRig`, so the twin and a real rig calibrate the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from specgpu.calibration.bundle import (
    DEFAULT_MAX_EXPOSURE_S,
    CalibrationBundle,
    measure_line_shapes,
    primary_lines,
    rig_fingerprint,
)
from specgpu.calibration.loops import camera_loop, spectral_loop
from specgpu.calibration.rigs import (
    CalibrationRig,
    NoiseSeeds,
    TwinCalibrationRig,
    as_calibration_rig,
    centre_window,
    distribute_counts,
)
from specgpu.core.numerics import DEAD_PIXEL_GAIN, fit_levels
from specgpu.rig.config import RigDescription
from specgpu.rig.lights import light_kind, light_summary
from specgpu.rig.scene import white_plate_scene

__all__ = ["MIRRORS_OFF_TOLERANCE", "calibrate"]


@dataclass
class _Bench:
    """The rig under calibration and what every step shares: the frames' noise seeds (drawn in the procedure's
    order, so a twin calibration repeats exactly), the sequences averaged per measurement, and the central windows
    of the frame where outputs are read (a quarter of the frame, and 5 % of it for the flat field's reference)."""

    rig: CalibrationRig
    seeds: NoiseSeeds
    repeats: int
    win: tuple = field(init=False)
    small: tuple = field(init=False)

    def __post_init__(self):
        self.win = centre_window(self.rig.frame_shape)
        self.small = centre_window(self.rig.frame_shape, 0.05)

    def capture(self, patterns, repeats, **kwargs) -> np.ndarray:
        """Mean frames of ``patterns`` with fresh temporal noise."""
        return self.rig.capture_mean(patterns, repeats, noise_seed=self.seeds.next(), **kwargs)


@dataclass(frozen=True)
class _ColumnMap:
    """Step (2)'s result: what the spectroradiometer says about the light's columns."""

    wavelengths: np.ndarray  # (C,) the column-wavelength map, nm
    power: np.ndarray  # (C,) each column's power, every mirror on
    slope: float  # the straight line through the probes' centroids, nm per column
    intercept: float  # nm
    all_on: np.ndarray  # the spectroradiometer's reading with every mirror on, on its own grid
    line: tuple | None  # (offsets, shapes) of the measured line shape, or None for the design Gaussian


def _check_arguments(white_reflectance, white_uncertainty, band_step_nm, perturbation, repeats, line_shape) -> None:
    """Refuse :func:`calibrate`'s arguments out of range, before any measurement."""
    if not 0 < white_reflectance <= 1.5:
        raise ValueError(f"white_reflectance must lie in (0, 1.5], got {white_reflectance!r}")
    if not 0 <= white_uncertainty <= 0.2:
        raise ValueError(f"white_uncertainty must lie in [0, 0.2], got {white_uncertainty!r}")
    if not 2 <= band_step_nm <= 50:
        raise ValueError(f"band_step_nm must lie in [2, 50], got {band_step_nm!r}")
    if not 0 <= perturbation <= 0.9:
        raise ValueError(f"perturbation must lie in [0, 0.9], got {perturbation!r}")
    if int(repeats) < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}")
    if line_shape not in ("measured", "gaussian"):
        raise ValueError(f"line_shape must be 'measured' or 'gaussian', got {line_shape!r}")


def _calibration_rig(description: RigDescription, rig, white_reflectance: float) -> CalibrationRig:
    """The rig to measure: ``rig`` as a :class:`CalibrationRig`, or by default the twin of ``description`` looking at
    a white plate. The twin's white is what the certificate says, off by the bench's ``white_error`` (its truth)."""
    if rig is not None:
        return as_calibration_rig(rig)
    d = description
    return TwinCalibrationRig(d, scene=white_plate_scene(
        d.camera.roi_height, d.camera.roi_width, reflectance=white_reflectance * (1.0 + d.realism.white_error)))


def _dark_level(bench: _Bench, zero, t_cal: float):
    """Step (1): the all-off frame at the calibration exposure and a short one; their difference per second is the
    dark current. Returns (dark (H, W), short exposure s, dark there (H, W), dark current DN/s)."""
    rig = bench.rig
    dark = bench.capture(zero, 2 * bench.repeats)[0]
    t_short = _whole_periods(rig, max(rig.light.minimum_exposure_s, t_cal / 4))
    dark_short = bench.capture(zero, 2 * bench.repeats, exposure_s=t_short)[0]
    rate = float(np.mean(dark - dark_short) / (t_cal - t_short)) if t_cal > t_short else 0.0
    return dark, t_short, dark_short, rate


def _probe_centroids(rig):
    """The spectroradiometer's reading of 48 narrow probes (8 columns each, every mirror on) across the DMD.
    Returns (first column of each probe, centroid wavelength of each reading nm, the readings)."""
    p = rig.light.params
    probe_cols = np.linspace(16, p.columns - 24, 48).astype(int)
    probes = np.zeros((probe_cols.size, p.columns), np.int32)
    for i, c in enumerate(probe_cols):
        probes[i, c:c + 8] = p.rows
    rig.light.load_sequence(probes)
    inst = rig.spectroradiometer.wavelengths
    cents, probe_spectra = [], []
    for i in range(probe_cols.size):
        s = np.mean([rig.measure_spectrum(i)[1] for _ in range(2)], axis=0)
        probe_spectra.append(s)
        peak = int(np.argmax(s))
        sel = np.abs(inst - inst[peak]) <= 6.0 + p.line_fwhm_nm  # the probe's band, not noise far away
        if not np.sum(s[sel]) > 0:
            raise ValueError(f"calibrate: the spectroradiometer sees no light from probe columns {probe_cols[i]}-"
                             f"{probe_cols[i] + 7}; check the light, the fibre and the instrument")
        cents.append(float(np.sum(inst[sel] * s[sel]) / np.sum(s[sel])))
    return probe_cols, np.array(cents), probe_spectra


def _column_wavelengths(columns: int, probe_cols, cents):
    """The column-wavelength map from the probes' centroids: (map (C,) nm, slope nm/column, intercept nm)."""
    slope, icpt = np.polyfit(probe_cols + 3.5, cents, 1)
    # Non-parametric map: the straight line plus a smoothed interpolation of the probes' departures from it (a
    # grating's map is not straight in column position: bow), held at the ends' departure beyond the probes.
    resid = cents - (icpt + slope * (probe_cols + 3.5))
    if resid.size >= 5:
        resid = np.convolve(np.pad(resid, 2, mode="edge"), np.ones(5) / 5.0, mode="valid")
    col_wl = icpt + slope * np.arange(columns) + np.interp(np.arange(columns), probe_cols + 3.5, resid)
    if np.any(np.diff(col_wl) <= 0):  # a noisy reading must not fold the map: keep the straight line then
        col_wl = icpt + slope * np.arange(columns)
    return col_wl, slope, icpt


def _column_map(bench: _Bench, line_shape: str) -> _ColumnMap:
    """Step (2), the spectroradiometer: the column-wavelength map from narrow probes, the lamp's power per column
    from the all-on spectrum and, with ``line_shape="measured"``, the line shape from the probes' readings."""
    rig = bench.rig
    light, p = rig.light, rig.light.params
    rig.zero_spectrometer()
    probe_cols, cents, probe_spectra = _probe_centroids(rig)
    col_wl, slope, icpt = _column_wavelengths(p.columns, probe_cols, cents)
    inst = rig.spectroradiometer.wavelengths
    light.load_sequence(np.full((1, p.columns), p.rows, np.int32))
    full = np.mean([rig.measure_spectrum(0)[1] for _ in range(4)], axis=0)
    col_power = np.interp(col_wl, inst, full) * np.abs(np.gradient(col_wl))
    line = None
    response = getattr(rig.spectroradiometer, "response_matrix", None)
    if line_shape == "measured" and response is not None:
        # Only the readings near each probe: far away lie the DMD's off-state and stray background, not the line.
        half = 2.5 * p.line_fwhm_nm
        near = [np.abs(inst - c_i) <= half + 2.0 * rig.spectroradiometer.params.bandwidth_nm for c_i in cents]
        line = measure_line_shapes(probe_spectra, probe_cols, 8, col_wl, col_power, response(light.wavelengths),
                                   light.wavelengths, half, masks=near)
    return _ColumnMap(col_wl, col_power, slope, icpt, full, line)


def _primary_map(bench: _Bench) -> _ColumnMap:
    """Step (2) for a light of a few broad primaries (an LED array): each primary alone at full level, read by the
    spectroradiometer (four readings averaged) onto the light's grid; each primary's centroid is its wavelength,
    its integral its power, its unit-area shape the measured line. The reading is used as it is: the instrument's
    bandpass (5 nm) barely widens a 15-35 nm LED, and solving it out amplifies the noise more than it removes (on
    the twin, 0.2-0.7 % of the peak RMS as read against 1-3 % solved out)."""
    rig = bench.rig
    light, p = rig.light, rig.light.params
    rig.zero_spectrometer()
    grid, inst = light.wavelengths, rig.spectroradiometer.wavelengths
    light.load_sequence(np.eye(p.columns, dtype=np.int32) * p.rows)
    spectra = []
    for c in range(p.columns):
        s = np.mean([rig.measure_spectrum(c)[1] for _ in range(4)], axis=0)
        if not s.max() > 0:
            raise ValueError(f"calibrate: the spectroradiometer sees no light from primary {c}; check the light, "
                             "the fibre and the instrument")
        spectra.append(np.interp(grid, inst, s, left=0.0, right=0.0))
    centroid, power, line = primary_lines(grid, np.stack(spectra, axis=1), p.line_fwhm_nm)
    if np.any(np.diff(centroid) <= 0):
        raise ValueError("calibrate: the light's primaries are not in order of wavelength (centroids "
                         f"{', '.join(f'{x:.1f}' for x in centroid)} nm)")
    light.load_sequence(np.full((1, p.columns), p.rows, np.int32))
    full = np.mean([rig.measure_spectrum(0)[1] for _ in range(4)], axis=0)
    return _ColumnMap(centroid, power, 0.0, 0.0, full, line)


def _whole_periods(rig, exposure_s: float) -> float:
    """``exposure_s`` rounded to whole periods of the light's PWM or grey levels (unchanged for the DMD), so every
    exposure calibration asks for gives the levels exactly."""
    q = float(getattr(rig.light.params, "exposure_quantum_s", 0.0))
    return exposure_s if q <= 0 else max(1, round(exposure_s / q)) * q


#: A pixel whose white reading is under this fraction of the field centre's is unlit (outside the light's spot, or
#: dead): its gain is DEAD_PIXEL_GAIN, which the decoders read as "no measurement" (NaN). Calibration refuses a
#: field with more than UNLIT_SHARE of them (isolated dead pixels stay under it).
UNLIT_FRACTION = 1.0 / DEAD_PIXEL_GAIN
UNLIT_SHARE = 1e-3


def _flat_field(bench: _Bench, dark):
    """Step (3): the flat field from a broadband pattern on the white at about half the camera's range.
    Returns (flat (H, W) float32, its mirror count, the probe's mirror count, the probe's level DN, the number of
    unlit pixels: dead, or outside the light, their gain DEAD_PIXEL_GAIN)."""
    rig, win, small = bench.rig, bench.win, bench.small
    p, max_code = rig.light.params, int(rig.max_code)
    n_probe = p.rows // 8
    while True:  # a probe level that does not saturate, to scale the flat-field pattern from
        probe = bench.capture(np.full((1, p.columns), n_probe, np.int32), 2)[0]
        lvl = float(np.mean((probe - dark)[win]))
        if float(probe[win].max()) < 0.95 * max_code or n_probe == 1:
            break
        n_probe = max(1, n_probe // 4)
    if not lvl > 0:
        raise ValueError("calibrate: the white gives no signal; check the light and the camera")
    n_flat = int(min(p.rows, max(1, round(n_probe * 0.5 * max_code / lvl))))  # about half the range
    white_mean = bench.capture(np.full((1, p.columns), n_flat, np.int32), 2 * bench.repeats)[0] - dark
    centre = float(np.median(white_mean[small]))
    unlit_map = white_mean * DEAD_PIXEL_GAIN <= centre  # under UNLIT_FRACTION of the centre: every live gain < 50
    unlit = float(np.mean(unlit_map))
    if unlit > UNLIT_SHARE:  # a few dead pixels pass; a field the light does not cover has no flat field
        raise ValueError(f"calibrate: {unlit:.1%} of the camera's {white_mean.shape[1]} x {white_mean.shape[0]} "
                         f"field gets under {UNLIT_FRACTION:.0%} of the centre's light on the white: the light's "
                         "spot does not cover the field; frame a smaller field (camera.object_pixel_um, a longer "
                         "lens) or widen the spot (light.spot_diameter_mm)")
    # a dead pixel (or one stuck at the dark level) reads no white: its gain is DEAD_PIXEL_GAIN, which the decoders
    # read as "no measurement" (NaN), rather than ~1e8, which would make the bundle unloadable; its count is reported
    flat = (centre / np.maximum(white_mean, centre / DEAD_PIXEL_GAIN)).astype(np.float32)
    flat[unlit_map] = DEAD_PIXEL_GAIN
    # the float32 map decides (a live gain that rounds up to 50 counts as dead, as the decoders will read it)
    return flat, n_flat, n_probe, lvl, int(np.sum(flat >= DEAD_PIXEL_GAIN))


#: The bands of the wavelength-dependent flat field, nm.
_FLAT_BANDS_NM = ((400.0, 475.0), (475.0, 550.0), (550.0, 625.0), (625.0, 700.0))


def _flat_field_bands(bench: _Bench, dark, flat, n_flat: int, col_wl):
    """Wavelength-dependent flat field: the same on the white with 4 bands across 400-700 nm, each at a level that
    does not saturate (the broadband flat stays the bundle's flat_field; the bands correct it per pattern).
    Returns (flats (H, W) float32 per band, the bands' mean column wavelengths), both empty where one flat serves."""
    from scipy.ndimage import gaussian_filter

    rig, win, small = bench.rig, bench.win, bench.small
    p, max_code = rig.light.params, int(rig.max_code)
    flat_bands, flat_wl = [], []
    flat_departure = 0.0
    live = flat < DEAD_PIXEL_GAIN  # dead pixels read nothing in any band: left out, their gain kept
    for a, b in _FLAT_BANDS_NM:
        band = (col_wl >= a) & (col_wl < b)
        if not band.any():
            continue
        n_band = int(min(p.rows, max(1, round(n_flat * p.columns / band.sum() * 0.5))))
        while True:
            pat = np.where(band, n_band, 0).astype(np.int32)[None]
            m_band = bench.capture(pat, 2 * bench.repeats)[0]
            if float(m_band[win].max()) < 0.9 * max_code or n_band == 1:
                break
            n_band = max(1, n_band // 2)
        m_band = m_band - dark
        if not float(np.median(m_band[small])) > 0 or np.any(m_band[live] <= 0):
            continue  # too dim to flat-field with (the broadband flat serves)
        # keep the smooth part of the band's departure from the broadband flat (the per-pixel part is noise here),
        # blurred over the live pixels only (normalised by their weight)
        with np.errstate(divide="ignore", invalid="ignore"):
            raw = np.where(live, (float(np.median(m_band[small])) / m_band) / flat, 0.0)
        ratio = gaussian_filter(raw, 6.0, mode="nearest") / gaussian_filter(live.astype(np.float64), 6.0,
                                                                              mode="nearest")
        band_flat = (flat * ratio).astype(np.float32)
        band_flat[~live] = DEAD_PIXEL_GAIN
        flat_bands.append(band_flat)
        flat_wl.append(float(col_wl[band].mean()))
        flat_departure = max(flat_departure, float(np.max(np.abs(ratio[live] - 1.0))))
    if flat_bands and flat_departure < 0.005:
        flat_bands = []  # the field is the same at every wavelength to within the measurement: one flat serves
    return flat_bands, flat_wl


def _linearity(bench: _Bench, dark, n_probe: int, lvl: float) -> float:
    """The sensor's compression ``c`` (1/DN^2) from a broadband ramp on the white up to near the full well: the
    light is linear in the mirror count, so the departure of the output from a line is the sensor's:
    y = s (1 - c s^2), s the linear signal (DN). 0 where the ramp is too short or the departure within its noise."""
    rig, small = bench.rig, bench.small
    p, max_code = rig.light.params, int(rig.max_code)
    linearity_c = 0.0
    top = 0.92 * (max_code - float(np.mean(dark[small])))
    n_top = int(min(p.rows, max(1, n_probe * top / max(lvl, 1e-9))))
    if n_top >= 16:
        levels = np.unique(np.linspace(n_top / 8, n_top, 8).astype(int))
        ramp = bench.capture(np.repeat(levels[:, None], p.columns, axis=1).astype(np.int32), bench.repeats)
        y = np.array([float(np.mean((f - dark)[small])) for f in ramp])
        x = levels.astype(np.float64)
        if np.all(y < 0.99 * max_code) and np.all(y > 0):
            coef = np.linalg.lstsq(np.stack([x, x**3], axis=1), y, rcond=None)[0]  # y = b1 x + b3 x^3
            if coef[0] > 0:
                linearity_c = float(max(0.0, -coef[1] / coef[0] ** 3))
                if linearity_c * (max_code - float(np.mean(dark[small]))) ** 2 < 0.002:
                    linearity_c = 0.0  # below 0.2 % at full well: within the ramp's noise, no correction
    return linearity_c


def _loop_a_bands(col_wl, band_step_nm: float, band_range_nm):
    """Loop (a)'s bands of ``band_step_nm`` over ``band_range_nm`` that hold a column: (bands (K, 2) nm, masks
    (K, C))."""
    lo, hi = band_range_nm
    edges = np.arange(lo, hi - 1e-9, band_step_nm)
    bands = np.stack([edges, np.minimum(edges + band_step_nm, hi)], axis=1)
    masks = np.stack([(col_wl >= a) & (col_wl < b) for a, b in bands])
    keep = masks.any(axis=1)
    return bands[keep], masks[keep]


def _loop_a_start(bench: _Bench, dark, flat, masks, bands, t_cal: float, equalize_range_nm, white_reflectance,
                  perturbation: float, rng):
    """Loop (a)'s exposure, target and start, from every band's output with every mirror on.

    The loop runs at the exposure that lets the weakest band of the equalized range, every mirror on, reach half
    the range above dark (the paper's dim blue end would otherwise sit a few DN above the noise); the target is
    the white's reflectance times 97 % of that band's level. Returns (exposure s, output per unit reflectance DN,
    starting levels (K,), perturbed by ``perturbation``)."""
    rig, win = bench.rig, bench.win
    rows, max_code = rig.light.params.rows, int(rig.max_code)
    full_out = bench.capture(distribute_counts(np.ones(len(masks)), masks, rows), bench.repeats)
    full_out = np.array([np.mean(((f - dark) * flat)[win]) for f in full_out])
    centre = bands.mean(axis=1)
    inside = (centre >= equalize_range_nm[0]) & (centre <= equalize_range_nm[1])
    headroom = max_code - float(np.mean(dark))
    weakest = float(full_out[inside].min())
    if not weakest > 0:
        raise ValueError("calibrate: a band of the equalized range gives no signal on the white")
    longest = max(t_cal, DEFAULT_MAX_EXPOSURE_S)
    t_a = _whole_periods(rig, float(np.clip(t_cal * 0.5 * headroom / weakest, t_cal, longest)))
    full_a = full_out * (t_a / t_cal)
    level = 0.97 * float(full_a[inside].min()) / white_reflectance  # output per unit reflectance
    targets = np.full(len(masks), level * white_reflectance)
    start = np.clip(targets / np.maximum(full_a, 1e-9), 1e-3, 1.0)
    start = np.clip(start * (1 + perturbation * rng.uniform(-1, 1, start.size)), 1e-3, 1.0)
    return t_a, level, start


def _model(rig, columns: _ColumnMap, t_cal, dark, rate, flat, white_reflectance, patterns, bands):
    """The bundle from what is measured so far, with a flat responsivity (:func:`_responsivity` replaces it)."""
    light, p = rig.light, rig.light.params
    grid = light.wavelengths
    # The slit FWHM is a design value of the light; the line's measured shape (if any) replaces it in the model.
    est = CalibrationBundle(grid, columns.wavelengths, columns.power, float(p.line_fwhm_nm), p.rows,
                            np.ones_like(grid), t_cal, dark.astype(np.float32), rate, flat, int(rig.max_code),
                            light.minimum_exposure_s, rig.frame_period_s - p.switch_time_s, white_reflectance,
                            patterns, bands)
    if columns.line is not None:
        est = replace(est, line_offsets_nm=columns.line[0], line_shapes=columns.line[1])
    return est


def _responsivity(est: CalibrationBundle, loop_a, t_a: float, white_reflectance: float) -> np.ndarray:
    """The V estimate (G,): per band, output / (t * white * integral of the band's estimated emission), at its
    centroid, interpolated; then refined so that the model reproduces every band's measured output exactly."""
    grid = est.wavelengths
    e = est.emitted(loop_a.patterns)  # (K, G)
    power = e.sum(axis=1) * (grid[1] - grid[0])
    rho_band = loop_a.outputs / (t_a * white_reflectance * power)
    centroid = (e @ grid) / e.sum(axis=1)
    rho = np.interp(grid, centroid, rho_band)
    # Non-parametric refinement: V varies inside a band (sensor ripple, the light's slope), so rho is corrected
    # at each band's centroid by measured / modelled.
    dl = grid[1] - grid[0]
    for _ in range(6):
        modelled = t_a * white_reflectance * dl * (e * rho[None, :]).sum(axis=1)
        rho = rho * np.interp(grid, centroid, loop_a.outputs / modelled)
    return rho


def _light_fluctuation(bench: _Bench, dark, n_flat: int) -> float | None:
    """The light's frame-to-frame power fluctuation: 16 frames of the flat-field pattern in one sequence, the
    spread of their centre means (the camera's own noise there is a few hundredths of a per cent). Drift
    correction compares a reference white's gains with it. A camera link that drops a frame loses the sequence:
    tried three times, then left unmeasured (None)."""
    rig, small = bench.rig, bench.small
    columns = rig.light.params.columns
    fluctuation = None
    fluct_seed = bench.seeds.next()
    for attempt in range(3):
        try:
            singles = rig.capture_mean(np.full((16, columns), n_flat, np.int32), 1, noise_seed=fluct_seed + attempt)
        except RuntimeError:
            continue
        levels = np.array([float(np.mean((f - dark)[small])) for f in singles])
        if np.all(levels > 0):
            fluctuation = float(np.std(levels, ddof=1) / np.mean(levels))
        break
    return fluctuation


def _with_band_flat_fields(bundle: CalibrationBundle, flat_bands, flat_wl, col_wl) -> CalibrationBundle:
    """``bundle`` with the wavelength-dependent flat fields, placed at the bands' response centroids (lamp and
    camera weight the band) now that the model knows them, else at the bands' mean column wavelengths."""
    if not flat_bands:
        return bundle
    bundle = replace(bundle, flat_fields=np.stack(flat_bands), flat_wavelengths=np.array(flat_wl))
    grid = bundle.wavelengths
    cent = []
    for a, b in _FLAT_BANDS_NM:
        band = (col_wl >= a) & (col_wl < b)
        if band.any():
            pr = bundle.system_matrix[:, band].sum(axis=1)
            cent.append(float(pr @ grid / pr.sum()))
    if len(cent) == len(flat_wl) and np.all(np.diff(cent) > 0):
        bundle = replace(bundle, flat_wavelengths=np.array(cent))
    return bundle


def _spectral_check(rig, bundle: CalibrationBundle, all_on, equalize_range_nm, perturbation: float, rng):
    """Step (5), loop (b) as a check of the lamp model: an equal-energy spectrum at 40 % of the lamp's weakest
    point over the equalized range (the lamp as the rig knows it, else as the spectroradiometer read it with every
    mirror on)."""
    p = rig.light.params
    grid = bundle.wavelengths
    sel = (grid >= equalize_range_nm[0]) & (grid <= equalize_range_nm[1])
    lamp = rig.max_spectrum
    if lamp is None:
        lamp = np.interp(grid, rig.spectroradiometer.wavelengths, all_on)
    flat_target = np.where(sel, 0.4 * float(lamp[sel].min()), 0.0)
    if bundle.light_kind == "led":  # a few broad primaries cannot make a flat band: the closest shape they can,
        w = fit_levels(bundle.column_matrix, flat_target)  # its brightest LED at 40 % (the flat band's level would
        flat_target = bundle.column_matrix @ (0.4 * w / w.max())  # leave the LEDs a few duty steps each)
    initial = None
    if perturbation > 0:
        f = fit_levels(bundle.column_matrix, flat_target)
        initial = np.clip(np.rint(f * (1 + perturbation * rng.uniform(-1, 1, f.size)) * p.rows), 0, p.rows)
    return spectral_loop(rig, flat_target, bundle=bundle, initial=initial)


def calibrate(description: RigDescription | None = None, *, white_reflectance: float = 0.99,
              white_uncertainty: float = 0.01,
              band_step_nm: float = 10.0, band_range_nm=(380.0, 780.0), equalize_range_nm=(400.0, 700.0),
              repeats: int = 8, tolerance: float = 0.01, max_iterations: int = 10, perturbation: float = 0.0,
              spectral_check: bool = True, seed: int = 0, rig: CalibrationRig | None = None,
              line_shape: str = "gaussian") -> CalibrationBundle:
    """Calibrate a rig (the twin described by ``description``, or the real one ``rig``) and return its bundle.

    Steps: (1) dark level at two exposures (dark current); (2) spectroradiometer: column-wavelength map from
    the centroids of narrow probe patterns (linear fit) and lamp power per column from the all-on spectrum;
    (3) flat field from a broadband pattern on the reference white; (4) loop (a) on the white with
    ``band_step_nm`` bands over ``band_range_nm``, the target being the white's reflectance times the level the
    weakest band in ``equalize_range_nm`` reaches with every mirror on: the converged sequence is the 1/V
    sequence, and the outputs per band give the responsivity V (per band, at the band's centroid, interpolated);
    (5) with ``spectral_check``, loop (b) on an equal-energy target, as a check of the lamp model (reported);
    (6) the all-off level of the white from the short exposure up to the longest a plan picks by default (what
    :meth:`CalibrationBundle.dark_at` interpolates) and, where the rig can cap its lens, the camera's own dark:
    the difference is light the object gets with every mirror off (room light, the DMD's off-state), which
    scales with the object's reflectance, so plans need an ambient frame where it is found.

    Parameters
    ----------
    description : RigDescription, optional
        The rig (the paper's by default). For the twin its camera exposure is the calibration exposure; the
        bundle records its :func:`~specgpu.calibration.bundle.rig_fingerprint` either way.
    white_reflectance : float
        Reflectance of the reference white plate, in (0, 1.5] (its certificate's value).
    white_uncertainty : float
        Relative standard uncertainty of that value, in [0, 0.2] (a PTFE standard's certificate: about 0.01).
        Every responsivity scales with it, so it is a scale uncertainty of every recovered reflectance; it is
        kept in the bundle's reports (``white_reflectance_uncertainty``) and written with every recovery.
    band_step_nm : float
        Width of loop (a)'s bands, nm, in [2, 50].
    repeats : int
        Sequences averaged per measurement (>= 1).
    tolerance, max_iterations : float, int
        Loop (a)'s convergence bound (RMS relative output error) and adjustment bound.
    perturbation : float
        Relative random spread, in [0, 0.9], applied to loop (a)'s starting levels (to exercise the loop).
    spectral_check : bool
        Run loop (b) once and report it.
    seed : int
        Seed of the frames' temporal noise (twin) and of the perturbation.
    line_shape : str
        ``"gaussian"`` (default): a Gaussian of the light's design FWHM; ``"measured"``: each column's line shape
        tabulated from the spectroradiometer's probe readings
        (:func:`~specgpu.calibration.bundle.measure_line_shapes`; no model of the slit; the Gaussian where the
        spectroradiometer gives no ``response_matrix``). On the lab twin the measured shape cuts the model's
        line-shape error tenfold (``tools/studies/calibration_truth.py``) but changes no per-patch figure (loop (a)
        already pins each band's response) and moves the symmetric plan's per-pixel noise (its decoder is sensitive
        to the
        model's details), so it is not yet the default.
    rig : CalibrationRig, optional
        The rig to measure (e.g. :func:`specgpu.hardware.rig.open_calibration_rig` for real devices, looking at the
        reference white); by default the twin of ``description`` looking at a white plate of ``white_reflectance``.

    Returns
    -------
    CalibrationBundle
        Made on the rig :func:`~specgpu.calibration.bundle.rig_fingerprint` names, its loops' outcomes in
        ``reports``.

    Raises
    ------
    ValueError
        An argument out of range, or a measurement that sees no light (the message names what to check).

    Examples
    --------
    A quick calibration of the twin at the camera's smallest region of interest:

    >>> from specgpu.calibration import calibrate
    >>> from specgpu.rig.camera import CameraParameters
    >>> from specgpu.rig.config import RigDescription
    from specgpu.rig.lights import light_kind, light_summary
    >>> rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    >>> bundle = calibrate(rig, repeats=1, band_step_nm=25.0, spectral_check=False)
    >>> bundle.reports["loop_a"]["converged"]
    True
    """
    d = description if description is not None else RigDescription()
    _check_arguments(white_reflectance, white_uncertainty, band_step_nm, perturbation, repeats, line_shape)
    rig = _calibration_rig(d, rig, white_reflectance)
    bench = _Bench(rig, NoiseSeeds(seed), repeats)
    p = rig.light.params
    t_cal = float(rig.exposure_s)
    zero = np.zeros((1, p.columns), np.int32)
    dark, t_short, dark_short, rate = _dark_level(bench, zero, t_cal)  # (1)
    primaries = light_kind(p) == "led"  # a few broad primaries: each measured whole, no column map
    columns = _primary_map(bench) if primaries else _column_map(bench, line_shape)  # (2)
    flat, n_flat, n_probe, lvl, unlit = _flat_field(bench, dark)  # (3)
    flat_bands, flat_wl = _flat_field_bands(bench, dark, flat, n_flat, columns.wavelengths)
    linearity_c = _linearity(bench, dark, n_probe, lvl)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9E27]))
    bands, masks = _loop_a_bands(columns.wavelengths, band_step_nm, band_range_nm)  # (4)
    t_a, level, start = _loop_a_start(bench, dark, flat, masks, bands, t_cal, equalize_range_nm, white_reflectance,
                                      perturbation, rng)
    loop_a = camera_loop(rig, masks, np.full(len(masks), level * white_reflectance), flat_field=flat,
                         dark=dark + rate * (t_a - t_cal), initial_levels=start, repeats=repeats,
                         tolerance=tolerance, max_iterations=max_iterations, noise_seed=bench.seeds.next(),
                         exposure_s=t_a)
    est = _model(rig, columns, t_cal, dark, rate, flat, white_reflectance, loop_a.patterns, bands)
    rho = _responsivity(est, loop_a, t_a, white_reflectance)
    fluctuation = _light_fluctuation(bench, dark, n_flat)
    reports = {"source": "calibrated", "loop_a": loop_a.summary(), "band_step_nm": float(band_step_nm),
               **({} if primaries else {"column_map": {"slope_nm": float(columns.slope),
                                                        "intercept_nm": float(columns.intercept)}}),
               "level_dn_per_reflectance": level, "loop_a_exposure_s": t_a, "repeats": int(repeats),
               "white_reflectance_uncertainty": float(white_uncertainty), "linearity_c_per_dn2": linearity_c,
               "unlit_pixels": unlit}
    if fluctuation is not None:
        reports["light_fluctuation"] = fluctuation
        reports["light_fluctuation_exposure_s"] = t_cal
    if hasattr(rig, "clock_s"):
        reports["rig_clock_end_s"] = float(rig.clock_s)
    reports["slit_model"] = "measured" if columns.line is not None else "gaussian"
    if light_summary(p):  # an LED array or the OL490: what plans must know of it (the DMD's bundles unchanged)
        reports["light"] = {**light_summary(p), "primaries_nm": [float(x) for x in columns.wavelengths]
                            if primaries else []}
    bundle = replace(est, responsivity=rho, reports=reports, rig=rig_fingerprint(d))
    bundle = _with_band_flat_fields(bundle, flat_bands, flat_wl, columns.wavelengths)
    if spectral_check:  # (5)
        loop_b = _spectral_check(rig, bundle, columns.all_on, equalize_range_nm, perturbation, rng)
        bundle = replace(bundle, reports={**reports, "loop_b": loop_b.summary()})
    survey = _dark_survey(rig, zero, repeats, bench.seeds, {t_short: dark_short, t_cal: dark}, t_cal, bench.win,
                          white_reflectance, level / t_a)  # (6)
    return replace(bundle, reports={**bundle.reports, **survey})


#: Light on the object with every mirror off (room light, the DMD's off-state background) at or below this fraction
#: of the weakest equalized band's signal (every mirror on, same reflectance and exposure) counts as none: it
#: biases a reflectance by at most this much. Above it a plan needs an ambient frame.
MIRRORS_OFF_TOLERANCE = 1e-3


def _dark_survey(rig, zero, repeats, seeds, measured, t_cal, win, white_reflectance, band_dn_per_s) -> dict:
    """Step (6) of :func:`calibrate`: the all-off level on the white at the exposures plans use, and, where the rig
    can cap its lens (``capture_dark``), how much of it is light from the object rather than the camera's dark.

    The all-off frame of the white is the camera's dark (offset, dark current) plus the light that reaches the white
    with every mirror off (room light, the DMD's off-state and diffraction background). That light scales with the
    object's reflectance: a dark level measured on the white is too high for every darker object by the
    difference, and grows with exposure. Returns report entries (plain data):

    ``dark_exposures_s`` / ``dark_levels_dn``: exposures (from the calibration's short one up to the longest a
    plan picks by default) and the mean all-off level on the white at each (what :meth:`CalibrationBundle.dark_at`
    interpolates); with a capped lens, ``camera_dark_levels_dn`` at ``camera_dark_exposures_s``,
    ``mirrors_off_dn_per_s`` (the all-off light per unit reflectance at the spot centre, DN/s),
    ``mirrors_off_fraction`` (that light over the weakest equalized band's signal) and ``mirrors_off_light``
    (whether it exceeds :data:`MIRRORS_OFF_TOLERANCE`: then a plan needs an ambient frame); without,
    ``mirrors_off_light`` is None (not measured).
    """
    t_long = max(t_cal, DEFAULT_MAX_EXPOSURE_S)
    levels = dict(measured)
    for t in (_whole_periods(rig, float(np.sqrt(t_cal * t_long))), t_long):
        if t not in levels:
            levels[t] = rig.capture_mean(zero, 2 * repeats, exposure_s=t, noise_seed=seeds.next())[0]
    ts = sorted(levels)
    out = {"dark_exposures_s": [float(t) for t in ts],
           "dark_levels_dn": [float(np.mean(levels[t])) for t in ts], "mirrors_off_light": None}
    capture_dark = getattr(rig, "capture_dark", None)
    if capture_dark is None:
        return out
    capped_t = sorted({t_cal, t_long})
    capped = {t: capture_dark(2 * repeats, exposure_s=t, noise_seed=seeds.next()) for t in capped_t}
    out["camera_dark_exposures_s"] = [float(t) for t in capped_t]
    out["camera_dark_levels_dn"] = [float(np.mean(capped[t])) for t in capped_t]
    light = max(0.0, float(np.mean((levels[t_long] - capped[t_long])[win]))) / (t_long * white_reflectance)
    fraction = light / band_dn_per_s if band_dn_per_s > 0 else float("inf")
    out.update({"mirrors_off_dn_per_s": light, "mirrors_off_fraction": fraction,
                "mirrors_off_light": bool(fraction > MIRRORS_OFF_TOLERANCE)})
    return out
