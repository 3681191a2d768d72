"""The motion-compensated recovery of one sequence (:func:`recover_moving`), with a second motion layer: an object
moving on its own over a scene whose global motion is compensated.

Global compensation samples every frame where the scene's (or camera's) motion says it saw each pixel; a hand, a
chart on a conveyor, anything moving on its own is then misregistered, and the consistency check
(:func:`specgpu.motion.consistency.consistency`) flags its pixels where some frame has structure, the residual
check (:mod:`specgpu.motion.residual`) where its samples mix spectra, and leaves them NaN. When the flagged
pixels gather into a region of some size, that region is taken to be one object with a motion of its own:

1. its translation per frame is registered on the frames' gradient images restricted to the region (the whitened
   cross-power of the region of the reference frame against each frame: the highest correlation peaks away from
   the background's displacement, refined to sub-pixel by a Gaussian fit, are the candidates, and the steady motion
   most frames' candidates agree on, up to :data:`specgpu.motion.object_motion.MAX_LAYER_SPEED_PX` per frame, is
   the object's: :mod:`specgpu.motion.object_motion`);
2. the frames are decoded again with that motion, in the same kind of warped device pass;
3. the object's footprint at the reference time is found: the convex hull of the pixels its motion makes agree
   (textured, every frame with structure correlating with the median) clearly better than the global motion, less
   the rim the check's window adds. Its pixels take the object's decoding unless the frames, compensated by the
   object's motion, disagree there; a pixel of the rim takes it only where they positively agree;
4. the background the object covered in some frame of the sequence (the footprint moved by the object's motion
   relative to the background's) is flagged: its samples mix the two surfaces. So are the object's pixels its own
   decoding cannot give. Pixels consistent under neither motion stay flagged and NaN.

Where a mode offers two motions, each is a hypothesis its decoding's checks judge, and what they cannot decide is
flagged: ``affine`` decodes the translation too and keeps the decoding that explains more of the field
(:func:`explained`); under ``flow`` a pixel that both the flow's decoding and the other one pass but that they
decode differently (:func:`disagreeing`) is flagged.

Pixels decoded with an object's motion carry ``Mask.LAYER`` in the mask. A motion under which the checks flag
most of the field (:data:`MAX_REFUTED_SHARE`) is refuted and every pixel flagged (:func:`refuted`): an estimate
taken over by a fast object, an affine map pulled by one; what passes under it passes because nothing there can
tell, not because it holds.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from specgpu.core.mask import UNSEEN, Mask
from specgpu.core.numerics import live_gain
from specgpu.engine.linear_map import LinearResult
from specgpu.engine.noise_floor import FloorPlanes
from specgpu.engine.runtime import get_queue
from specgpu.engine.warp_map import apply_linear_warped
from specgpu.motion.ambient import STEADY_PX, misplaced, place_frame
from specgpu.motion.consistency import CHECK_THRESHOLD, consistency, noise_floors, noise_floors_on_device
from specgpu.motion.estimate import at_reference_time
from specgpu.motion.flow import choose_flow, flow_field, tile_motion
from specgpu.motion.images import device_takes, frame_gradients
from specgpu.motion.methods import estimate_motion
from specgpu.motion.object_motion import (
    MIN_LAYER_SHARE,
    estimate_layer_motion,
    flagged_regions,
    object_footprint,
    occluded_by,
)
from specgpu.motion.reference import check_reference_frames
from specgpu.motion.residual import residual_chi2
from specgpu.pipeline.moving_device import noise_floor_set_up, warped_checked

__all__ = ["MAX_REFUTED_SHARE", "grow_flags", "refuted", "ObjectLayer", "MovingRecovery",
           "explained", "disagreeing", "DISAGREE_RMS", "decode_object_layers", "recover_moving"]

#: A region is an object's when its motion makes at least this share of the region's pixels agree.
MIN_SEED_SHARE = 0.02

#: A pixel seeds an object's footprint where the frames' worst correlation under its motion beats the global
#: motion's by this.
SEED_MARGIN = 0.3

#: The consistency check's window (px; :func:`specgpu.motion.consistency.consistency`'s default).
WINDOW = 9


@dataclass(frozen=True)
class ObjectLayer:
    """One object's motion and what it changed.

    Attributes
    ----------
    shifts : numpy.ndarray
        (K, 2) displacement (x, y) of the object in each frame from the reference time, px.
    box : tuple
        (y0, y1, x0, x1) of the region registered.
    pixels : int
        Pixels decoded with the object's motion (its footprint at the reference time, less those its frames
        disagree on).
    occluded : int
        Pixels of the background the object covered in some frame of the sequence (flagged and NaN).
    decoded : numpy.ndarray or None
        (H, W) bool: the pixels this layer's decoding was given (a later layer or its own flags may take some back:
        the mask's bit 16 says which still hold it).
    """

    shifts: np.ndarray
    box: tuple
    pixels: int
    occluded: int = 0
    decoded: np.ndarray | None = field(default=None, repr=False, compare=False)


def decode_object_layers(frames, A, estimate, check, y, mask, dark=None, gain=None, *, saturation=None, device=None,
                         threshold: float = CHECK_THRESHOLD, min_share: float = MIN_LAYER_SHARE,
                         read=None, residual=None, checked=None, floors=None) -> list:
    """Decode again, with an object's own motion, the flagged regions of a globally compensated recovery.

    ``y`` (H, W, B) and ``mask`` (H, W) uint8 are the global recovery's (``Mask.INCONSISTENT`` where flagged)
    and are updated in place: the object's footprint takes the object's decoding (bit 16, the object pass's own
    mask bits; bit 8 cleared); the background it covered and the object's pixels it cannot decode are NaN with bit
    8 (or the object pass's saturated / outside bit). Pixels flagged by the global check elsewhere keep their bit
    8: the caller leaves them NaN. ``estimate``: the global :class:`specgpu.motion.estimate.MotionEstimate`
    (translation model; its gradient images are reused where kept); ``check``: the (textured, worst) maps of the
    global motion's :func:`~specgpu.motion.consistency.consistency`, whose flags ``mask`` holds. Returns the
    :class:`ObjectLayer` of each region decoded (empty: none found). ``read``: the frames the decoder reads (all
    by default; a plan's broadband reference frames left out, as the global pass and check leave them out);
    ``residual``: the :class:`~specgpu.motion.residual.ResidualCheck` the object's decoding must pass too;
    ``checked``: the frames the consistency check reads (default ``read``; a plan's ambient frame, which the pass
    reads, left out: it holds no projector light to compare).
    """
    frames = np.asarray(frames)
    if estimate.model != "translation":
        return []
    flagged = (mask & Mask.INCONSISTENT) > 0
    regions = flagged_regions(flagged, min_share=min_share)
    if not regions:
        return []
    gradients = frame_gradients(frames, dark, gain, estimate.gradients, device=device)
    # the frames the object is registered in: the global estimate's; with reference frames every frame (they alone
    # are too few, two where M >= K, for a steady motion to be told from one frame's candidate peaks)
    usable = estimate.registered if read is None else np.ones(len(frames), bool)
    # and registered to the global estimate's reference frame, or with reference frames (whose own anchor may be far
    # from the middle: the first of two) to the brightest of the middle frames, as the global estimate picks its own
    anchor = estimate.reference_frame
    if read is not None:
        near = [k for k in range(len(frames)) if abs(k - (len(frames) - 1) / 2.0) <= 1.0]
        anchor = max(near, key=lambda k: float(np.mean(frames[k], dtype=np.float64)))
    textured_global, worst_global = check
    layers = []
    for region in regions:
        raw, box = estimate_layer_motion(gradients, region, estimate.shifts, anchor, usable)
        if raw is None:
            continue
        shifts = raw - at_reference_time(raw)
        res = _warped(frames, A, shifts, dark, gain, read, residual, saturation=saturation, return_mask=True,
                      device=device)
        looked = read if checked is None else checked
        textured, worst = _checked_consistency(looked, frames, shifts, dark, gain, gradients, residual, floors)
        valid = (res.mask & UNSEEN) == 0
        fits = (res.mask & Mask.INCONSISTENT) == 0  # one reflectance explains the samples the object's motion takes
        # the object's pixels: its motion makes the frames agree there, and clearly better than the global one
        # (or where it makes a pixel the global motion left flagged agree)
        agree = valid & fits & textured & (worst >= threshold)
        seed = agree & ((worst - worst_global >= SEED_MARGIN) | (region & flagged))
        if seed.sum() < MIN_SEED_SHARE * region.sum():
            continue  # the object's motion explains too little of the region to be an object's
        # less any background it took in: where the global motion makes the frames clearly agree better
        hull = object_footprint(seed)
        hull &= ~(textured_global & (worst_global >= threshold) & (worst_global - worst >= SEED_MARGIN))
        # the seeds reach about half a window past the object's edge (their window holds its texture): the object
        # is the hull less that rim, and a rim pixel is the object's only where its motion positively agrees
        footprint = ndimage.binary_erosion(hull, iterations=WINDOW // 2)
        background = estimate.shifts if estimate.shifts.shape == shifts.shape else np.zeros_like(shifts)
        covered = occluded_by(footprint, shifts - background)
        use = valid & fits & ~covered & ((footprint & (worst >= threshold)) | (hull & ~footprint & agree))
        y[use] = res.y[use]
        mask[use] = res.mask[use] | np.uint8(Mask.LAYER)
        # the object's pixels its own decoding cannot give (its frames disagree, or its pass saw a sample
        # saturated or outside the field: that reason kept), and the background it covered in some frame
        hidden = (footprint & ~use) | covered
        mask[hidden] = (mask[hidden] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)
        failed = footprint & ~valid & ~covered
        mask[failed] = ((mask[failed] & ~np.uint8(Mask.INCONSISTENT))
                        | (res.mask[failed] & np.uint8(UNSEEN)))
        y[hidden] = np.nan
        flagged = (flagged & ~use) | hidden
        layers.append(ObjectLayer(shifts, box, int(use.sum()), int(covered.sum()), decoded=use))
    return layers


def _reading(read, *arrays) -> list:
    """Each of ``arrays`` (per frame along its first axis, or a list) at the frames ``read`` (None: as it is)."""
    if read is None:
        return list(arrays)
    return [[a[k] for k in read] if isinstance(a, (list, tuple)) else np.asarray(a)[read] for a in arrays]


def _checked_consistency(checked, frames, motion, dark, gain, gradients, residual, floors=None):
    """:func:`~specgpu.motion.consistency.consistency` of the frames ``checked`` (None: all) under ``motion``, their
    gradient images taken from ``gradients`` (None: made); with the ``residual`` check, the frames' noise floors of
    its noise model too (a bright flat area's shot noise is no structure of its own): taken from ``floors`` (every
    frame's, ``_sequence_floors``) where given, else made here; without it, the median's test alone."""
    per_frame = dark is not None and np.ndim(dark) == 3
    used_dark = _reading(checked, dark)[0] if per_frame else dark
    looked, moved = _reading(checked, frames, motion)
    given = None if gradients is None else _reading(checked, gradients)[0]
    if floors is None or residual is None:
        floor = None
    else:  # on the device (the check reads them there), or on the host
        floor = floors.take(checked) if isinstance(floors, FloorPlanes) else _reading(checked, floors)[0]
    return consistency(looked, moved, used_dark, gain, gradients=given,
                       noise=None if residual is None else residual.noise, floor=floor)


def _sequence_floors(frames, dark, gain, residual, device=None):
    """Every frame's noise floor under the ``residual`` check's noise model (None without one), made once per
    sequence: a frame's floor is its own, whatever the motion, so the global check, each object layer's and the
    flow's read the same. On the device, where the check runs there
    (:func:`~specgpu.motion.consistency.noise_floors_on_device`, the sensor's set-up kept per thread:
    :func:`~specgpu.pipeline.moving_device.noise_floor_set_up`), else (a dark level per frame, inputs the device
    refuses) on the host (:func:`~specgpu.motion.consistency.noise_floors`)."""
    if residual is None:
        return None
    if (dark is not None and np.ndim(dark) == 3) or not device_takes(
            frames, None if dark is None else np.asarray(dark, np.float32), gain):
        return noise_floors(frames, residual.noise, dark, gain)
    prepared = noise_floor_set_up(get_queue(device), frames.shape[1:], dark, gain, residual.noise)
    return noise_floors_on_device(frames, residual.noise, dark, gain, prepared=prepared)


def _warped(frames, A, shifts, dark, gain, read, residual=None, **kw):
    """:func:`~specgpu.engine.warp_map.apply_linear_warped` of the frames ``read`` only (None: every frame); a
    sample of a pixel with no response (:func:`specgpu.core.numerics.live_gain`) makes its output NaN. With a
    ``residual`` (:class:`~specgpu.motion.residual.ResidualCheck`; ``return_mask``), the same pass also
    outputs what the check needs of each pixel's compensated samples, and a pixel no single reflectance explains
    is flagged :attr:`~specgpu.core.mask.Mask.INCONSISTENT` in the mask."""
    if residual is None:
        return apply_linear_warped(frames, A, shifts, dark, live_gain(gain), read=read, **kw)
    A = np.asarray(A, np.float64)
    if kw.get("return_mask"):  # a translation per frame: the check beside the pass, on the device
        done = warped_checked(frames, A, shifts, dark, gain, read, residual, saturation=kw.get("saturation"),
                              device=kw.get("device"))
        if done is not None:
            return done
    res = apply_linear_warped(frames, np.vstack([A, residual.rows]), shifts, dark, live_gain(gain), read=read, **kw)
    B = A.shape[0]
    chi = residual_chi2(res.y[..., B:], residual, gain)
    mask = res.mask
    mask[chi > residual.threshold] |= np.uint8(Mask.INCONSISTENT)
    return LinearResult(np.ascontiguousarray(res.y[..., :B]), mask)


#: Two decodings of one pixel disagree where the RMS over the outputs of their difference exceeds this (output
#: units: reflectance for a reflectance plan). Half the drill's bound on a wrong pixel (twice a still recovery's
#: worst, about 0.07 on the twin): two decodings of the same surface differ by their noise and by where the
#: bilinear samples fall, a few hundredths; one of them wrong by the bound differs from the other by more.
DISAGREE_RMS = 0.05


def disagreeing(y, other, tolerance: float = DISAGREE_RMS) -> np.ndarray:
    """(H, W) bool: where two decodings ``y`` and ``other`` (H, W, B) of the same pixels differ by more than
    ``tolerance`` (RMS over the B outputs); False where either is not finite."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.mean((np.asarray(y, np.float32) - np.asarray(other, np.float32)) ** 2, axis=2)) > tolerance


def _with_flow(frames, A, est, gradients, y, mask, layers, maps, dark, gain, *, saturation, device, residual=None,
               checked=None, floors=None):
    """The flow's part of a ``model="flow"`` recovery (:mod:`specgpu.motion.flow`), in place on ``y`` and
    ``mask``: each pixel the flow's decoding gives (:func:`~specgpu.motion.flow.choose_flow`, with the
    global check's ``maps``; every pixel without them; the flow's check reads the frames ``checked``, every one by
    default). Returns ``est`` with ``shifts`` the (K, 2, H, W) displacement each pixel was decoded with and
    ``model`` "flow"."""
    K, h, w = np.shape(frames)
    per_pixel = np.empty((K, 2, h, w), np.float32)
    per_pixel[...] = np.asarray(est.shifts, np.float32)[:, :, None, None]
    held = np.zeros((h, w), bool)
    for layer in layers:  # the pixels an object's own motion decoded
        mine = layer.decoded & ((mask & np.uint8(Mask.LAYER)) != 0)
        per_pixel[:, :, mine] = np.asarray(layer.shifts, np.float32)[:, :, None]
        held |= mine
    motion = tile_motion(gradients, est.shifts, est.reference_frame, est.registered)
    if motion.measured.any() and np.any(motion.velocity != 0):
        flow = flow_field(motion, est.shifts, (h, w))
        res = _warped(frames, A, flow, dark, gain, None, residual, saturation=saturation, return_mask=True,
                      device=device)
        disagree = np.zeros((h, w), bool)
        if maps is not None:
            flow_maps = _checked_consistency(checked, frames, flow, dark, gain, gradients, residual, floors)
            use = choose_flow(mask, maps, res.mask, flow_maps, held, threshold=CHECK_THRESHOLD,
                              inconsistent=Mask.INCONSISTENT)
            # two motions each pass every check at a pixel yet decode it differently: one of them samples other
            # surfaces that no check can tell apart (a flat background under a velocity interpolated across an
            # object's edge, an object's edge under the background's motion), and which is not known
            passed = (mask & np.uint8(UNSEEN | Mask.INCONSISTENT)) == 0
            passed &= (res.mask == 0) & (flow_maps[1] >= CHECK_THRESHOLD)
            disagree = passed & disagreeing(y, res.y)
        else:
            use = np.ones((h, w), bool)
        y[use], mask[use] = res.y[use], res.mask[use]
        per_pixel[:, :, use] = flow[:, :, use]
        mask[disagree] = (mask[disagree] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)
    return replace(est, shifts=per_pixel, model="flow")


#: A motion under which the checks flag more than this share of the pixels in the field is refuted: the scene does
#: not move so, and the pixels that pass under it pass because nothing there can tell (flat surfaces sampled far
#: from where they are), not because it holds. On the twin an estimate taken over by a chart moving 14 px per frame
#: left 95 % of the field flagged and a few hundred wrong pixels unflagged; affine maps pulled by a chart 65 %.
MAX_REFUTED_SHARE = 0.5


#: Pixels not flagged that flagged ones enclose are flagged too where they are fewer than this: the check's window.
ISLAND_PX = WINDOW * WINDOW


def grow_flags(mask) -> None:
    """Flag (in place) the pixels next to an inconsistent one (8-connected) that their own pass saw in the field.
    A compensated sample is bilinear, read from the 2 x 2 sensor pixels about its point, so where samples that mix
    surfaces begin is known to a pixel: the pixel beside a flagged one reads sensor pixels the flagged one reads,
    and its check, a statistic of few samples, may pass just below its threshold. (On the twin at 640 x 480 every
    unflagged pixel decoded wrong in the cases of ``tools/studies/motion_flags.py`` lay within 1.4 px of a flagged one.)
    The islands of fewer than :data:`ISLAND_PX` pixels the flags enclose are flagged as well."""
    flagged = (mask & np.uint8(Mask.INCONSISTENT)) != 0
    if not flagged.any():  # no flag to grow, and the one region left is the whole field
        return
    # the 8-connected neighbours: the flags or-ed over 3 rows, then over 3 columns (whole-array operations, a
    # binary dilation's structuring element walked per pixel costing tens of ms)
    rows = flagged.copy()
    rows[1:] |= flagged[:-1]
    rows[:-1] |= flagged[1:]
    ring = rows.copy()
    ring[:, 1:] |= rows[:, :-1]
    ring[:, :-1] |= rows[:, 1:]
    ring &= ~flagged
    # and the islands the flags enclose, smaller than the check's window: a region whose motion is refuted all
    # about them (an object fast enough to be over a pixel in one frame only leaves its flat inside so)
    labels, n = ndimage.label(~(flagged | ring))
    if n:
        small = np.bincount(labels.ravel(), minlength=n + 1) < ISLAND_PX  # each region's pixels, counted once
        small[0] = False  # label 0: the flags and their ring
        ring |= small[labels]
    ring &= (mask & np.uint8(UNSEEN)) == 0
    mask[ring] = (mask[ring] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)


def refuted(mask) -> bool:
    """Flag every pixel of ``mask`` (in place, :attr:`~specgpu.core.mask.Mask.INCONSISTENT`) where more than
    :data:`MAX_REFUTED_SHARE` of the pixels in the field (not saturated, non-finite or outside it) are flagged
    inconsistent: the motion they were decoded with is not the scene's. Returns whether it did."""
    seen = (mask & np.uint8(UNSEEN)) == 0
    flagged = seen & ((mask & np.uint8(Mask.INCONSISTENT)) != 0)
    if not seen.any() or flagged.sum() <= MAX_REFUTED_SHARE * seen.sum():
        return False
    mask[seen] = (mask[seen] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)
    return True


def explained(recovery) -> int:
    """The pixels a motion-compensated ``recovery`` (:class:`MovingRecovery`) decoded: every output finite (not
    flagged, saturated or outside the field); what a motion hypothesis is judged by against another."""
    return int(np.all(np.isfinite(recovery.y), axis=2).sum())


#: The motion method (:data:`specgpu.motion.methods.MOTION_METHODS`) that estimates each model of
#: :func:`recover_moving`: a flow starts from the global translation.
MODEL_METHODS = {"translation": "global", "affine": "affine", "flow": "flow"}


@dataclass(frozen=True)
class MovingRecovery:
    """A motion-compensated recovery: the outputs at the reference time, the mask and each sequence's motion."""

    y: np.ndarray
    mask: np.ndarray
    estimates: list
    #: the :class:`ObjectLayer` of each object decoded with its own motion
    layers: list = field(default_factory=list)
    #: with an ambient frame placed by the others' motion: the largest departure (px) of a registered frame from the
    #: steady motion it was placed on (:func:`specgpu.motion.ambient.place_frame`); None without one
    ambient_misfit: float | None = None


def recover_moving(frames: ArrayLike, A: ArrayLike, *, dark: ArrayLike | None = None, gain: ArrayLike | None = None,
                   saturation=None, upsample: int = 10, binning: int = 1,
                   shifts: ArrayLike | None = None, model: str = "translation", check: bool = True, layers: bool = True,
                   device=None, seconds: dict | None = None, reference_frames=None, residual=None,
                   ambient: int | None = None) -> MovingRecovery:
    """Recover one sequence of a moving scene: estimate each frame's displacement (or take ``shifts``), then decode
    with frame k sampled at x + d_k in one device pass.

    Parameters
    ----------
    frames : array_like, (K, H, W)
    A : array_like, (B, K)
    dark, gain, saturation
        As :func:`specgpu.engine.apply_linear`.
    upsample, binning
        Of :func:`~specgpu.motion.global_motion.estimate_global_motion`.
    model : {"translation", "affine", "flow"}
        A translation or an affine map per frame (:func:`~specgpu.motion.global_motion.estimate_global_motion`; with
        ``check``, an affine map is decoded beside the translation, with its object layers, and the one that
        explains more pixels (:func:`explained`) kept, the translation on a tie); or
        ``"flow"``: the translation's decoding, then a dense flow where its frames agree and the translation's are
        flagged, untextured or not clearly better correlated (:mod:`specgpu.motion.flow`):
        ``estimates[0].shifts`` is then (K, 2, H, W), the displacement each pixel was decoded with.
    shifts : array_like, (K, 2) or (K, 2, 3), optional
        Known displacements (e.g. the twin's truth); no estimation then.
    check : bool
        Flag (mask bit 8) and leave NaN the pixels whose compensated frames disagree
        (:func:`~specgpu.motion.consistency.inconsistent_pixels`): an object moving on its own, an occlusion.
    layers : bool
        With ``check`` and an estimated translation per frame: decode the flagged regions again with an object's own
        motion where one stands out (:func:`decode_object_layers`).
    device : optional
        OpenCL device selector (or queue).
    seconds : dict, optional
        Host seconds of each step (``"estimate"``, ``"warp"``, ``"check"``: the check, the layers and the NaN)
        added to it.
    reference_frames : sequence of int, optional
        The sequence's broadband reference frames (a plan made with ``--reference-every``,
        :func:`specgpu.planning.reference_frames.reference_indices`): the motion is estimated from them alone
        (:func:`specgpu.motion.reference.estimate_reference_motion`), and the warped pass and the global
        consistency check read the other frames only (the decoder does not read the reference frames: where they
        saw outside the field, saturated or disagree cannot reach the outputs).
    residual : ResidualCheck, optional
        With ``check``: every decoding (global, an object layer's, the flow's) also flags the pixels whose
        compensated samples no single reflectance explains (:mod:`specgpu.motion.residual`; made for the
        plan by :func:`~specgpu.motion.residual.residual_check`). Without it only the gradient images
        judge, which cannot where no frame has structure of its own.
    ambient : int, optional
        The sequence's ambient frame (a plan made with ``--ambient``; ``A``'s column for it minus the sum of the
        others', :func:`specgpu.planning.correction.subtracting_ambient`): the motion is estimated from the other
        frames and the ambient frame placed on their steady motion (:func:`specgpu.motion.ambient.place_frame`);
        the warped pass samples it like the others (its pixels seen outside the field NaN with bit 4), the
        consistency check reads the other frames only. Where they depart from a steady motion by more than
        :data:`specgpu.motion.ambient.STEADY_PX`, the pixels where the room light has structure within that
        reach are flagged inconsistent (:func:`specgpu.motion.ambient.misplaced`) and a warning says so.

    Returns
    -------
    MovingRecovery
        ``y`` (H, W, B) float32, NaN where a pixel was seen outside the field, saturated or inconsistent;
        ``mask`` (H, W) uint8 (1 saturated, 2 non-finite, 4 outside the field, 8 inconsistent, 16 decoded with an
        object's own motion); ``estimates`` [MotionEstimate] (empty with ``shifts``); ``layers`` [ObjectLayer];
        ``ambient_misfit``.
    """
    if model == "affine" and shifts is None and check:
        # an affine map per frame is a hypothesis beside the translation (of which it is a refinement), not a
        # replacement: fitted over a field whose parts move differently (an object over the scene) or to tiles a
        # fast motion leaves with little overlap it can be pulled off the motion the translation follows, and
        # wrong samples of flat surfaces can pass every check. Each decoding is checked; the one whose motion
        # explains more of the field is kept (the translation where they tie: the fewer parameters).
        given = dict(dark=dark, gain=gain, saturation=saturation, upsample=upsample, binning=binning, check=check,
                     layers=layers, device=device, seconds=seconds, reference_frames=reference_frames,
                     residual=residual, ambient=ambient)
        return max((_recover(frames, A, model=m, shifts=None, **given) for m in ("translation", "affine")),
                   key=explained)
    return _recover(frames, A, dark=dark, gain=gain, saturation=saturation, upsample=upsample, binning=binning,
                    shifts=shifts, model=model, check=check, layers=layers, device=device, seconds=seconds,
                    reference_frames=reference_frames, residual=residual, ambient=ambient)


def _estimate(frames, dark, gain, model, refs, upsample, binning, device, ambient):
    """The motion of the sequence ``frames`` (its MotionEstimate) and, with an ``ambient`` frame, the misfit of the
    steady motion it was placed on (else None)."""
    method = MODEL_METHODS.get(model, model)
    if ambient is None:
        return estimate_motion(frames, dark, gain, method=method, reference_frames=refs, upsample=upsample,
                               binning=binning, device=device), None
    others = [k for k in range(len(frames)) if k != ambient]
    est = estimate_motion(np.asarray(frames)[others], dark, gain, method=method, upsample=upsample,
                          binning=binning, device=device)
    return place_frame(est, others, len(frames), ambient, np.shape(frames)[1:])


def _recover(frames, A, *, dark, gain, saturation, upsample, binning, shifts, model, check, layers, device, seconds,
             reference_frames, residual, ambient) -> MovingRecovery:
    """:func:`recover_moving` with the one motion ``model`` given."""
    clock = [time.perf_counter()]

    def lap(step):  # host seconds of each step, added to ``seconds``
        clock.append(time.perf_counter())
        if seconds is not None:
            seconds[step] = seconds.get(step, 0.0) + clock[-1] - clock[-2]

    est, gradients, maps = None, None, None
    dense = model == "flow"
    refs = [] if not reference_frames else check_reference_frames(reference_frames, len(frames))
    if ambient is not None and (refs or not 0 <= int(ambient) < len(frames)):
        raise ValueError(f"ambient frame {ambient}: must be a frame of the sequence's {len(frames)} and not with "
                         "broadband reference frames")
    if dense and shifts is not None:
        raise ValueError("model='flow' estimates its own displacement per pixel: give shifts with the translation or "
                         "affine model")
    misfit = None
    if shifts is None:  # the flow starts from the global translation, which its method estimates
        est, misfit = _estimate(frames, dark, gain, model, refs, upsample, binning, device, ambient)
        gradients = est.gradients
        shifts = est.shifts
    lap("estimate")
    # the decoder reads no reference frame: where they saw outside the field, saturated or disagree does not matter
    read = [k for k in range(len(frames)) if k not in set(refs)] if refs else None
    # the checks compare the frames the decoder reads, less an ambient frame (no projector light to compare)
    checked = read if ambient is None else [k for k in range(len(frames)) if k != ambient]
    residual = residual if check else None
    reading = read or list(range(len(frames)))
    if residual is not None and (residual.K != len(frames) or list(residual.frames) != reading):
        raise ValueError(f"the residual check is for {residual.K} frames reading {list(residual.frames)}; the "
                         f"sequence has {len(frames)} reading {reading}")
    res = _warped(frames, A, shifts, dark, gain, read, residual, saturation=saturation, return_mask=True,
                  device=device)
    y, mask = res.y, res.mask
    lap("warp")
    found = []
    if dense or (check and checked):  # every frame's gradient image made once (the check, the layers, the flow)
        gradients = frame_gradients(frames, dark, gain, gradients, device=device)
        est = None if est is None else replace(est, gradients=tuple(gradients))
    floors = _sequence_floors(frames, dark, gain, residual, device) if check else None
    if check:
        maps = _checked_consistency(checked, frames, shifts, dark, gain, gradients, residual, floors)
        # every pixel judged, textured or not: a frame with structure of its own that the others do not share
        mask[maps[1] < CHECK_THRESHOLD] |= np.uint8(Mask.INCONSISTENT)
        if layers and est is not None:
            found = decode_object_layers(frames, A, est, maps, y, mask, dark, gain, saturation=saturation,
                                         device=device, read=read, residual=residual, checked=checked,
                                         floors=floors)
    if dense and est is not None:
        est = _with_flow(frames, A, est, gradients, y, mask, found, maps if check else None, dark, gain,
                         saturation=saturation, device=device, residual=residual,
                         checked=None if ambient is None else checked, floors=floors)
    if check:
        grow_flags(mask)
        refuted(mask)
    if misfit is not None:
        _flag_misplaced(frames, dark, gain, ambient, est.shifts, misfit, mask)
    y[(mask & (Mask.SATURATED | Mask.INCONSISTENT)) > 0] = np.nan
    lap("check")
    # the gradient images served the check and the layers; not kept with a result
    return MovingRecovery(y, mask, [] if est is None else [replace(est, gradients=None)], found, misfit)


def _flag_misplaced(frames, dark, gain, ambient: int, shifts, misfit: float, mask) -> None:
    """Flag (in place, inconsistent) the pixels whose ambient sample the unsteady motion leaves uncertain
    (:func:`specgpu.motion.ambient.misplaced`), and say so in one warning."""
    if misfit <= STEADY_PX:
        return
    a = np.asarray(frames[ambient], np.float64)
    if dark is not None:
        a = a - np.asarray(dark, np.float64)
    if gain is not None:
        a = a * live_gain(gain)
    flags = misplaced(a, shifts, ambient, misfit) & ((mask & np.uint8(UNSEEN)) == 0)
    mask[flags] = (mask[flags] & ~np.uint8(Mask.LAYER)) | np.uint8(Mask.INCONSISTENT)
    warnings.warn(f"the ambient frame's place is uncertain: the registered frames depart from a steady motion by "
                  f"up to {misfit:.2f} px (over {STEADY_PX} px); {int(flags.sum())} pixels where its room light "
                  "changes within that reach are flagged inconsistent", RuntimeWarning, stacklevel=3)
