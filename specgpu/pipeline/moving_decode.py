"""What the motion mode of the sequence decoder can make of a moving scene's sequence, and its uncertainty.

``specgpu recover --motion`` decodes one sequence of a moving scene through
:func:`specgpu.pipeline.moving_layers.recover_moving`:
the frames corrected as recover corrects them (the sensor's linearisation, the per-pattern flat ratio), each
frame's displacement estimated within the sequence, one warped device pass, the pixels seen outside the field or
whose compensated frames disagree left NaN with their mask bits.
:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder` in its motion mode (``specgpu batch --motion``,
``specgpu stream --motion``) runs it on each sequence with every linear output asked for (basis coefficients, the
cube, XYZ) stacked as rows of one decoder (:meth:`specgpu.pipeline.decoder_outputs.Outputs.rows`), so the estimate
and the warped pass are made once per sequence; Lab and dE follow from XYZ by the launches the denoised stream
uses (:func:`specgpu.pipeline.decoder_outputs.lab_and_delta_E`).

The uncertainty outputs (``sigma``, ``sigma_rms``, ``dE_sigma``) are taken at the warped samples
(:func:`warped_uncertainty`): a bilinear sample of the four sensor pixels it reads has the variance
``sum_i w_i^2 var_i`` of their own noise (:func:`warped_sample_variance`, the noise model of
:mod:`specgpu.planning.noise` per pixel), the light's fluctuation, common to a frame's pixels, at the sample's own
signal; an object layer's pixels with its own shifts. With ``--denoise`` they are carried through the filter
(``warped_uncertainty(smoothed=...)``).

A plan with an ambient frame (``plan --ambient``) is decoded with its ambient frame warped like the others: it is
placed on the steady motion of the frames registered (:mod:`specgpu.motion.ambient`), sampled where it saw each
pixel and subtracted there, in the same pass (the decoder's column for it minus the sum of the others:
:func:`specgpu.planning.correction.subtracting_ambient`); its sample's own noise goes into every output through that
column. What is still refused with a motion mode, in one line naming the option (:func:`check_motion_options`), is
what the flow cannot serve and an output whose covariance model needs fixed pixels.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.engine.guided_variance import box_box_squares
from specgpu.motion.flow import MIN_FRAMES
from specgpu.motion.methods import check_motion_mode
from specgpu.pipeline.denoise import carried_through_filter, warped_guide_row
from specgpu.planning.correction import ambient_index, subtracting_ambient
from specgpu.planning.noise import NoiseModel
from specgpu.planning.reference_frames import reference_indices
from specgpu.planning.uncertainty import constant_covariance

__all__ = ["MOTION_OUTPUTS", "check_motion_options", "warped_sample_variance", "warped_sample_variances",
           "warped_sigma_rms", "warped_uncertainty"]

#: The outputs a motion-compensated decoding carries: linear maps of the warped samples, colour from them, and
#: their uncertainty at the warped samples (:func:`warped_uncertainty`).
MOTION_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")


def check_motion_options(motion, plan=None, *, outputs=()) -> str:
    """``motion`` checked (a key of :data:`specgpu.motion.methods.MOTION_METHODS`) and, unless ``"none"``, every
    option that cannot be motion-compensated yet refused in one line naming it. Returns the mode."""
    mode = check_motion_mode(motion)
    if mode == "none":
        return mode
    for name in outputs:
        if name not in MOTION_OUTPUTS:
            raise ValueError(f"the {name} output with --motion {mode}: its covariance model assumes each pixel's "
                             f"samples came from one sensor pixel, which motion compensation breaks; motion "
                             f"outputs are {', '.join(MOTION_OUTPUTS)}")
    if mode == "flow" and plan is not None and plan.K < MIN_FRAMES + 1:
        raise ValueError(f"--motion flow needs a plan of at least {MIN_FRAMES + 1} frames (each tile's steady motion "
                         f"is fitted to {MIN_FRAMES} frames besides the reference), the {plan.method} plan has "
                         f"{plan.K}")
    if mode == "flow" and plan is not None and reference_indices(plan):
        raise ValueError("--motion flow with a plan with broadband reference frames: the flow is estimated from "
                         "every frame of the sequence; compensate with --motion global or affine")
    return mode


def _sample_points(d: np.ndarray, k: int, h: int, w: int):
    """Where frame ``k`` saw each pixel (``d``: the shifts, as :func:`warped_sample_variance` takes them): the four
    bilinear taps (row, column, weight), the points outside the sensor's footprint, and the fractions (fx, fy)
    (of a translation, a column's along x and a row's along y: arrays that broadcast to (H, W))."""
    if d.shape[1:] == (2,):  # a translation: x moves along x only, y along y only, so the grid is an outer product
        yy, xx = np.arange(h, dtype=np.float64)[:, None], np.arange(w, dtype=np.float64)[None, :]
    else:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    if d.shape[1:] == (2, 3):  # an affine map
        sx, sy = d[k, 0, 0] * xx + d[k, 0, 1] * yy + d[k, 0, 2], d[k, 1, 0] * xx + d[k, 1, 1] * yy + d[k, 1, 2]
    else:  # a translation (2,) or a flow's displacement per pixel (2, H, W)
        sx, sy = xx + d[k, 0], yy + d[k, 1]
    outside = (sx < -0.5 - 1e-3) | (sy < -0.5 - 1e-3) | (sx > w - 0.5 + 1e-3) | (sy > h - 0.5 + 1e-3)
    sx, sy = np.clip(sx, 0, w - 1), np.clip(sy, 0, h - 1)
    x0, y0 = np.floor(sx).astype(np.intp), np.floor(sy).astype(np.intp)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = sx - x0, sy - y0
    taps = ((y0, x0, (1 - fx) * (1 - fy)), (y0, x1, fx * (1 - fy)), (y1, x0, (1 - fx) * fy), (y1, x1, fx * fy))
    return taps, outside, fx, fy


def _interpolation_correlation(radius: int) -> float:
    """``1 - R(1) / R(0)``, R the autocorrelation of the box-box weights ``t`` of the guided filter of
    ``radius`` along one axis (:func:`specgpu.engine.guided_variance.box_box_squares`)."""
    t = np.sqrt(box_box_squares(radius))
    return float(1.0 - np.dot(t[1:], t[:-1]) / np.dot(t, t))


def warped_sample_variance(frames: ArrayLike, plan, dark, gain, shifts, *, read, light: bool = True,
                           filtered: int | None = None, ambient: int | None = None) -> np.ndarray:
    """(len(read), H, W) float64: the variance of each read frame's motion-compensated sample, the bilinear
    interpolation of the corrected frame ``(o - dark) * gain`` at the point the frame saw each pixel
    (``shifts``: (K, 2) translations, (K, 2, 3) affine maps or a (K, 2, H, W) flow, as
    :func:`specgpu.engine.warp_map.apply_linear_warped` samples them).

    A sample ``s = sum_i w_i c_i`` of the four pixels it reads has the variance ``sum_i w_i^2 var c_i`` of their
    own noise (shot, read and dark: :class:`specgpu.planning.noise.NoiseModel`, ``gain^2 (x / g + s_read^2)``
    per pixel, ``x`` its signal above dark), plus, with ``light``, the light's fluctuation, common to every pixel
    of a frame and so not averaged by the interpolation: ``(l s)^2``. NaN where the point lies outside the
    sensor's footprint.

    ``filtered`` (a guided filter's radius r): instead, the own part (no light) as that filter's weights
    (:mod:`specgpu.engine.guided_variance`) must take it. Neighbouring samples share sensor pixels, so their noise is
    correlated and the filter, which averages them, averages the sensor pixels beneath: the pixels' variance
    interpolated with the weights themselves, ``sum_i w_i var c_i``, times ``rho(fx) rho(fy)``, where
    ``rho(f) = 1 - 2 f (1 - f) (1 - R(1) / R(0))`` with R the autocorrelation of the box-box weights along an
    axis (the box-box of the bilinear kernel convolved with the filter's over that of the filter's alone; 0.97 at
    a half pixel for r = 2, where ``sum w_i^2`` alone would say 0.5).

    ``ambient``: the plan's ambient frame (room light only): its sample has no light's fluctuation, and the
    other frames' is at their signal above it (the light fluctuates, the room light does not)."""
    total, own, smoothed = warped_sample_variances(frames, plan, dark, gain, shifts, read=read, light=light,
                                                   filtered=filtered, ambient=ambient)
    return smoothed if filtered is not None else total


def warped_sample_variances(frames: ArrayLike, plan, dark, gain, shifts, *, read, light: bool = True,
                            filtered: int | None = None,
                            ambient: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`warped_sample_variance`'s three variances of the samples, from one pass over the frames (each frame's
    sample points and its pixels' own variance made once): (with ``light``, ``total``; without, ``own``, the
    pixels' own part; ``filtered``, that part as the filter of radius ``filtered`` takes it, or None), each
    (len(read), H, W) float64."""
    noise = NoiseModel.from_params(plan.params["noise"])
    h, w = np.shape(frames)[1:]
    g2 = live_gain(gain).astype(np.float64) ** 2 if gain is not None else np.ones((h, w))
    d = np.asarray(shifts, np.float64)
    corr = None if filtered is None else _interpolation_correlation(filtered)
    with_light = light and noise.light_rms > 0
    total, own_out = np.empty((len(read), h, w)), np.empty((len(read), h, w)) if with_light else None
    smoothed = None if corr is None else np.empty((len(read), h, w))
    dark = np.asarray(dark, np.float64)
    root_g2 = np.sqrt(g2) if with_light else None
    room = 0.0 if ambient is None else np.asarray(frames[ambient], np.float64) - dark
    for n, k in enumerate(read):
        x = np.asarray(frames[k], np.float64) - dark  # the frames read, one at a time in float64
        own = (g2 * (x / noise.gain_e_per_dn + noise.read_var_dn2)).reshape(-1)
        taps, outside, fx, fy = _sample_points(d, k, h, w)
        flat = [(r * w + c, wt) for r, c, wt in taps]  # one flat gather per tap, not a 2-D fancy index
        values = [np.take(own, i) for i, _ in flat]
        var = sum(wt * wt * v for (_, wt), v in zip(flat, values))
        if own_out is not None:
            own_out[n] = var
            own_out[n][outside] = np.nan
            if k != ambient:  # the room light does not fluctuate with the light
                signal = (root_g2 * (x - room)).reshape(-1)
                var = var + (noise.light_rms * sum(wt * np.take(signal, i) for i, wt in flat)) ** 2
        var[outside] = np.nan
        total[n] = var
        if smoothed is not None:
            sv = sum(wt * v for (_, wt), v in zip(flat, values)) * (1 - 2 * fx * (1 - fx) * corr) * (
                1 - 2 * fy * (1 - fy) * corr)
            sv[outside] = np.nan
            smoothed[n] = sv
    return total, (own_out if own_out is not None else total), smoothed


def _slope_basis(rows: np.ndarray, terms: list) -> tuple[np.ndarray, list]:
    """The decoder's output ``rows`` (D, K) span at most K dimensions, and so do the unfiltered outputs the filter's
    guide noise passes by (the slopes): an orthonormal basis U (D, r) of that span, and each channel's ``terms``
    (lists of (d, e, weight) over the D slopes) as terms over the r slopes ``slopes @ U`` (U^T T U): the same
    quadratic form of the filter's slopes, read from r images instead of D.

    One channel (``sigma_rms``): the basis turned to the eigenvectors of its form, so that its terms are the
    diagonal's (r of them, not r^2, and no image of a zero eigenvalue): the same form, fewer products per pixel."""
    U, s, _ = np.linalg.svd(rows, full_matrices=False)
    U = U[:, s > s[0] * 1e-9] if s.size and s[0] > 0 else U[:, :0]
    if len(terms) == 1 and U.shape[1]:
        T = np.zeros((rows.shape[0], rows.shape[0]))
        for d, e, weight in terms[0]:
            T[d, e] += weight
        lam, V = np.linalg.eigh(U.T @ (T + T.T) / 2 @ U)  # the form's symmetric part is all that it reads
        keep = np.abs(lam) > np.abs(lam).max(initial=0.0) * 1e-12
        if keep.any():
            return U @ V[:, keep], [[(i, i, float(v)) for i, v in enumerate(lam[keep])]]
    reduced = []
    for channel in terms:
        T = np.zeros((rows.shape[0], rows.shape[0]))
        for d, e, weight in channel:
            T[d, e] += weight
        Tr = U.T @ T @ U
        reduced.append([(i, j, float(Tr[i, j])) for i, j in zip(*np.nonzero(Tr))])
    return U, reduced


def warped_uncertainty(frames: ArrayLike, plan, dark, gain, rec, A=None, *, M=None, light: bool = True,
                       smoothed=None, rms: bool = False, variance=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The standard deviation (H, W, B) of the outputs of the decoder ``A`` (the plan's by default, with its ambient
    frame's column, :func:`specgpu.planning.correction.subtracting_ambient`) of the
    motion-compensated decoding ``rec`` (a :class:`~specgpu.pipeline.moving_layers.MovingRecovery`) and, given
    ``M`` (3, B), the covariance (H, W, 3, 3) of ``M y`` (XYZ), float32: each frame's sample variance
    (:func:`warped_sample_variance`, with the sequence's shifts, an object layer's own on the pixels decoded with
    it) through ``A^2`` (the frames are independent), plus the plan's constant (the prior's mismatch); NaN where
    the outputs are. ``frames``: the corrected frames on the sensor's scale. ``light=False``: a reference white's
    gains divide the light's fluctuation out.

    ``smoothed``: the outputs were denoised (:meth:`specgpu.pipeline.sequence_decoder.SequenceDecoder.smoothed`
    says on which ``pixels``, by which guide, with which unfiltered outputs' ``slopes``): there the variance is
    carried through the filter (:func:`specgpu.pipeline.denoise.carried_through_filter`), the own part as the
    filter takes the warped samples (``warped_sample_variance(filtered=radius)``), the guide's noise that of its
    warped samples. The slopes are read in the span of the decoder's rows (at most K images, not B): from the
    unfiltered outputs (``smoothed["slopes"]``) or from the frames' warped samples and the decoder that makes the
    outputs of them (``smoothed["samples"]``, ``smoothed["decoder"]``).

    ``rms``: only the RMS over the outputs of their standard deviation, (H, W, 1) (one channel carried through the
    filter instead of B).

    ``variance``: a :class:`specgpu.engine.warped_variance.PreparedWarpedVariance` of the sensor (its dark, flat
    field and the plan's noise, which must be ``dark``, ``gain`` and the plan's: its size and noise are checked):
    the frames' sample variances are made and summed through the decoder's squared rows on the device, in one
    pass, for translations and affine maps (a flow's on the host, as without it)."""
    ambient = ambient_index(plan)
    A = subtracting_ambient(plan.A, ambient) if A is None else np.asarray(A, np.float64)
    read = np.flatnonzero(np.any(A != 0, axis=0))
    own = (rec.mask & np.uint8(Mask.LAYER)) != 0

    pixels = None if smoothed is None else smoothed["pixels"]
    smoothing = pixels is not None and pixels.any()

    # the outputs' variances are weighted sums of the frames' sample variances: one block of weights per part
    Ar = A[:, read]
    B = A.shape[0]
    if rms:  # only the outputs' mean variance: one channel, the mean of their rows' squares
        blocks, terms = [(Ar * Ar).mean(axis=0)[None]], [[[(b, b, 1.0 / B) for b in range(B)]]]
    else:
        blocks, terms = [Ar * Ar], [[[(b, b, 1.0)] for b in range(B)]]
    if M is not None:  # the XYZ covariance: channel 3 i + j, sum_k (M A)_ik (M A)_jk V_k
        MA = np.asarray(M, np.float64) @ Ar
        blocks.append((MA[:, None, :] * MA[None, :, :]).reshape(9, -1))
        terms.append([[(B + i, B + j, 1.0)] for i in range(3) for j in range(3)])
    at = np.cumsum([0] + [b.shape[0] for b in blocks])
    weights = np.concatenate(blocks)
    if smoothing:  # and the guide's: its row squared, on the own part
        row = subtracting_ambient(warped_guide_row(plan), ambient)[0, read]
        weights = np.concatenate([weights, (row * row)[None]])
    total, own_part, filtered = _variance_channels(
        frames, plan, dark, gain, rec, read, weights, light=light, ambient=ambient, own=own,
        radius=smoothed["radius"] if smoothing else None, variance=variance)
    out = [total[..., a:b] for a, b in zip(at[:-1], at[1:])]
    if smoothing:
        rows = A if M is None else np.concatenate([A, np.asarray(M, np.float64) @ A])
        U, reduced = _slope_basis(rows, [t for ts in terms for t in ts])
        # the slopes' coordinates in the rows' span (the XYZ slopes are M times the cube's)
        P = U[:B] if M is None else U[:B] + np.asarray(M, np.float64).T @ U[B:]
        if "samples" in smoothed:  # the cube is the decoder times the frames' samples: K images, not B
            slopes = np.asarray(smoothed["samples"], np.float32) @ (smoothed["decoder"].T @ P).astype(np.float32)
        else:
            slopes = np.asarray(smoothed["slopes"], np.float32) @ P.astype(np.float32)  # the kernel reads float32
        n = at[-1]
        state = {"guide": smoothed["guide"], "radius": smoothed["radius"], "eps": smoothed["eps"], "slopes": slopes,
                 "guide_var": own_part[..., n] / smoothed["level"] ** 2}
        # every part in one call (the filter's weights made once): the own part as the filter takes it in place of
        # the samples' own, W^2 own_filtered + (total - own)
        own_filtered = filtered[..., :n]
        adjusted = total[..., :n] - own_part[..., :n]
        den = carried_through_filter(own_filtered, adjusted + own_filtered, terms=reduced, **state).astype(np.float64)
        out = [np.where(pixels[..., None], den[..., a:b], o) for o, a, b in zip(out, at[:-1], at[1:])]
    flagged = (rec.mask & ~np.uint8(Mask.LAYER)) != 0
    const = constant_covariance(plan)
    diag = np.diag(const).mean(keepdims=True) if rms else np.diag(const)
    sigma = np.sqrt(np.maximum(out[0] + diag, 0.0)).astype(np.float32)
    sigma[flagged] = np.nan
    if M is None:
        return sigma, None
    cov = out[1].reshape(out[1].shape[:-1] + (3, 3)) + np.asarray(M) @ const @ np.asarray(M).T
    cov[flagged] = np.nan
    return sigma, cov.astype(np.float32)


def warped_sigma_rms(frames: ArrayLike, plan, dark, gain, rec, *, device=None) -> np.ndarray:
    """(H, W) float32: the RMS over ``plan``'s outputs of their standard deviation at the samples the
    motion-compensated decoding ``rec`` read (:func:`warped_uncertainty`); NaN where the outputs are.
    ``frames``: the corrected frames on the sensor's scale."""
    sigma, _ = warped_uncertainty(frames, plan, dark, gain, rec)
    return np.sqrt(np.mean(sigma.astype(np.float64) ** 2, axis=-1)).astype(np.float32)


def _variance_channels(frames, plan, dark, gain, rec, read, weights, *, light, ambient, own, radius, variance):
    """The weighted sums (H, W, C) of the read frames' sample variances, ``(total, own part, as the filter of
    ``radius`` takes it)`` (without ``radius`` the last is None and the own part is not to be read), with the
    sequence's shifts and each object layer's own on its pixels (``own``: the pixels decoded with a layer): on the
    device with ``variance`` (translations, affine maps; the frames uploaded once), else from
    :func:`warped_sample_variances` on the host."""
    shifts = rec.estimates[0].shifts
    device = variance is not None and np.ndim(shifts) != 4
    corr = None if radius is None else _interpolation_correlation(radius)
    if device:
        noise = NoiseModel.from_params(plan.params["noise"])
        if variance.shape != np.shape(frames)[1:] or variance.noise != (
                noise.gain_e_per_dn, noise.read_var_dn2, noise.light_rms):
            raise ValueError(f"variance: prepared for {variance.shape} frames and noise {variance.noise}, not the "
                             f"{np.shape(frames)[1:]} frames and the plan's noise {noise}")
        frames = variance.upload(frames)

    def once(d):
        if device:
            return variance.channels(frames, d, read, weights, light=light, ambient=ambient, own=radius is not None,
                                     corr=corr)
        Vs = warped_sample_variances(frames, plan, dark, gain, d, read=read, light=light, filtered=radius,
                                     ambient=ambient)
        return tuple(None if V is None else np.tensordot(V, weights.T, axes=([0], [0])) for V in Vs)

    channels = list(once(shifts))
    for layer in rec.layers if np.ndim(shifts) != 4 else ():  # a flow holds the layers' own already
        mine = own & layer.decoded
        if mine.any():
            for c, theirs in zip(channels, once(layer.shifts)):
                if c is not None:
                    c[mine] = theirs[mine]
    return channels
