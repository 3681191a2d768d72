"""The one registry of plan methods (:data:`PLAN_METHODS`) and the dispatcher that makes a plan by name
(:func:`make_plan`): the paper's methods, the optimal design and Hadamard multiplexing alike.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from specgpu.core.validate import BadArgument
from specgpu.planning.basis_plans import plan_biased_basis, plan_symmetric_basis
from specgpu.planning.design import plan_hadamard, plan_optimal
from specgpu.planning.narrowband import plan_narrowband, plan_reciprocal_narrowband
from specgpu.planning.plans import Plan
from specgpu.planning.response import plan_camera_simulator, plan_steady_state, plan_tristimulus

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["NARROWBAND_METHODS", "PLAN_METHODS", "check_light_can", "make_plan"]

#: Plan methods by name: each takes the calibration bundle first, then the method's own arguments.
PLAN_METHODS = {
    "narrowband": plan_narrowband,
    "reciprocal": plan_reciprocal_narrowband,
    "biased": plan_biased_basis,
    "symmetric": plan_symmetric_basis,
    "tristimulus": plan_tristimulus,
    "camera": plan_camera_simulator,
    "steady": plan_steady_state,
    "optimal": plan_optimal,
    "hadamard": plan_hadamard,
}


def make_plan(method: str, bundle: CalibrationBundle, *args, **kwargs) -> Plan:
    """Make a plan by method name.

    Parameters
    ----------
    method : str
        A key of :data:`PLAN_METHODS`: ``narrowband``, ``reciprocal``, ``biased``, ``symmetric``,
        ``tristimulus``, ``camera``, ``steady``, ``optimal`` or ``hadamard``.
    bundle : CalibrationBundle
        The calibration whose forward model the plan is designed on.
    *args, **kwargs
        The method's own arguments, e.g. the basis of ``biased``, the prior and ``noise_at`` of ``optimal``
        (``make_plan("optimal", bundle, prior, noise_at, frames=6)``), ``bands=`` of ``hadamard``.

    Returns
    -------
    Plan

    Raises
    ------
    ValueError
        An unknown method (the message lists the valid ones), or the method's own refusal.

    Examples
    --------
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.planning import make_plan
    >>> from specgpu.rig import load_rig
    >>> bundle = oracle_calibration(load_rig())
    >>> make_plan("hadamard", bundle, bands=7).K
    7
    >>> make_plan("tristimulus", bundle, illuminant="D65").output_labels
    ('X', 'Y', 'Z')
    """
    if method not in PLAN_METHODS:
        raise ValueError(f"unknown plan method {method!r}; valid methods: {', '.join(PLAN_METHODS)}")
    check_light_can(method, bundle)
    return PLAN_METHODS[method](bundle, *args, **kwargs)


#: Methods that shape each frame into a narrow band the light must be able to make at any wavelength: a DMD (or the
#: OL490) can, an LED array cannot. Every other method designs within any primaries (``P . w``, w in [0, 1]).
NARROWBAND_METHODS = ("narrowband", "reciprocal")


def check_light_can(method: str, bundle) -> None:
    """Refuse (:class:`~specgpu.core.validate.BadArgument`, one line) a method the calibrated light cannot make:
    a narrow-band method on a light of a few fixed primaries, naming the bands it has (its LEDs)."""
    if method in NARROWBAND_METHODS and getattr(bundle, "light_kind", "dmd") == "led":
        peaks = bundle.light.get("primaries_nm") or list(bundle.column_wavelengths)
        others = ", ".join(m for m in PLAN_METHODS if m not in NARROWBAND_METHODS)
        raise BadArgument(f"{method} needs a light tunable to any narrow band; this LED light has {len(peaks)} fixed "
                          f"bands at {', '.join(f'{x:.0f}' for x in peaks)} nm: use one of {others}")
