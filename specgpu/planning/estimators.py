"""Decoders beyond the paper's projections: Wiener (LMMSE) and smoothness-regularised least squares, the noise
model they need, the expected error of any decoder, and per-pixel uncertainty.

Every estimator here is still one per-pixel linear map ``y = A (o - dark) * gain``, so the
device kernels do not change; only the host decides A.

Notation (per plan): the calibration's forward model gives ``F`` (K x B), the frames' output in DN above dark per
unit reflectance on the prior's grid (``o = F r + noise``); ``W`` (P x B) maps a reflectance on that grid to the
plan's outputs (interpolation for reflectance outputs, colour-matching weights for XYZ).

- **Prior** (:class:`Prior`): the training spectra's second moment ``S = E[r r^T]`` and mean ``mu``. The second
  moment, not the covariance: the decoder has no offset term (``apply_linear`` has none), so the best *linear*
  map through the origin is ``A = W S F^T (F S F^T + N)^-1``, the LMMSE estimate without intercept.
- **Noise** (:class:`NoiseModel`): per frame, in DN^2, ``var o_k = o_k / g + s_read^2 + (l o_k)^2`` with ``g`` the
  conversion gain (e-/DN; shot noise), ``s_read^2`` the read, dark-shot and quantization variance at the plan's
  exposure and ``l`` the light's relative frame-to-frame fluctuation. For the decoder the signal is the expected
  one over the prior (``o = F mu``; ``E[o^2] = (F S F^T)_kk`` for the fluctuation term).
- **Expected error** (:func:`expected_error`) of *any* linear decoder A on the prior:
  ``E = W S W^T - A F S W^T - W S F^T A^T + A (F S F^T + N) A^T``; its diagonal per output, its mean the MSE.
- **Smooth** (:func:`smooth_decoder`): for users with no training set, ``A = W (F^T N^-1 F + C^-1)^-1 F^T N^-1``:
  least squares regularised by the norm of a smooth prior C (a flat level plus squared-exponential variation).
- **Per-pixel sigma** (:func:`sigma_map`): ``var y_b = gain^2 sum_k A_bk^2 (o_k / g + s_read^2 + (l o_k)^2) + m_b``
  with ``o_k`` each frame's own signal above dark at the pixel: :func:`specgpu.engine.linear_map.apply_linear` computes it
  with ``A^2 / g`` as the matrix, ``gain^2`` as the gain and, per frame sample, ``x + g l^2 (x - g s_read^2)^2``
  where ``x = o - (dark - g s_read^2)`` (:meth:`NoiseModel.light_square`; the stream's sigma kernels square the
  samples on the device). The light's term is the frame's own: its fluctuation scales the whole frame, so it grows
  with the pixel's signal squared, and a multiplexed plan (Hadamard: about half the light in every frame) has
  bright frames whose fluctuation its decoder's differences do not cancel. ``m_b``, the prior's mismatch
  ``diag((W - A F) S (W - A F)^T)``, is a constant per output added on the host.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = [
    "ESTIMATORS",
    "NoiseModel",
    "Prior",
    "prior_from_spectra",
    "default_prior",
    "training_spectra",
    "read_training",
    "output_weights",
    "forward",
    "wiener_decoder",
    "smooth_decoder",
    "smooth_prior",
    "expected_error",
    "with_estimator",
    "sigma_map",
    "output_covariance",
    "frame_variance",
    "frame_covariance",
    "variance_rows",
    "ambient_variance",
    "constant_covariance",
    "delta_E_sigma",
    "HELD_OUT_CHART",
    "training_database",
    "held_out_basis",
    "held_out_spectra",
    "patch_scene",
    "STUDY_METHODS",
    "study_plans",
    "study_rows",
    "format_study",
    "chart_error",
    "prior_size_rows",
    "subspace_bound",
    "training_sets",
    "cross_validated_error",
]

#: Estimator names: the plan's own decoder, Wiener (LMMSE) on a training prior, smoothness-regularised LS.
ESTIMATORS = ("projection", "wiener", "smooth")

#: The colour-science set held out of training to evaluate the estimators and designs on (14 Munsell chips of
#: the CIE 1995 colour rendering test samples: in neither the default training nor the ColorChecker).
HELD_OUT_CHART = "CIE 1995 TCS"


# ---- noise -------------------------------------------------------------------------------------------------
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
    def from_rig(cls, description, exposure_s: float) -> "NoiseModel":
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

    def as_params(self) -> dict:
        return {"gain_e_per_dn": float(self.gain_e_per_dn), "read_var_dn2": float(self.read_var_dn2),
                "light_rms": float(self.light_rms)}

    def light_square(self) -> tuple[float, float]:
        """``(q, c)``: per frame sample ``x = o - (dark - g s_read^2)`` (the sample above the variance model's
        shifted dark), ``(x + q (x - c)^2) / g`` is the sample's variance ``o / g + s_read^2 + (l o)^2`` with ``o``
        its signal above dark: ``q = g l^2``, ``c = g s_read^2``."""
        g = self.gain_e_per_dn
        return float(g * self.light_rms ** 2), float(g * self.read_var_dn2)

    def covariance(self, F, prior: "Prior") -> np.ndarray:
        """(K, K) diagonal noise covariance at the prior's expected signal ``F mu``."""
        F = np.asarray(F, np.float64)
        o = F @ prior.mean
        o2 = np.einsum("kb,bc,kc->k", F, prior.moment, F)
        return np.diag(np.maximum(o, 0.0) / self.gain_e_per_dn + self.read_var_dn2 + self.light_rms ** 2 * o2)


# ---- prior ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Prior:
    """Second-order statistics of training reflectances on a grid.

    Attributes
    ----------
    wavelengths : (B,) nm
    moment : (B, B) ``E[r r^T]`` (uncentred)
    mean : (B,) ``E[r]``
    n : number of training spectra
    source : description for reports
    """

    wavelengths: np.ndarray
    moment: np.ndarray
    mean: np.ndarray
    n: int
    source: str = ""


