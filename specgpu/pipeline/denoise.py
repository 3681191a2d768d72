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

The standard deviation (:func:`carried_through_filter`, on the device: :mod:`specgpu.engine.guided_variance`):
with its guide fixed the filter is a linear map of each output, ``q_i = sum_j W_ij p_j``, so the pixels' own shot
and read noise, independent from pixel to pixel, leaves ``sum_j W_ij^2 var p_j``: where the guide is flat the mean
of box means (about 54 times less at radius 2), at an edge or in texture, where the weights follow the guide, far
less averaging. The guide's own noise passes where the output follows the guide, ``abar^2 var g`` with abar the
filter's slope of the output on the guide: in a textured scene most of what the filter leaves. The light's
frame-to-frame fluctuation (common to every pixel of a frame) and the prior's mismatch (common to a surface) are not
averaged down and stay as they were. The XYZ covariance (of dE_sigma) is carried the same way, entry by entry. The
stream does it on the device (:class:`specgpu.pipeline.decoder_outputs.FusedLaunches`); a motion-compensated
decoding takes each frame's own part at its warped samples first
(:func:`specgpu.pipeline.moving_decode.warped_uncertainty`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.core.validate import check_number, check_sequence
from specgpu.engine.guided import guided_filter
from specgpu.engine.guided_variance import MAX_RADIUS, filtered_variance
from specgpu.engine.linear_map import apply_linear
from specgpu.planning.correction import ambient_index
from specgpu.planning.uncertainty import frame_variance

__all__ = ["DENOISE_RADIUS", "DENOISE_EPS", "denoise_design_warning", "sequence_guide", "output_subspace",
           "denoise_recovery", "stream_denoise", "warped_guide_row", "denoise_compensated", "compensated_parts",
           "frames_guide", "guide_variance", "check_sigma_radius", "carried_through_filter", "column_span",
           "filter_in_span", "derived_channels"]

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
    ambient frame and broadband reference frames left out, so the guide samples no frame the outputs do not),
    scaled to the outputs' magnitude (the mean over the decoder's rows of their absolute sums over the frames' sum).

    The filter divides its guide by its 99th percentile, so the scale changes nothing there; the pass's rows are
    compared together (the flow's check of two decodings, an RMS over the rows), where a frames' sum thousands of
    times the outputs would outweigh them all."""
    row = guide_row(plan)
    A = np.asarray(plan.A, np.float64)
    row[0, ~np.any(A != 0, axis=0)] = 0.0
    total = row.sum()
    return row * (np.abs(A).sum(axis=1).mean() / total) if total > 0 else row


def compensated_parts(y: ArrayLike, guide: ArrayLike, mask: ArrayLike, *, radius: int = DENOISE_RADIUS):
    """What :func:`denoise_compensated` works from, made once for the outputs ``y`` (H, W, C) guided by ``guide``
    (H, W): (``bad``, the pixels with no valid value; ``smoothed``, those it filters: whose filter reads no flagged
    pixel; the guide as the filter takes it, 0 on the flagged pixels and divided by the 99th percentile of the
    others; that level), or None when it filters none (every pixel flagged, or a guide with no light)."""
    from scipy.ndimage import maximum_filter  # scipy: heavy, needed only here

    r = int(check_number("--denoise-radius", radius, integer=True, low=1, high=64))
    g = np.asarray(guide, np.float32)
    bad = _flagged(y, g, mask)
    if bad.all():
        return None
    level = float(np.percentile(g[~bad], 99))
    if not level > 0:
        return None
    smoothed = ~maximum_filter(bad, size=4 * r + 1, mode="constant", cval=False) if bad.any() else ~bad
    return bad, smoothed, np.where(bad, np.float32(0), g / np.float32(level)), level


def _flagged(y, guide, mask) -> np.ndarray:
    """A pixel with no valid value: flagged in ``mask`` (any bit but an object's own motion) or not finite."""
    g = np.asarray(guide, np.float32)
    y = np.asarray(y)
    bad = ((np.asarray(mask) & ~np.uint8(Mask.LAYER)) != 0) | ~np.isfinite(g)
    # the sum over the channels (one BLAS product, not C tests) is NaN or infinite wherever a channel is; the few
    # pixels it flags are tested channel by channel (a sum of finite values past float32's range is no flag)
    total = None
    if y.dtype.kind == "f":
        with np.errstate(over="ignore", invalid="ignore"):  # a view of some channels: read in place, no copy
            total = np.matmul(y, np.ones(y.shape[-1], y.dtype))
    maybe = ~np.isfinite(total) if total is not None else np.ones(g.shape, bool)
    if maybe.any():
        maybe[maybe] = ~np.all(np.isfinite(y[maybe]), axis=-1)
    return bad | maybe


#: The default of the ``parts`` arguments: :func:`compensated_parts` made by the callee (None is one of its results:
#: the filter smooths no pixel)
PARTS_MADE_HERE = object()


def denoise_compensated(y: ArrayLike, guide: ArrayLike, mask: ArrayLike, *, radius: int = DENOISE_RADIUS,
                        eps: float = DENOISE_EPS, rows: ArrayLike | None = None, device=None,
                        parts=PARTS_MADE_HERE) -> np.ndarray:
    """The motion-compensated outputs ``y`` (H, W, C) smoothed by the guided filter of ``guide`` (H, W), the sum
    of the warped samples at the reference time (:func:`warped_guide_row`), so no window mixes the surfaces the
    compensation separated; float32.

    A pixel flagged in ``mask`` (any bit but 16, an object's own motion: saturated, outside the field,
    inconsistent) or not finite has no valid value: it stays NaN, and every pixel whose filter would read it
    (within ``2 radius``: the windows of the windows about it) is left unfiltered, its decoded value kept
    (:func:`compensated_parts` says which are filtered). The guide is divided by its 99th percentile over the
    valid pixels, as :func:`sequence_guide`; a guide with no light leaves ``y`` as it is.

    ``rows`` (C, K): the decoder's rows ``y`` was decoded with (one pass over the same samples). A channel whose row
    is a linear combination of earlier ones (XYZ of the cube or of the coefficients: :func:`derived_channels`) is
    then not filtered but made from the filtered channels by the same combination: the filter is linear and the same
    for every channel, and the flagged pixels are the same for all, so the result is the same, and the channels
    filtered are those a decoding of fewer outputs filters (in the same order, to the same rounding).

    ``parts``: :func:`compensated_parts` already made for this guide, mask and radius (of the pass these outputs
    are rows of: the outputs and their sigmas filter the same pixels).
    """
    r, e = _check(radius, eps)
    y = np.asarray(y, np.float32)
    made = compensated_parts(y, guide, mask, radius=r) if parts is PARTS_MADE_HERE else parts
    if made is None:
        return y.copy()
    bad, smoothed, g, _ = made
    C = y.shape[-1]
    kept, others, L = derived_channels(rows) if rows is not None else (np.arange(C), np.arange(0), None)
    # the channels filtered, one contiguous copy with the flagged pixels 0 (a slice where they are a run: no
    # gather), through the filter; the others made from them
    filled = np.array(y[..., _index(kept)], np.float32, order="C")  # a copy, never the caller's array
    filled[bad] = 0
    part = np.asarray(guided_filter(filled, g, radius=r, eps=e, device=device), np.float32)
    if len(others) == 0 and len(kept) == C:
        filtered = part
    else:  # every channel in one product: the kept ones times 1 (exact: the filtered values are finite)
        to_all = np.zeros((C, len(kept)), np.float32)
        to_all[kept, np.arange(len(kept))] = 1.0
        to_all[others] = L
        filtered = np.matmul(part, to_all.T)
    kept_as_decoded = ~smoothed
    filtered[kept_as_decoded] = y[kept_as_decoded]
    return filtered


def _index(ix: np.ndarray):
    """``ix`` (increasing indices) as a slice where it is a run (a view, not a gather)."""
    ix = np.asarray(ix)
    if ix.size and np.array_equal(ix, np.arange(ix[0], ix[0] + ix.size)):
        return slice(int(ix[0]), int(ix[0]) + ix.size)
    return ix


def derived_channels(rows: ArrayLike, *, growth: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which outputs of a decoder's ``rows`` (C, K) are made from others: (``kept``, the indices of the rows that
    are filtered; ``others``, the rest; ``L`` (len(others), len(kept)) float64 with ``rows[others] = L @
    rows[kept]``).

    In order, a row is made from the rows kept before it where it is their combination (its part outside their
    span below 1e-9 of its norm) with a rounding error at most ``growth`` times its own
    (``sum_j |L_ij| |row_j| <= growth |row_i|``: XYZ from the cube or the coefficients, not a band from its
    near-collinear neighbours); else it is kept."""
    R = np.asarray(rows, np.float64)
    norms = np.linalg.norm(R, axis=1)
    kept, made = [], {}
    for i in range(len(R)):
        if kept and norms[i] > 0:
            x = np.linalg.lstsq(R[kept].T, R[i], rcond=None)[0]
            if (np.linalg.norm(R[kept].T @ x - R[i]) <= 1e-9 * norms[i]
                    and np.abs(x) @ norms[kept] <= growth * norms[i]):
                made[i] = (len(kept), x)
                continue
        kept.append(i)
    L = np.zeros((len(made), len(kept)))
    for n, (width, x) in enumerate(made.values()):
        L[n, :width] = x
    return np.asarray(kept, np.intp), np.asarray(list(made), np.intp), L


def column_span(matrix: ArrayLike) -> np.ndarray:
    """(C, r) orthonormal basis of the column space of ``matrix`` (C, K), rank r <= K: the space a decoder's
    outputs lie in (singular values below 1e-9 of the largest dropped)."""
    U, s, _ = np.linalg.svd(np.asarray(matrix, np.float64), full_matrices=False)
    return U[:, s > 1e-9 * s.max()] if s.size and s.max() > 0 else U[:, :0]


def filter_in_span(y: ArrayLike, guide: ArrayLike, span: ArrayLike | None, *, radius: int, eps: float,
                   device=None) -> np.ndarray:
    """The guided filter of ``y`` (H, W, C) whose channels lie in the column span ``span`` (C, r) (None: anywhere).

    With the guide fixed the filter is linear and the same for every channel, so it commutes with the per-pixel
    map from the r coordinates of ``y`` in the span to its C channels: the r coordinates are filtered (C / r
    times less work) and mapped back, the same result as filtering every channel."""
    y = np.asarray(y, np.float32)
    if span is None or span.shape[1] >= y.shape[-1]:
        return np.asarray(guided_filter(y, guide, radius=radius, eps=eps, device=device), np.float32)
    U = np.asarray(span, np.float32)
    c = y @ U
    residual = y - c @ U.T  # zero up to rounding: kept so the map back is exact
    return guided_filter(c, guide, radius=radius, eps=eps, device=device) @ U.T + residual


def sequence_guide(folder, *, sequence: int | None = None, device=None) -> np.ndarray:
    """(H, W) float32: the sum of the plan's frames above dark, flat-fielded (the ambient frame left out), of one
    sequence or the mean of all, divided by its 99th percentile."""
    return frames_guide(folder, sequence=sequence, device=device)[0]


def frames_guide(folder, *, sequence: int | None = None, device=None) -> tuple[np.ndarray, float]:
    """:func:`sequence_guide` and the level it was divided by."""
    frames, dark, _, _ = _mean_frames(folder, sequence)
    g = np.asarray(apply_linear(frames, guide_row(folder.plan), dark, live_gain(folder.calibration.flat_field),
                                device=device))[..., 0]
    level = float(np.nanpercentile(g, 99)) if np.isfinite(g).any() else 0.0
    if not level > 0:
        raise ValueError(f"{folder.path}: the frames hold no light above dark: nothing to guide the denoising")
    return (g / level).astype(np.float32), level


def guide_variance(folder, level: float, *, sequence: int | None = None, device=None) -> np.ndarray:
    """(H, W) float32: the variance of the own (shot, read and dark) noise of :func:`sequence_guide`, the guide
    divided by ``level``."""
    plan, bundle = folder.plan, folder.calibration
    frames, dark, S, amb = _mean_frames(folder, sequence)
    v = frame_variance(frames, plan, dark, bundle.flat_field, A=guide_row(plan), sequences=S, light=False,
                       ambient_dark=None if amb is None else bundle.dark_at(plan.exposure_s), device=device)
    return (v[..., 0] / np.float32(level) ** 2).astype(np.float32)


def check_sigma_radius(radius) -> int:
    """``radius`` of a denoising whose sigma maps are carried through the filter, checked (one line)."""
    r = int(check_number("--denoise-radius", radius, integer=True, low=1, high=64))
    if r > MAX_RADIUS:
        raise ValueError(f"--denoise-radius {r}: the sigma maps are carried through the filter up to radius "
                         f"{MAX_RADIUS}; choose a smaller radius or leave the sigma outputs out")
    return r


def carried_through_filter(own, total, *, guide, radius: int, eps: float, slopes, guide_var, terms, offsets=None,
                           sqrt: bool = False, device=None) -> np.ndarray:
    """(H, W, C) float32: the variance ``total`` (H, W, C) of unfiltered outputs, its pixels' own part ``own``,
    carried through the guided filter of ``guide`` (:func:`specgpu.engine.guided_variance.filtered_variance`:
    the own part through the filter's weights, the guide's own noise ``guide_var`` passed by the slopes of the
    unfiltered ``slopes`` (H, W, D) the ``terms`` name, the rest kept), NaN where ``total`` is. Non-finite slopes
    and guide values (pixels the filter leaves out) are read as 0."""
    g = np.nan_to_num(np.asarray(guide, np.float32))
    return filtered_variance(own, total, g, radius=check_sigma_radius(radius), eps=eps,
                             slopes=np.nan_to_num(np.asarray(slopes, np.float32)),
                             guide_var=np.nan_to_num(np.asarray(guide_var, np.float32)), terms=terms,
                             offsets=offsets, sqrt=sqrt, device=device)


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
    return column_span(plan.A)


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
    return filter_in_span(y, guide, output_subspace(folder.plan), radius=r, eps=e, device=device)


#: The stream outputs the guided filter applies to (linear in the frames, so filtering them is filtering the
#: cube), those computed from the filtered XYZ (CIELAB and dE, as recover --denoise computes them from the
#: filtered cube), and the uncertainty outputs carried through the filter
#: (:func:`specgpu.engine.guided_variance.filtered_variance_device`; dE_sigma from the filtered XYZ and its
#: covariance carried the same way).
DENOISED_STREAM_OUTPUTS = ("coefficients", "cube", "XYZ")
FROM_DENOISED_XYZ = ("Lab", "dE")
DENOISED_SIGMAS = ("sigma", "sigma_rms", "dE_sigma")


def stream_denoise(plan, outputs, cube_dtype, denoise) -> dict:
    """The stream's denoising set-up for ``denoise`` = (radius, eps): the guide's row (every frame but an ambient
    one), the channels of each filtered output (XYZ too when Lab, dE or dE_sigma come from it), whether Lab and dE
    are recomputed from the filtered XYZ, and the sigma outputs carried through the filter; refuses (one line) a
    float16 cube."""
    r, e = _check(*denoise)
    if any(o in DENOISED_SIGMAS for o in outputs):
        check_sigma_radius(r)
    known = DENOISED_STREAM_OUTPUTS + FROM_DENOISED_XYZ + DENOISED_SIGMAS
    bad = [o for o in outputs if o not in known]
    if bad:
        raise ValueError(f"--denoise carries the stream's {', '.join(known)} outputs; {', '.join(bad)} cannot be "
                         f"denoised in the stream (leave {'them' if len(bad) > 1 else 'it'} out)")
    if "cube" in outputs and np.dtype(cube_dtype) != np.float32:
        raise ValueError("--denoise needs a float32 cube (leave --half out)")
    m = int(plan.params["m"]) if "m" in plan.params else output_subspace(plan).shape[1]
    derived = [o for o in outputs if o in FROM_DENOISED_XYZ]
    channels = {"coefficients": m, "cube": plan.A.shape[0], "XYZ": 3}
    filtered = {k: v for k, v in channels.items()
                if k in outputs or (k == "XYZ" and (derived or "dE_sigma" in outputs))}
    return {"radius": r, "eps": e, "row": guide_row(plan), "channels": filtered, "from_XYZ": derived,
            "sigmas": [o for o in outputs if o in DENOISED_SIGMAS]}
