"""What the recovery and the stream write beside their maps: the metadata every output records, the uncertainty
maps (each output's standard deviation with their RMS, and the first-order dE2000 standard deviation), and the list
of writes ``specgpu recover`` stages. One definition each, so the stream and the offline recovery agree."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from specgpu import io
from specgpu.engine.colorimetry import delta_E
from specgpu.io.sequence import capture_hash
from specgpu.pipeline.recovery import to_Lab, to_XYZ, uncertainty
from specgpu.planning.correction import DEFAULT_WHITE_REFLECTANCE
from specgpu.planning.uncertainty import delta_E_sigma

__all__ = [
    "DELTA_E_KINDS",
    "delta_E_sigma_map",
    "recovery_metadata",
    "recovery_writes",
    "sigma_with_rms",
    "stream_metadata",
    "white_metadata",
]

#: The channel name of a colour-difference map, by formula.
DELTA_E_KINDS = {"CIE 1976": "dE76", "CIE 1994": "dE94", "CIE 2000": "dE2000"}


def white_metadata(white_roi, white_reflectance) -> dict:
    """The reference white recorded with an output corrected for drift (empty without one)."""
    if not white_roi:
        return {}
    return {"white_roi": white_roi, "white_reflectance": white_reflectance or DEFAULT_WHITE_REFLECTANCE}


def recovery_metadata(folder, seq, *, sequence, illuminant, observer, white_roi=None, white_reflectance=None,
                      untrusted=None, integration: str = "rectangle") -> dict:
    """The metadata every output of ``specgpu recover`` records: the plan, its calibration, the capture (its
    folder, its identity :func:`specgpu.io.sequence.capture_hash` and the scene it recorded, so ``specgpu
    evaluate`` can tell another truth), the sequences averaged, the colorimetry (with the integration of its XYZ
    and white), the reference white, the reflectance scale's uncertainty and a dark-level warning."""
    plan = folder.plan
    reports = folder.calibration.reports
    scene = (folder.meta.get("metadata") or {}).get("scene")
    return {"plan_method": plan.method, "projections": plan.K, "plan_hash": plan.hash,
            "calibration": plan.calibration, "sequence_folder": str(seq),
            **({"capture": capture_hash(folder.records)} if folder.records else {}),
            **({"scene": scene} if isinstance(scene, str) else {}),
            "sequences_averaged": 1 if sequence is not None else folder.sequences,
            **({"sequence": int(sequence)} if sequence is not None else {}), "illuminant": illuminant,
            "observer": observer, "integration": integration, **white_metadata(white_roi, white_reflectance),
            **({"reflectance_scale_uncertainty": reports["white_reflectance_uncertainty"]}
               if "white_reflectance_uncertainty" in reports else {}),
            **({"dark_untrusted": untrusted} if untrusted else {})}


def stream_metadata(truth, *, illuminant, observer, method, seed, white_roi=None, white_reflectance=None,
                    integration: str = "rectangle") -> dict:
    """The metadata a stream's recording (and its EXR maps) records."""
    return {"scene": truth.name, "illuminant": illuminant, "observer": observer, "integration": integration,
            "method": method, "seed": seed,
            **({"scene_resampled": truth.resampled} if truth.resampled else {}),
            **white_metadata(white_roi, white_reflectance)}


def sigma_with_rms(sigma: np.ndarray, labels) -> tuple[np.ndarray, list[str]]:
    """Each output's standard deviation with their RMS as a last channel, and the channel names
    (``sigma_<label>`` ..., ``sigma_rms``): the ``sigma`` map of recover and of the stream."""
    rms = np.sqrt(np.mean(sigma.astype(np.float64) ** 2, axis=-1, keepdims=True)).astype(np.float32)
    return np.concatenate([sigma, rms], axis=-1), [f"sigma_{label}" for label in labels] + ["sigma_rms"]


def delta_E_sigma_map(XYZ: np.ndarray, cov: np.ndarray, white) -> np.ndarray:
    """The first-order dE2000 standard deviation per pixel from XYZ and its covariance, for the reference white
    XYZ ``white`` (:meth:`specgpu.planning.plans.Plan.white_XYZ`); NaN where XYZ is not finite (a saturated
    pixel)."""
    des = delta_E_sigma(np.nan_to_num(XYZ), np.nan_to_num(cov), white)
    des[~np.isfinite(XYZ).all(axis=-1)] = np.nan
    return des


