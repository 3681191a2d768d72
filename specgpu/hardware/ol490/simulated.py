"""A simulated OL490 behind the same SDK calls as the vendor's (:class:`~specgpu.hardware.ol490.sdk.OL490Sdk`).

It keeps what the unit would: the calibration loaded, the grey depth, the pattern shown, the sequence in memory and
its trigger steps, and checks every argument as strictly as the interface documents (1024 columns, levels within
the grey depth, slits 1 to 4). The highest frame rate at ``b`` bit is ``binary_rate_hz / (2**b - 1)``: a grey
pattern is shown as binary planes weighted 1, 2, 4 ... (the real unit reports its own figures through the SDK).

Faults a test can inject: ``present=False`` (no unit answers ``connect``), ``fail_calls`` (call name -> the message
of the exception that call raises, as a .NET exception would surface through pythonnet) and :meth:`unplug`.
"""

from __future__ import annotations

import numpy as np

from specgpu.hardware.ol490.sdk import COLUMNS, GREY_BITS, SLITS, OL490Sdk

__all__ = ["SimulatedOL490Sdk", "SdkException"]


class SdkException(Exception):
    """What a failing SDK call raises (pythonnet surfaces .NET exceptions as Python exceptions)."""


class SimulatedOL490Sdk(OL490Sdk):
    """An OL490 in memory (module docstring).

    Parameters
    ----------
    serial : str
        The unit's serial number.
    present : bool
        Whether a unit answers ``connect``.
    binary_rate_hz : float
        Binary pattern rate of the simulated unit.
    memory_patterns : int
        Patterns the unit's memory holds.
    """

    def __init__(self, serial: str = "OL490-SIM", *, present: bool = True, binary_rate_hz: float = 16000.0,
                 memory_patterns: int = 1000):
        self.serial, self.present = serial, present
        self.binary_rate_hz, self.memory_patterns = binary_rate_hz, memory_patterns
        self.connected = False
        self.calibration: int | None = None
        self.bits = 6
        self.shown = np.zeros(COLUMNS, np.int64)
        self.sequence: np.ndarray | None = None
        self.running = False
        self.steps = 0
        self.fail_calls: dict[str, str] = {}
        self.calls: list[str] = []

    def _enter(self, name: str) -> None:
        self.calls.append(name)
        if name in self.fail_calls:
            raise SdkException(self.fail_calls[name])
        if name != "connect" and not self.connected:
            raise SdkException("OL490 is not connected")

    def unplug(self) -> None:
        """The unit goes away: every later call fails and it reports itself not connected."""
        self.present = self.connected = self.running = False

    # ---- the SDK calls -----------------------------------------------------------------------------------------------
    def connect(self, serial=""):
        self._enter("connect")
        self.connected = self.present and serial in ("", self.serial)
        return self.connected

    def disconnect(self):
        self.calls.append("disconnect")
        self.connected = self.running = False

    def is_connected(self):
        return self.connected

    def load_calibration(self, slit):
        self._enter("load_calibration")
        if slit not in SLITS:
            raise SdkException(f"no stored calibration for slit {slit}; slits are 1 to 4")
        self.calibration = int(slit)

    def set_grey_depth(self, bits):
        self._enter("set_grey_depth")
        if bits not in GREY_BITS:
            raise SdkException(f"grey depth {bits} bit is not 1 to 6")
        if self.running:
            raise SdkException("stop the sequence before changing the grey depth")
        self.bits = int(bits)

    def max_frame_rate(self, bits):
        self._enter("max_frame_rate")
        if bits not in GREY_BITS:
            raise SdkException(f"grey depth {bits} bit is not 1 to 6")
        return self.binary_rate_hz / (2 ** int(bits) - 1)

    def _levels(self, patterns) -> np.ndarray:
        p = np.asarray(patterns)
        if p.shape[-1] != COLUMNS or not np.issubdtype(p.dtype, np.integer):
            raise SdkException(f"a pattern is {COLUMNS} integer column levels, got {p.shape} {p.dtype}")
        if p.min() < 0 or p.max() > 2 ** self.bits - 1:
            raise SdkException(f"column level out of range 0 to {2 ** self.bits - 1} at {self.bits} bit")
        if self.calibration is None:
            raise SdkException("no calibration loaded")
        return p.astype(np.int64)

    def send_pattern(self, levels):
        self._enter("send_pattern")
        self.running = False
        self.shown = self._levels(levels).reshape(COLUMNS)

    def load_sequence(self, patterns):
        self._enter("load_sequence")
        p = self._levels(patterns)
        if p.ndim != 2 or not 1 <= p.shape[0] <= self.memory_patterns:
            raise SdkException(f"a sequence is 1 to {self.memory_patterns} patterns, got {p.shape}")
        self.running = False
        self.sequence = p

    def start_sequence(self, triggered=True):
        self._enter("start_sequence")
        if self.sequence is None:
            raise SdkException("no sequence in memory")
        self.running, self.steps = True, 0
        self.shown = np.zeros(COLUMNS, np.int64)

    def stop_sequence(self):
        self._enter("stop_sequence")
        self.running = False
        self.shown = np.zeros(COLUMNS, np.int64)

    def sequence_steps(self):
        self._enter("sequence_steps")
        return self.steps

    def sequence_running(self):
        self._enter("sequence_running")
        return self.running

    # ---- the trigger input (the camera's strobe on the bench) --------------------------------------------------------
    def trigger(self) -> int:
        """One edge on the trigger input: the next pattern of a running sequence (-1 if not running)."""
        if not (self.connected and self.running):
            return -1
        k = self.steps % self.sequence.shape[0]
        self.steps += 1
        self.shown = self.sequence[k]
        return k
