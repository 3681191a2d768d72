"""The limit of K-frame linear designs at a time budget (:func:`design_bound`): a proven lower bound on the
expected per-pixel RMSE any K frames the light can emit within the budget can reach with any linear decoder, and
beside it the best design the optimal designer finds (an achievable error, so the limit lies between the two).

**Lower bound.** A linear decoder of frames ``o = F r + n`` (F: K x B, DN per unit reflectance; noise variance per
frame ``v_k = E[o_k]/g + s_read^2 + (l o_k)^2`` averaged over the prior) does no better than the Wiener decoder,
whose error covariance is ``(S^-1 + F^T N^-1 F)^-1`` (S: the prior's second moment). Every relaxation below only
lowers that error, so the result stays below what any real design reaches:

* the light's fluctuation term is dropped (``v_k >= s_read^2 + F_k mu / g``);
* each frame's spectrum may be any ``0 <= F_k <= t w`` (w: the response with every mirror on that lights the
  prior's range, as the designs, :func:`specgpu.planning.design.columns_within`; t the longest
  exposure the budget allows), not only what the slit's blur lets the mirrors make, and no sign or shape limit;
* the information ``I = sum_k F_k F_k^T / v_k`` is kept only through its rank (<= K) and trace
  (<= K c, c the largest ``|F|^2 / v`` of one frame: exact over the box, and at most ``sum u_b F_b / v`` under
  the camera's range on a white);
* then ``tr((S^-1 + I)^-1) >= sum_i s_i / (1 + s_i d_i)`` (eigenvalues s_i of S descending, d_i of I descending;
  Lidskii's majorization and the Schur-convexity of ``sum 1/x``), minimized over ``d`` by water-filling the top
  K eigenvalues of S.

On a light of a few broad primaries (an LED array) every frame is a combination of them, so two more limits hold
and the bound takes the largest: the water-filling above with the rank of their span in place of K where it is
smaller, and the error of the best linear estimate from every primary's noise-free response
(:func:`primaries_limit`: no number of frames, no exposure does better).

**Achievable.** The photon-limited optimal design at the same budget with several starts
(:func:`specgpu.planning.design.plan_optimal`): its expected RMSE on the prior (before quantizing the mirrors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from specgpu.planning.design import _system_on, design_optimal
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import Prior
from specgpu.planning.timing import exposure_within

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["Bound", "design_bound", "frame_information", "primaries_limit", "waterfill_mse"]


@dataclass(frozen=True)
class Bound:
    """The limit of K-frame linear designs at a budget (RMSE per band, on the prior's grid).

    Attributes
    ----------
    frames, sequence_s, exposure_s : the design's K, budget and the longest exposure it allows.
    lower_rmse : proven lower bound on the expected RMSE of any K-frame linear design within the budget.
    noise_free_rmse : the error of K noise-free measurements (the prior's rank-K limit; no light can do better).
    achieved_rmse : expected RMSE of the best design found (an achievable error; the limit is at most this).
    starts : starting points of that search.
    averaged : the shot and read noise taken as a mean over this many pixels (1: one pixel's; more: where a
        spatial filter flattens it, ``specgpu bound --denoise``).
    """

    frames: int
    sequence_s: float
    exposure_s: float
    lower_rmse: float
    noise_free_rmse: float
    achieved_rmse: float
    starts: int
    averaged: float = 1.0
    #: the noise-free limit of the light's own primaries (any number of frames; None where they span every band)
    primaries_rmse: float | None = None

    def lines(self) -> list[str]:
        noise = "shot and read noise" if self.averaged == 1.0 else \
            f"shot and read noise averaged over {self.averaged:.0f} pixels, as the filter does where the scene is flat"
        return [f"{self.frames} frames within {self.sequence_s * 1e3:g} ms per sequence (exposure at most "
                f"{self.exposure_s * 1e3:.3f} ms):",
                f"  lower bound, any linear design: RMSE >= {self.lower_rmse:.4f} ({noise}; frames "
                "relaxed to any spectrum within every mirror's light)",
                f"  best design found ({self.starts} starts): RMSE {self.achieved_rmse:.4f} (achievable: the limit "
                "lies between the two)",
                f"  noise-free rank-{self.frames} limit of the prior: RMSE {self.noise_free_rmse:.4f}"] + (
            [] if self.primaries_rmse is None else
            [f"  noise-free limit of the light's primaries (they span fewer dimensions than the prior's bands): "
             f"RMSE {self.primaries_rmse:.4f}"])


def frame_information(upper, mean_dn_per_e, read_var_dn2: float, cap: float | None = None) -> float:
    """Largest ``|F|^2 / (read + m . F)`` over ``0 <= F <= upper`` (B,), and, with ``cap``, at most the largest
    ``u . F / (read + m . F)`` with ``sum F <= cap`` too (an upper value of the capped maximum)."""
    u = np.asarray(upper, np.float64)
    m = np.asarray(mean_dn_per_e, np.float64)
    a = float(read_var_dn2)
    if a <= 0:
        raise ValueError("the bound needs a read noise variance > 0")
    # convex over the box: a vertex; for a fixed ratio the best vertex lights the bands in order of u / m
    order = np.argsort(-(u / np.maximum(m, 1e-300)))
    num = np.cumsum(u[order] ** 2)
    den = a + np.cumsum(m[order] * u[order])
    best = float(np.max(num / den))
    if cap is None or u.sum() <= cap:
        return best

    def h(lam):  # max of sum F (u - lam m) - lam a over the box with sum F <= cap: a fractional knapsack
        gain = u - lam * m
        left, total = float(cap), -lam * a
        for b in np.argsort(-gain):
            if gain[b] <= 0 or left <= 0:
                break
            take = min(u[b], left)
            total += take * gain[b]
            left -= take
        return total

    lo, hi = 0.0, float(np.max(u / np.maximum(m, 1e-300)) + (u @ u) / a + 1.0)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if h(mid) > 0 else (lo, mid)
    return min(best, hi)


def waterfill_mse(eigenvalues, frames: int, information: float) -> float:
    """``min sum_i s_i / (1 + s_i d_i)`` over ``d >= 0`` with at most ``frames`` non-zero and ``sum d <= frames x
    information`` (the top eigenvalues get it, ``d_i = max(0, 1/sqrt(nu) - 1/s_i)``); the total over every band."""
    s = np.sort(np.clip(np.asarray(eigenvalues, np.float64), 0.0, None))[::-1]
    top, tail = s[:frames], s[frames:].sum()
    total = frames * float(information)
    pos = top[top > 0]
    if pos.size == 0 or total <= 0:
        return float(s.sum())
    lo, hi = 0.0, 1.0 / pos.min() + total  # 1/sqrt(nu)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.maximum(0.0, mid - 1.0 / pos).sum() < total else (lo, mid)
    d = np.maximum(0.0, hi - 1.0 / pos)
    return float(np.sum(pos / (1.0 + pos * d)) + tail)


def design_bound(bundle: CalibrationBundle, prior: Prior, noise_at, *, frames: int, sequence_s: float,
                 min_frame_period_s: float = 0.0,
                 level: float = 0.9, starts: int = 8, iterations: int = 300, seed: int = 0,
                 averaged: float = 1.0) -> Bound:
    """The limit of ``frames``-frame linear designs within ``sequence_s`` on ``bundle``'s light and camera, for
    ``prior`` and the camera's noise ``noise_at(exposure_s) -> NoiseModel`` (see the module notes).

    ``level``: the fraction of the range above dark a frame may reach on a white (the designs' own);
    ``averaged``: the shot and read noise taken as a mean over that many pixels (:meth:`NoiseModel.averaged`:
    the limit where ``recover --denoise`` flattens the noise, the light's fluctuation kept).
    """
    K = int(frames)
    t = exposure_within(sequence_s, K, bundle.min_exposure_s, min_frame_period_s)
    noise: NoiseModel = noise_at(t).averaged(averaged)
    Sb = _system_on(bundle, prior.wavelengths)  # (C, B) DN/s per full column per unit reflectance
    B = prior.wavelengths.size
    cap = level * (bundle.max_code - float(np.mean(bundle.dark)))
    upper = t * Sb.sum(axis=0)  # every mirror on: DN per unit reflectance per band
    c = frame_information(upper, prior.mean / noise.gain_e_per_dn, noise.read_var_dn2, cap)
    s = np.linalg.eigvalsh(prior.moment)
    lower = math.sqrt(max(waterfill_mse(s, K, c), 0.0) / B)
    noise_free = math.sqrt(max(np.sort(np.clip(s, 0, None))[::-1][K:].sum(), 0.0) / B)
    primaries = primaries_limit(Sb, prior.moment)
    if primaries is not None:  # a few broad primaries (LEDs): every frame lies in their span, of rank r
        r, mse = primaries
        lower = max(lower, math.sqrt(max(waterfill_mse(s, min(K, r), c * K / min(K, r)), 0.0) / B),
                    math.sqrt(mse / B))
    _, J = design_optimal(Sb, prior, noise, K, cap, starts=int(starts), iterations=int(iterations), seed=seed,
                          exposure_s=t)
    return Bound(K, float(sequence_s), float(t), lower, noise_free, math.sqrt(max(J, 0.0)), int(starts),
                 float(averaged), None if primaries is None else math.sqrt(primaries[1] / B))


def primaries_limit(system, moment) -> tuple[int, float] | None:
    """Where the light's primaries span fewer dimensions than the bands (an LED array): (their rank r, the total
    squared error over the bands of the best linear estimate of a reflectance from every primary's noise-free
    response, ``tr(S - S U^T (U S U^T)^+ U S)``, S the prior's second moment, U (C, B) the responses). Any
    design's frames are combinations of the primaries, so none does better. None where they span every band."""
    U = np.asarray(system, np.float64)
    U = U[np.any(U > 0, axis=1)]
    sv = np.linalg.svd(U, compute_uv=False)
    r = int(np.sum(sv > sv.max() * 1e-9)) if sv.size else 0
    B = U.shape[1]
    if r >= B or r == 0:
        return None
    S = np.asarray(moment, np.float64)
    G = U @ S
    mse = float(np.trace(S) - np.trace(G.T @ np.linalg.pinv(G @ U.T) @ G))
    return r, max(mse, 0.0)