def recovery_writes(folder, y, meta, *, out, colours, sequence=None, half=False, interleave="bsq", xyz_path=None,
                    lab_path=None, de_path=None, reference=None, method="CIE 2000", sigma_path=None,
                    de_sigma_path=None, device=None, white_roi=None, white_reflectance=None,
                    denoise=None, integration: str = "rectangle", motion: str = "none",
                    white_moves: str = "scene") -> list:
    """The outputs of ``specgpu recover`` as ``(final path, write(path)[, companion suffixes])`` entries, every
    map computed now and written later (all or nothing); ``colours``: the (illuminant, observer) of XYZ, Lab and
    dE, integrated by ``integration`` (the white of Lab and dE the same); ``reference``: called with (height,
    width, meta), gives the dE reference Lab; ``denoise``: ``y`` was denoised (:mod:`specgpu.pipeline.denoise`)
    with that (radius, eps), so the sigma map and the XYZ covariance of the dE sigma are carried through the
    filter (the dE sigma at the filtered XYZ); ``motion``, ``white_moves``: ``y`` was decoded
    motion-compensated, and so is its uncertainty (at the warped samples)."""
    plan = folder.plan
    illuminant, observer = colours
    writes = []
    if plan.output == "reflectance":
        if Path(out).suffix.lower() == ".hdr":  # ENVI: the .img data file renamed with its header
            writes.append((out, lambda p: io.write_cube(p, y, plan.output_wavelengths, half=half,
                                                              metadata=meta, interleave=interleave), (".img",)))
        else:
            writes.append((out, lambda p: io.write_cube(p, y, plan.output_wavelengths, half=half,
                                                              metadata=meta)))
    else:
        kind = "XYZ" if plan.output == "XYZ" else tuple(plan.output_labels)
        # kind bound now: the dE branch below reuses the name (a late-bound lambda wrote XYZ as a dE map)
        writes.append((out, lambda p, kind=kind: io.write_map(p, y, kind, half=half, metadata=meta)))
    XYZ = Lab = None
    if xyz_path or lab_path or de_path:
        XYZ = to_XYZ(y, plan, illuminant, observer=observer, integration=integration, device=device)
        Lab = to_Lab(XYZ, plan, illuminant, observer=observer, integration=integration, device=device)
    if xyz_path:
        writes.append((xyz_path, lambda p: io.write_map(p, XYZ, "XYZ", metadata=meta)))
    if lab_path:
        writes.append((lab_path, lambda p: io.write_map(p, Lab, "Lab", metadata=meta)))
    if sigma_path or de_sigma_path:
        sigma, cov = uncertainty(folder, sequence=sequence, illuminant=illuminant if de_sigma_path else None,
                                 observer=observer, device=device, white_roi=white_roi,
                                 white_reflectance=white_reflectance, integration=integration, motion=motion,
                                 white_moves=white_moves, denoise=denoise)
        if sigma_path:
            sig, names = sigma_with_rms(sigma, plan.output_labels)
            writes.append((sigma_path, lambda p: io.write_map(p, sig, names, metadata=meta)))
        if de_sigma_path:
            xyz = XYZ if XYZ is not None else to_XYZ(y, plan, illuminant, observer=observer,
                                                     integration=integration, device=device)
            des = delta_E_sigma_map(xyz, cov, plan.white_XYZ(illuminant, observer, integration))
            writes.append((de_sigma_path, lambda p: io.write_map(p, des, ["dE2000_sigma"], metadata=meta)))
    if de_path:
        height, width = y.shape[:2]
        dE = delta_E(reference(height, width, meta), Lab, method, device=device)
        if Path(de_path).suffix.lower() == ".png":
            writes.append((de_path, lambda p: io.write_delta_E_png(p, dE, metadata=meta)))
        else:
            kind = DELTA_E_KINDS[method]
            writes.append((de_path, lambda p, kind=kind: io.write_map(p, dE, kind, metadata=meta)))
    return writes
