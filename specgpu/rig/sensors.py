"""Camera presets: the paper's camera and common machine-vision sensors, for the rig TOML and the benchmarks.

``[camera] preset = "cmv4000"`` in a rig TOML starts the camera table from a preset; keys given beside it
override the preset's values. Every preset is a full :class:`~specgpu.rig.camera.CameraParameters` set, so the
twin renders, calibrates and streams at the sensor's size with its bit depth, full well, read noise and
frame-period model (``frame_overhead_s + roi_width * roi_height / pixel_clock_hz``, the camera's rule).

Sources of the figures (data sheets as published; the rest is said to be assumed):

``paper``  The paper's camera (Epix SV643M class, 640 x 480, 10 bit): :class:`CameraParameters` defaults.

``cmv4000``  CMOSIS / ams CMV4000, 2048 x 2048, 5.5 um global shutter. ams data sheet DS000728 v6-00 (2023),
    section 1: 16 LVDS channels at 480 Mbps, 180 fps at full resolution with 10 bits per pixel. The pixel clock is
    that link rate (16 x 480 Mbps / 10 bit = 768 Mpx/s) and the overhead makes 2048 x 2048 exactly 180 fps
    (95 us). Full well 13.5 ke-, temporal read noise 13 e-, dark current 125 e-/s at 25 C: CMOSIS
    CMV4000 v2 data sheet, specification overview (figures as published there; not re-read in this project).

``imx250``  Sony IMX250 (Pregius, 2448 x 2048, 3.45 um global shutter, 12-bit ADC), as characterised in the
    Teledyne DALSA Genie Nano M2450 manual ("Standard Design 12-bit"): full well 10.7 ke-, dynamic range
    75.46 dB, hence read noise 10700 / 10^(75.46 / 20) = 1.8 e-; readout time = horizontal line time x (lines +
    28) with 8.333 us lines at 12 bit, i.e. a pixel clock of 2448 / 8.333 us = 293.8 Mpx/s and 28 lines
    (233 us) of overhead: 57.8 fps at full resolution (the manual's 57 fps).

``imx304``  Sony IMX304 class (4096 x 3000, the IMX253's 3.45 um Pregius pixel on a slower interface): the same
    pixel as the IMX250 (same full well and read noise; the Pregius second generation shares one pixel design),
    and, as a stated model, the IMX250's 12-bit pixel clock and overhead: 23.8 fps at full resolution.

Every preset frames the paper's object field: its lens images the width the paper's camera sees (640 pixels of
48 um on the object, 30.72 mm) onto the sensor's longer side (``object_pixel_um`` = 30720 / that side's pixels),
so the light's spot covers the field as in the paper. The bare sensor with the paper's 48 um pixels on the object
would see a field wider than the spot, whose corners get under 1 % of the centre's light: no flat field corrects
that (calibration refuses such a field). The longer lens has its price: a magnification of 0.27-0.46 instead of
0.07-0.12, so the image irradiance is 0.54-0.71 of what the bare sensor would get (the ``(1 + m)^2`` of
:meth:`~specgpu.rig.camera.Camera.responsivity`), and a preset cropped to 640 x 480 sees a 5-10 mm
field. A rig TOML that gives ``object_pixel_um`` beside the preset keeps its own.

Quantum efficiency peaks (Pregius monochrome about 0.65, CMV4000 about 0.60 including fill factor) and dark
currents of the Sony parts are typical published values, used as assumed; the spectral shape stays the
documented ``"cmos"`` model unless a CSV is given.
"""

from __future__ import annotations

from dataclasses import fields, replace

from specgpu.rig.camera import CameraParameters

__all__ = ["OBJECT_FIELD_MM", "PRESETS", "framing_um", "preset_names", "camera_preset", "expand_preset",
           "camera_for_size"]

