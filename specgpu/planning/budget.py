"""Plans within a sequence-time budget (:func:`budget_plan`): any method of the registry, its exposure capped so
the sequence's frames fit the budget; the optimal design photon-limited under that cap
(:func:`specgpu.planning.design.plan_optimal`'s ``sequence_s``).

The paper's methods and Hadamard keep their frames' spectral shapes: under a cap shorter than the exposure that
brings their brightest frame to the designed level, every frame is dimmer by the same factor (fewer photons,
more relative noise), which the expected error recorded by the Wiener or projection decoder then states.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

from specgpu.planning.design import plan_optimal
from specgpu.planning.registry import make_plan
from specgpu.planning.timing import budget_params, check_budget, exposure_within, extra_count

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["budget_plan"]


def budget_plan(method: str, bundle: CalibrationBundle, sequence_s: float | None, *args,
                min_frame_period_s: float = 0.0,
                extra_frames: int = 0, **kwargs):
    """The plan of ``method`` (a key of :data:`specgpu.planning.registry.PLAN_METHODS`) whose sequence, with
    ``extra_frames`` frames more (an ambient frame, drift probes added afterwards), fits ``sequence_s``.

    Parameters
    ----------
    method : str
    bundle : CalibrationBundle
    sequence_s : float or None
        Budget of one sequence, s; None: the method's own exposure (no budget), with the camera's read-out floor
        still recorded so the plan states its real frame period.
    *args, **kwargs
        The method's own arguments (``max_exposure_s`` a further cap).
    min_frame_period_s : float
        The camera's shortest frame period (read-out) at its ROI, s.
    extra_frames : int or callable
        Frames the caller adds to each sequence after planning (a callable: of the plan's K, for reference frames).

    Returns
    -------
    Plan
        With ``params["sequence_budget_s"]`` and ``params["min_frame_period_s"]`` recorded; its
        :attr:`~specgpu.planning.plans.Plan.sequence_s` plus the extra frames' periods within the budget.

    Raises
    ------
    ValueError
        The budget cannot hold the frames (one line saying the least that can), or the method's own refusal.

    Examples
    --------
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.rig import load_rig
    >>> plan = budget_plan("hadamard", oracle_calibration(load_rig()), 0.030, bands=7)
    >>> plan.K, plan.sequence_s <= 0.030
    (7, True)
    """
    floor = float(min_frame_period_s)
    if method == "optimal":
        return plan_optimal(bundle, *args, sequence_s=sequence_s, min_frame_period_s=floor,
                            extra_frames=extra_frames, **kwargs)
    plan = make_plan(method, bundle, *args, **kwargs)
    if sequence_s is not None:
        cap = exposure_within(sequence_s, plan.K + extra_count(extra_frames, plan.K), bundle.min_exposure_s, floor)
        if plan.exposure_s > cap:
            given = kwargs.pop("max_exposure_s", None)
            plan = make_plan(method, bundle, *args, max_exposure_s=cap if given is None else min(cap, given),
                             **kwargs)
    plan = replace(plan, params={**plan.params, **(budget_params(sequence_s, floor) if sequence_s is not None
                                                  else {"min_frame_period_s": floor})})
    check_budget(plan, extra_frames)
    return plan
