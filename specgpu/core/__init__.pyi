"""Public names of :mod:`specgpu.core`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .guard import OutputClash, check_outputs
from .locks import OutputLocked, output_lock
from .mask import Mask
from .spectra import DEFAULT_CMFS, OBSERVERS, XYZ_weights, resolve_cmfs, resolve_illuminant_sd, white_point_XYZ
from .validate import BadArgument

__all__ = [
    "BadArgument",
    "check_outputs",
    "DEFAULT_CMFS",
    "Mask",
    "OBSERVERS",
    "output_lock",
    "OutputClash",
    "OutputLocked",
    "resolve_cmfs",
    "resolve_illuminant_sd",
    "white_point_XYZ",
    "XYZ_weights",
]
