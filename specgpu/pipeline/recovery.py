"""Offline recovery of a sequence folder (:func:`recover`, :func:`uncertainty`, :func:`dark_warning`) and the
colorimetry of its outputs (:func:`to_XYZ`, :func:`to_Lab`); used by the CLI, ``specgpu demo``, the report, the
viewer and the studies.

The folder is read by :mod:`specgpu.pipeline.capture_folder`, captured on the twin by
:mod:`specgpu.pipeline.twin_capture` and salvaged by :mod:`specgpu.pipeline.salvage`; each sequence is decoded by
:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder`, whose corrections and warped pass the stream and the
batch run too.
"""

from __future__ import annotations

import numpy as np

from specgpu.engine.colorimetry import XYZ_to_Lab, reflectance_to_XYZ
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.denoise import (
    carried_through_filter,
    check_sigma_radius,
    denoise_recovery,
    frames_guide,
    guide_variance,
)
from specgpu.pipeline.evaluate import true_patch_spectra
from specgpu.pipeline.moving_decode import warped_uncertainty
from specgpu.pipeline.sequence_decoder import SequenceDecoder, corrections_for
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.basis import DEFAULT_WAVELENGTHS, evaluation_exclusions, load_reflectances, pca_basis
from specgpu.planning.plans import Plan
from specgpu.planning.uncertainty import constant_covariance, frame_covariance, frame_variance
from specgpu.rig.scene import colorchecker_scene

__all__ = ["EVALUATION_CHART", "default_basis", "recover", "uncertainty", "dark_warning", "to_XYZ", "to_Lab",
           # still imported from here by the studies (moved to their own modules)
           "SequenceFolder", "capture_plan"]

#: The chart the demo and the accuracy study evaluate on (and leave out of basis training).
EVALUATION_CHART = "ColorChecker N Ohta"


def default_basis(chart: str = EVALUATION_CHART):
    """The uncentred PCA basis of colour-science's measured reflectances with ``chart`` left out of training:
    every set holding the same patches, and any spectrum within 0.01 RMS of one of its patches."""
    _, chart_spectra = true_patch_spectra(colorchecker_scene(24, 36, chart=chart), DEFAULT_WAVELENGTHS)
    return pca_basis(load_reflectances(exclude=evaluation_exclusions(chart), exclude_similar_to=chart_spectra))



