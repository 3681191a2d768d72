"""The camera's temporal noise per frame (:class:`NoiseModel`): shot, read, dark and quantization noise and the
light's frame-to-frame fluctuation, as the Wiener decoder, the designs and the per-pixel uncertainty need it.

Per frame, in DN^2, ``var o_k = o_k / g + s_read^2 + (l o_k)^2`` with ``g`` the conversion gain (e-/DN; shot noise),
``s_read^2`` the read, dark-shot and quantization variance at the plan's exposure and ``l`` the light's relative
frame-to-frame fluctuation. For a decoder the signal is the expected one over the prior (``o = F mu``;
``E[o^2] = (F S F^T)_kk`` for the fluctuation term).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.planning.priors import Prior

if TYPE_CHECKING:
    from specgpu.rig.config import RigDescription

__all__ = ["NoiseModel"]


@dataclass(frozen=True)
class NoiseModel:
    """Temporal noise of one frame, in DN: ``var = o / gain_e_per_dn + read_var_dn2 + (light_rms * o)^2``.

    Attributes
    ----------
    gain_e_per_dn : float
        Conversion gain, electrons per DN (> 0).
    read_var_dn2 : float
        Signal-independent variance, DN^2 (read noise, dark-current shot noise, quantization), >= 0.
    light_rms : float
        Relative RMS frame-to-frame fluctuation of the light, >= 0 (common to all pixels of a frame).
    """

    gain_e_per_dn: float
    read_var_dn2: float
    light_rms: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.gain_e_per_dn) and self.gain_e_per_dn > 0):
            raise ValueError(f"noise gain_e_per_dn must be finite and > 0, got {self.gain_e_per_dn!r}")
        if not (math.isfinite(self.read_var_dn2) and self.read_var_dn2 >= 0):
            raise ValueError(f"noise read_var_dn2 must be finite and >= 0, got {self.read_var_dn2!r}")
        if not (math.isfinite(self.light_rms) and 0 <= self.light_rms < 1):
            raise ValueError(f"noise light_rms must lie in [0, 1), got {self.light_rms!r}")

    @classmethod
    def from_rig(cls, description: RigDescription, exposure_s: float) -> "NoiseModel":
        """The noise of a rig description's camera and light at an exposure (s): the conversion gain, read noise
        and dark current the camera is specified with, quantization 1/12 DN^2, the light's fluctuation."""
        cam, light = description.camera, description.light
        g = float(cam.gain_e_per_dn)
        read = (cam.read_noise_e ** 2 + cam.dark_current_e_per_s * exposure_s) / g ** 2 + 1.0 / 12.0
        rms = float(light.fluctuation_rms) * math.sqrt(light.fluctuation_reference_exposure_s / exposure_s)
        return cls(g, float(read), rms)

    @classmethod
    def from_params(cls, params: dict) -> "NoiseModel":
        """From a plan's ``params["noise"]`` (ValueError naming what is missing)."""
        try:
            return cls(float(params["gain_e_per_dn"]), float(params["read_var_dn2"]), float(params["light_rms"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"plan noise model is incomplete ({exc})") from None

    def averaged(self, pixels: float) -> "NoiseModel":
        """The noise of a mean over ``pixels`` pixels of independent shot and read noise (a spatial filter where
        the scene is flat): those terms divided by ``pixels``; the light's fluctuation, common to every pixel of a
        frame, stays."""
        n = float(pixels)
        if not (math.isfinite(n) and n >= 1):
            raise ValueError(f"averaged pixels must be finite and >= 1, got {pixels!r}")
        return NoiseModel(self.gain_e_per_dn * n, self.read_var_dn2 / n, self.light_rms)

    def as_params(self) -> dict:
        return {"gain_e_per_dn": float(self.gain_e_per_dn), "read_var_dn2": float(self.read_var_dn2),
                "light_rms": float(self.light_rms)}

    def light_square(self) -> tuple[float, float]:
        """``(q, c)``: per frame sample ``x = o - (dark - g s_read^2)`` (the sample above the variance model's
        shifted dark), ``(x + q (x - c)^2) / g`` is the sample's variance ``o / g + s_read^2 + (l o)^2`` with ``o``
        its signal above dark: ``q = g l^2``, ``c = g s_read^2``."""
        g = self.gain_e_per_dn
        return float(g * self.light_rms ** 2), float(g * self.read_var_dn2)

    def covariance(self, F: ArrayLike, prior: Prior) -> np.ndarray:
        """(K, K) diagonal noise covariance at the prior's expected signal ``F mu``."""
        F = np.asarray(F, np.float64)
        o = F @ prior.mean
        o2 = np.einsum("kb,bc,kc->k", F, prior.moment, F)
        return np.diag(np.maximum(o, 0.0) / self.gain_e_per_dn + self.read_var_dn2 + self.light_rms ** 2 * o2)
