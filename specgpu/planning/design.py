"""Illumination design: K non-negative illuminants, within the light's limits, that minimise the expected error
of the Wiener decoder for a training prior and the camera's noise (``specgpu plan optimal``), and multiplexed
narrowband (``specgpu plan hadamard``).

**Optimal.** A frame's model output per unit reflectance is ``F_k = t (n_k / rows) S`` (S: DN/s per full column
per unit reflectance, from the calibration; n_k the mirror counts; t the common exposure). Only columns whose
light falls within the prior's wavelength range are lit (:func:`columns_within`): beyond it the prior knows nothing
of the reflectance, and light there would be decoded as if it were the end band's. More light always
lowers the relative noise, so the best frames reach the camera's usable range on a perfect white; the design
therefore optimises the *shape* of each frame, ``F_k = cap x_k S / (x_k S 1)`` with ``x_k >= 0`` column levels and
``cap`` the level the plan allows above dark, minimising the expected weighted error of the Wiener estimate

    J = trace(P S_r) - trace(M^-1 F S_r P S_r F^T),   M = F S_r F^T + N(F)

(S_r the prior's second moment, N the noise at the prior's mean signal, P the error weighting: the identity for
``"rmse"``, the mean CIELAB Jacobian metric of the training spectra under an illuminant for ``"dE2000"``) by
L-BFGS-B with the analytic gradient, from several starts. The exposure is then the shortest at which every frame
can reach ``cap`` with at most every mirror on (clipped to the light's switch time and to the longest exposure
the frame time allows), the patterns are quantized to mirror counts, and the decoder is the Wiener decoder of the
quantized frames (:func:`specgpu.planning.estimators.with_estimator`), so the recorded expected error is that
of what the light will really emit.

**Hadamard.** N narrow bands multiplexed by the rows of the S-matrix of order N (N = 3, 7, 15, 31, 63): each frame
lights (N + 1) / 2 bands; ``A = diag(1 / c) S^-1`` gives the bands back. In read-noise-limited light it gains
``(N + 1) / (2 sqrt(N))`` in SNR over one band per frame at equal capture time (Harwit and Sloane).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu.calibration.bundle import DEFAULT_MAX_EXPOSURE_S
from specgpu.core.spectra import XYZ_weights
from specgpu.engine.colorimetry import XYZ_to_Lab
from specgpu.engine.guided import flat_variance_reduction
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.plans import _band_masks, _base, _quantize
from specgpu.planning.priors import Prior
from specgpu.planning.timing import budget_params, check_budget, exposure_within, extra_count
from specgpu.rig.scene import interpolation_matrix

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["OBJECTIVES", "WITHIN_PRIOR", "columns_within", "denoise_params", "design_optimal", "plan_optimal",
           "plan_hadamard", "s_matrix", "objective_weights", "wiener_objective"]

OBJECTIVES = ("rmse", "dE2000", "dEab")


def objective_weights(prior: Prior, objective: str, illuminant="D65", training=None) -> np.ndarray:
    """(B, B) PSD weighting P of the reflectance error: identity / B for ``"rmse"`` (the mean squared error per
    band); for ``"dE2000"`` the mean over the training spectra of ``(G^1/2 J C)^T (G^1/2 J C)`` with C the XYZ
    weights, J the XYZ -> Lab Jacobian and G the local CIEDE2000 metric at each spectrum's colour (its diagonal
    along L*, a*, b*, by finite differences of colour-science's ``delta_E``); ``"dEab"``: G = I (CIE 1976)."""
    obj = str(objective)
    if obj.lower() == "rmse":
        B = prior.wavelengths.size
        return np.eye(B) / B
    if obj.lower() not in ("de2000", "deab"):
        raise ValueError(f"unknown objective {objective!r}; valid: {', '.join(OBJECTIVES)}")
    C = XYZ_weights(prior.wavelengths, illuminant)
    if training is None:
        raise ValueError("the dE2000 objective needs the training spectra")
    r = np.asarray(training, np.float64)
    xyz = r @ C.T
    lab = np.asarray(XYZ_to_Lab(xyz, illuminant, wavelengths=prior.wavelengths), np.float64)
    h = 1e-4
    Js = []
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        Js.append((np.asarray(XYZ_to_Lab(xyz + d, illuminant, wavelengths=prior.wavelengths), np.float64) - lab) / h)
    J = np.stack(Js, axis=-1)  # (N, 3, 3)
    G = np.empty((r.shape[0], 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 0.5
        G[:, i] = (np.asarray(colour.delta_E(lab, lab + e, method="CIE 2000"), np.float64) / 0.5) ** 2
    if obj.lower() == "deab":  # CIE 1976: the Lab distance itself
        G[:] = 1.0
    M = (np.sqrt(G)[:, :, None] * J) @ C  # (N, 3, B)
    return np.einsum("nib,nic->bc", M, M) / r.shape[0]


def wiener_objective(F, prior: Prior, noise: NoiseModel, P) -> tuple[float, np.ndarray]:
    """(J, dJ/dF) of the Wiener estimate's expected weighted error ``E[e^T P e]`` for frames F (K, B)."""
    S = prior.moment
    mu = prior.mean
    SF = S @ F.T  # (B, K)
    o = F @ mu
    o2 = np.einsum("kb,bk->k", F, SF)
    nvar = np.maximum(o, 0.0) / noise.gain_e_per_dn + noise.read_var_dn2 + noise.light_rms ** 2 * o2
    M = F @ SF + np.diag(nvar)
    SPS = S @ P @ S
    X = np.linalg.solve(M, F @ SPS)  # M^-1 F S P S   (K, B)
    J = float(np.trace(P @ S) - np.einsum("kb,kb->", X, F))
    Q = np.linalg.solve(M, F @ X.T).T  # M^-1 F SPS F^T M^-1 (symmetric)
    Q = 0.5 * (Q + Q.T)
    grad = -2.0 * X + 2.0 * Q @ F @ S
    dq = np.diag(Q)
    grad += dq[:, None] * (mu[None, :] / noise.gain_e_per_dn + 2.0 * noise.light_rms ** 2 * SF.T)
    return J, grad


def _shape_to_frames(x, Sb, cap):
    g = x @ Sb  # (K, B)
    s = g.sum(axis=1)
    return cap * g / s[:, None], g, s


def design_optimal(system, prior: Prior, noise: NoiseModel, K: int, cap: float, *, P=None, starts: int = 4,
                   iterations: int = 300, seed: int = 0, exposure_s: float | None = None,
                   init=None) -> tuple[np.ndarray, float]:
    """Frame shapes (K, C) >= 0 (column levels) minimising the Wiener objective. ``system`` (C, B): DN/s per full
    column per unit reflectance on the prior's grid.

    Without ``exposure_s`` every frame is at ``cap`` DN on a perfect white (the exposure follows the shapes);
    returns (levels scaled so each row's maximum is 1, objective). With ``exposure_s`` (a time budget) the
    levels are mirror fractions in [0, 1] at that exposure, each frame at ``min(cap, its white signal)``: a
    narrow frame collects fewer photons than a broad one, and the search trades shape against light; returns
    (the levels as designed, objective). ``init`` (K, C): a starting point tried first."""
    from scipy.optimize import minimize

    Sb = np.asarray(system, np.float64)
    C, B = Sb.shape
    if not (isinstance(K, (int, np.integer)) and 1 <= K <= 200):
        raise ValueError(f"frames must be an integer in [1, 200], got {K!r}")
    if not cap > 0:
        raise ValueError(f"cap must be > 0, got {cap!r}")
    t = None if exposure_s is None else float(exposure_s)
    if t is not None and not t > 0:
        raise ValueError(f"exposure_s must be > 0, got {exposure_s!r}")
    P = np.eye(B) / B if P is None else np.asarray(P, np.float64)
    active = Sb.sum(axis=1) > 1e-12 * Sb.sum(axis=1).max()
    Sa = Sb[active]
    Ca = Sa.shape[0]
    # Coarse column groups (about 2 nm) keep the search small; the fine columns follow their group.
    groups = np.array_split(np.arange(Ca), min(Ca, 160))
    G = np.zeros((len(groups), Ca))
    for i, g in enumerate(groups):
        G[i, g] = 1.0
    Sg = G @ Sa  # (NG, B)
    scale = None

    def fun(z):
        x = z.reshape(K, -1)
        g = x @ Sg  # (K, B) DN/s per unit reflectance
        s = g.sum(axis=1)  # DN/s on a white
        if t is None:
            c, dc = cap / s, cap / s ** 2
        else:  # the exposure's photons, dimmed to the cap where they would exceed it
            lit = t * s > cap
            c = np.where(lit, cap / s, t)
            dc = np.where(lit, cap / s ** 2, 0.0)
        J, dF = wiener_objective(c[:, None] * g, prior, noise, P)
        dg = c[:, None] * dF - (dc * np.einsum("kb,kb->k", dF, g))[:, None]
        return J / scale, (dg @ Sg.T).ravel() / scale

    rng = np.random.default_rng(seed)
    best = (np.inf, None)
    NG = Sg.shape[0]
    x_init = None
    if init is not None:
        xi = np.asarray(init, np.float64)[:, active]
        x_init = np.clip((xi @ G.T) / G.sum(axis=1), 1e-6, 1.0)
        x_init = x_init / x_init.max(axis=1, keepdims=True)
    for start in range(starts + (x_init is not None)):
        if x_init is not None and start == 0:
            x0 = x_init
        elif start == (x_init is not None):  # smooth bumps across the range
            centres = np.linspace(0, NG - 1, K)
            idx = np.arange(NG)
            x0 = np.exp(-0.5 * ((idx[None, :] - centres[:, None]) / max(NG / (1.5 * K), 1.0)) ** 2) + 0.05
            x0 = np.minimum(x0, 1.0)
        else:
            x0 = rng.uniform(0.05, 1.0, (K, NG))
        scale = 1.0
        scale = max(abs(fun(x0.ravel())[0]), 1e-30)
        res = minimize(fun, x0.ravel(), jac=True, method="L-BFGS-B", bounds=[(1e-6, 1.0)] * (K * NG),
                       options={"maxiter": iterations})
        val = res.fun * scale
        if val < best[0]:
            best = (val, res.x.reshape(K, NG))
    xg = best[1]
    levels = np.zeros((K, C))
    levels[:, active] = xg @ G
    if t is None:
        levels /= levels.max(axis=1, keepdims=True)
    return levels, float(best[0])


#: The least share of a column's camera signal (on a white) that must fall within the prior's wavelength range
#: for a design to light it (:func:`columns_within`).
WITHIN_PRIOR = 0.99


def columns_within(bundle, wavelengths, share: float = WITHIN_PRIOR) -> np.ndarray:
    """(C,) bool: the light's columns of which at least ``share`` of the camera signal on a white falls within
    ``wavelengths``' range. Light outside the prior's range measures a reflectance the prior cannot predict: the
    decoder takes it for the end band's (constant beyond the ends), so a design that lit the far red beyond 700
    nm (where leaves and skin rise steeply) biased every band it decodes."""
    wl = np.asarray(wavelengths, np.float64)
    bw = np.asarray(bundle.wavelengths, np.float64)
    sm = np.asarray(bundle.system_matrix, np.float64)  # (G, C) DN/s per nm per full column
    inside = sm[(bw >= wl.min()) & (bw <= wl.max())].sum(axis=0)
    total = sm.sum(axis=0)
    return inside >= share * np.where(total > 0, total, np.inf)


def _system_on(bundle, wavelengths) -> np.ndarray:
    """(C, B) DN/s per full column per unit reflectance on ``wavelengths``; zero for a column whose light falls
    outside their range (:func:`columns_within`), which a design therefore never lights."""
    dl = float(bundle.wavelengths[1] - bundle.wavelengths[0])
    wl = np.asarray(wavelengths, np.float64)
    S = dl * bundle.system_matrix.T @ interpolation_matrix(bundle.wavelengths, wl)
    return S * columns_within(bundle, wl)[:, None]


def denoise_params(radius: int) -> dict:
    """What a plan designed for ``recover --denoise --denoise-radius radius`` records as ``params["denoise"]``: the
    radius and the variance reduction where the scene is flat (:func:`flat_variance_reduction`)."""
    return {"radius": int(radius), "variance_reduction": flat_variance_reduction(radius)}


def plan_optimal(bundle: CalibrationBundle, prior: Prior, noise_at, *, frames: int = 9, objective: str = "rmse",
                 illuminant: str = "D65",
                 training: ArrayLike | None = None, output_wavelengths: ArrayLike | None = None, level: float = 0.9,
                 max_exposure_s: float | None = None,
                 target: float | None = None, exposure_s: float | None = None, starts: int = 4, seed: int = 0,
                 iterations: int = 300, sequence_s: float | None = None, min_frame_period_s: float = 0.0,
                 extra_frames: int = 0, denoise_radius: int | None = None):
    """An optimal K-frame plan (see the module notes) with the Wiener decoder and its expected error recorded.

    Parameters
    ----------
    bundle : CalibrationBundle
    prior : Prior
        Training prior (its grid is the design grid).
    noise_at : callable
        ``exposure_s -> NoiseModel`` (the camera's noise at an exposure).
    frames : int
        K, the number of illuminants.
    objective : {"rmse", "dE2000", "dEab"}
    illuminant : str
        For ``"dE2000"``.
    training : (N, B) array, optional
        The training spectra (needed for ``"dE2000"``).
    output_wavelengths : array_like, optional
        Reflectance output grid (default 400-700 nm every 10 nm).
    level, max_exposure_s
        As :func:`specgpu.planning.narrowband.plan_narrowband`.
    exposure_s : float, optional
        Expose at least this long (the frames dimmed to stay at ``level``): a longer exposure averages the light's
        frame-to-frame fluctuation down, at a lower frame rate. Default: the shortest at which every frame can
        reach ``level``.
    target : float, optional
        Refuse (one line) a design whose expected error (RMSE, or dE2000 for that objective) is above it.
    sequence_s : float, optional
        Time budget of one sequence, s: the exposure is capped so ``frames + extra_frames`` frame periods (exposure
        plus the light's switch time, at least ``min_frame_period_s``, the camera's read-out) fit in it
        (:func:`specgpu.planning.timing.exposure_within`). With a budget or a ``max_exposure_s`` the design is
        photon-limited: at the capped exposure each frame's light is what its mirrors give, so the search trades
        spectral shape against photons (broad frames collect more light) instead of lengthening the exposure.
    starts, seed, iterations
        The search's starting points, their seed and its L-BFGS-B iterations per start (:func:`design_optimal`).
    denoise_radius : int, optional
        Design for outputs that ``recover --denoise`` will filter with this radius: the frames and the Wiener
        decoder are made for the shot and read noise the filter leaves where the scene is flat
        (:func:`specgpu.engine.guided.flat_variance_reduction` times lower; the light's fluctuation, common to a
        frame, unchanged), so the design spends fewer photons on averaging noise and more on spectral shape. The
        plan's noise model stays the camera's (its sigma maps are the raw outputs'); ``params["denoise"]`` records
        the radius and the reduction, ``params["expected"]`` the error without the filter and
        ``rmse_at_decoder_noise`` on flat regions with it. Without the filter such a plan is noisier than one
        designed for none.
    """
    if prior.n < 1:
        raise ValueError("the training set is empty: give at least one spectrum")
    obj = {o.lower(): o for o in OBJECTIVES}.get(str(objective).lower())
    if obj is None:
        raise ValueError(f"unknown objective {objective!r}; valid: {', '.join(OBJECTIVES)}")
    if not 0 < level <= 1:
        raise ValueError(f"level must lie in (0, 1], got {level!r}")
    ow = np.arange(400.0, 700.0 + 1e-9, 10.0) if output_wavelengths is None else np.asarray(output_wavelengths, float)
    P = objective_weights(prior, obj, illuminant, training)
    camera_noise_at = noise_at
    denoise = None if denoise_radius is None else denoise_params(denoise_radius)
    reduction = None if denoise is None else denoise["variance_reduction"]
    if denoise is not None:

        def noise_at(t):  # the noise the filter leaves where the scene is flat: what the design and decoder see
            return camera_noise_at(t).averaged(reduction)
    Sb = _system_on(bundle, prior.wavelengths)
    cap = level * (bundle.max_code - float(np.mean(bundle.dark)))
    # the frame time follows the exposure (Plan.rig_description lowers the frame rate), as for narrowband plans
    longest = DEFAULT_MAX_EXPOSURE_S if max_exposure_s is None else float(max_exposure_s)
    if longest < bundle.min_exposure_s:
        raise ValueError(f"max_exposure_s must be >= the light's switch time {bundle.min_exposure_s:g} s")
    limited = sequence_s is not None or max_exposure_s is not None
    if sequence_s is not None:
        longest = min(longest, exposure_within(sequence_s, int(frames) + extra_count(extra_frames, frames),
                                               bundle.min_exposure_s,
                                               min_frame_period_s))
    # the noise at a typical exposure for the shape search (the shot and read terms scale with the signal only)
    white = Sb.sum(axis=1)  # DN/s per full column on a white
    t_typ = float(np.clip(cap / (white.sum() / max(frames, 1)), bundle.min_exposure_s, longest))
    if exposure_s is not None:
        if not bundle.min_exposure_s <= exposure_s <= longest:
            raise ValueError(f"exposure_s must lie in [{bundle.min_exposure_s:g}, {longest:g}] s, got {exposure_s!r}")
        t_typ = float(exposure_s)
    if limited:  # photon-limited: the frames' light at the capped exposure, dimmed only where above the cap
        x, _ = design_optimal(Sb, prior, noise_at(longest), int(frames), cap, P=P, starts=starts, seed=seed,
                              iterations=iterations, exposure_s=longest)
        sig = x @ white  # DN/s of each frame on a white
        t = float(np.clip(max(min(longest, (cap / sig).max()), exposure_s or 0.0), bundle.min_exposure_s, longest))
        levels = x * np.minimum(1.0, cap / (t * sig))[:, None]
    else:
        shapes, _ = design_optimal(Sb, prior, noise_at(t_typ), int(frames), cap, P=P, starts=starts, seed=seed,
                                   iterations=iterations)
        # exposure: every frame reaches cap with its levels <= 1 (or as close as the longest exposure allows)
        need = cap / (shapes @ white)
        t = float(np.clip(max(need.max(), exposure_s or 0.0), bundle.min_exposure_s, longest))
        levels = np.minimum(shapes * (cap / (t * (shapes @ white)))[:, None], 1.0)
    patterns = _quantize(levels, bundle.rows)
    if np.any(patterns.sum(axis=1) == 0):
        raise ValueError("a designed frame quantizes to no mirror on: raise max_exposure_s or lower frames")
    targets = bundle.emitted(patterns)
    plan = _base(bundle, "optimal", patterns, targets, np.zeros((ow.size, patterns.shape[0])), level, t,
                 output="reflectance", output_wavelengths=ow, output_labels=tuple(f"{x:g}nm" for x in ow),
                 illuminant="", observer="", params={"frames": int(frames), "objective": obj,
                                                     "objective_illuminant": str(illuminant),
                                                     **budget_params(sequence_s, min_frame_period_s),
                                                     **({} if denoise is None else {"denoise": denoise})})
    plan = with_estimator(plan, bundle, "wiener", prior=prior, noise=camera_noise_at(plan.exposure_s),
                          decoder_noise=None if reduction is None else noise_at(plan.exposure_s))
    exp = dict(plan.params["expected"])
    F = bundle.forward_matrix(plan.patterns, prior.wavelengths, plan.exposure_s)
    Jw, _ = wiener_objective(F, prior, noise_at(plan.exposure_s), P)
    exp["objective_value"] = float(Jw)
    if obj != "rmse":
        exp[obj] = float(math.sqrt(max(Jw, 0.0)))
    # the objective and the target at the noise the decoder is built for (the filtered one with denoise_radius)
    value = exp["rmse_at_decoder_noise"] if obj == "rmse" and reduction is not None else exp[obj]
    plan = replace(plan, params={**plan.params, "expected": exp})
    check_budget(plan, extra_frames)
    if target is not None and value > target:
        raise ValueError(f"objective unreachable: the best {frames}-frame design expects {obj} {value:.4g}, above "
                         f"the target {target:g}")
    return plan


def s_matrix(n: int) -> np.ndarray:
    """The (n, n) 0/1 S-matrix (n = 2^k - 1) from the Sylvester Hadamard matrix of order n + 1."""
    from scipy.linalg import hadamard  # scipy: heavy, needed by this design alone

    if not (isinstance(n, (int, np.integer)) and n >= 3 and (n + 1) & n == 0):
        raise ValueError(f"hadamard bands must be 3, 7, 15, 31, 63 ... (2^k - 1), got {n!r}")
    H = hadamard(n + 1)
    return (H[1:, 1:] < 0).astype(np.int32)


def _primary_groups(bundle, bands: int, start_nm: float, stop_nm: float):
    """A light of fixed primaries (LEDs) split into ``bands`` groups of neighbours within ``start_nm``-``stop_nm``:
    (masks (bands, C), each group's mean wavelength, the mean spacing of the groups nm)."""
    cw = bundle.column_wavelengths
    inside = np.flatnonzero((cw >= start_nm - 10.0) & (cw <= stop_nm + 10.0))
    if bands > inside.size:
        raise ValueError(f"hadamard bands ({bands}) must not exceed this light's {inside.size} LEDs within "
                         f"{start_nm:g}-{stop_nm:g} nm (at {', '.join(f'{x:.0f}' for x in cw[inside])} nm)")
    groups = np.array_split(inside, bands)
    masks = np.zeros((bands, cw.size), bool)
    for i, g in enumerate(groups):
        masks[i, g] = True
    centres = np.array([float(cw[g].mean()) for g in groups])
    return masks, centres, float(np.ptp(centres) / max(1, bands - 1))


def plan_hadamard(bundle: CalibrationBundle, *, bands: int = 31, start_nm: float = 400.0, stop_nm: float = 700.0,
                  level: float = 0.9, max_exposure_s: float | None = None):
    """Multiplexed narrowband: ``bands`` equal bands over ``start_nm``-``stop_nm``, frame k lighting the bands of
    row k of the S-matrix; ``A = diag(1/c) S^-1`` with c the model output of each band on a white. On an LED light
    the bands are ``bands`` groups of neighbouring LEDs (at most its LEDs), each output at its group's mean
    wavelength."""
    Smat = s_matrix(bands)
    if bundle.light_kind == "led":  # fixed primaries: the bands are groups of neighbouring LEDs
        masks, centres, step = _primary_groups(bundle, bands, start_nm, stop_nm)
    else:
        step = (stop_nm - start_nm) / (bands - 1)
        centres = np.linspace(start_nm, stop_nm, bands)
        masks = _band_masks(bundle, centres, step)
    band_pat = np.where(masks, bundle.rows, 0).astype(np.int32)  # (N, C)
    patterns = np.clip(Smat @ band_pat, 0, bundle.rows).astype(np.int32)
    resp = bundle.forward_matrix(band_pat, bundle.wavelengths, 1.0).sum(axis=1)
    if np.any(resp <= 0):
        raise ValueError("a band gives no camera signal in the calibration model")
    A = np.diag(1.0 / resp) @ np.linalg.inv(Smat.astype(np.float64))
    return _base(bundle, "hadamard", patterns, bundle.emitted(patterns), A, level, max_exposure_s,
                 output="reflectance", output_wavelengths=centres, output_labels=tuple(f"{x:g}nm" for x in centres),
                 illuminant="", observer="", params={"bands": int(bands), "bandwidth_nm": float(step)})
