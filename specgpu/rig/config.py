"""The rig description: every physical parameter of the twin, with the paper's values as defaults, from TOML.

A rig TOML has up to six tables; every key is optional and defaults to the paper's rig::

    [light]                      # LightParameters: lamp, grating, DMD, spot, timing, fluctuation ...
    lamp = "xenon"               # or "kinoton-75p", or a two-column CSV (wavelength nm, value)
                                 # kind = "led" (LEDParameters: preset = "led12", spectra CSV, PWM ...) or
                                 # kind = "ol490" (OL490Parameters: grey_bits, slit): specgpu.rig.lights
    illuminance_lux = 15000
    [camera]                     # CameraParameters: sensitivity (CSV), ROI, bit depth, noise, optics, timing;
                                 # preset = "cmv4000" | "imx250" | "imx304" starts from a sensor (rig/sensors.py)
    sensitivity = "cmos"
    bit_depth = 10
    [scene]
    source = "colorchecker"      # "colorchecker", "white", "natural", "natural:coffee" or a .exr / .npz / .hdr cube
    [twin]
    seed = 0
    pacing = "free"              # "free": as fast as it renders; "paced": at the camera's frame rate
    [faults]                     # FaultRates: for drills; all off by default
    drop_rate = 0.0
    [spectroradiometer]          # SpectroradiometerParameters: the instrument of the spectral feedback loop
    bandwidth_nm = 5.0
    [realism]                    # Realism: the bench's imperfections; defaults from [twin] profile
    stray_light_fraction = 0.003
    [drift]                      # Drift: the light's change since calibration (not in the rig fingerprint)
    lamp_cct_K = -200
    [motion]                     # MotionParameters: the world moves during the capture (specgpu.rig.motion)
    velocity_px_per_frame = [3.0, 0.0]

``[twin] profile`` is ``"ideal"`` (default: the twin is the planner's model) or ``"lab"`` (every imperfection on
at a typical magnitude, :mod:`specgpu.rig.realism`); ``[twin] capture_delay_s`` is the time from a calibration's
end to a capture's start on the rig's clock (the profile's by default: 0 ideal, 1800 s lab).

Relative file paths (lamp, sensitivity, scene) are resolved against the TOML's folder. Unknown tables or keys,
wrong types and out-of-range values are errors that name the file and the key.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from specgpu.core.validate import check_number
from specgpu.rig.camera import CameraParameters
from specgpu.rig.light import LightParameters
from specgpu.rig.lights import light_from_table
from specgpu.rig.motion import MotionParameters, motion_from_table
from specgpu.rig.realism import CAPTURE_DELAY_S, PROFILES, Drift, Realism, profile_realism
from specgpu.rig.scene import _NATURAL_IMAGES
from specgpu.rig.sensors import PRESETS, expand_preset
from specgpu.rig.spectroradiometer import SpectroradiometerParameters
from specgpu.rig.tables import build_table

__all__ = ["FaultRates", "RigDescription", "load_rig", "rig_from_dict", "dump_rig", "PACING"]

PACING = ("free", "paced")


@dataclass(frozen=True)
class FaultRates:
    """Per-frame fault probabilities for drills (``[faults]`` table); all off by default.

    Attributes
    ----------
    drop_rate : float
        Probability that a frame is exposed but never delivered, in [0, 1).
    duplicate_rate : float
        Probability that a delivered frame is delivered twice, in [0, 1).
    missed_trigger_rate : float
        Probability that the light misses a frame's trigger (frame lit by the previous pattern), in [0, 1).
    jitter_s : float
        Standard deviation of the exposure start times, s, >= 0 (truncated at 2 sigma).
    """

    drop_rate: float = 0.0
    duplicate_rate: float = 0.0
    missed_trigger_rate: float = 0.0
    jitter_s: float = 0.0

    def __post_init__(self):
        for name in ("drop_rate", "duplicate_rate", "missed_trigger_rate"):
            check_number(f"faults.{name}", getattr(self, name), low=0, high=0.999)
        check_number("faults.jitter_s", self.jitter_s, low=0, high=1)

    @property
    def any(self) -> bool:
        return any(getattr(self, f.name) > 0 for f in fields(self))


@dataclass(frozen=True)
class RigDescription:
    """A whole rig: light, camera, scene, twin settings and fault rates.

    Attributes
    ----------
    light : LightParameters, LEDParameters or OL490Parameters
        By ``[light] kind`` (:mod:`specgpu.rig.lights`).
    camera : CameraParameters
    scene : str
        Built-in scene name (``"colorchecker"``, ``"white"``, ``"natural"``) or a cube file path.
    seed : int
        Seed of the twin (camera fixed pattern, noise, light fluctuation), >= 0.
    pacing : str
        ``"free"`` (frames as fast as the twin renders) or ``"paced"`` (at the camera's frame rate).
    faults : FaultRates
    spectroradiometer : SpectroradiometerParameters
    source : str
        Where the description came from (a file path or ``"<defaults>"``), for messages.
    hardware : dict
        The ``[hardware]`` table naming real devices (empty: the digital twin). It is kept as given here and
        checked by :class:`specgpu.hardware.rig.HardwareConfig` where it is used (the rig model never imports
        the drivers); relative file paths in it resolve against ``base_dir``.
    base_dir : str
        Folder of the TOML file ("" for descriptions not read from a file).
    """

    light: LightParameters = field(default_factory=LightParameters)
    camera: CameraParameters = field(default_factory=CameraParameters)
    scene: str = "colorchecker"
    seed: int = 0
    pacing: str = "free"
    faults: FaultRates = field(default_factory=FaultRates)
    source: str = "<defaults>"
    spectroradiometer: SpectroradiometerParameters = field(default_factory=SpectroradiometerParameters)
    hardware: dict = field(default_factory=dict)
    base_dir: str = field(default="", compare=False)  # provenance, like source: not part of the rig
    profile: str = "ideal"
    realism: Realism | None = None  # None: the profile's
    drift: Drift = field(default_factory=Drift)
    capture_delay_s: float | None = None
    motion: MotionParameters = field(default_factory=MotionParameters)

    def __post_init__(self):
        check_number("twin.seed", self.seed, low=0, high=2**63 - 1, integer=True)
        if self.pacing not in PACING:
            raise ValueError(f"twin.pacing must be one of {', '.join(PACING)}, got {self.pacing!r}")
        if self.profile not in PROFILES:
            raise ValueError(f"twin.profile must be one of {', '.join(PROFILES)}, got {self.profile!r}")
        if self.realism is None:
            object.__setattr__(self, "realism", profile_realism(self.profile))
        if self.capture_delay_s is not None:
            check_number("twin.capture_delay_s", self.capture_delay_s, low=0, high=1e7)

    @property
    def capture_delay(self) -> float:
        """Seconds on the rig's clock from the end of a calibration to the start of a capture."""
        return CAPTURE_DELAY_S[self.profile] if self.capture_delay_s is None else float(self.capture_delay_s)

    def to_dict(self) -> dict:
        """The description as nested plain data (the TOML tables), e.g. for a capture's metadata."""
        return {
            "light": dataclasses.asdict(self.light),
            "camera": dataclasses.asdict(self.camera),
            "scene": {"source": self.scene},
            "twin": {"seed": self.seed, "pacing": self.pacing, "profile": self.profile,
                     **({} if self.capture_delay_s is None else {"capture_delay_s": float(self.capture_delay_s)})},
            "faults": dataclasses.asdict(self.faults),
            "spectroradiometer": dataclasses.asdict(self.spectroradiometer),
            **({"hardware": dict(self.hardware)} if self.hardware else {}),
            **({"realism": self.realism.to_dict()} if self.realism != profile_realism(self.profile) else {}),
            **({"drift": self.drift.to_dict()} if self.drift.any else {}),
            **({"motion": self.motion.to_dict()} if self.motion != MotionParameters() else {}),
        }


_TABLES = ("light", "camera", "scene", "twin", "faults", "spectroradiometer", "hardware", "realism", "drift", "motion")
_TWIN_KEYS = ("seed", "pacing", "profile", "capture_delay_s")


def rig_from_dict(data: dict, *, source: str = "<dict>", base_dir=None) -> RigDescription:
    """Build a :class:`RigDescription` from the TOML tables as a dict (unknown tables or keys are errors)."""
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a rig description must be a table, got {type(data).__name__}")
    base = Path(base_dir) if base_dir is not None else None
    for table, value in data.items():
        if table not in _TABLES:
            raise ValueError(f"{source}: unknown table [{table}]; valid tables: {', '.join(_TABLES)}")
        if not isinstance(value, dict):
            raise ValueError(f"{source}: [{table}] must be a table, got {value!r}")
    light = light_from_table(data.get("light", {}), source, base)  # by [light] kind: dmd, led, ol490
    try:  # [camera] preset = "cmv4000": the preset's values under the keys given (specgpu.rig.sensors)
        camera_table = expand_preset(data.get("camera", {}))
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None
    camera = build_table(CameraParameters, camera_table, "camera", source, base)
    scene_table = dict(data.get("scene", {}))
    extra = set(scene_table) - {"source"}
    if extra:
        raise ValueError(f"{source}: unknown key scene.{sorted(extra)[0]}; valid keys: source")
    scene = scene_table.get("source", "colorchecker")
    if not isinstance(scene, str):
        raise ValueError(f"{source}: scene.source must be a string, got {scene!r}")
    if scene.startswith("natural:"):

        if scene[8:] not in _NATURAL_IMAGES:
            raise ValueError(f"{source}: scene.source {scene!r}: unknown image; valid: {', '.join(_NATURAL_IMAGES)}")
    elif scene not in ("colorchecker", "white", "natural"):
        p = Path(scene)
        scene = str(p if p.is_absolute() or base is None else base / p)
        if not Path(scene).is_file():
            raise ValueError(f"{source}: scene.source file not found: {scene!r}")
    twin = dict(data.get("twin", {}))
    extra = set(twin) - set(_TWIN_KEYS)
    if extra:
        raise ValueError(f"{source}: unknown key twin.{sorted(extra)[0]}; valid keys: {', '.join(_TWIN_KEYS)}")
    profile = twin.get("profile", "ideal")
    if profile not in PROFILES:
        raise ValueError(f"{source}: twin.profile must be one of {', '.join(PROFILES)}, got {profile!r}")
    delay = twin.get("capture_delay_s")
    if delay is not None and (isinstance(delay, bool) or not isinstance(delay, (int, float))):
        raise ValueError(f"{source}: twin.capture_delay_s must be a number, got {delay!r}")
    table = data.get("realism", {})
    given = build_table(Realism, table, "realism", source, base)
    realism = dataclasses.replace(profile_realism(profile), **{k: getattr(given, k) for k in table})
    drift = build_table(Drift, data.get("drift", {}), "drift", source, base)
    motion = motion_from_table(data.get("motion", {}), source)
    if motion.object and motion.object not in ("colorchecker", "white", "natural") \
            and not motion.object.startswith("natural:"):
        p = Path(motion.object)
        obj = str(p if p.is_absolute() or base is None else base / p)
        if not Path(obj).is_file():
            raise ValueError(f"{source}: motion.object file not found: {obj!r}")
        motion = dataclasses.replace(motion, object=obj)
    seed = twin.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"{source}: twin.seed must be an integer, got {seed!r}")
    pacing = twin.get("pacing", "free")
    faults = build_table(FaultRates, data.get("faults", {}), "faults", source, base)
    meter = build_table(SpectroradiometerParameters, data.get("spectroradiometer", {}), "spectroradiometer", source,
                        base)
    hardware = dict(data.get("hardware", {}))
    for key, value in hardware.items():
        if isinstance(value, (dict, list)):
            raise ValueError(f"{source}: hardware.{key} must be a string or a number, got {value!r}")
    try:
        return RigDescription(light=light, camera=camera, scene=scene, seed=seed, pacing=pacing, faults=faults,
                              source=source, spectroradiometer=meter, hardware=hardware,
                              base_dir=str(base) if base is not None else "", profile=profile, realism=realism,
                              drift=drift, capture_delay_s=None if delay is None else float(delay),
                              motion=motion)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def load_rig(path: str | os.PathLike[str] | None = None) -> RigDescription:
    """Read a rig TOML (``None``: the paper's rig with every default).

    Raises
    ------
    ValueError
        Naming the file: missing file, TOML syntax errors (with line), unknown tables or keys, wrong types,
        out-of-range values, missing CSV curves.
    """
    if path is None:
        return RigDescription()
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ValueError(f"{path}: rig description not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: invalid TOML ({exc})") from None
    except UnicodeDecodeError as exc:  # a binary file
        raise ValueError(f"{path}: invalid TOML (not UTF-8 text at byte {exc.start}: not a TOML text file)") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read rig description ({exc})") from None
    return rig_from_dict(data, source=str(path), base_dir=path.parent)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)  # shortest repr: reads back bit-identical
    if isinstance(value, str):  # a TOML basic string: quote, backslash and control characters escaped
        return '"' + "".join(f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else "\\" + c if c in '"\\'
                             else c for c in value) + '"'
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")


