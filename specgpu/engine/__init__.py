"""The OpenCL engine: runtime (device order, program cache, the one kernel loader), launchers, transfers, the
linear map, colorimetry, selftest.

The NumPy-facing API (``apply_linear``, ``XYZ_to_Lab``, ``delta_E``, ``reflectance_to_XYZ``,
``frames_to_delta_E``) validates its inputs and accepts host or device arrays; the ``launch_*`` and ``prepare_*``
launchers of :mod:`specgpu.engine.kernels` take device arrays already validated.
"""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