def prior_from_spectra(reflectance, wavelengths, source: str = "") -> Prior:
    """The prior of (N, B) training spectra on ``wavelengths``; an empty set is a one-line error."""
    r = np.asarray(reflectance, np.float64)
    wl = np.asarray(wavelengths, np.float64).reshape(-1)
    if r.ndim != 2 or r.shape[1] != wl.size:
        raise ValueError(f"training spectra must be (N, {wl.size}), got shape {r.shape}")
    if r.shape[0] == 0:
        raise ValueError(f"the training set is empty{f' ({source})' if source else ''}: give at least one spectrum")
    if not np.all(np.isfinite(r)):
        raise ValueError("training spectra must be finite")
    return Prior(wl, r.T @ r / r.shape[0], r.mean(axis=0), int(r.shape[0]), source)


def read_training(path, wavelengths) -> tuple[np.ndarray, list]:
    """Training spectra from a file, on ``wavelengths``: a CSV (:func:`specgpu.planning.basis.read_reflectance_csv`) or an
    ``.npz`` with ``wavelengths`` (B,) and ``reflectance`` (N, B). Returns ((N, B), labels); one-line errors."""
    from specgpu.planning.basis import MAX_REFLECTANCE, read_reflectance_csv

    path = Path(path)
    wl = np.asarray(wavelengths, np.float64)
    if path.suffix.lower() == ".npz":
        if not path.is_file():
            raise ValueError(f"{path}: training file not found")
        from specgpu.io.npz import npz_members

        npz_members(path)  # the declared sizes, checked before any array is inflated
        try:
            with np.load(path, allow_pickle=False) as data:
                swl = np.asarray(data["wavelengths"], np.float64).reshape(-1)
                r = np.asarray(data["reflectance"], np.float64)
        except KeyError as exc:
            raise ValueError(f"{path}: training npz needs 'wavelengths' and 'reflectance' arrays ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - any unreadable file is one line naming it
            raise ValueError(f"{path}: cannot read training npz ({exc.__class__.__name__})") from None
        r = r.reshape(-1, swl.size) if r.ndim == 1 else r
        if r.ndim != 2 or r.shape[1] != swl.size or swl.size < 2 or np.any(np.diff(swl) <= 0):
            raise ValueError(f"{path}: reflectance must be (N, {swl.size}) on increasing wavelengths")
        if not np.all(np.isfinite(r)) or r.size and (r.min() < 0 or r.max() > MAX_REFLECTANCE):
            raise ValueError(f"{path}: reflectance must be finite and in [0, {MAX_REFLECTANCE}]")
        samples = [(f"{path.stem}:{i + 1}", swl, r[i]) for i in range(r.shape[0])]
    else:
        samples = read_reflectance_csv(path)
    if not samples:
        raise ValueError(f"{path}: the training file holds no spectra")
    out = []
    for name, swl, val in samples:
        if swl[0] > wl[0] + 1e-9 or swl[-1] < wl[-1] - 1e-9:
            raise ValueError(f"{path}: spectrum {name!r} covers {swl[0]:g}-{swl[-1]:g} nm, not {wl[0]:g}-{wl[-1]:g} nm")
        out.append(np.interp(wl, swl, val))
    return np.array(out), [f"{path.stem}/{s[0]}" for s in samples]


def held_out_spectra(chart: str = HELD_OUT_CHART, wavelengths=None) -> tuple[list, np.ndarray, np.ndarray]:
    """(names, wavelengths, (N, B) spectra) of a colour-science set, on its own grid clipped to 380-780 nm
    (``wavelengths`` None) or interpolated onto ``wavelengths``."""
    from specgpu.planning.basis import REFLECTANCE_SETS

    if chart not in REFLECTANCE_SETS:
        raise ValueError(f"unknown chart {chart!r}; valid: {', '.join(REFLECTANCE_SETS)}")
    samples = REFLECTANCE_SETS[chart]()
    swl = samples[0][1]
    wl = swl[(swl >= 380) & (swl <= 780)] if wavelengths is None else np.asarray(wavelengths, np.float64)
    return [s[0] for s in samples], wl, np.array([np.interp(wl, s[1], s[2]) for s in samples])


def training_database(chart: str = HELD_OUT_CHART, wavelengths=None):
    """colour-science's reflectance sets minus ``chart`` (every set of the same patches, and any spectrum within
    0.01 RMS of one of its patches), on ``wavelengths`` (default 400-700 nm at 5 nm)."""
    from specgpu.planning.basis import DEFAULT_WAVELENGTHS, evaluation_exclusions, load_reflectances

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, np.float64)
    _, _, test = held_out_spectra(chart, wl)
    return load_reflectances(wavelengths=wl, exclude=evaluation_exclusions(chart), exclude_similar_to=test)


def held_out_basis(chart: str = HELD_OUT_CHART):
    """The uncentred PCA basis of :func:`training_database` (the paper's basis methods, for the same chart)."""
    from specgpu.planning.basis import pca_basis

    return pca_basis(training_database(chart))


def training_spectra(chart: str = HELD_OUT_CHART, wavelengths=None, *, training_files=(),
                     builtin: bool = True) -> np.ndarray:
    """(N, B) training spectra: :func:`training_database` (``builtin``) plus the user's files, on ``wavelengths``."""
    return _training(chart, wavelengths, training_files, builtin)[0]


def _training(chart, wavelengths, training_files, builtin):
    from specgpu.planning.basis import DEFAULT_WAVELENGTHS

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, np.float64)
    rows, source = [], []
    if builtin:
        db = training_database(chart, wl)
        rows.append(db.reflectance)
        source.append(f"colour-science sets without {chart} ({len(db)} spectra)")
    for p in training_files:
        r, lab = read_training(p, wl)
        rows.append(r)
        source.append(f"{Path(p).name} ({len(lab)} spectra)")
    r = np.concatenate(rows) if rows else np.zeros((0, wl.size))
    return r, wl, "; ".join(source) or "no training files"


def default_prior(chart: str = HELD_OUT_CHART, wavelengths=None, *, training_files=(), builtin: bool = True) -> Prior:
    """Every reflectance set colour-science ships minus ``chart`` (and every set of the same patches, and any
    spectrum within 0.01 RMS of one of its patches), plus the user's training files; on ``wavelengths``
    (default 400-700 nm at 5 nm). ``builtin=False`` uses the files alone (none: a one-line error)."""
    r, wl, source = _training(chart, wavelengths, training_files, builtin)
    return prior_from_spectra(r, wl, source)


