"""Capture: the driver interface, the ring buffer, the sequence assembler and the capture loop.

Backends are chosen by name (:func:`open_driver`: the digital twin ``"twin"`` by default, ``"replay"`` for recorded
frames) and imported on demand.
"""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
