"""Spectral rendering projector (paper section 3) and scene appearance under any illuminant.

The programmable light reproduces a target spectrum: CIE illuminants A and D65, a phosphor white LED and an
RGB-mixing LED near 6500 K, or any SPD. :func:`project` runs the spectroradiometer feedback loop
(:func:`specgpu.calibration.spectral_loop`, the paper's Fig. 8b) on the rig and reports the produced-vs-target
spectral RMSE, chromaticity, CCT and colour rendering index (colour-science). :func:`render_scene` renders a
spectral scene's appearance under an illuminant as a display image, and :func:`metamer_map` gives per pixel the
CIEDE2000 difference between a scene seen under two illuminants of the same white point: the white looks the
same under both, colourful objects do not (metamerism, colour rendering).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import colour
import numpy as np

from specgpu.calibration import spectral_loop
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS, XYZ_to_Lab, delta_E, reflectance_to_XYZ
from specgpu.rig.twin import TwinRig

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.rig.scene import SpectralScene

__all__ = [
    "PROJECTOR_TARGETS",
    "target_spectrum",
    "rgb_led_spectrum",
    "spectrum_report",
    "ProjectionReport",
    "project",
    "render_scene",
    "metamer_map",
]

#: The paper's RGB-mixing LED: 6485 K, x, y = 0.314, 0.332 (section 3).
RGB_LED_XY = (0.314, 0.332)
#: Peak wavelengths (nm) and half spectral widths (nm) of the three LEDs mixed (typical InGaN blue and green,
#: AlInGaP red), for colour-science's Ohno 2005 LED model.
RGB_LED_PEAKS = (457.0, 530.0, 620.0)
RGB_LED_WIDTHS = (20.0, 30.0, 18.0)
OBSERVER = "CIE 1931 2 Degree Standard Observer"


def rgb_led_spectrum(xy=RGB_LED_XY, peaks=RGB_LED_PEAKS, widths=RGB_LED_WIDTHS) -> colour.SpectralDistribution:
    """An RGB-mixing LED whose chromaticity is ``xy``: three Ohno 2005 LED spectra, powers solved exactly.

    Returns
    -------
    colour.SpectralDistribution
        Relative SPD on 360-780 nm at 1 nm, normalised to 100 at 560 nm.
    """
    shape = colour.SpectralShape(360, 780, 1)
    cmfs = colour.MSDS_CMFS[OBSERVER]
    leds = [colour.sd_single_led(p, shape=shape, half_spectral_width=w) for p, w in zip(peaks, widths)]
    XYZ = np.array([colour.sd_to_XYZ(led, cmfs, method="Integration") for led in leds]).T  # 3 x 3
    weights = np.linalg.solve(XYZ, colour.xy_to_XYZ(np.asarray(xy, np.float64)))
    if np.any(weights <= 0):
        raise ValueError(f"xy={tuple(xy)} is outside the gamut of LEDs peaking at {peaks} nm")
    values = sum(w * led.values for w, led in zip(weights, leds))
    values = 100 * values / np.interp(560, shape.wavelengths, values)
    return colour.SpectralDistribution(values, shape.wavelengths, name=f"RGB LED xy {tuple(xy)}")


def _named_targets() -> dict:
    return {
        "A": lambda: colour.SDS_ILLUMINANTS["A"],
        "D65": lambda: colour.SDS_ILLUMINANTS["D65"],
        # phosphor-converted white LED near 6500 K: CIE 2018 LED-B5 (6597 K)
        "LED white": lambda: colour.SDS_ILLUMINANTS["LED-B5"],
        "LED RGB": rgb_led_spectrum,
    }


#: Targets of the paper's projector experiment, by name.
PROJECTOR_TARGETS = tuple(_named_targets())


def target_spectrum(target) -> colour.SpectralDistribution:
    """A target SPD: one of :data:`PROJECTOR_TARGETS`, a name of ``colour.SDS_ILLUMINANTS`` or
    ``colour.SDS_LIGHT_SOURCES``, or a ``colour.SpectralDistribution`` as given."""
    if isinstance(target, colour.SpectralDistribution):
        return target
    if not isinstance(target, str):
        raise TypeError(f"target must be a name or colour.SpectralDistribution, not {type(target).__name__}")
    named = _named_targets()
    for name, make in named.items():
        if name.lower() == target.lower():
            return make()
    for table in (colour.SDS_ILLUMINANTS, colour.SDS_LIGHT_SOURCES):
        for name in table:
            if name.lower() == target.lower():
                return table[name]
    raise ValueError(f"target={target!r} is not one of {', '.join(repr(n) for n in named)} nor a name of "
                     "colour.SDS_ILLUMINANTS / colour.SDS_LIGHT_SOURCES")


def spectrum_report(wavelengths, values) -> dict:
    """Chromaticity xy, CCT and Duv (Ohno 2013) and general colour rendering index Ra of an SPD."""
    sd = colour.SpectralDistribution(np.asarray(values, np.float64), np.asarray(wavelengths, np.float64))
    cmfs = colour.MSDS_CMFS[OBSERVER]
    xy = colour.XYZ_to_xy(colour.sd_to_XYZ(sd, cmfs, method="Integration"))
    cct, duv = colour.uv_to_CCT(colour.xy_to_UCS_uv(xy), method="Ohno 2013")
    return {"xy": [float(xy[0]), float(xy[1])], "CCT_K": float(cct), "Duv": float(duv),
            "CRI_Ra": float(colour.colour_rendering_index(sd))}


@dataclass
class ProjectionReport:
    """Produced vs target spectrum of the projector, on the spectroradiometer's grid.

    ``target`` and ``produced`` are normalised to 100 at 560 nm (the CIE convention for relative SPDs), and
    ``rmse`` (over the light's whole range) and ``rmse_400_700`` (over 400-700 nm) are in those units;
    ``relative_rmse`` is the loop's criterion (RMS over the target's support divided by its maximum). At the ends
    of the grating's range the light cannot follow a target at full level (half the slit function falls outside
    it), which dominates ``rmse`` for targets that are high there (A at 780 nm).
    """

    name: str
    wavelengths: np.ndarray
    target: np.ndarray
    produced: np.ndarray
    rmse: float
    rmse_400_700: float
    relative_rmse: float
    target_colour: dict
    produced_colour: dict
    loop: dict = field(default_factory=dict)
    patterns: np.ndarray | None = None

    def summary(self) -> dict:
        return {"name": self.name, "rmse": self.rmse, "rmse_400_700": self.rmse_400_700,
                "relative_rmse": self.relative_rmse,
                "target": self.target_colour, "produced": self.produced_colour, "loop": self.loop}


def project(target, *, rig: TwinRig | None = None, bundle: CalibrationBundle | None = None, tolerance: float = 0.01,
            max_iterations: int = 20,
            headroom: float = 0.9) -> ProjectionReport:
    """Produce ``target`` with the programmable light, closing the loop on the spectroradiometer.

    Parameters
    ----------
    target : str or colour.SpectralDistribution
        See :func:`target_spectrum`.
    rig : specgpu.rig.TwinRig, optional
        The rig (its light and spectroradiometer); a default twin when omitted.
    bundle : specgpu.calibration.bundle.CalibrationBundle, optional
        Calibration whose lamp model gives the loop's first guess.
    tolerance, max_iterations
        Loop (b) convergence criterion and bound.
    headroom : float
        Fraction of the largest reachable multiple of the target that is asked for, in (0, 1], so the loop can
        raise columns as well as lower them.
    """
    sd = target_spectrum(target)
    if not 0 < headroom <= 1:
        raise ValueError(f"headroom must lie in (0, 1], got {headroom!r}")
    rig = TwinRig() if rig is None else rig
    light = rig.light
    wl = light.wavelengths
    relative = np.interp(wl, sd.wavelengths, sd.values, left=0.0, right=0.0)
    reachable = light.spectrum_to_pattern(relative, fit="scale")
    result = spectral_loop(rig, relative * reachable.scale * headroom, bundle=bundle, tolerance=tolerance,
                           max_iterations=max_iterations)
    inst = rig.spectroradiometer.wavelengths
    norm_t = np.interp(560.0, inst, result.targets)
    norm_p = np.interp(560.0, inst, result.outputs)
    if norm_t <= 0 or norm_p <= 0:
        raise ValueError(f"{sd.name}: no light at 560 nm to normalise on")
    target_100 = 100 * result.targets / norm_t
    produced_100 = 100 * result.outputs / norm_p
    inside = result.targets > 0
    visible = inside & (inst >= 400.0) & (inst <= 700.0)
    return ProjectionReport(
        name=str(sd.name), wavelengths=inst, target=target_100, produced=produced_100,
        rmse=float(np.sqrt(np.mean((produced_100 - target_100)[inside] ** 2))),
        rmse_400_700=float(np.sqrt(np.mean((produced_100 - target_100)[visible] ** 2))),
        relative_rmse=float(result.residual),
        target_colour=spectrum_report(inst, target_100), produced_colour=spectrum_report(inst, produced_100),
        loop=result.summary(), patterns=result.patterns,
    )


def _scene_XYZ(scene, illuminant, device):
    sd = target_spectrum(illuminant)
    XYZ = reflectance_to_XYZ(scene.reflectance, scene.wavelengths, illuminant=sd, device=device)
    white = reflectance_to_XYZ(np.ones(len(scene.wavelengths), np.float32), scene.wavelengths, illuminant=sd,
                               device=device)
    return XYZ, np.asarray(white, np.float64)


def render_scene(scene: SpectralScene, illuminant, *, adaptation: str = "CAT02", device=None) -> np.ndarray:
    """The appearance of a spectral scene under ``illuminant`` as an sRGB image.

    XYZ under the illuminant (device), then sRGB for an observer adapted to the illuminant's white
    (``adaptation``, a colour-science chromatic adaptation transform; ``None`` shows the raw colour cast).

    Parameters
    ----------
    scene : SpectralScene
        Reflectance (H, W, B) on its wavelengths.
    illuminant : str or colour.SpectralDistribution
        A colour-science illuminant name (``"D65"``, ``"A"``, ...) or a spectrum.
    adaptation : str or None
        Chromatic adaptation transform to the illuminant's white.
    device : optional
        OpenCL device selector.

    Returns
    -------
    ndarray, (H, W, 3), float32
        Display-encoded sRGB in [0, 1] (clipped).

    Examples
    --------
    >>> from specgpu.pipeline import render_scene
    >>> from specgpu.rig import colorchecker_scene
    >>> image = render_scene(colorchecker_scene(24, 36), "A")
    >>> image.shape, str(image.dtype)
    ((24, 36, 3), 'float32')
    """
    XYZ, white = _scene_XYZ(scene, illuminant, device)
    rgb = colour.XYZ_to_sRGB(np.asarray(XYZ, np.float64), illuminant=colour.XYZ_to_xy(white),
                             chromatic_adaptation_transform=adaptation)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def metamer_map(scene: SpectralScene, illuminant_1, illuminant_2, *, method: str = "CIE 2000",
                device=None) -> np.ndarray:
    """Per-pixel colour difference of the scene seen under two illuminants, each with its own white.

    For two sources of the same white point (the paper's white and RGB LEDs) a white surface gives 0 and
    colourful surfaces show how differently the sources render them.

    Returns
    -------
    ndarray, (H, W), float32
        dE (``method``) between CIELAB under ``illuminant_1`` (reference) and under ``illuminant_2``.
    """
    validate_method(method, DELTA_E_METHODS)
    XYZ_1, white_1 = _scene_XYZ(scene, illuminant_1, device)
    XYZ_2, white_2 = _scene_XYZ(scene, illuminant_2, device)
    Lab_1 = XYZ_to_Lab(XYZ_1, illuminant=white_1, device=device)
    Lab_2 = XYZ_to_Lab(XYZ_2, illuminant=white_2, device=device)
    return delta_E(Lab_1, Lab_2, method=method, device=device)
