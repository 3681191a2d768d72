"""The per-pixel residual check of a motion-compensated decoding: are a pixel's K compensated samples explained by one
reflectance?

The gradient-image check (:func:`specgpu.motion.consistency.consistency`) compares each frame with the others over a
window; where no frame has structure of its own it cannot judge, and a wrong motion that samples flat surfaces of
different colours there decodes a wrong spectrum. The linear model judges every pixel on its own: the plan's decoder
A turns the samples s (K) into a reflectance y = A s, the calibration's forward matrix E predicts the frames that
reflectance would have made, E y, and the residual ``(I - E A) s`` is what no single reflectance explains. For a
pixel whose samples come from one surface it holds the camera's noise and the part of the surface's spectrum outside
the plan's model (the mismatch); samples of different surfaces add what their spectra do not share.

Per pixel the residual's components along the r directions ``I - E A`` does not null (``r = K - rank(E A)`` for a
basis plan; for narrowband, which decodes every frame on its own, ``E A`` is the reflectance linear between the band
centres, a weaker check whose mismatch the prior mostly covers) are weighed by their covariance, the noise at the
pixel's samples (the plan's noise model) plus the mismatch of a smooth prior
(:func:`specgpu.planning.priors.smooth_prior`): ``chi2 = r^T C^-1 r``, chi-square with r degrees of freedom where
the samples agree. A pixel is flagged where it exceeds the chi-square's ``1 - P_FALSE`` quantile. The samples come
from the warped pass itself (rows of the identity appended to the decoder), so the check costs no extra pass over
the frames and judges every decoding: global, affine, an object layer's and the flow's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from specgpu.planning.correction import ambient_index, subtracting_ambient
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import smooth_prior
from specgpu.planning.reference_frames import reference_indices
from specgpu.rig.config import RigDescription

__all__ = ["P_FALSE", "ResidualCheck", "residual_check", "residual_chi2"]

#: The share of pixels whose samples agree that the check may flag (the chi-square's upper tail). On the twin's
#: still natural scene (symmetric-9, 320 x 240) it flags 0.01 % of the field; chi-square would flag 0.1 %.
P_FALSE = 1e-3


@dataclass(frozen=True)
class ResidualCheck:
    """What the residual check of one plan needs.

    Attributes
    ----------
    K : int
        The frames of the decoder's sequence.
    frames : tuple of int
        The frames the check reads (a plan's broadband reference frames left out), in order: the pattern frames
        and, for a plan with an ambient frame, that frame, whose sample is subtracted from theirs (``project``'s
        column for it minus the sum of theirs).
    project : numpy.ndarray
        (r, len(frames)): the samples' residual components, ``U_r^T (I - E A)`` on the frames read.
    mismatch : numpy.ndarray
        (r, r) covariance of the components from spectra outside the plan's model, DN^2.
    noise : NoiseModel
        The camera's noise per raw sample, DN.
    threshold : float
        chi2 above which a pixel is flagged.
    """

    K: int
    frames: tuple
    project: np.ndarray
    mismatch: np.ndarray
    noise: NoiseModel
    threshold: float

    @property
    def rows(self) -> np.ndarray:
        """(len(frames), K) rows that, appended to a (B, K) decoder, make its pass output the compensated samples
        of the frames read."""
        return np.eye(self.K)[list(self.frames)]


def plan_noise(plan) -> NoiseModel:
    """The plan's recorded noise model (``specgpu plan --rig``), else the default camera's at the plan's exposure
    (the paper's camera, :class:`specgpu.rig.config.RigDescription`'s defaults)."""
    if isinstance(plan.params, dict) and plan.params.get("noise"):
        return NoiseModel.from_params(plan.params["noise"])
    return NoiseModel.from_rig(RigDescription(), plan.exposure_s)


def residual_check(plan, bundle, *, noise: NoiseModel | None = None,
                   p_false: float = P_FALSE) -> ResidualCheck | None:
    """The :class:`ResidualCheck` of ``plan`` (reflectance outputs) made on ``bundle``; None where the plan's
    outputs are not a reflectance or its decoder leaves no residual (the frames predicted from its reflectance are
    the frames).
    ``noise``: default :func:`plan_noise`."""
    if plan.output != "reflectance":
        return None
    refs, ambient = set(reference_indices(plan)), ambient_index(plan)
    pattern = [k for k in range(plan.K) if k not in refs and k != ambient]
    A = np.asarray(plan.A, np.float64)[:, pattern]
    E = bundle.forward_matrix(plan.patterns, plan.output_wavelengths, plan.exposure_s)[pattern]
    M = np.eye(len(pattern)) - E @ A
    U, s, _ = np.linalg.svd(M)
    rank = int(np.sum(s > 1e-2 * max(float(s[0]), 1e-30))) if s.size else 0
    if rank == 0:
        return None
    project = U[:, :rank].T @ M
    read = pattern
    if ambient is not None:
        # the pattern frames' samples above the ambient frame's: its sample is read too, with minus the sum of
        # the pattern frames' weights, so the noise it shares with all of them is weighed as one sample's
        read = sorted(pattern + [ambient])
        project = subtracting_ambient(np.insert(project, read.index(ambient), 0.0, axis=1), read.index(ambient))
    prior = smooth_prior(bundle.wavelengths)
    F = project @ bundle.forward_matrix(plan.patterns, prior.wavelengths, plan.exposure_s)[read]
    return ResidualCheck(int(plan.K), tuple(read), project, F @ prior.moment @ F.T, noise or plan_noise(plan),
                         float(stats.chi2.isf(p_false, rank)))


def residual_chi2(samples, check: ResidualCheck, gain=None) -> np.ndarray:
    """(H, W) float32 chi2 of each pixel's compensated ``samples`` (H, W, len(check.frames)): dark-subtracted and
    flat-fielded by ``gain`` (H, W), as the decoder reads them; NaN where a sample is."""
    s = np.asarray(samples, np.float32)
    h, w, n = s.shape
    s = s.reshape(-1, n).astype(np.float64)
    P = np.asarray(check.project, np.float64)
    r = len(P)
    g = np.ones(h * w) if gain is None else np.asarray(gain, np.float64).reshape(-1)
    g = np.where(np.isfinite(g) & (g > 0), g, 1.0)
    nm = check.noise
    raw = np.maximum(s / g[:, None], 0.0)  # the raw signal above dark, DN
    var = (raw / nm.gain_e_per_dn + nm.read_var_dn2 + (nm.light_rms * raw) ** 2) * (g * g)[:, None]
    # each pixel's covariance C = P diag(var) P^T + mismatch, its lower triangle as one product with the variances
    pairs = [(i, j) for i in range(r) for j in range(i + 1)]
    C = var @ np.stack([P[i] * P[j] for i, j in pairs], axis=1)
    C += np.array([check.mismatch[i, j] for i, j in pairs])[None]
    entry = {pair: C[:, m] for m, pair in enumerate(pairs)}
    res = s @ P.T
    # chi2 = |L^-1 res|^2 with C = L L^T: a Cholesky factorisation and forward substitution per pixel, each step
    # one operation over every pixel (r is a few: the frames the plan's model leaves free)
    L, z = {}, []
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(r):
            d = entry[(j, j)] - sum(L[(j, m)] ** 2 for m in range(j))
            L[(j, j)] = np.sqrt(d)
            for i in range(j + 1, r):
                L[(i, j)] = (entry[(i, j)] - sum(L[(i, m)] * L[(j, m)] for m in range(j))) / L[(j, j)]
            z.append((res[:, j] - sum(L[(j, m)] * z[m] for m in range(j))) / L[(j, j)])
        chi = sum(zj * zj for zj in z)
    return np.asarray(chi, np.float32).reshape(h, w)
