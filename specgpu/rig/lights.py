"""Every programmable light the twin models, chosen by ``[light] kind``: one light is ``P . w``.

``kind = "dmd"`` (default): the xenon lamp, grating and DMD of :mod:`specgpu.rig.light`; ``"led"``: an LED array
(:mod:`specgpu.rig.led`); ``"ol490"``: the OL490 with its grey-level controller (:mod:`specgpu.rig.ol490`). All
present one interface (:class:`~specgpu.rig.light.ProgrammableLight`'s): ``columns`` primaries with spectra
``column_matrix`` (P), integer patterns in ``[0, rows]`` (w times rows), so the twin, the capture path, calibration
and planning handle every kind alike. This module holds the dispatch: the parameters from a ``[light]`` table and
the light from its parameters.
"""

from __future__ import annotations

from specgpu.rig.led import LEDLight, LEDParameters
from specgpu.rig.light import LightParameters, ProgrammableLight
from specgpu.rig.ol490 import OL490Light, OL490Parameters
from specgpu.rig.tables import build_table

__all__ = ["LIGHT_KINDS", "light_from_table", "light_kind", "light_summary", "make_light"]

#: Parameter class of each ``[light] kind``.
LIGHT_KINDS = {"dmd": LightParameters, "led": LEDParameters, "ol490": OL490Parameters}


def light_kind(params) -> str:
    """The ``kind`` of a light's parameters (``"dmd"`` for :class:`LightParameters`, which has no such key)."""
    return getattr(params, "kind", "dmd")


def light_from_table(table: dict, source: str, base=None):
    """The light's parameters from a rig TOML's ``[light]`` table, by its ``kind`` (errors name ``source`` and the
    key). A DMD table keeps no ``kind``, so every existing rig description reads and fingerprints as before."""
    if not isinstance(table, dict):
        raise ValueError(f"{source}: [light] must be a table, got {table!r}")
    table = dict(table)
    kind = table.get("kind", "dmd")
    if kind not in LIGHT_KINDS:
        raise ValueError(f"{source}: light.kind must be one of {', '.join(LIGHT_KINDS)}, got {kind!r}")
    if kind == "dmd":
        table.pop("kind", None)
    return build_table(LIGHT_KINDS[kind], table, "light", source, base)


def make_light(params, *, seed: int = 0, realism=None, drift=None, clock_s: float = 0.0,
               exposure_s: float | None = None) -> ProgrammableLight:
    """The twin's light for ``params`` of any kind; ``exposure_s`` (the camera's) sets the PWM or grey periods an
    exposure holds (the DMD's mirrors need none)."""
    kind = light_kind(params)
    if kind == "led":
        return LEDLight(params, seed=seed, realism=realism, drift=drift, clock_s=clock_s, exposure_s=exposure_s)
    if kind == "ol490":
        return OL490Light(params, seed=seed, realism=realism, drift=drift, clock_s=clock_s, exposure_s=exposure_s)
    return ProgrammableLight(params, seed=seed, realism=realism, drift=drift, clock_s=clock_s)


def light_summary(params) -> dict:
    """Plain data a calibration records about its light: ``kind``, and for an LED array its LEDs' wavelengths and
    PWM, for the OL490 its grey depth and slit (the DMD records nothing: its bundles stay as they were)."""
    kind = light_kind(params)
    if kind == "dmd":
        return {}
    out = {"kind": kind, "rows": int(params.rows), "exposure_quantum_s": float(params.exposure_quantum_s)}
    if kind == "led":
        out.update(pwm_frequency_hz=float(params.pwm_frequency_hz), pwm_bits=int(params.pwm_bits))
    else:
        out.update(grey_bits=int(params.grey_bits), slit=int(params.slit),
                   grey_period_s=float(params.grey_period_s))
    return out

