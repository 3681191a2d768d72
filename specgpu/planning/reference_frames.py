"""Broadband reference frames interleaved in a plan's sequence, for the motion estimate of a moving scene.

A plan's frames are each lit by a different spectrum; the motion estimate registers them to one another through
images that do not depend on the spectrum (gradient magnitude, whitened), which works but compares frames whose
contrasts differ. ``specgpu plan ... --reference-every M`` (:func:`with_reference_frames`) inserts a frame lit by
one broadband pattern before the sequence's first frame and after every ``M`` of its frames (and after the last),
so frames lit by the same spectrum are spread over the sequence: the estimate registers those to each other
directly and gives every frame its displacement by interpolation in time between them
(:mod:`specgpu.motion.reference`). For K = 9 and M = 3 the sequence is ``R p p p R p p p R p p p R``:
13 frames (4 more, 44 % more time per sequence); M = 9 gives ``R p ... p R`` (11 frames, 22 % more).

The reference pattern is every mirror of every column on, scaled down evenly (the same count in each column, so
the spectrum keeps the light's own broadband shape) until a white gives the level of the plan's brightest frame
at the plan's exposure: it never saturates where the plan's own frames do not. The decoder gets a zero column for
each reference frame: the decode is the plan's own, and a still scene decodes exactly as without them. Reading them
too gains little: a Wiener decoder re-fitted over all 13 frames of symmetric-9 with M = 3 lowers the still scene's
per-pixel RMSE from 0.0294 to 0.0279 and its dE2000 from 4.45 to 4.41
(``tools/studies/reference_decode_study.py``, 640 x 480, 3 draws), and would make the reference frames' samples part
of every output, so that where they saw outside
the field or disagree after compensation would count too. Their indices are recorded in
``params["reference_frames"]`` (:func:`reference_indices`), the interval in ``params["reference_every"]``.

The reference frames count in the plan's timing (``Plan.sequence_s``: every frame); a plan designed within a
sequence-time budget is made for the frames it will have (:func:`reference_count` per designed K) and refused in
one line where they overrun it. They do not combine with drift probes, which serve a correction on fixed pixels (the
reference white's fit) that a moving scene, the only reason for reference frames, moves across; nor with an ambient
frame, which ``recover --motion`` places on the motion registered on the pattern frames
(:mod:`specgpu.motion.ambient`), the registration reference frames replace.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from specgpu.planning.correction import ambient_index, probe_indices
from specgpu.planning.timing import check_budget

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["check_reference_every", "reference_count", "reference_positions", "with_reference_frames",
           "reference_indices", "pattern_indices"]


def check_reference_every(every) -> int:
    """``every`` as an int >= 1 (the pattern frames between two reference frames); a one-line ValueError naming
    ``--reference-every`` otherwise (a bool, a float with a fraction, text that is not a whole number)."""
    if isinstance(every, (bool, np.bool_)):
        raise ValueError(f"--reference-every must be a whole number of frames >= 1, got {every!r}")
    try:
        value = int(str(every).strip()) if isinstance(every, str) else int(every)
        whole = isinstance(every, str) or float(every) == value
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"--reference-every must be a whole number of frames >= 1, got {every!r}") from None
    if not whole or value < 1:
        raise ValueError(f"--reference-every must be a whole number of frames >= 1, got {every!r}")
    return value


def reference_count(frames: int, every: int) -> int:
    """Reference frames a sequence of ``frames`` pattern frames gets with one every ``every``: one before the first
    and one after each group of ``every`` (the last group may be shorter)."""
    every = check_reference_every(every)
    return 1 + -(-int(frames) // every)


def reference_positions(frames: int, every: int) -> list[int]:
    """Indices of the reference frames in the interleaved sequence of ``frames`` pattern frames (see
    :func:`reference_count`): ``0, M + 1, 2 (M + 1), ...`` and the last frame."""
    every = check_reference_every(every)
    groups = -(-int(frames) // every)
    return [i * (every + 1) for i in range(groups)] + [int(frames) + groups]


def with_reference_frames(plan: Plan, bundle: CalibrationBundle, every: int):
    """The plan with broadband reference frames added (see the module docstring): one before its first frame and
    one after every ``every`` of its frames; the decoder gets zero columns for them.

    Parameters
    ----------
    plan : Plan
        Without an ambient frame or drift probes.
    bundle : CalibrationBundle
        The calibration the plan was made from (the reference pattern's level on a white).
    every : int
        Pattern frames between two reference frames (>= 1).

    Raises
    ------
    ValueError
        ``every`` not a whole number >= 1, a plan with an ambient frame, drift probes or reference frames already,
        a reference pattern that saturates a white even at one mirror per column, or a plan designed within a
        sequence-time budget that the added frames overrun (one line each).
    """
    every = check_reference_every(every)
    if reference_indices(plan):
        raise ValueError("the plan has reference frames already")
    if ambient_index(plan) is not None or probe_indices(plan):
        raise ValueError("--reference-every does not combine with an ambient frame or drift probes: the probes serve "
                         "a correction on fixed pixels, which a moving scene moves across, and an ambient frame is "
                         "placed on the pattern frames' registered motion (plan --ambient without reference frames)")
    K, C = plan.patterns.shape
    grid = bundle.wavelengths
    full = np.full((1, C), int(plan.rows), np.int32)
    white = float(bundle.forward_matrix(full, grid, plan.exposure_s).sum())
    brightest = float(bundle.forward_matrix(plan.patterns, grid, plan.exposure_s).sum(axis=1).max())
    count = int(np.clip(np.floor(plan.rows * min(1.0, brightest / max(white, 1e-30))), 1, plan.rows))
    pattern = np.full((1, C), count, np.int32)
    per_level = float(np.max(plan.expected_level)) / max(brightest, 1e-30)
    level = float(bundle.forward_matrix(pattern, grid, plan.exposure_s).sum()) * per_level
    if level > 1.0:
        raise ValueError(f"the broadband reference frame saturates a white ({level:.2f} x the camera's range) even "
                         f"at one mirror per column at the plan's {plan.exposure_s * 1e3:.2f} ms exposure")
    refs = reference_positions(K, every)
    n = K + len(refs)
    is_ref = np.zeros(n, bool)
    is_ref[refs] = True
    slot = np.flatnonzero(~is_ref)  # where pattern frame j goes

    def interleave(values, reference_value):
        values = np.asarray(values)
        out = np.empty((n, *values.shape[1:]), values.dtype)
        out[slot] = values
        out[is_ref] = reference_value
        return out

    A = np.zeros((plan.A.shape[0], n))
    A[:, slot] = plan.A
    out = replace(plan, patterns=interleave(plan.patterns, pattern[0]),
                  target_spectra=interleave(plan.target_spectra, bundle.emitted(pattern)[0]),
                  A=A, expected_level=interleave(plan.expected_level, level),
                  params={**plan.params, "reference_frames": refs, "reference_every": every})
    check_budget(out)
    return out


def reference_indices(plan) -> list[int]:
    """Indices of the plan's broadband reference frames (:func:`with_reference_frames`), or [].

    Raises a one-line ValueError where the recorded indices are not frames of the plan with one pattern and a zero
    decoder column (a plan file edited by hand)."""
    idx = plan.params.get("reference_frames") if isinstance(plan.params, dict) else None
    if not idx:
        return []
    idx = [int(i) for i in idx]
    if any(not 0 <= i < plan.K for i in idx) or len(set(idx)) != len(idx) or len(idx) < 2:
        raise ValueError(f"plan's reference frames {idx} are not at least two distinct frames of its {plan.K}")
    if np.any(plan.patterns[idx] != plan.patterns[idx[0]]) or np.any(plan.A[:, idx] != 0):
        raise ValueError(f"plan's reference frames {idx} do not share one pattern with zero decoder columns")
    return sorted(idx)


def pattern_indices(plan) -> list[int]:
    """Indices of the plan's frames that are not reference frames (all of them without reference frames)."""
    refs = set(reference_indices(plan))
    return [k for k in range(plan.K) if k not in refs]