def dump_rig(description: RigDescription | None = None, *, hardware_defaults: dict | None = None) -> str:
    """The rig description as TOML text, every key ``load_rig`` reads written out (the paper's defaults if
    ``None``).

    ``load_rig`` reads it back to an equal description: a starting point for a rig file, and a record of the
    exact rig a capture was made with. Keys whose value comes from elsewhere are written as comments holding the
    value in force, so the text still round-trips and an edit of ``[twin] profile`` still acts: ``[camera]
    preset`` (its values are written out as the camera keys), ``[twin] capture_delay_s`` when it follows the
    profile, each ``[realism]`` key at the profile's value, and the ``[hardware]`` keys of a twin rig (an
    uncommented ``[hardware]`` key drives real devices) when ``hardware_defaults`` gives them: the rig sits below
    the hardware room and does not know its devices, so the caller passes
    ``{f.name: f.default for f in dataclasses.fields(specgpu.hardware.HardwareConfig)}``.

    >>> rig = load_rig(None)
    >>> "[light]" in dump_rig(rig)
    True
    """
    d = description if description is not None else RigDescription()
    data = d.to_dict()
    lines = [f"# specgpu rig description ({d.source})"]

    def table(name, values, commented=(), note=""):
        lines.append(f"\n[{name}]" + (f"  # {note}" if note else ""))
        lines.extend(f"{key} = {_toml_value(value)}" for key, value in values.items())
        lines.extend(f"# {key} = {_toml_value(value)}" for key, value in dict(commented).items())

    for name in ("light", "camera", "scene"):
        table(name, data[name])
        if name == "camera":

            lines.insert(len(lines) - len(data[name]), "# preset = " + " | ".join(_toml_value(p) for p in PRESETS)
                         + "  # a sensor's data-sheet values for every camera key not given")
    twin = {k: data["twin"][k] for k in _TWIN_KEYS if k in data["twin"]}
    table("twin", twin, {} if "capture_delay_s" in twin else {"capture_delay_s": d.capture_delay},
          "" if "capture_delay_s" in twin else "capture_delay_s unset: the profile's")
    table("faults", data["faults"])
    table("spectroradiometer", data["spectroradiometer"])
    profile = profile_realism(d.profile).to_dict()
    own = d.realism.to_dict()
    table("realism", {k: v for k, v in own.items() if v != profile[k]},
          {k: v for k, v in own.items() if v == profile[k]}, f"commented keys: the {d.profile} profile's values")
    table("drift", d.drift.to_dict(), note="the light's change since calibration (not in the rig fingerprint)")
    still = MotionParameters().to_dict()
    own = d.motion.to_dict()
    table("motion", {k: v for k, v in own.items() if v != still[k]}, {k: v for k, v in own.items() if v == still[k]},
          "the world moves during the capture; commented keys: a still world")
    if d.hardware:
        table("hardware", d.hardware)
    else:
        table("hardware", {}, hardware_defaults or {}, "empty: the digital twin; any key here drives real devices")
    return "\n".join(lines) + "\n"