# ---- forward model and output weights ----------------------------------------------------------------------------
def forward(bundle, plan, wavelengths) -> np.ndarray:
    """(K, B) model output (DN above dark, flat-fielded) of the plan's frames per unit reflectance on
    ``wavelengths``, at the plan's exposure."""
    return bundle.forward_matrix(plan.patterns, wavelengths, plan.exposure_s)


def output_weights(plan, wavelengths) -> np.ndarray:
    """(P, B) matrix W giving the plan's ideal outputs from a reflectance on ``wavelengths``: interpolation for a
    reflectance plan, colour-matching weights for an XYZ plan; other outputs have no Wiener form (ValueError)."""
    wl = np.asarray(wavelengths, np.float64)
    if plan.output == "reflectance":
        return _interp_rows(plan.output_wavelengths, wl)
    if plan.output == "XYZ":
        from specgpu.core.spectra import XYZ_weights

        return XYZ_weights(wl, plan.illuminant or "D65", plan.observer or "CIE 1931 2 Degree Standard Observer")
    raise ValueError(f"a {plan.output!r} plan ({plan.method}) has no estimator other than its projection")


def _interp_rows(points, grid) -> np.ndarray:
    """(P, B) rows that linearly interpolate a function on ``grid`` at ``points`` (constant beyond the ends)."""
    p = np.asarray(points, np.float64)
    g = np.asarray(grid, np.float64)
    return np.stack([np.interp(p, g, e) for e in np.eye(g.size)], axis=1)


# ---- decoders ----------------------------------------------------------------------------------------------------
def wiener_decoder(F, W, prior: Prior, noise: NoiseModel) -> np.ndarray:
    """LMMSE decoder (P, K) through the origin: ``W S F^T (F S F^T + N)^-1``."""
    F = np.asarray(F, np.float64)
    S = prior.moment
    M = F @ S @ F.T + noise.covariance(F, prior)
    return np.linalg.solve(M, F @ S @ np.asarray(W, np.float64).T).T


def smooth_prior(wavelengths, *, correlation_nm: float = 40.0, level: float = 0.4, spread: float = 0.25) -> Prior:
    """A prior with no training set: a flat level (RMS ``level``) plus a smooth variation (RMS ``spread``,
    squared-exponential correlation over ``correlation_nm``): second moment ``level^2 11^T + spread^2 K``."""
    wl = np.asarray(wavelengths, np.float64).reshape(-1)
    for name, v in (("correlation_nm", correlation_nm), ("level", level), ("spread", spread)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"smooth {name} must be finite and > 0, got {v!r}")
    K = np.exp(-0.5 * ((wl[:, None] - wl[None, :]) / correlation_nm) ** 2)
    return Prior(wl, level ** 2 + spread ** 2 * K, np.full(wl.size, level), 1,
                 f"smooth prior ({correlation_nm:g} nm correlation)")


def smooth_decoder(F, W, noise: NoiseModel, wavelengths, *, correlation_nm: float = 40.0) -> np.ndarray:
    """Smoothness-regularised least squares (P, K) for users with no training set:
    ``W argmin_r |N^-1/2 (F r - o)|^2 + r^T C^-1 r`` with C the :func:`smooth_prior`'s second moment, i.e.
    ``W (F^T N^-1 F + C^-1)^-1 F^T N^-1`` (computed in the equivalent form ``W C F^T (F C F^T + N)^-1``)."""
    return wiener_decoder(F, W, smooth_prior(wavelengths, correlation_nm=correlation_nm), noise)


def expected_error(A, F, W, prior: Prior, noise: NoiseModel) -> dict:
    """Expected error of a decoder (P, K) on the prior: ``{"mse": (P,) total, "mismatch": (P,) the part with no
    noise, "noise": (P,) the part from the noise, "rmse": sqrt(mean mse)}``."""
    A = np.asarray(A, np.float64)
    F = np.asarray(F, np.float64)
    W = np.asarray(W, np.float64)
    S = prior.moment
    bias = W - A @ F
    mismatch = np.einsum("pb,bc,pc->p", bias, S, bias)
    noise_part = np.einsum("pk,kl,pl->p", A, noise.covariance(F, prior), A)
    mse = mismatch + noise_part
    return {"mse": mse, "mismatch": mismatch, "noise": noise_part, "rmse": float(math.sqrt(max(mse.mean(), 0.0)))}


def with_estimator(plan, bundle, estimator: str, *, prior: Prior | None = None, noise: NoiseModel,
                   correlation_nm: float = 40.0):
    """The plan with its decoder replaced by ``estimator`` (:data:`ESTIMATORS`), with the noise model and the
    expected error recorded in ``params`` (``"estimator"``, ``"noise"``, ``"expected"``: RMSE, per-output
    mismatch variance). ``"projection"`` keeps the decoder and records its expected error when a prior is given."""
    est = str(estimator).lower()
    if est not in ESTIMATORS:
        raise ValueError(f"unknown estimator {estimator!r}; valid: {', '.join(ESTIMATORS)}")
    if est == "wiener" and prior is None:
        raise ValueError("the wiener estimator needs a training prior")
    params = dict(plan.params)
    params["estimator"] = est
    params["noise"] = noise.as_params()
    A = plan.A
    if est == "projection" and plan.output not in ("reflectance", "XYZ"):
        prior = None  # RGB / relative outputs: the decoder stays and no expected error can be stated
    if est != "projection" or prior is not None:
        wl = prior.wavelengths if prior is not None else np.arange(400.0, 700.0 + 1e-9, 5.0)
        F = forward(bundle, plan, wl)
        W = output_weights(plan, wl)
        if est == "wiener":
            A = wiener_decoder(F, W, prior, noise)
        elif est == "smooth":
            A = smooth_decoder(F, W, noise, wl, correlation_nm=correlation_nm)
            params["smooth_correlation_nm"] = float(correlation_nm)
            if prior is None:  # the expected error on the smoothness prior itself
                prior = smooth_prior(wl, correlation_nm=correlation_nm)
        if prior is not None:
            e = expected_error(A, F, W, prior, noise)
            bias = W - A @ F
            # what no frame shows: the prior's mismatch alone (the light's fluctuation is each frame's own, per
            # pixel: sigma_map adds it from the frames' signal)
            mismatch = bias @ prior.moment @ bias.T
            params["expected"] = {"rmse": e["rmse"], "mismatch_var": e["mismatch"].tolist(),
                                  "noise_var": e["noise"].tolist(), "mismatch_cov": mismatch.ravel().tolist(),
                                  "prior": prior.source, "n_training": prior.n}
    return replace(plan, A=np.asarray(A, np.float64), params=params)