def recover(folder: SequenceFolder, *, sequence: int | None = None, out_dtype=np.float32, device=None,
            white_roi=None, white_reflectance=None, motion: str = "none", denoise=None,
            white_moves: str = "scene") -> np.ndarray:
    """The plan's outputs (H, W, B) from a sequence folder: one sequence, or the mean of all (``sequence=None``:
    averaging repeated sequences of a still scene lowers the temporal noise).

    A pixel where any frame used sits at the sensor's maximum code (saturated, flagged per sequence before any
    averaging) has no valid measurement: its outputs are NaN, never a clipped, wrong value.

    ``white_roi`` (``"X,Y,W,H"``) names a reference white of ``white_reflectance`` (a number or a CSV; 0.99 by
    default) in the field: each sequence's decoder is rescaled for the light's drift since calibration
    (:mod:`specgpu.planning.correction`): the colour change fitted once on the sequences' mean white gains (it
    drifts over
    hours; each frame's own power fluctuation averages down over the sequences), each sequence then rescaled by
    its own gains. A plan with an ambient frame (``plan --ambient``) has that frame subtracted
    instead of the calibration's dark level. Either way each sequence is decoded on its own, then averaged.

    Parameters
    ----------
    folder : SequenceFolder
        Frames, plan and calibration (:func:`read_capture`).
    sequence : int, optional
        The sequence to recover; None averages all.
    out_dtype : numpy dtype
        Storage of the result.
    device : optional
        OpenCL device selector.
    white_roi, white_reflectance : optional
        The reference white in the field, as above.
    motion : {"none", "global", "affine", "flow"}
        ``"global"``: the scene moved during the sequence; a translation per frame (``"affine"``: an affine map,
        for a rotation or zoom) is estimated and compensated in the decoding pass (:mod:`specgpu.motion.global_motion`),
        the outputs are the scene at the sequence's
        reference time, and pixels some frame saw outside the field are NaN. One sequence at a time (the scene
        moves between sequences too): ``sequence`` is required unless the folder holds one.
    white_moves : {"scene", "camera"}
        With ``motion`` and ``white_roi``: the white moves with the scene (measured on the motion-compensated
        samples, the ROI where it is at the reference time) or is fixed in the field (its raw pixels).
    denoise : (radius, eps), optional
        Smooth the outputs by the guided filter of ``recover --denoise`` (:mod:`specgpu.pipeline.denoise`): its
        guide the frames' sum, or with ``motion`` the warped frames' sum, pixels the compensation flags left out
        (:func:`specgpu.pipeline.denoise.denoise_compensated`).

    Returns
    -------
    ndarray, (H, W, B)
        The plan's outputs on ``plan.output_wavelengths`` (reflectance, or XYZ for a tristimulus plan); NaN
        where saturated.

    Examples
    --------
    A white plate, captured on a small twin through 20 nm narrowband frames, recovers as a white plate:

    >>> from pathlib import Path
    >>> import numpy as np
    >>> from specgpu import calibration, pipeline, planning, rig
    >>> small = rig.RigDescription(camera=rig.CameraParameters(roi_width=320, roi_height=240))
    >>> cal = calibration.oracle_calibration(small)
    >>> bands = planning.make_plan("narrowband", cal, step_nm=20.0)
    >>> shot = pipeline.capture_plan(small, bands, rig.white_plate_scene(240, 320), noise_seed=3, calibration=cal)
    >>> cube = pipeline.recover(pipeline.SequenceFolder(Path("mem"), shot.sequences[0].frames[None], bands, cal,
    ...                                                 [], {}))
    >>> cube.shape[:2], bool(abs(np.nanmedian(cube) - 0.99) < 0.05)
    ((240, 320), True)
    """
    decoder = SequenceDecoder(folder.plan, folder.calibration, white_roi=white_roi,
                              white_reflectance=white_reflectance, motion=motion, device=device, denoise=denoise,
                              white_moves=white_moves)
    y = decoder.decode(folder.frames, sequence=sequence, where=folder.path, out_dtype=out_dtype)
    if denoise is not None and decoder.motion == "none":  # the motion mode filters in its own pass
        y = denoise_recovery(folder, y, sequence=sequence, radius=denoise[0], eps=denoise[1], device=device)
    return y


