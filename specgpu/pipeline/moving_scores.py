"""How much a moving scene costs a recovery, and how much compensation gives back (:func:`compare_motion`): one
sequence of a plan captured with the scene still and with it moving (the same noise), recovered as it is and
motion-compensated (:func:`specgpu.pipeline.moving_layers.recover_moving`), each scored per pixel against its truth (the
scene, or the scene at the moving sequence's reference time) over the field and near the scene's edges, with the
per-pixel error maps. Used by ``specgpu demo``'s moving-scene section and ``tools/studies/motion_study.py``.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy import ndimage

from specgpu.engine.linear_map import apply_linear
from specgpu.motion.residual import residual_check
from specgpu.pipeline.evaluate import evaluate_pixels
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.reference_frames import reference_indices
from specgpu.rig.scene import SpectralScene
from specgpu.rig.twin import TwinRig

__all__ = ["RECOVERIES", "edge_band", "motion_scores", "compare_motion"]

#: The three recoveries compared: the still scene, the moving one decoded as it is, and compensated.
RECOVERIES = ("still", "moving", "compensated")


def edge_band(reflectance, threshold: float, width: int = 3) -> np.ndarray:
    """(H, W) bool: pixels within ``width`` px of a step of the reflectance (H, W, B) above ``threshold`` (RMS over
    the bands between neighbours)."""
    r = np.asarray(reflectance)
    dx = np.sqrt(np.mean((r[:, 1:] - r[:, :-1]) ** 2, axis=2)) > threshold
    dy = np.sqrt(np.mean((r[1:] - r[:-1]) ** 2, axis=2)) > threshold
    edges = np.zeros(r.shape[:2], bool)
    edges[:, 1:] |= dx
    edges[:, :-1] |= dx
    edges[1:] |= dy
    edges[:-1] |= dy
    if not edges.any():  # no edge: no band (the distance transform of a field without zeros is not a distance)
        return edges
    return ndimage.distance_transform_edt(~edges) <= width


def motion_scores(y, truth, wavelengths, valid, band) -> tuple[dict, np.ndarray]:
    """({rmse_field, rmse_edge, dE_field, dE_edge}, per-pixel RMSE map) of the outputs ``y`` against ``truth`` (a
    scene): means over ``valid`` pixels and over those of them in ``band``; dE2000 under D65."""
    rep = evaluate_pixels(y, truth, wavelengths=wavelengths)
    out = {}
    for name, where in (("field", valid), ("edge", valid & band)):
        out[f"rmse_{name}"] = float(np.mean(rep.rmse[where]))
        out[f"dE_{name}"] = float(np.mean(rep.delta_E_2000[where]))
    return out, np.asarray(rep.rmse, np.float32)


def compare_motion(description, bundle, plan, scene, motion, seed: int, *, edge: float = 0.08,
                   model: str = "translation") -> dict:
    """One sequence of ``plan`` on ``scene``, still and moving by ``motion`` (a
    :class:`specgpu.rig.motion.MotionParameters`) with the same noise ``seed``, recovered still, moving as it is
    and compensated by ``model``; every score over the pixels all three recover (compensation leaves NaN where a
    frame saw outside the field or its frames disagree: the ``flagged`` share), leaving out a 3 px band about a
    moving object's edges; ``edge``: the RMS reflectance step that counts as an edge of the scene.

    Returns
    -------
    dict
        ``still``, ``moving``, ``compensated``: the scores of :func:`motion_scores`; ``maps``: their per-pixel
        RMSE maps (NaN where not scored); ``flagged``, ``object_flagged`` (of the object, of the rest; None
        without one), ``edge_share``, ``shift_error_px`` (the largest error of the estimated displacement),
        ``seconds`` (the compensated recovery); with a flow, ``shift_error_px`` is the 99th percentile over the
        decoded pixels away from the object.
    """
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    still = capture_plan(description, plan, scene, noise_seed=seed).sequences[0]
    moving_desc = replace(description, motion=motion)
    seq = capture_plan(moving_desc, plan, scene, noise_seed=seed).sequences[0]
    rig = TwinRig(plan.rig_description(moving_desc), scene=scene)
    truth = rig.motion_truth(seq.timestamps_s)
    t_scene = SpectralScene(scene.wavelengths, truth["reflectance"], name="truth at the reference time")
    t0 = time.perf_counter()
    comp = recover_moving(seq.frames, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code), model=model,
                          reference_frames=reference_indices(plan), residual=residual_check(plan, bundle))
    seconds = time.perf_counter() - t0
    recovered = {"still": apply_linear(still.frames, plan.A, dark, gain),
                 "moving": apply_linear(seq.frames, plan.A, dark, gain), "compensated": comp.y}
    valid = np.all([np.all(np.isfinite(y), axis=2) for y in recovered.values()], axis=0)
    flagged = float(1.0 - valid.mean())
    obj = truth["object_mask"]
    object_flagged = None
    if obj is not None:  # scored outside a 3 px band about the object's edges at the reference time
        inside = obj > 0.5
        border = ndimage.distance_transform_edt(~inside) <= 3
        border &= ndimage.distance_transform_edt(inside) <= 3
        object_flagged = (float((~valid & inside).sum() / inside.sum()), float((~valid & ~inside).mean()))
        valid &= ~border
    ow = plan.output_wavelengths
    bands = {"still": edge_band(scene.reflectance, edge)}
    bands["moving"] = bands["compensated"] = edge_band(truth["reflectance"], edge)
    out = {"maps": {}}
    for kind, y in recovered.items():
        out[kind], error = motion_scores(y, scene if kind == "still" else t_scene, ow, valid, bands[kind])
        out["maps"][kind] = np.where(valid, error, np.nan).astype(np.float32)
    est = comp.estimates[0].shifts
    if est.ndim == 4:  # flow: the background's error (the truth's map at each pixel), over the decoded pixels
        away = np.ones(scene.shape, bool) if obj is None else ndimage.distance_transform_edt(obj < 0.5) > 40
        away &= valid
        h, w = scene.shape
        yy, xx = np.mgrid[0:h, 0:w]
        points = np.stack([xx[away], yy[away], np.ones(int(away.sum()))]).astype(np.float64)  # (3, N)
        true = np.einsum("kij,jn->kin", truth["maps"], points) - points[None, :2]
        # the 99th percentile: a flat region's few pixels may follow any motion at no cost to their spectra
        shift_error = float(np.percentile(np.abs(est[:, :, away] - true).max(axis=(0, 1)), 99)) if away.any() else 0.0
    elif est.ndim == 3:  # affine: the error of the displacement at the corners of the field
        h, w = scene.shape
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
        shift_error = float(np.abs(np.einsum("kij,cj->kci", est - truth["maps"], corners)).max())
    else:
        shift_error = float(np.abs(est - truth["displacement"]).max())
    out.update(flagged=flagged, object_flagged=object_flagged,
               edge_share=float((valid & bands["moving"]).sum() / max(valid.sum(), 1)),
               shift_error_px=shift_error, seconds=seconds)
    return out