# ---- per-pixel uncertainty ---------------------------------------------------------------------------------------
def sigma_map(frames, plan, dark, gain, *, sequences: int = 1, light: bool = True, ambient_dark=None,
              device=None) -> np.ndarray:
    """(H, W, P) standard deviation of each output per pixel (float32), from the frames (K, H, W) the outputs
    were recovered from (the mean of ``sequences`` sequences): ``var y = gain^2 sum_k A^2 (o / g + s_read^2 +
    (l o)^2) / S + m`` (:func:`frame_variance`), plus the prior's mismatch ``m`` on the host. ``light=False``
    leaves out the light's frame-to-frame fluctuation (a decoder rescaled per sequence by a white reference's
    gains divides each frame's fluctuation out). A plan with an ambient frame: ``dark`` is that frame (what the
    recovery subtracted) and ``ambient_dark`` the calibration's dark level under it (:func:`frame_variance`)."""
    var = frame_variance(frames, plan, dark, gain, sequences=sequences, light=light, ambient_dark=ambient_dark,
                         device=device)
    var += constant_variance(plan).astype(np.float32)  # in place, float32: as cheap as the recovery itself
    np.maximum(var, 0.0, out=var)
    return np.sqrt(var, out=var)


def frame_variance(frames, plan, dark, gain, *, A=None, sequences: int = 1, light: bool = True, ambient_dark=None,
                   device=None) -> np.ndarray:
    """(H, W, P) float32: the part of each output's variance the frames' noise makes, for the decoder ``A`` (the
    plan's by default) applied to the mean of ``sequences`` sequences (no constant term): each frame's shot, read
    and dark noise and, with ``light``, the light's fluctuation at the frame's own signal.

    A plan with an ambient frame (``plan --ambient``) has that frame subtracted instead of a dark level: ``dark``
    is the ambient frame and ``ambient_dark`` (required) the calibration's dark level at the exposure. Its own
    noise is then in every output, ``(sum_k A_k)^2`` times, and the room light it holds adds shot noise to every
    frame: ``var y = gain^2 [sum_k A_k^2 (s_k / g + (l s_k)^2) + (sum_k A_k^2 + (sum_k A_k)^2) (a / g +
    s_read^2)]`` with ``s_k`` each frame above the ambient frame and ``a`` the ambient frame above the dark level
    (:func:`variance_rows`, :func:`ambient_variance`)."""
    A = np.asarray(plan.A if A is None else A, np.float64)
    return _noise_products(frames, plan, dark, gain, (A, A), sequences, device, light, ambient_dark)


def output_covariance(frames, plan, dark, gain, M, *, sequences: int = 1, light: bool = True, ambient_dark=None,
                      device=None) -> np.ndarray:
    """(H, W, Q, Q) covariance of ``M y`` per pixel (M: (Q, P), e.g. the XYZ weights of a reflectance plan):
    each entry ``sum_k (MA)_ik (MA)_jk var o_k`` is linear in the frames' sample variances (one apply_linear pass
    over the Q (Q + 1) / 2 products), plus ``M C M^T`` with C the plan's constant covariance (the mismatch)."""
    M = np.asarray(M, np.float64)
    cov = frame_covariance(frames, plan, dark, gain, M, sequences=sequences, light=light, ambient_dark=ambient_dark,
                           device=device)
    return cov + M @ constant_covariance(plan) @ M.T


def frame_covariance(frames, plan, dark, gain, M, *, A=None, sequences: int = 1, light: bool = True,
                     ambient_dark=None, device=None) -> np.ndarray:
    """(H, W, Q, Q) float64: the frames' noise part of the covariance of ``M y`` for the decoder ``A`` (the plan's
    by default), without the constant ``M C M^T``."""
    M = np.asarray(M, np.float64)
    MA = M @ (plan.A if A is None else np.asarray(A, np.float64))
    Q = M.shape[0]
    pairs = [(i, j) for i in range(Q) for j in range(i, Q)]
    left = np.stack([MA[i] for i, _ in pairs])
    right = np.stack([MA[j] for _, j in pairs])
    v = np.asarray(_noise_products(frames, plan, dark, gain, (left, right), sequences, device, light, ambient_dark),
                   np.float64)
    cov = np.empty(v.shape[:-1] + (Q, Q))
    for n, (i, j) in enumerate(pairs):
        cov[..., i, j] = cov[..., j, i] = v[..., n]
    return cov


def variance_rows(left, right, ambient: int | None = None) -> np.ndarray:
    """(R, K) the rows whose products with the frames' sample variances give ``cov(left . o, right . o)`` per
    pixel: ``left * right``; with an ambient frame (index ``ambient``, subtracted from every frame) its column is
    ``sum_k left_k right_k + (sum_k left_k) (sum_k right_k)`` (its noise in every output, and the room light's
    shot noise it stands for in every frame; :func:`frame_variance`)."""
    L = np.array(left, np.float64, ndmin=2)
    R = np.array(right, np.float64, ndmin=2)
    if ambient is None:
        return L * R
    L[:, ambient] = 0.0
    R[:, ambient] = 0.0
    rows = L * R
    rows[:, ambient] = rows.sum(axis=1) + L.sum(axis=1) * R.sum(axis=1)
    return rows


def ambient_variance(ambient_frame, dark, noise: NoiseModel) -> np.ndarray:
    """(H, W) float32 ``g`` times the variance of an ambient frame's sample: its signal above the dark level
    (floored at 0; the room light's shot noise) plus ``g s_read^2``: the ambient frame's "sample" in the variance
    products of :func:`frame_variance` (the stream writes the same into that frame's plane)."""
    a = np.asarray(ambient_frame, np.float32) - np.asarray(dark, np.float32)
    np.maximum(a, np.float32(0.0), out=a)
    a += np.float32(noise.gain_e_per_dn * noise.read_var_dn2)
    return a