def uncertainty(folder: SequenceFolder, *, sequence: int | None = None, illuminant: str | None = None,
                observer: str | None = None, device=None, white_roi=None, white_reflectance=None,
                integration: str = "rectangle", motion: str = "none", white_moves: str = "scene",
                denoise=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-pixel standard deviation (H, W, P) of :func:`recover`'s outputs for the same frames, options and
    corrections (white ROI, ambient frame, linearisation, per-pattern flat field) and, given an illuminant, the
    covariance (H, W, 3, 3) of their XYZ for ``observer`` (:mod:`specgpu.planning.uncertainty`); NaN where saturated.
    With ``motion``: at the motion-compensated samples (:func:`specgpu.pipeline.moving_decode.warped_uncertainty`),
    NaN where the outputs are. With ``denoise`` (radius, eps): of the outputs denoised so (``recover --denoise``),
    carried through the guided filter (:func:`specgpu.pipeline.denoise.carried_through_filter`)."""
    M = None if illuminant is None else folder.plan.outputs_to_XYZ(illuminant, observer, integration)
    if denoise is not None:
        check_sigma_radius(denoise[0])
    if motion != "none":
        dec = SequenceDecoder(folder.plan, folder.calibration, white_roi=white_roi,
                              white_reflectance=white_reflectance, white_moves=white_moves, motion=motion,
                              device=device, denoise=denoise)
        sensor = dec.corrections.moving(folder.frames[dec.picked(folder.frames, sequence, folder.path)[0]])
        rec, y, gains, A = dec.warped_outputs(sensor)
        smoothed = dec.smoothed(y, rec.mask, samples=None if gains is None else rec.y, decoder=A)
        return warped_uncertainty(sensor, folder.plan, dec.corrections.dark, folder.calibration.flat_field, rec, A,
                                  M=M, light=gains is None, smoothed=smoothed,
                                  variance=dec.variance_launch())
    dec = SequenceDecoder(folder.plan, folder.calibration, white_roi=white_roi, white_reflectance=white_reflectance,
                          device=device)
    picked = dec.picked(folder.frames, sequence, folder.path)
    plan, corr = folder.plan, dec.corrections
    const = constant_covariance(plan)
    var, cov = _noise_parts(folder, dec, picked, M, light=corr.white_roi is None, device=device)
    saturated = dec.saturated(folder.frames, picked)
    var[saturated] = np.nan
    if cov is not None:
        cov[saturated] = np.nan
    if denoise is not None:
        # the pixels' own part (no light) through the filter's weights, the guide's own noise passed by the
        # outputs' slopes on it (a saturated pixel adds nothing to its neighbours)
        own_var, own_cov = _noise_parts(folder, dec, picked, M, light=False, device=device)
        p = dec.decode(folder.frames, sequence=sequence, where=folder.path).astype(np.float64)
        guide, level = frames_guide(folder, sequence=sequence, device=device)
        B, h, w = p.shape[-1], *p.shape[:2]
        own, total = [own_var], [var]
        terms = [[(b, b, 1.0)] for b in range(B)]
        if cov is not None:  # the covariance's entries in the same call (the filter's weights made once)
            p = np.concatenate([p, p @ np.asarray(M, np.float64).T], axis=-1)
            own.append(own_cov.reshape(h, w, 9))
            total.append(cov.reshape(h, w, 9))
            terms += [[(B + i, B + j, 1.0)] for i in range(3) for j in range(3)]
        carried = carried_through_filter(np.concatenate(own, axis=-1), np.concatenate(total, axis=-1),
                                         guide=guide, radius=denoise[0], eps=denoise[1], slopes=p, terms=terms,
                                         guide_var=guide_variance(folder, level, sequence=sequence, device=device),
                                         device=device)
        var = carried[..., :B]
        if cov is not None:
            cov = carried[..., B:].astype(np.float64).reshape(h, w, 3, 3)
    sigma = np.sqrt(np.maximum(var + np.diag(const).astype(np.float32), 0.0)).astype(np.float32)
    sigma[saturated] = np.nan
    if cov is not None:
        cov = cov + M @ const @ M.T
    return sigma, cov


def _noise_parts(folder, dec, picked, M, *, light: bool, device) -> tuple[np.ndarray, np.ndarray | None]:
    """The frames' noise part (no constant) of the outputs' variance (H, W, P) and, given ``M``, of their XYZ
    covariance (H, W, 3, 3) for :func:`uncertainty`; ``light``: with the light's fluctuation."""
    plan, corr, gain = folder.plan, dec.corrections, folder.calibration.flat_field
    if corr.per_sequence:
        # decoded one sequence at a time by its own decoder: the variance of their mean is the sum of each
        # sequence's frame noise over S^2. A white reference's gains rescale each sequence's decoder by its own
        # frames' power, so the light's fluctuation is divided out there; with the ambient frame alone it stays,
        # at each frame's own signal above that frame. An ambient frame brings its own noise, and the room
        # light's shot noise in every frame. The noise model is of the sensor's samples: the corrected frames on
        # its scale.
        decoded = [(signal + level[None], level, A)
                   for signal, level, A in dec.sequence_decoders(folder.frames, picked)]
        S = len(decoded)
        kw = {"light": light, "device": device, "ambient_dark": None if corr.ambient is None else corr.dark}
        var = sum(frame_variance(fr, plan, dark, gain, A=A, **kw) for fr, dark, A in decoded) / S ** 2
        cov = None if M is None else sum(frame_covariance(fr, plan, dark, gain, M, A=A, **kw)
                                         for fr, dark, A in decoded) / S ** 2
        return np.asarray(var, np.float32), cov
    frames = corr.sensor(dec.mean_frames(folder.frames, picked))  # as recover decodes them
    kw = {"sequences": len(picked), "light": light, "device": device}
    var = frame_variance(frames, plan, corr.dark, gain, **kw)
    cov = None if M is None else frame_covariance(frames, plan, corr.dark, gain, M, **kw)
    return np.asarray(var, np.float32), cov


def dark_warning(folder: SequenceFolder, sequence: int | None = None) -> str | None:
    """One line saying why the dark level :func:`recover` subtracts from this capture cannot be trusted, or None.

    A plan with an ambient frame has its dark measured on the scene in every sequence: trusted. Otherwise the
    calibration's level at the plan's exposure is subtracted, and it is not trusted when: the calibration found
    light on the object with every mirror off (:attr:`CalibrationBundle.mirrors_off_light`: the white's share of it
    is subtracted from every darker object); the plan's exposure lies outside the exposures the calibration
    measured the dark level at; or more than 1 % of the pixels read, in some frame (mean of the sequences used),
    further below that level than the camera's noise allows (5 standard deviations of the dark level's temporal
    noise, from the plan's noise model, 1 DN without one, plus 0.5 DN).
    """
    plan, bundle = folder.plan, folder.calibration
    if corrections_for(bundle, plan).ambient is not None:
        return None
    t = float(plan.exposure_s)
    reasons = []
    if bundle.mirrors_off_light:
        light = bundle.reports.get("mirrors_off_dn_per_s")
        amount = (f" ({float(light) * t * bundle.white_reflectance:.1f} DN on its white at {t * 1e3:.3g} ms)"
                  if isinstance(light, (int, float)) else "")
        reasons.append(f"the calibration found light with every mirror off{amount}")
    lo, hi = bundle.dark_range_s
    if not lo * (1 - 1e-6) <= t <= hi * (1 + 1e-6):
        reasons.append(f"the plan's exposure {t * 1e3:.3g} ms lies outside the {lo * 1e3:.3g}-{hi * 1e3:.3g} ms "
                       "the calibration measured its dark level at")
    used = folder.frames if sequence is None else folder.frames[sequence:sequence + 1]
    noise = plan.params.get("noise") if isinstance(plan.params, dict) else None
    var = noise.get("read_var_dn2") if isinstance(noise, dict) else None
    var = float(var) if isinstance(var, (int, float)) and np.isfinite(var) and var > 0 else 1.0
    margin = 5.0 * float(np.sqrt(var / used.shape[0])) + 0.5
    dark = bundle.dark_at(t)
    low = np.full(dark.shape, np.inf, np.float32)
    for k in range(used.shape[1]):
        np.minimum(low, used[:, k].mean(axis=0, dtype=np.float32) - dark, out=low)
    below = float(np.mean(low < -margin))
    if below > 0.01:
        reasons.append(f"{below:.1%} of the pixels read more than {margin:.1f} DN below that level")
    if not reasons:
        return None
    return (f"dark level not trusted ({bundle.dark_at(t).mean():.1f} DN subtracted, no ambient frame): "
            + "; ".join(reasons) + "; plan with --ambient")


def to_XYZ(y: np.ndarray, plan: Plan, illuminant: str = "D65", *, observer: str | None = None,
           integration: str = "rectangle", device=None) -> np.ndarray:
    """XYZ (Y = 1 for the white) of a plan's outputs for ``observer`` (None: the plan's own for a tristimulus
    plan, else the 2 degree observer; :meth:`specgpu.planning.plans.Plan.resolve_observer`), reflectance integrated
    by ``integration`` (see :meth:`specgpu.planning.plans.Plan.outputs_to_XYZ`)."""
    observer = plan.resolve_observer(observer)
    plan.outputs_to_XYZ(illuminant, observer, integration)  # refuses outputs with no XYZ, or another light/observer
    if plan.output == "reflectance":  # the same weights, applied on the device
        return reflectance_to_XYZ(y, plan.output_wavelengths, illuminant=illuminant, cmfs=observer,
                                  integration=integration, device=device)
    return y  # a tristimulus plan's outputs are XYZ already


def to_Lab(XYZ: np.ndarray, plan: Plan, illuminant: str = "D65", *, observer: str | None = None,
           integration: str = "rectangle", device=None) -> np.ndarray:
    """CIELAB of :func:`to_XYZ`'s XYZ: its white is the plan's (:meth:`specgpu.planning.plans.Plan.white_XYZ`,
    the perfect diffuser integrated with the same weights), so a perfect white is (100, 0, 0)."""
    white = plan.white_XYZ(illuminant, plan.resolve_observer(observer), integration)
    return XYZ_to_Lab(XYZ, illuminant=white, device=device)

