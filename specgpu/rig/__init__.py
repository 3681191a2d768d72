"""The physical system, modelled: light source, camera, scene and the synchronous twin.

Everything is NumPy on the host; the defaults reproduce the paper's rig (Tominaga and Horiuchi 2012, Section 2)
and every parameter can be overridden from a rig TOML (:func:`load_rig`).
"""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