# Per preset: the CameraParameters fields that differ from the paper's camera. Exposure and frame rate are
# chosen inside the sensor's frame-rate limit.
_PRESET_FIELDS: dict[str, dict] = {
    "paper": {},
    "cmv4000": dict(
        sensor_width=2048, sensor_height=2048, roi_width=2048, roi_height=2048, bit_depth=10,
        full_well_e=13500.0, read_noise_e=13.0, dark_current_e_per_s=125.0, pedestal_e=13500.0 * 16 / 1023,
        quantum_efficiency_peak=0.60, pixel_pitch_um=5.5, pixel_clock_hz=16 * 480e6 / 10,
        frame_overhead_s=1 / 180.0 - 2048 * 2048 / (16 * 480e6 / 10), frame_rate_hz=90.0, exposure_s=0.0110,
    ),
    "imx250": dict(
        sensor_width=2448, sensor_height=2048, roi_width=2448, roi_height=2048, bit_depth=12,
        full_well_e=10700.0, read_noise_e=1.8, dark_current_e_per_s=10.0, pedestal_e=10700.0 * 60 / 4095,
        quantum_efficiency_peak=0.65, pixel_pitch_um=3.45, pixel_clock_hz=2448 / 8.333e-6,
        frame_overhead_s=28 * 8.333e-6, frame_rate_hz=50.0, exposure_s=0.0150,
    ),
    "imx304": dict(
        sensor_width=4096, sensor_height=3000, roi_width=4096, roi_height=3000, bit_depth=12,
        full_well_e=10700.0, read_noise_e=1.8, dark_current_e_per_s=10.0, pedestal_e=10700.0 * 60 / 4095,
        quantum_efficiency_peak=0.65, pixel_pitch_um=3.45, pixel_clock_hz=2448 / 8.333e-6,
        frame_overhead_s=28 * 8.333e-6, frame_rate_hz=20.0, exposure_s=0.0400,
    ),
}

_PAPER = CameraParameters()
#: Width of the object the paper's camera sees, mm (640 pixels of 48 um): the field every preset frames.
OBJECT_FIELD_MM = _PAPER.sensor_width * _PAPER.object_pixel_um * 1e-3


def _framed(values: dict) -> dict:
    """A preset's fields with the lens that frames :data:`OBJECT_FIELD_MM` on its sensor's longer side."""
    if "sensor_width" not in values or "object_pixel_um" in values:
        return values
    return {**values, "object_pixel_um": framing_um(values["sensor_width"], values["sensor_height"])}


def framing_um(width: int, height: int) -> float:
    """Object pixel (um) of the lens that images :data:`OBJECT_FIELD_MM` onto the longer side of a sensor of
    ``width`` x ``height`` pixels."""
    return OBJECT_FIELD_MM * 1e3 / max(int(width), int(height))


#: Preset name -> CameraParameters (built once; each is checked by CameraParameters itself).
PRESETS: dict[str, CameraParameters] = {name: CameraParameters(**_framed(values))
                                        for name, values in _PRESET_FIELDS.items()}


def preset_names() -> tuple[str, ...]:
    return tuple(PRESETS)


def camera_preset(name: str, **overrides) -> CameraParameters:
    """The preset ``name`` (case-insensitive) with ``overrides`` (CameraParameters fields) applied."""
    key = str(name).strip().lower()
    if key not in PRESETS:
        raise ValueError(f"camera.preset {name!r} is unknown (choose from {', '.join(PRESETS)})")
    return replace(PRESETS[key], **overrides) if overrides else PRESETS[key]


def expand_preset(table: dict) -> dict:
    """A rig TOML ``[camera]`` table with its ``preset`` key replaced by the preset's values (keys given in the
    table win). A table without ``preset`` is returned unchanged."""
    if "preset" not in table:
        return table
    rest = {k: v for k, v in table.items() if k != "preset"}
    name = table["preset"]
    if not isinstance(name, str):
        raise ValueError(f"camera.preset must be a name ({', '.join(PRESETS)}), got {name!r}")
    base = camera_preset(name)
    return {**{f.name: getattr(base, f.name) for f in fields(CameraParameters)}, **rest}


def camera_for_size(width: int, height: int, base: CameraParameters | None = None) -> CameraParameters:
    """A camera that reads ``width`` x ``height`` frames: ``base`` (the paper's camera by default) with that ROI
    when its sensor holds it, else the smallest preset sensor that holds it (ROI centred), else a sensor of
    exactly that size with the IMX250's pixel and 12-bit timing model (each preset's lens framing the paper's
    object field on its sensor's longer side)."""
    base = base if base is not None else CameraParameters()
    width, height = int(width), int(height)
    candidates = [base] + sorted(PRESETS.values(), key=lambda p: p.sensor_width * p.sensor_height)
    for cam in candidates:
        if width <= cam.sensor_width and height <= cam.sensor_height:
            chosen = cam
            break
    else:
        chosen = replace(PRESETS["imx250"], sensor_width=width, sensor_height=height, roi_width=width,
                         roi_height=height, frame_rate_hz=1.0, exposure_s=0.5,
                         object_pixel_um=framing_um(width, height))
    rate = min(chosen.frame_rate_hz, _max_rate(chosen, width, height))
    return replace(chosen, roi_width=width, roi_height=height, frame_rate_hz=rate,
                   exposure_s=min(chosen.exposure_s, 0.9 / rate))


def _max_rate(cam: CameraParameters, width: int, height: int) -> float:
    return 1.0 / (cam.frame_overhead_s + width * height / cam.pixel_clock_hz)
