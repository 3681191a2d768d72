"""The OL490's vendor SDK as specgpu uses it: the calls (:class:`OL490Sdk`), the .NET assembly through pythonnet
(:func:`load_dotnet_sdk`) and :class:`OL490Unit`, which makes every call's failure one line naming the call.

The Optronic Laboratories OL490 is programmed through the vendor's .NET SDK. specgpu needs seven things of it:
connect to a unit, load one of the unit's four stored calibrations (one per slit), set the grey depth (1 to 6 bit;
the deeper, the lower the highest frame rate, which the SDK reports), send one column pattern (1024 DMD columns,
a grey level each), load a sequence of patterns into the unit's memory, and run it stepped by the trigger input,
reporting how far it has stepped. :class:`OL490Sdk` is that interface; the real SDK is reached through
:class:`DotNetSdk`, whose table :data:`DOTNET_CALLS` maps each call to the SDK's method name. Those names are
assumptions until checked against the vendor's SDK: adapting to it means editing that table (or passing
``calls=``), nothing else. :class:`~specgpu.hardware.ol490.simulated.SimulatedOL490Sdk` implements the same
interface for CI.

pythonnet is an optional dependency (``pip install 'specgpu[ol490]'``), imported only when a real unit is opened.
"""

from __future__ import annotations

import abc
import importlib
from pathlib import Path

from specgpu.hardware.errors import BackendMissing, CommandRejected, DeviceDisconnected, DeviceNotFound, HardwareError

__all__ = ["OL490Sdk", "DotNetSdk", "DOTNET_CALLS", "DEFAULT_SDK_TYPE", "load_dotnet_sdk", "OL490Unit", "COLUMNS",
           "SLITS", "GREY_BITS"]

#: DMD columns of the OL490 (the wavelength axis).
COLUMNS = 1024
#: The four stored calibrations, one per slit.
SLITS = (1, 2, 3, 4)
#: Grey depths the unit offers, bits.
GREY_BITS = (1, 2, 3, 4, 5, 6)


class OL490Sdk(abc.ABC):
    """The OL490 SDK calls specgpu makes (module docstring); every one may raise on failure."""

    @abc.abstractmethod
    def connect(self, serial: str = "") -> bool:
        """Connect to the unit with this serial number ("" for the first); False if none is there."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the unit."""

    @abc.abstractmethod
    def is_connected(self) -> bool:
        """Whether a unit is connected and answering."""

    @abc.abstractmethod
    def load_calibration(self, slit: int) -> None:
        """Load the unit's stored calibration for slit 1 to 4."""

    @abc.abstractmethod
    def set_grey_depth(self, bits: int) -> None:
        """Set the grey depth of the column patterns, 1 to 6 bit."""

    @abc.abstractmethod
    def max_frame_rate(self, bits: int) -> float:
        """Highest pattern rate (Hz) at a grey depth."""

    @abc.abstractmethod
    def send_pattern(self, levels) -> None:
        """Show one pattern now: a grey level (0 to 2**bits - 1) for each of the 1024 columns."""

    @abc.abstractmethod
    def load_sequence(self, patterns) -> None:
        """Load (K, 1024) grey-level patterns into the unit's memory."""

    @abc.abstractmethod
    def start_sequence(self, triggered: bool = True) -> None:
        """Run the loaded sequence: each trigger-input edge shows the next pattern (the first edge pattern 0)."""

    @abc.abstractmethod
    def stop_sequence(self) -> None:
        """Stop the sequence (outputs dark)."""

    @abc.abstractmethod
    def sequence_steps(self) -> int:
        """Trigger steps taken since :meth:`start_sequence`."""

    @abc.abstractmethod
    def sequence_running(self) -> bool:
        """Whether the loaded sequence is running."""


#: Interface call -> the SDK assembly's method name (assumed; see the module docstring).
DOTNET_CALLS = {
    "connect": "ConnectToOL490",
    "disconnect": "CloseOL490",
    "is_connected": "IsConnected",
    "load_calibration": "LoadCalibrationData",
    "set_grey_depth": "SetGrayScaleValue",
    "max_frame_rate": "GetMaxFrameRate",
    "send_pattern": "SendColumnPattern",
    "load_sequence": "LoadSequenceToMemory",
    "start_sequence": "StartSequence",
    "stop_sequence": "StopSequence",
    "sequence_steps": "GetSequenceStepCount",
    "sequence_running": "IsSequenceRunning",
}
#: The SDK's class ("Namespace.Type") that :func:`load_dotnet_sdk` instantiates (assumed; ``hardware.ol490_sdk_type``).
DEFAULT_SDK_TYPE = "OL490_SDK_Dll.OL490SdkLibrary"


