"""Real devices behind the capture interfaces: the DLPC900 light (:mod:`.dlpc900`), LED arrays on a serial controller
board (:mod:`.led`), the OL490 through its vendor's SDK (:mod:`.ol490`), GenICam cameras through
harvesters (:mod:`.genicam`), Ocean spectrometers through python-seabreeze (:mod:`.ocean`) and the USB device list
(:func:`list_usb_devices`). Optional dependencies load only when a backend is used.
"""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
