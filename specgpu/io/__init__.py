"""File formats: Fichet 2021 spectral EXR, ENVI, npz / CSV, previews, sequence folders (journal, salvage), zarr
recordings."""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
