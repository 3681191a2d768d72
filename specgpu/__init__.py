"""specgpu: active-illumination spectral imaging on OpenCL.

Frames lit by a programmed sequence of spectra are turned, per pixel, into spectral reflectance,
CIE XYZ, CIELAB and colour-difference maps (Tominaga and Horiuchi, JOSA A 29(9), 2012).

The public API is re-exported here from the subpackage that owns each name, lazily: ``import specgpu`` loads
neither OpenCL nor colour-science, and ``specgpu.apply_linear`` imports :mod:`specgpu.engine` on first use.

>>> import specgpu
>>> specgpu.apply_linear is specgpu.engine.apply_linear
True
"""

import lazy_loader

__version__ = "0.1.0"

# The public API by the subpackage (room) that owns each name; each is imported on first access.
_API = {
    "engine": [
        "apply_linear",
        "XYZ_to_Lab",
        "delta_E",
        "reflectance_to_XYZ",
        "frames_to_delta_E",
        "get_queue",
        "run_selftest",
    ],
    "core": ["XYZ_weights"],
    "io": [
        "read_cube",
        "write_cube",
        "read_map",
        "write_map",
        "read_sequence",
        "write_sequence",
        "open_recording",
    ],
    "planning": ["make_plan", "load_plan", "save_plan", "Plan", "PLAN_METHODS"],
    "calibration": ["calibrate", "load_calibration", "save_calibration", "CalibrationBundle"],
    "pipeline": [
        "recover",
        "read_capture",
        "capture_plan",
        "evaluate_reflectance",
        "evaluate_pixels",
        "render_scene",
    ],
    "rig": ["load_rig", "dump_rig", "colorchecker_scene", "load_scene"],
}

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs=_API)