def _noise_products(frames, plan, dark, gain, pair, sequences, device, light=True, ambient_dark=None):
    """``gain^2 sum_k rows_k var(o_k) / S`` per pixel, ``rows = variance_rows(*pair)``: the frames' samples above
    the shifted dark ``dark - g s_read^2`` through apply_linear with ``rows / g`` (linear in the frames), or, with
    the light's fluctuation, the samples first mapped to ``x + q (x - c)^2`` (:meth:`NoiseModel.light_square`, as
    the stream's kernels). With an ambient frame (``dark`` is that frame): the samples above it, squared for the
    light, and the ambient frame's own sample :func:`ambient_variance`."""
    from specgpu.planning.correction import ambient_index
    from specgpu.engine.linear_map import apply_linear

    if "noise" not in plan.params:
        raise ValueError(f"the {plan.method} plan records no noise model; re-plan it with specgpu plan --rig RIG.toml "
                         "(the rig the calibration was made on) to record one")
    if not (isinstance(sequences, (int, np.integer)) and sequences >= 1):
        raise ValueError(f"sequences must be an integer >= 1, got {sequences!r}")
    noise = NoiseModel.from_params(plan.params["noise"])
    amb = ambient_index(plan)
    rows = variance_rows(*pair, ambient=amb)
    matrix = rows / noise.gain_e_per_dn / sequences
    g = None if gain is None else np.asarray(gain, np.float32) ** 2
    if amb is not None:
        if ambient_dark is None:
            raise ValueError(f"the {plan.method} plan subtracts its ambient frame: its noise model needs the "
                             "calibration's dark level under it (ambient_dark)")
        x = np.asarray(frames, np.float32) - np.asarray(dark, np.float32)
        if light and noise.light_rms > 0:
            q = np.float32(noise.light_square()[0])
            x += q * (x * x)
        x[amb] = ambient_variance(dark, ambient_dark, noise)
        return np.asarray(apply_linear(x, matrix, None, g, device=device), np.float32)
    d = np.asarray(dark, np.float32) - np.float32(noise.gain_e_per_dn * noise.read_var_dn2)
    if light and noise.light_rms > 0:
        q, c = (np.float32(v) for v in noise.light_square())
        x = np.asarray(frames, np.float32) - d
        s = x - c
        s *= s
        s *= q
        x += s
        return np.asarray(apply_linear(x, matrix, None, g, device=device), np.float32)
    return np.asarray(apply_linear(frames, matrix, d, g, device=device), np.float32)


def constant_covariance(plan) -> np.ndarray:
    """(P, P) the output covariance no frame shows: the prior's mismatch (zero when the plan records no expected
    error). A plan saved before the light's fluctuation was taken per pixel recorded it, at the prior's mean
    signal, in ``constant_cov`` beside the mismatch: that is used as it is (the sigma then errs high by the light
    at the prior's signal; re-plan to drop it)."""
    P = plan.A.shape[0]
    expected = plan.params.get("expected", {})
    c = expected.get("mismatch_cov", expected.get("constant_cov"))
    return np.zeros((P, P)) if c is None else np.asarray(c, np.float64).reshape(P, P)


def constant_variance(plan) -> np.ndarray:
    """(P,) the diagonal of :func:`constant_covariance`."""
    return np.diag(constant_covariance(plan)).copy()


