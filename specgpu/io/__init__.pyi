"""Public names of :mod:`specgpu.io`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .cube import MAP_KINDS, read_cube, read_map, write_cube, write_map
from .envi import ENVI_INTERLEAVES, read_cube_envi, read_envi_header, write_cube_envi
from .exr import SPECTRAL_LAYOUT_VERSION, read_cube_exr, read_exr, write_cube_exr, write_exr
from .journal import salvage_sequence
from .npz import read_cube_npz, read_spectrum_csv, write_cube_npz
from .previews import PERCEPTUAL_COLORMAPS, read_png, write_delta_E_png, write_png, write_sRGB_preview
from .recording import COMPRESSIONS, RECORDING_FORMAT, RECORDING_VERSION, Recording, ZarrRecorder, open_recording
from .sequence import (
    JOURNAL_FILE,
    SEQUENCE_FILE,
    SEQUENCE_FORMAT,
    SEQUENCE_VERSION,
    SequenceWriter,
    read_sequence,
    read_sequence_header,
    write_sequence,
)
from .tables import content_hash, load_npz, save_npz

__all__ = [
    "COMPRESSIONS",
    "content_hash",
    "ENVI_INTERLEAVES",
    "JOURNAL_FILE",
    "load_npz",
    "MAP_KINDS",
    "open_recording",
    "PERCEPTUAL_COLORMAPS",
    "read_cube",
    "read_cube_envi",
    "read_cube_exr",
    "read_cube_npz",
    "read_envi_header",
    "read_exr",
    "read_map",
    "read_png",
    "read_sequence",
    "read_sequence_header",
    "read_spectrum_csv",
    "Recording",
    "RECORDING_FORMAT",
    "RECORDING_VERSION",
    "salvage_sequence",
    "save_npz",
    "SEQUENCE_FILE",
    "SEQUENCE_FORMAT",
    "SEQUENCE_VERSION",
    "SequenceWriter",
    "SPECTRAL_LAYOUT_VERSION",
    "write_cube",
    "write_cube_envi",
    "write_cube_exr",
    "write_cube_npz",
    "write_delta_E_png",
    "write_exr",
    "write_map",
    "write_png",
    "write_sequence",
    "write_sRGB_preview",
    "ZarrRecorder",
]
