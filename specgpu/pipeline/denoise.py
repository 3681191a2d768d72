"""Per-pixel noise removed without losing edges (``recover --denoise``): the decoded outputs smoothed on the
device by a guided filter (:func:`specgpu.engine.guided.guided_filter`) whose guide is the sum of the sequence's
frames, and the per-pixel standard deviation carried through the filter so it stays calibrated.

The guide: every frame of the plan (the ambient frame left out) above its dark level and flat-fielded, summed: an
image of K times the light of one frame, far higher in SNR than any decoded band, which every change of the
scene's reflectance that changes the frames' sum marks as an edge. It is divided by its 99th percentile, so
``eps`` is in units of that level squared. Where the guide is flat the outputs become window means (shot and
read noise averaged over about ``(2r + 1)^2`` pixels); at an edge the outputs follow the guide. An edge between
two spectra of equal frame sum is not in the guide and is smoothed (the filter's known limit with a one-channel
guide).

The standard deviation: of each output's variance only the part from each pixel's own shot and read noise is
independent from pixel to pixel; it is carried through the filter as through the mean of box means
(:func:`specgpu.engine.guided.box_box_variance`). The light's frame-to-frame fluctuation (common to every pixel of
a frame) and the prior's mismatch (common to a surface) are not averaged down and stay as they were.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.core.validate import check_number, check_sequence
from specgpu.engine.guided import box_box_variance, guided_filter
from specgpu.engine.linear_map import apply_linear
from specgpu.planning.correction import ambient_index
from specgpu.planning.uncertainty import frame_variance

__all__ = ["DENOISE_RADIUS", "DENOISE_EPS", "denoise_design_warning", "sequence_guide", "output_subspace",
           "denoise_recovery", "denoised_sigma", "stream_denoise", "warped_guide_row", "denoise_compensated"]

#: Window radius and regularisation of ``--denoise``, chosen by measurement (``tools/studies/budget_study.py
#: --tune``): on
#: the CIE 2017 CES chart and the natural scene, the pair with the lowest per-pixel RMSE whose error within 2 px of
#: the scene's edges is no worse than the raw recovery's.
DENOISE_RADIUS = 2
DENOISE_EPS = 1e-4


def _mean_frames(folder, sequence):
    check_sequence(sequence, folder.sequences, folder.path)
    used = folder.frames if sequence is None else folder.frames[sequence:sequence + 1]
    frames = used.mean(axis=0, dtype=np.float32) if used.shape[0] > 1 else used[0].astype(np.float32)
    plan, bundle = folder.plan, folder.calibration
    amb = ambient_index(plan)
    dark = frames[amb] if amb is not None else bundle.dark_at(plan.exposure_s)
    return frames, dark, used.shape[0], amb


def guide_row(plan) -> np.ndarray:
    """(1, K) decoder of the guide: the sum of every frame but an ambient one."""
    row = np.ones((1, plan.K))
    amb = ambient_index(plan)
    if amb is not None:
        row[0, amb] = 0.0
    return row


def warped_guide_row(plan) -> np.ndarray:
    """(1, K) the guide's row for the motion-compensated pass: the sum of the frames the plan's decoder reads (an
    ambient frame and broadband reference frames left out, so the guide samples no frame the outputs do not)."""
    row = guide_row(plan)
    row[0, ~np.any(np.asarray(plan.A) != 0, axis=0)] = 0.0
    return row


def denoise_compensated(y: ArrayLike, guide: ArrayLike, mask: ArrayLike, *, radius: int = DENOISE_RADIUS,
                        eps: float = DENOISE_EPS, device=None) -> np.ndarray:
    """The motion-compensated outputs ``y`` (H, W, C) smoothed by the guided filter of ``guide`` (H, W), the sum
    of the warped samples at the reference time (:func:`warped_guide_row`), so no window mixes the surfaces the
    compensation separated; float32.

    A pixel flagged in ``mask`` (any bit but 16, an object's own motion: saturated, outside the field,
    inconsistent) or not finite has no valid value: it stays NaN, and every pixel whose filter would read it
    (within ``2 radius``: the windows of the windows about it) is left unfiltered, its decoded value kept. The
    guide is divided by its 99th percentile over the valid pixels, as :func:`sequence_guide`; a guide with no
    light leaves ``y`` as it is.
    """
    from scipy.ndimage import maximum_filter  # scipy: heavy, needed only here

    r, e = _check(radius, eps)
    y = np.asarray(y, np.float32)
    g = np.asarray(guide, np.float32)
    bad = ((np.asarray(mask) & ~np.uint8(Mask.LAYER)) != 0) | ~np.isfinite(g) | ~np.all(np.isfinite(y), axis=-1)
    if bad.all():
        return y.copy()
    level = float(np.percentile(g[~bad], 99))
    if not level > 0:
        return y.copy()
    filled = np.where(bad[..., None], np.float32(0), y)
    filtered = np.asarray(guided_filter(filled, np.where(bad, np.float32(0), g / np.float32(level)), radius=r,
                                        eps=e, device=device), np.float32)
    near = maximum_filter(bad, size=4 * r + 1, mode="constant", cval=False)
    return np.where(near[..., None], y, filtered)


def sequence_guide(folder, *, sequence: int | None = None, device=None) -> np.ndarray:
    """(H, W) float32: the sum of the plan's frames above dark, flat-fielded (the ambient frame left out), of one
    sequence or the mean of all, divided by its 99th percentile."""
    frames, dark, _, _ = _mean_frames(folder, sequence)
    g = np.asarray(apply_linear(frames, guide_row(folder.plan), dark, live_gain(folder.calibration.flat_field),
                                device=device))[..., 0]
    level = float(np.nanpercentile(g, 99)) if np.isfinite(g).any() else 0.0
    if not level > 0:
        raise ValueError(f"{folder.path}: the frames hold no light above dark: nothing to guide the denoising")
    return (g / level).astype(np.float32)


def denoise_design_warning(plan, radius: int | None) -> str | None:
    """One line when a plan designed for the filter (``specgpu plan --denoise``, ``params["denoise"]``) is
    recovered without it (``radius`` None) or with another radius: its decoder is made for the filtered noise, so
    unfiltered it is noisier than a plan designed for none; None otherwise."""
    designed = plan.params.get("denoise") if isinstance(plan.params, dict) else None
    if not designed:
        return None
    r = int(designed["radius"])
    if radius is None:
        return (f"the {plan.method} plan's decoder is designed for --denoise --denoise-radius {r}: without the "
                "filter its outputs are noisier than those of a plan designed for none")
    if int(radius) != r:
        return (f"the {plan.method} plan's decoder is designed for --denoise-radius {r}, filtered here with "
                f"{int(radius)}")
    return None


def _check(radius, eps):
    return (int(check_number("--denoise-radius", radius, integer=True, low=1, high=64)),
            float(check_number("--denoise-eps", eps, low=0, low_open=True, high=1e3)))


def output_subspace(plan) -> np.ndarray:
    """(B, r) orthonormal basis of the space a plan's outputs lie in: the column space of its decoder A (rank r
    <= K frames). A drift correction rescales A's columns, an ambient frame subtracts a frame: the outputs stay
    in it."""
    U, s, _ = np.linalg.svd(np.asarray(plan.A, np.float64), full_matrices=False)
    return U[:, s > 1e-9 * s.max()] if s.size and s.max() > 0 else U[:, :0]


def denoise_recovery(folder, y: ArrayLike, *, sequence: int | None = None, radius: int = DENOISE_RADIUS,
                     eps: float = DENOISE_EPS, device=None) -> np.ndarray:
    """The outputs ``y`` (H, W, B) of :func:`specgpu.pipeline.recovery.recover` for ``folder`` (and ``sequence``)
    smoothed by the guided filter of the frames' sum (see the module notes); float32.

    With the guide fixed the filter is linear and the same for every channel, so it commutes with the per-pixel
    map from the r <= K coordinates of the outputs in their subspace (:func:`output_subspace`) to the B outputs:
    the r coordinates are filtered (B / r times less work: 31 bands of a 9-frame plan through 9 channels) and
    mapped back, the same result as filtering every band."""
    r, e = _check(radius, eps)
    guide = sequence_guide(folder, sequence=sequence, device=device)
    y = np.asarray(y, np.float32)
    U = output_subspace(folder.plan).astype(np.float32)
    if U.shape[1] >= y.shape[-1]:
        return guided_filter(y, guide, radius=r, eps=e, device=device)
    c = y @ U
    residual = y - c @ U.T  # zero up to rounding: kept so the map back is exact
    return guided_filter(c, guide, radius=r, eps=e, device=device) @ U.T + residual


def denoised_sigma(folder, sigma, *, sequence: int | None = None, radius: int = DENOISE_RADIUS,
                   device=None) -> np.ndarray:
    """The standard deviation (H, W, B) of :func:`denoise_recovery`'s outputs, from ``sigma``, that of the raw
    recovery (:func:`specgpu.pipeline.recovery.uncertainty`): its per-pixel shot and read part carried through the
    filter, the rest kept (see the module notes); NaN where ``sigma`` is."""
    r, _ = _check(radius, DENOISE_EPS)
    plan, bundle = folder.plan, folder.calibration
    frames, dark, S, amb = _mean_frames(folder, sequence)
    ambient_dark = None if amb is None else bundle.dark_at(plan.exposure_s)
    own = frame_variance(frames, plan, dark, bundle.flat_field, sequences=S, light=False, ambient_dark=ambient_dark,
                         device=device).astype(np.float64)
    total = np.asarray(sigma, np.float64) ** 2
    own = np.minimum(np.nan_to_num(own), np.nan_to_num(total))  # never more than the whole
    var = box_box_variance(own, r) + (total - own)
    return np.sqrt(np.maximum(var, 0.0)).astype(np.float32)


#: The stream outputs the guided filter applies to (linear in the frames, so filtering them is filtering the
#: cube), and those computed from the filtered XYZ (CIELAB and dE, as recover --denoise computes them from the
#: filtered cube).
DENOISED_STREAM_OUTPUTS = ("coefficients", "cube", "XYZ")
FROM_DENOISED_XYZ = ("Lab", "dE")
#: Where denoised sigma maps are made: ``recover --denoise --sigma`` carries the sigma through the filter, and it
#: reads a sequence folder (what ``specgpu capture`` writes), not a stream's recording.
DENOISED_SIGMA_ADVICE = ("; for denoised sigma maps capture a sequence folder and recover it: specgpu capture --rig "
                         "RIG.toml --plan PLAN.npz --calib CALIB.npz --out SEQ, then specgpu recover SEQ --out "
                         "CUBE.exr --denoise --sigma SIGMA.exr")


def stream_denoise(plan, outputs, cube_dtype, denoise) -> dict:
    """The stream's denoising set-up for ``denoise`` = (radius, eps): the guide's row (every frame but an ambient
    one), the channels of each filtered output (XYZ too when Lab or dE come from it), and whether Lab and dE are
    recomputed from the filtered XYZ; refuses (one line) the sigma maps (not carried through the filter in the
    stream) and a float16 cube."""
    r, e = _check(*denoise)
    bad = [o for o in outputs if o not in DENOISED_STREAM_OUTPUTS + FROM_DENOISED_XYZ]
    if bad:
        raise ValueError(f"--denoise filters the stream's {', '.join(DENOISED_STREAM_OUTPUTS)} outputs and computes "
                         f"{', '.join(FROM_DENOISED_XYZ)} from the filtered XYZ; {', '.join(bad)} cannot be denoised "
                         f"in the stream (leave {'them' if len(bad) > 1 else 'it'} out"
                         f"{DENOISED_SIGMA_ADVICE if {'sigma', 'sigma_rms'} & set(bad) else ''})")
    if "cube" in outputs and np.dtype(cube_dtype) != np.float32:
        raise ValueError("--denoise needs a float32 cube (leave --half out)")
    m = int(plan.params["m"]) if "m" in plan.params else output_subspace(plan).shape[1]
    derived = [o for o in outputs if o in FROM_DENOISED_XYZ]
    channels = {"coefficients": m, "cube": plan.A.shape[0], "XYZ": 3}
    filtered = {k: v for k, v in channels.items() if k in outputs or (k == "XYZ" and derived)}
    return {"radius": r, "eps": e, "row": guide_row(plan), "channels": filtered, "from_XYZ": derived}