def delta_E_sigma(XYZ, XYZ_sigma_cov, illuminant="D65", observer: str | None = None) -> np.ndarray:
    """First-order propagation of an XYZ covariance (..., 3, 3) to dE2000 (..., ): the colour difference of a
    small perturbation is (to first order) its CIEDE2000 metric at the colour, ``dE^2 = dLab^T G dLab``; the
    sigma is ``sqrt(trace(G J C J^T))`` with J the XYZ -> Lab Jacobian at each pixel (analytic) and G the local
    CIEDE2000 metric (its diagonal along L*, a*, b*, by finite differences of colour-science's ``delta_E``; the
    stream's ``delta_e_sigma`` kernel computes the same on the device). The white is ``illuminant``'s for
    ``observer`` (None: the CIE 1931 2 degree observer), the one the XYZ was made for."""
    import colour

    from specgpu.core.spectra import DEFAULT_CMFS, white_point_XYZ

    xyz = np.asarray(XYZ, np.float64)
    C = np.asarray(XYZ_sigma_cov, np.float64)
    shape = xyz.shape[:-1]
    x = xyz.reshape(-1, 3)
    C = C.reshape(-1, 3, 3)
    # the XYZ -> Lab Jacobian analytically (CIE 1976: f(t) = t^(1/3) above (24/116)^3, linear below), in float64
    white = white_point_XYZ(illuminant, observer or DEFAULT_CMFS)
    lab = colour.XYZ_to_Lab(x, colour.XYZ_to_xy(white))
    eps = 216.0 / 24389.0
    t = x / white
    d = np.where(t > eps, (1.0 / 3.0) / np.cbrt(np.maximum(t, eps)) ** 2, 841.0 / 108.0) / white  # df/dX, dY, dZ
    J = np.zeros((x.shape[0], 3, 3))
    J[:, 0, 1] = 116.0 * d[:, 1]
    J[:, 1, 0], J[:, 1, 1] = 500.0 * d[:, 0], -500.0 * d[:, 1]
    J[:, 2, 1], J[:, 2, 2] = 200.0 * d[:, 1], -200.0 * d[:, 2]
    covLab = J @ C @ np.transpose(J, (0, 2, 1))
    # local CIEDE2000 metric: dE(lab, lab + e_i) ~ sqrt(G_ii) for unit steps along L, a, b
    step = 0.5
    diag = np.empty((x.shape[0], 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        diag[:, i] = (np.asarray(colour.delta_E(lab, lab + e, method="CIE 2000"), np.float64) / step) ** 2
    var = np.einsum("ni,nii->n", diag, covLab)
    return np.sqrt(np.maximum(var, 0.0)).reshape(shape).astype(np.float32)


# ---- held-out chart as a scene -----------------------------------------------------------------------------------
def patch_scene(names, wavelengths, spectra, height: int = 240, width: int = 320, *, surround: float = 0.03,
                name: str = "held-out chart", white_tile: float | None = None):
    """A chart scene of arbitrary patch spectra (N, B): a grid of square patches on a dark surround, one mask
    per patch (its central 70 %), like :func:`specgpu.rig.scene.colorchecker_scene`; ``white_tile`` (a flat
    reflectance) puts a reference white above the patches at :func:`specgpu.rig.scene.white_tile_roi` (not a
    mask), for the drift correction of a lab rig."""
    from specgpu.core.validate import check_number
    from specgpu.rig.scene import SpectralScene, white_tile_roi

    spectra = np.asarray(spectra, np.float64)
    n = spectra.shape[0]
    cols = int(math.ceil(math.sqrt(n * width / height)))
    rows = int(math.ceil(n / cols))
    pitch = min(width / (cols + 0.4), height / (rows + 0.4))
    size = 0.84 * pitch
    x0 = (width - cols * pitch) / 2 + (pitch - size) / 2
    y0 = (height - rows * pitch) / 2 + (pitch - size) / 2
    refl = np.full((height, width, spectra.shape[1]), surround, np.float32)
    masks = {}
    for k in range(n):
        r, c = divmod(k, cols)
        ya, xa = y0 + r * pitch, x0 + c * pitch
        refl[int(round(ya)):int(round(ya + size)), int(round(xa)):int(round(xa + size))] = spectra[k]
        m = np.zeros((height, width), bool)
        inset = 0.15 * size
        y0i, y1i = int(round(ya + inset)), int(round(ya + size - inset))
        m[y0i:y1i, int(round(xa + inset)):int(round(xa + size - inset))] = True
        masks[str(names[k])] = m
    if white_tile is not None:
        wt = check_number("white_tile", white_tile, low=0, low_open=True, high=1.5)
        x, y, tw, th = white_tile_roi(height, width)
        tile = np.zeros((height, width), bool)
        tile[max(0, y - 3):y + th + 3, max(0, x - 3):x + tw + 3] = True
        if np.any(tile & np.any(list(masks.values()), axis=0)):
            raise ValueError(f"white_tile: no room above {n} patches at {width} x {height}")
        refl[tile] = wt
    return SpectralScene(np.asarray(wavelengths, np.float64), refl, masks, name)


# ---- the study: the must-show table ------------------------------------------------------------------------------
#: Rows of the estimator study: name -> (method, keyword arguments, estimator). Optimal plans take the design's
#: own keywords (frames, objective, exposure_s, max_exposure_s). Designs expose at most 0.1 s: past it a lab's
#: room light (3 lux, the ambient frame) fills the white's headroom above the designed level, for a gain of 1 %
#: in expected RMSE on the prior (0.0090 at 0.22 s against 0.0091 at 0.1 s for optimal-9).
STUDY_METHODS = {
    "narrowband-31": ("narrowband", {"step_nm": 10.0}, "projection"),
    "biased-6": ("biased", {"m": 5}, "projection"),
    "symmetric-9": ("symmetric", {"m": 5}, "projection"),
    "tristimulus-D65": ("tristimulus", {"illuminant": "D65"}, "projection"),
    "wiener-6": ("biased", {"m": 5}, "wiener"),
    "wiener-9": ("symmetric", {"m": 5}, "wiener"),
    "optimal-9": ("optimal", {"frames": 9, "max_exposure_s": 0.1}, "wiener"),
    "optimal-6": ("optimal", {"frames": 6, "max_exposure_s": 0.1}, "wiener"),
    "optimal-3": ("optimal", {"frames": 3, "objective": "dEab", "exposure_s": 0.1}, "wiener"),
}


def study_plans(description, bundle, prior, basis, *, methods=None, training=None,
                chart: str = HELD_OUT_CHART, starts: int = 4, iterations: int = 300,
                sets: dict | None = None) -> dict:
    """The plans of :data:`STUDY_METHODS` (or the named subset), every one with the camera's noise model and its
    expected error on the prior recorded. A colour objective (optimal-3) weighs the error by the colours of
    ``training`` (default: :func:`training_spectra` without ``chart``, the evaluation chart); ``starts`` and
    ``iterations``: the designs' starting points and L-BFGS-B iterations (:func:`specgpu.planning.design.design_optimal`). With ``sets`` (the prior's spectra by set,
    :func:`training_sets`) every Wiener plan also records ``expected["rmse_cv"]``, its
    :func:`cross_validated_error`."""
    from specgpu.planning.design import plan_optimal
    from specgpu.planning.plans import make_plan

    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    ow = np.arange(400.0, 700.0 + 1e-9, 10.0)
    plans = {}
    for name in (methods or STUDY_METHODS):
        method, kw, est = STUDY_METHODS[name]
        if method == "optimal":
            tr = None
            if kw.get("objective", "rmse") != "rmse":
                tr = training_spectra(chart, prior.wavelengths) if training is None else training
            plans[name] = plan_optimal(bundle, prior, noise_at, output_wavelengths=ow, training=tr, starts=starts,
                                       iterations=iterations, **kw)
            continue
        args = (basis,) if method in ("biased", "symmetric") else ()
        extra = {"output_wavelengths": ow} if method in ("biased", "symmetric") else {}
        plan = make_plan(method, bundle, *args, **kw, **extra)
        plans[name] = with_estimator(plan, bundle, est, prior=prior, noise=noise_at(plan.exposure_s))
    if sets is not None:
        for name, plan in plans.items():
            if plan.params.get("estimator") == "wiener":
                cv = cross_validated_error(plan, bundle, sets, prior, noise_at(plan.exposure_s))
                plans[name] = replace(plan, params={**plan.params,
                                                    "expected": {**plan.params["expected"], "rmse_cv": cv["rmse"]}})
    return plans


def training_sets(chart: str = HELD_OUT_CHART, wavelengths=None) -> dict:
    """:func:`training_database`'s spectra by set: name -> (N, B)."""
    db = training_database(chart, wavelengths)
    names = np.array([label.split("/")[0] for label in db.labels])
    return {n: db.reflectance[names == n] for n in dict.fromkeys(names)}


def cross_validated_error(plan, bundle, sets: dict, prior: Prior, noise: NoiseModel) -> dict:
    """The expected RMSE of a Wiener plan on a chart the prior has not seen, by leaving one training set out at a
    time: for each set, the Wiener decoder of the plan's frames learnt from the other sets and its mismatch on
    that set's spectra; the mean over sets (each set weighs the same, as a new chart is one more set) of their
    mean squared mismatch, plus the noise part of the plan's own decoder on the whole prior. Returns ``{"rmse",
    "mismatch": {set: RMS mismatch}}``; fewer than two sets is a one-line error."""
    if len(sets) < 2:
        raise ValueError(f"cross-validation needs at least two training sets, got {len(sets)}")
    wl = prior.wavelengths
    F = forward(bundle, plan, wl)
    W = output_weights(plan, wl)
    per = {}
    for name, held in sets.items():
        rest = np.concatenate([r for n, r in sets.items() if n != name])
        A = wiener_decoder(F, W, prior_from_spectra(rest, wl), noise)
        per[name] = float(np.mean((np.asarray(held, np.float64) @ (W - A @ F).T) ** 2))
    noise_part = float(expected_error(plan.A, F, W, prior, noise)["noise"].mean())
    return {"rmse": float(math.sqrt(np.mean(list(per.values())) + noise_part)),
            "mismatch": {n: math.sqrt(v) for n, v in per.items()}}


def study_rows(description, bundle, scene, plans: dict, *, runs: int = 3, seed: int = 0, de_sigma: bool = True,
               device=None, white_roi=None) -> list:
    """Capture each plan ``runs`` times with fresh noise on the twin, recover, and measure on the chart's patch
    pixels: per-pixel means of RMSE, dE2000 and dE*ab (D65; a tristimulus plan under its own illuminant), the
    same of the patch means (per patch), the RMS error beside the plan's expected RMSE, and the standard deviation
    of the standardised errors (error / sigma) and, with ``de_sigma``, the RMS dE2000 over the RMS of the
    predicted dE2000 sigma (:func:`delta_E_sigma`; first run only). Returns one dict per plan with mean and std
    over the runs.

    ``white_roi`` (a lab rig: a white tile in the scene there): the corrections of ``specgpu demo``'s lab profile,
    an ambient frame per sequence (subtracted instead of the dark) and the white's rescaling of the decoder for the
    lamp's drift (:func:`specgpu.pipeline.recovery.recover`). The sigma is then the plan's own decoder's on the frames
    above the ambient frame (the dark the recovery subtracts) with that frame's own noise and the room light's shot
    noise, without the light's fluctuation (the white's gains divide it out); the decoder's rescaling by a few per
    cent is not in it."""
    from specgpu.planning.correction import ambient_index, with_ambient_frame
    from specgpu.pipeline.evaluate import evaluate_pixels, patch_means, scene_XYZ, truth_cube
    from specgpu.pipeline.recovery import SequenceFolder, capture_plan, recover
    from specgpu.engine.linear_map import apply_linear

    mask = np.any(list(scene.masks.values()), axis=0)
    rows = []
    for i, (name, plan) in enumerate(plans.items()):
        if white_roi is not None:
            plan = with_ambient_frame(plan)
        acc = {k: [] for k in ("rmse", "dE2000", "dEab", "patch_rmse", "patch_dE2000", "patch_dEab", "rms", "z",
                               "dE_ratio")}
        for run in range(runs):
            res = capture_plan(description, plan, scene, noise_seed=10_000 + 97 * seed + 13 * i + run,
                               calibration=bundle)
            frames = res.sequences[0].frames
            dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
            if white_roi is None:
                y = np.asarray(apply_linear(frames, plan.A, dark, gain, device=device), np.float64)
            else:
                folder = SequenceFolder(Path("<memory>"), frames[None], plan, bundle, [], {})
                y = np.asarray(recover(folder, white_roi=white_roi, device=device), np.float64)
                dark = frames[ambient_index(plan)].astype(np.float32)  # what the recovery subtracted
            # the white's per-sequence gains divide each frame's fluctuation out; the ambient frame's noise stays
            kw = {"light": white_roi is None, "device": device,
                  "ambient_dark": None if white_roi is None else bundle.dark_at(plan.exposure_s)}
            sig = sigma_map(frames, plan, dark, gain, **kw)
            refl = plan.output == "reflectance"
            wl = plan.output_wavelengths if refl else None
            ill = "D65" if refl else plan.illuminant
            px = evaluate_pixels(y.astype(np.float32), scene, wavelengths=wl, illuminant=ill, device=device)
            truth = truth_cube(scene, wl) if refl else scene_XYZ(scene, ill, device=device)
            err = (y - truth)[mask]
            acc["z"].append(float((err / sig[mask]).std()))
            acc["dE2000"].append(float(px.delta_E_2000[mask].mean()))
            if de_sigma and run == 0:
                from specgpu.pipeline.recovery import to_XYZ

                xyz = to_XYZ(y.astype(np.float32), plan, ill, device=device)
                cov = output_covariance(frames, plan, dark, gain, plan.outputs_to_XYZ(ill), **kw)
                ds = delta_E_sigma(np.asarray(xyz)[mask], cov[mask], ill)
                acc["dE_ratio"].append(float(np.sqrt((px.delta_E_2000[mask] ** 2).mean() / (ds ** 2).mean())))
            acc["dEab"].append(float(px.delta_E_ab[mask].mean()))
            if refl:
                acc["rmse"].append(float(px.rmse[mask].mean()))
                acc["rms"].append(float(np.sqrt((err ** 2).mean())))
            # per patch: the patch means' errors
            _, ym = patch_means(y.astype(np.float32), scene.masks)
            _, tm = patch_means(np.asarray(truth, np.float32), scene.masks)
            pe = _patch_errors(np.asarray(ym, np.float64), np.asarray(tm, np.float64), plan, ill)
            for k, v in pe.items():
                acc[k].append(v)
        expected = plan.params.get("expected", {})
        row = {"name": name, "method": plan.method, "estimator": plan.params.get("estimator", "projection"),
               "K": plan.K, "exposure_ms": plan.exposure_s * 1e3, "runs": runs,
               "expected_rmse": expected.get("rmse") if plan.output == "reflectance" else None,
               "expected_rmse_cv": expected.get("rmse_cv")}
        for k, v in acc.items():
            if v:
                row[k] = (float(np.mean(v)), float(np.std(v)))
        rows.append(row)
    return rows


def _patch_errors(ym, tm, plan, illuminant) -> dict:
    """RMSE / dE2000 / dE*ab of patch means (N, P) against the truth's patch means."""
    import colour

    from specgpu.engine.colorimetry import XYZ_to_Lab
    from specgpu.core.spectra import XYZ_weights

    out = {}
    if plan.output == "reflectance":
        out["patch_rmse"] = float(np.sqrt(((ym - tm) ** 2).mean(axis=1)).mean())
        C = XYZ_weights(plan.output_wavelengths, illuminant)
        xe, xt = ym @ C.T, tm @ C.T
    else:
        xe, xt = ym, tm
    le = np.asarray(XYZ_to_Lab(xe, illuminant), np.float64)
    lt = np.asarray(XYZ_to_Lab(xt, illuminant), np.float64)
    out["patch_dE2000"] = float(np.mean(colour.delta_E(lt, le, method="CIE 2000")))
    out["patch_dEab"] = float(np.mean(colour.delta_E(lt, le, method="CIE 1976")))
    return out


def format_study(rows) -> str:
    """The study table as text: mean +- std over the runs."""
    def f(row, key, digits):
        v = row.get(key)
        return "-" if v is None else f"{v[0]:.{digits}f} +- {v[1]:.{digits}f}"

    head = (f"{'method':<16} {'K':>3} {'ms':>7} {'RMSE (pixel)':>18} {'dE2000 (pixel)':>16} {'dE*ab (pixel)':>16} "
            f"{'RMSE (patch)':>18} {'dE2000 (patch)':>16} {'expected':>8} {'RMS':>8} {'ratio':>6} {'cv':>7} "
            f"{'ratio':>6} {'z std':>6} {'dE/sig':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        exp = r.get("expected_rmse")
        rms = r.get("rms")
        ratio = f"{rms[0] / exp:.2f}" if exp and rms else "-"
        cv = r.get("expected_rmse_cv")
        cv_text, cv_ratio = (f"{cv:.4f}", f"{rms[0] / cv:.2f}") if cv and rms else ("-", "-")
        lines.append(f"{r['name']:<16} {r['K']:>3} {r['exposure_ms']:>7.1f} {f(r, 'rmse', 4):>18} "
                     f"{f(r, 'dE2000', 2):>16} {f(r, 'dEab', 2):>16} {f(r, 'patch_rmse', 4):>18} "
                     f"{f(r, 'patch_dE2000', 2):>16} {'-' if exp is None else round(exp, 4)!s:>8} "
                     f"{'-' if rms is None else round(rms[0], 4)!s:>8} {ratio:>6} {cv_text:>7} {cv_ratio:>6} "
                     f"{r['z'][0]:>6.2f} "
                     f"{r['dE_ratio'][0] if 'dE_ratio' in r else float('nan'):>6.2f}")
    return "\n".join(lines)


def chart_error(plan, bundle, spectra, wavelengths, noise: NoiseModel | None = None) -> float:
    """The RMSE a reflectance plan's decoder is expected to reach on known spectra (N, B) on ``wavelengths``:
    the exact mean squared mismatch over them plus the noise at their own signal (no capture needed)."""
    r = np.asarray(spectra, np.float64)
    F = forward(bundle, plan, wavelengths)
    W = output_weights(plan, wavelengths)
    noise = noise or NoiseModel.from_params(plan.params["noise"])
    err = r @ (W - plan.A @ F).T
    N = np.diag(noise.covariance(F, prior_from_spectra(r, wavelengths)))
    return float(math.sqrt((err ** 2).mean() + ((plan.A ** 2) @ N).mean()))


def prior_size_rows(description, bundle, sizes, *, frames: int = 9, chart: str = HELD_OUT_CHART,
                    seed: int = 0) -> list:
    """How the held-out error depends on the prior's size: for each size, a random subset of the training
    spectra, an optimal plan designed and decoded with it, and its expected RMSE on the prior beside the RMSE it
    reaches on the held-out chart (:func:`chart_error`)."""
    from specgpu.planning.design import plan_optimal

    full = training_spectra(chart)
    wl = default_prior(chart).wavelengths
    _, _, test = held_out_spectra(chart, wl)
    rng = np.random.default_rng(seed)
    rows = []
    for n in sizes:
        n = min(int(n), full.shape[0])
        sub = full[rng.choice(full.shape[0], n, replace=False)]
        prior = prior_from_spectra(sub, wl, f"{n} random training spectra")
        plan = plan_optimal(bundle, prior, lambda t: NoiseModel.from_rig(description, t), frames=frames,
                            starts=1, seed=seed)
        rows.append({"n": n, "expected_rmse": plan.params["expected"]["rmse"],
                     "chart_rmse": chart_error(plan, bundle, test, wl)})
    return rows


def subspace_bound(training, test, K: int, *, centred: bool = False) -> float:
    """The noise-free linear bound with K measurements learnt from ``training`` (N, B), on ``test`` (M, B): the
    RMSE of the test spectra's orthogonal projection onto the training's best K-dimensional subspace (the top K
    eigenvectors of its second moment; ``centred``: of its covariance, about its mean, i.e. an affine decoder).
    No linear decoder of K noise-free measurements designed on that training set does better on ``test`` than a
    projection onto the subspace it would learn, and the best the training set can teach is its own top K."""
    tr = np.asarray(training, np.float64)
    te = np.asarray(test, np.float64)
    if tr.ndim != 2 or te.ndim != 2 or tr.shape[1] != te.shape[1]:
        raise ValueError(f"training and test must be (N, B) and (M, B) on one grid, got {tr.shape} and {te.shape}")
    if not (isinstance(K, (int, np.integer)) and 1 <= K <= tr.shape[1]):
        raise ValueError(f"K must be an integer in [1, {tr.shape[1]}], got {K!r}")
    mu = tr.mean(axis=0) if centred else np.zeros(tr.shape[1])
    X = tr - mu
    U = np.linalg.eigh(X.T @ X)[1][:, ::-1][:, :K]
    e = (te - mu) - (te - mu) @ U @ U.T
    return float(np.sqrt(np.mean(e ** 2)))
