"""The calibration bundle and its file, and the two feedback loops that measure it on a rig.

Modules: :mod:`~specgpu.calibration.bundle` (the bundle, its file and fingerprint, the twin's oracle bundle),
:mod:`~specgpu.calibration.rigs` (what calibration needs from a rig, the twin's, the capture helpers),
:mod:`~specgpu.calibration.loops` (loop (a), camera plus white; loop (b), spectroradiometer) and
:mod:`~specgpu.calibration.procedure` (:func:`calibrate`, the whole procedure).
"""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