class DotNetSdk(OL490Sdk):
    """:class:`OL490Sdk` on the vendor's .NET object (loaded by :func:`load_dotnet_sdk`).

    Parameters
    ----------
    obj
        The SDK's library object.
    calls
        Interface call -> method name (default :data:`DOTNET_CALLS`).
    """

    def __init__(self, obj, calls: dict | None = None):
        self.obj = obj
        self.calls = dict(DOTNET_CALLS, **(calls or {}))

    def _call(self, name, *args):
        return getattr(self.obj, self.calls[name])(*args)

    @staticmethod
    def _array(rows):
        # a .NET Int32[] (or Int32[][] for a sequence), as the SDK's methods take
        import System  # pythonnet's namespace, present once load_dotnet_sdk ran

        def one(row):
            return System.Array[System.Int32]([int(v) for v in row])
        if rows and hasattr(rows[0], "__len__"):
            return System.Array[System.Array[System.Int32]]([one(r) for r in rows])
        return one(rows)

    def connect(self, serial=""):
        return bool(self._call("connect", serial))

    def disconnect(self):
        self._call("disconnect")

    def is_connected(self):
        return bool(self._call("is_connected"))

    def load_calibration(self, slit):
        self._call("load_calibration", int(slit))

    def set_grey_depth(self, bits):
        self._call("set_grey_depth", int(bits))

    def max_frame_rate(self, bits):
        return float(self._call("max_frame_rate", int(bits)))

    def send_pattern(self, levels):
        self._call("send_pattern", self._array([int(v) for v in levels]))

    def load_sequence(self, patterns):
        self._call("load_sequence", self._array([[int(v) for v in row] for row in patterns]))

    def start_sequence(self, triggered=True):
        self._call("start_sequence", bool(triggered))

    def stop_sequence(self):
        self._call("stop_sequence")

    def sequence_steps(self):
        return int(self._call("sequence_steps"))

    def sequence_running(self):
        return bool(self._call("sequence_running"))


def load_dotnet_sdk(path: str, type_name: str = DEFAULT_SDK_TYPE, calls: dict | None = None) -> DotNetSdk:
    """Load the vendor's SDK assembly through pythonnet and instantiate its library type.

    Raises
    ------
    BackendMissing
        pythonnet is not installed, or no assembly is named (one line naming the package and the setting).
    DeviceNotFound
        The assembly file does not exist.
    HardwareError
        The assembly or its type cannot be loaded.
    """
    if not path:
        raise BackendMissing("OL490: no SDK assembly set: set hardware.ol490_sdk to the vendor's OL490 SDK .dll")
    try:
        import clr
    except ImportError:
        raise BackendMissing(f"OL490: the vendor SDK ({path}, hardware.ol490_sdk) is loaded through pythonnet, "
                             f"which is not installed: pip install 'specgpu[ol490]'") from None
    dll = Path(path)
    if not dll.is_file():
        raise DeviceNotFound(f"OL490 SDK assembly {dll} (hardware.ol490_sdk) not found")
    module, _, cls = type_name.rpartition(".")
    try:
        clr.AddReference(str(dll))
        obj = getattr(importlib.import_module(module), cls)()
    except Exception as exc:  # noqa: BLE001 - .NET exceptions of any kind, made one line
        raise HardwareError(f"OL490 SDK {dll}: cannot load {type_name} (hardware.ol490_sdk_type): "
                            f"{_first_line(exc)}") from None
    return DotNetSdk(obj, calls)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class OL490Unit:
    """One OL490 through an :class:`OL490Sdk`: connected on creation, every call's failure one line naming it.

    Raises (from any call)
    ----------------------
    DeviceNotFound
        No unit answers :meth:`OL490Sdk.connect`.
    DeviceDisconnected
        A call failed and the unit no longer reports itself connected (unplugged, powered off).
    CommandRejected
        A call failed (an exception from the SDK) with the unit still connected.
    """

    def __init__(self, sdk: OL490Sdk, serial: str = ""):
        self.sdk = sdk
        self.who = f"OL490 {serial}" if serial else "OL490"
        try:
            found = sdk.connect(serial)
        except Exception as exc:  # noqa: BLE001
            raise DeviceNotFound(f"{self.who} not connected: SDK call connect failed: {_first_line(exc)}") from None
        if not found:
            raise DeviceNotFound(f"{self.who} not connected: the SDK found no unit{' with that serial' * bool(serial)}"
                                 f"; is it powered and on USB?")
        self.connected = True

    def call(self, name: str, *args):
        """``sdk.<name>(*args)``, its failure one line naming the call."""
        if not self.connected:
            raise DeviceDisconnected(f"{self.who} is not connected (SDK call {name})")
        try:
            return getattr(self.sdk, name)(*args)
        except Exception as exc:  # noqa: BLE001 - whatever the SDK raises
            try:
                still = bool(self.sdk.is_connected())
            except Exception:  # noqa: BLE001
                still = False
            if not still:
                self.connected = False
                raise DeviceDisconnected(f"{self.who} disconnected: SDK call {name} failed: {_first_line(exc)}") \
                    from None
            raise CommandRejected(f"{self.who}: SDK call {name} failed: {_first_line(exc)}",
                                  description=_first_line(exc)) from None

    def close(self) -> None:
        if self.connected:
            self.connected = False
            try:
                self.sdk.disconnect()
            except Exception:  # noqa: BLE001 - releasing a unit that is gone is not an error
                pass
