"""Which of a correlation's rival peaks is a sequence's motion: the candidates one registration offers, and the
choice among them that the sequence's other registrations agree on.

A scene that repeats itself (a chart's grid of patches, stripes, a tiled floor) correlates almost as well a whole
period off as at its true displacement, and the image's content decides which of the two peaks is the higher (on
the moving twin's chart, a dim narrow band's frame against the reference frame puts the true peak at a tenth of the
one a period off): taking the highest is a silent wrong answer of one period, and where the patches look alike
nothing downstream can tell. The period does not scale with time, though, while the motion does: over the frames
of one sequence (a few tens of milliseconds) the motion is steady, each pair's displacement the velocity times the
time between its frames, and a peak a period off lies on no velocity the other pairs share. So each registration
offers its candidates (:func:`peak_candidates`: the local maxima of its surface within reach, above a share of the
highest), and :func:`choose_candidates` keeps the velocity most pairs have a candidate on (ties: the one nearest
the prior, zero or a velocity given, e.g. the previous sequence's); each pair takes its candidate on it. A pair with
rivals and none on the motion is left unresolved (not guessed); a pair with one clear peak keeps it (a motion that
is not steady, a tripod's shake, is still seen).

:func:`choose_candidates` is a pure function of the pairs' candidates and their heights, so any registration (the
host's phase correlation, a device estimate) can hand it its peaks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from specgpu.motion.registration import fit_peak_within, peaks_at

__all__ = ["CANDIDATE_SHARE", "CONSISTENT_PX", "MAX_CANDIDATES", "CandidateChoice", "choose_candidates",
           "peak_candidates"]

#: A candidate within this distance (px, along each axis) of the steady motion's displacement is on it. Wide
#: enough for a frame's registration error and a tripod's shake about a steady motion (tenths of a pixel), narrow
#: against the period of any pattern whose rival peak lies apart from the true one (a few px at least).
CONSISTENT_PX = 1.5

#: A peak below this share of its surface's highest is not a candidate. A repeating scene's true peak can be well
#: below the one a period off (a dim narrow band's frame against the reference frame: a third of it on the moving
#: twin's chart), while the whitened correlation's noise peaks stay below a tenth.
CANDIDATE_SHARE = 0.05

#: The most peaks one registration offers (the highest kept).
MAX_CANDIDATES = 16


@dataclass(frozen=True)
class CandidateChoice:
    """What :func:`choose_candidates` chose, per pair of frames.

    Attributes
    ----------
    displacements : numpy.ndarray
        (P, 2) each pair's chosen displacement (x, y); NaN where the pair is unresolved.
    index : numpy.ndarray
        (P,) the index of the chosen candidate in the pair's list; -1 where unresolved.
    resolved : numpy.ndarray
        (P,) bool: a candidate was chosen (False: rivals, and none on the motion).
    on_line : numpy.ndarray
        (P,) bool: the chosen candidate lies on the steady motion (a clear peak off it is kept).
    velocity : numpy.ndarray
        (2,) the steady motion, px per unit of ``times``.
    """

    displacements: np.ndarray
    index: np.ndarray
    resolved: np.ndarray
    on_line: np.ndarray
    velocity: np.ndarray


def peak_candidates(surface: np.ndarray, radius: int, within: int | None = None,
                    min_ratio: float = CANDIDATE_SHARE, limit: int = MAX_CANDIDATES,
                    top: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The peaks of a periodic correlation surface a registration could mean: (N, 2) displacements (x, y),
    sub-pixel as :func:`~specgpu.motion.registration.peak_at` locates them, and (N,) their heights, highest first.

    Parameters
    ----------
    surface : numpy.ndarray
        (H, W) correlation surface (periodic: index -1 is -1 px).
    radius : int
        Peaks closer than this (px, along both axes) to a higher one are its shoulder, not a candidate.
    within : int, optional
        Only samples at most this far from zero displacement along each axis (the reach of the motion,
        :func:`~specgpu.motion.registration.fit_peak_within`); None: the whole surface.
    min_ratio : float
        Only peaks at least this share of the highest within reach.
    limit : int
        The most candidates returned.
    top : float, optional
        The highest sample within reach, where the caller has it (:func:`fit_peak_within` returns it).
    """
    s = np.asarray(surface)
    h, w = s.shape
    window = within is not None and 2 * int(within) + 1 < min(h, w)
    if top is None:
        top = float((s[np.ix_(*(np.arange(-int(within), int(within) + 1) % n for n in (h, w)))] if window else s).max())
    if not top > 0.0:  # no positive peak: the highest sample, as the plain fit takes it
        d, value = fit_peak_within(s, within)
        return d[None], np.array([value])
    i, j = np.divmod(np.flatnonzero(s >= min_ratio * top), w)  # only these can be candidates
    if window:
        near = (np.abs((i + h // 2) % h - h // 2) <= within) & (np.abs((j + w // 2) % w - w // 2) <= within)
        i, j = i[near], j[near]
    values = s[i, j]
    peak = np.ones(i.size, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                peak &= values >= s[(i + dy) % h, (j + dx) % w]
    i, j, values = i[peak], j[peak], values[peak].astype(np.float64)
    kept = []
    for n in np.argsort(-values, kind="stable"):
        if len(kept) == limit:
            break
        dy, dx = (i[kept] - i[n] + h // 2) % h - h // 2, (j[kept] - j[n] + w // 2) % w - w // 2
        if not kept or np.maximum(np.abs(dy), np.abs(dx)).min() > radius:
            kept.append(int(n))
    if not kept:  # the highest within reach is a plateau's edge: the plain fit's peak
        d, value = fit_peak_within(s, within)
        return d[None], np.array([value])
    return peaks_at(np.broadcast_to(s, (len(kept), h, w)), i[kept], j[kept]), values[kept]


def _on_lines(cands: list, spans: np.ndarray, velocities: np.ndarray, tolerance: float) -> np.ndarray:
    """(L, P) per velocity and pair the index of the pair's candidate nearest ``velocity * span`` if within
    ``tolerance`` along each axis, else -1."""
    index = np.full((len(velocities), len(cands)), -1)
    for i, c in enumerate(cands):
        if len(c):
            at = velocities * spans[i]  # (L, 2)
            d = np.abs(c[None, :, :] - at[:, None, :]).max(axis=2)  # (L, N_i)
            n = np.argmin(d, axis=1)
            index[:, i] = np.where(d[np.arange(len(n)), n] <= tolerance, n, -1)
    return index


def choose_candidates(times, pairs, candidates, heights, *, prior_velocity=None, tolerance: float = CONSISTENT_PX,
                      ambiguous: float = 0.3) -> CandidateChoice:
    """The candidate of each registered pair of frames that the others agree on: the one on the steady motion
    (a displacement proportional to the time between the two frames) that most pairs have a candidate on.

    Every candidate of every pair proposes a velocity (its displacement over the time between its frames), and so
    does ``prior_velocity``; the winner is the velocity with the most pairs on it (a candidate within
    ``tolerance`` along each axis of the velocity times the pair's time apart), ties going to the velocity nearest
    ``prior_velocity``, then to the higher sum of the candidates' heights (each as a share of its pair's highest).
    The velocity is then fitted by least squares to the candidates on it, and each pair takes its candidate
    nearest the motion, if on it; a pair with none on it keeps its highest where that is clear (no other above
    ``ambiguous`` of it: a motion that is not steady, a tripod's shake), and is unresolved otherwise (rivals,
    none of them on the motion: not guessed). A frame's candidates against the reference frame are the pairs
    (reference, k).

    Parameters
    ----------
    times : array_like, (K,)
        Each frame's time (any unit; e.g. its index in the sequence).
    pairs : sequence of (int, int)
        The registered pairs (a, b) of frames (indices into ``times``).
    candidates : sequence of array_like
        Per pair, its (N_i, 2) candidate displacements (x, y) of frame b's content relative to frame a's, px;
        N_i may be 0.
    heights : sequence of array_like
        Per pair, its (N_i,) candidates' peak heights.
    prior_velocity : array_like, (2,), optional
        The velocity expected (px per unit of ``times``), e.g. the previous sequence's; default zero.
    tolerance : float
        How far (px, along each axis) from the motion a candidate may be and lie on it.
    ambiguous : float
        A pair's highest candidate is clear where no other is above this share of it.

    Returns
    -------
    CandidateChoice
    """
    t = np.asarray(times, np.float64)
    cands = [np.asarray(c, np.float64).reshape(-1, 2) for c in candidates]
    hts = [np.asarray(v, np.float64).reshape(-1) for v in heights]
    if len(cands) != len(pairs) or len(hts) != len(pairs) or any(len(c) != len(v) for c, v in zip(cands, hts)):
        raise ValueError("pairs, candidates and heights must describe the same pairs, a height per candidate")
    spans = np.array([t[b] - t[a] for a, b in pairs], np.float64).reshape(-1)
    if np.any(spans == 0):
        raise ValueError("each pair's two frames must be taken at different times")
    prior = np.zeros(2) if prior_velocity is None else np.asarray(prior_velocity, np.float64).reshape(2)
    shares = [v / v.max() if len(v) and v.max() > 0 else np.ones(len(v)) for v in hts]
    velocities = np.concatenate([prior[None]] + [c / spans[i] for i, c in enumerate(cands)])
    index = _on_lines(cands, spans, velocities, tolerance)
    on = index >= 0
    weight = np.zeros(len(velocities))
    for i in range(len(cands)):
        if len(cands[i]):
            weight += np.where(on[:, i], shares[i][np.maximum(index[:, i], 0)], 0.0)
    # the most pairs on the motion; then the velocity nearest the prior; then the heights
    best = np.lexsort((-weight, np.abs(velocities - prior).max(axis=1), -on.sum(axis=1)))[0]
    velocity = velocities[best]
    index = _on_lines(cands, spans, velocity[None], tolerance)[0]
    on = index >= 0
    if on.any():  # the motion through every candidate on it, not through one of them
        Y = np.stack([cands[i][index[i]] for i in np.flatnonzero(on)])
        velocity = spans[on] @ Y / float(spans[on] @ spans[on])
        index = _on_lines(cands, spans, velocity[None], tolerance)[0]
        on = index >= 0
    for i, h in enumerate(hts):  # one clear peak off the motion: a motion that is not steady, kept
        if not on[i] and len(h) and (len(h) == 1 or np.sort(h)[-2] < ambiguous * h.max()):
            index[i] = int(np.argmax(h))
    resolved = index >= 0
    displacements = np.full((len(cands), 2), np.nan)
    for i in np.flatnonzero(resolved):
        displacements[i] = cands[i][index[i]]
    return CandidateChoice(displacements, index, resolved, on, np.asarray(velocity, np.float64))
