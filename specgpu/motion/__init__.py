"""Motion of a scene during a sequence, estimated on the host: the methods by name (global, affine, flow), the
phase correlation they run on, the consistency and residual checks of a compensated sequence, the motion from a
plan's broadband reference frames, and an object layer's own motion."""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
