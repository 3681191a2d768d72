"""Time in a plan: the longest exposure that lets K frames fit a sequence-time budget
(:func:`exposure_within`), the budget recorded in a plan's parameters (:func:`budget_params`) and the check that a
plan keeps it (:func:`check_budget`).

A frame takes its exposure plus the light's switch time (pattern load and mirror settling), and at least the
camera's shortest frame period (its read-out, which overlaps the exposure); a sequence takes K frame periods.
"""

from __future__ import annotations

import math

__all__ = ["exposure_within", "budget_params", "check_budget", "extra_count"]


def exposure_within(sequence_s: float, frames: int, switch_s: float, min_frame_period_s: float = 0.0) -> float:
    """The longest exposure (s) at which ``frames`` frame periods fit in ``sequence_s``.

    Parameters
    ----------
    sequence_s : float
        The budget of one sequence, s (> 0).
    frames : int
        Frames per sequence (ambient, probe and reference frames included).
    switch_s : float
        The light's switch time, s: the shortest exposure it can follow, and the time between two exposures.
    min_frame_period_s : float
        The camera's shortest frame period (read-out), s.

    Raises
    ------
    ValueError
        The budget cannot hold ``frames`` frames even at the light's shortest exposure and the camera's shortest
        frame period (the message says the least budget that can).
    """
    T = float(sequence_s)
    if not (math.isfinite(T) and T > 0):
        raise ValueError(f"sequence time must be a finite number > 0 s, got {sequence_s!r}")
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    shortest = max(2.0 * float(switch_s), float(min_frame_period_s))  # the shortest exposure is the switch time
    if T < frames * shortest * (1 - 1e-9):
        raise ValueError(f"a sequence of {T * 1e3:g} ms cannot hold {frames} frames: each takes at least "
                         f"{shortest * 1e3:.3f} ms (the light's {switch_s * 1e6:.0f} us switch time, the camera's "
                         f"{min_frame_period_s * 1e3:.3f} ms read-out), so {frames * shortest * 1e3:.3f} ms at least")
    return max(T / frames - float(switch_s), float(switch_s))


def budget_params(sequence_s, min_frame_period_s: float = 0.0) -> dict:
    """The plan parameters that record a time budget: ``sequence_budget_s`` and the camera's read-out floor
    ``min_frame_period_s`` (empty without a budget)."""
    if sequence_s is None:
        return {}
    return {"sequence_budget_s": float(sequence_s), "min_frame_period_s": float(min_frame_period_s)}


def extra_count(extra_frames, frames: int) -> int:
    """Frames added after planning to a sequence of ``frames``: ``extra_frames`` itself, or what it gives for
    ``frames`` where it is a callable (reference frames, whose number follows the plan's frames)."""
    return int(extra_frames(int(frames)) if callable(extra_frames) else extra_frames)


def check_budget(plan, extra_frames=0) -> None:
    """Refuse (ValueError) a plan that, with ``extra_frames`` frames more (an int, or a callable of the plan's K:
    :func:`extra_count`), overruns its recorded budget."""
    budget = plan.params.get("sequence_budget_s")
    if budget is None:
        return
    extra = extra_count(extra_frames, plan.K)
    took = (plan.K + extra) * plan.frame_period_s
    if took > float(budget) * (1 + 1e-9) + 1e-9:
        raise ValueError(f"{plan.method}: {plan.K + extra} frames of {plan.frame_period_s * 1e3:.3f} ms "
                         f"take {took * 1e3:.2f} ms, over the {float(budget) * 1e3:g} ms budget")
