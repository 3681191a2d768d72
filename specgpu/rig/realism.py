"""The imperfections of a real bench, for the twin: the ``[realism]`` and ``[drift]`` tables and the profiles.

A real rig differs from the planner's model in many small ways. Each is a key of the ``[realism]`` table; the
``[twin] profile`` key picks every default at once: ``"ideal"`` (the default: every effect off, the twin is the
model) or ``"lab"`` (every effect on at a typical magnitude for a xenon / grating / DMD source and a
machine-vision CMOS camera). Keys written in ``[realism]`` override the profile's value::

    [twin]
    profile = "lab"
    [realism]
    stray_light_fraction = 0.01      # this bench is worse than typical
    [drift]                          # the change since calibration (time, not set-up: not in the fingerprint)
    lamp_cct_K = -200
    lamp_output = -0.03
    cut_on_nm = 5

Typical ("lab") magnitudes and where they come from:

=============================  ========  ==================================================================
key                            lab       source
=============================  ========  ==================================================================
lamp_output_drift_per_hour     -0.005    xenon short-arc lamps after warm-up: 0.1-1 %/h output drift
                                         (Hamamatsu / Excelitas xenon lamp data sheets: "output stability")
lamp_cct_drift_K_per_hour      -20       arc wander and electrode wear shift a xenon arc's colour by tens
                                         of K per hour of running (lamp data sheets; CIE 63 on lamp ageing)
stray_light_fraction           0.003     single-grating monochromators: 1e-3 to 1e-2 of the in-band power
                                         scattered broadband (ASTM E387 stray-light ratios of grating
                                         instruments)
dmd_off_state                  0.001     DMD contrast ratio about 1000:1 (TI DLP9000 / DLP6500 data sheets),
                                         off-state plus diffraction background of every column
grating_ripple                 0.015     +-1-2 % ripple of a ruled grating's efficiency (Wood's anomalies,
                                         grating makers' efficiency curves)
grating_ripple_period_nm       37        ripple period (assumed, a few tens of nm)
sensor_ripple                  0.02      +-2-3 % thin-film interference ripple in CMOS quantum efficiency
                                         (cover glass and micro-lens stack; EMVA 1288 QE curves)
sensor_ripple_period_nm        23        (assumed; interference fringes of a few-um stack)
vignetting                     0.06      relative fall-off at the field corner of a C-mount lens at f/8
                                         (natural cos^4 fall-off at the lens's field angle)
field_colour                   0.03      relative change of the corner/centre ratio from 550 nm to the ends
                                         of 400-700 nm (a light guide's output is bluer on axis: chromatic
                                         spot profile of fibre/guide illuminators)
blur_px                        0.7       Gaussian sigma (px) of the lens point spread at f/8 (Airy radius
                                         2.44 lambda N = 11 um at 560 nm, about one 9.9 um pixel)
lateral_ca_px                  0.6       lateral colour at the field corner between 400 and 700 nm of a
                                         machine-vision lens (lens makers' MTF / distortion sheets: 0.5-2 px)
ambient_lux                    3         a darkened lab: monitor glow and door gaps, 1-10 lux
nonlinearity                   0.01      compression at full well: EMVA 1288 linearity error of CMOS
                                         cameras is 0.5-1 %
white_error                    -0.01     true white reflectance relative to its certificate: a sintered-PTFE
                                         standard is certified to +-1 % and loses 1 % with handling / UV
slit_flat_top                  0.6       box width (relative to the FWHM) of the slit function: the image of a
                                         rectangular entrance slit blurred by the optics is flat-topped
slit_fwhm_slope                0.08      relative change of the band's FWHM per 100 nm (grating dispersion
                                         varies with the diffraction angle, cos(beta) in the grating equation)
column_bow_nm                  1.5       departure of the column-wavelength map from a straight line at mid
                                         range (the grating equation is linear in sin(beta), not in position)
=============================  ========  ==================================================================

The rig's own clock (:class:`specgpu.rig.twin.TwinRig` ``clock_start_s``) runs on from calibration to capture:
the drifts per hour act on it, and ``[twin] capture_delay_s`` (lab: 1800 s) is the time between the end of a
calibration and the start of a capture.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

from specgpu.core.validate import check_number

__all__ = ["Realism", "Drift", "PROFILES", "profile_realism"]

PROFILES = ("ideal", "lab")

# name -> (low, high) physical range
_RANGES = {
    "lamp_output_drift_per_hour": (-0.2, 0.2),
    "lamp_cct_drift_K_per_hour": (-500.0, 500.0),
    "stray_light_fraction": (0.0, 0.2),
    "dmd_off_state": (0.0, 0.1),
    "grating_ripple": (0.0, 0.2),
    "grating_ripple_period_nm": (2.0, 500.0),
    "sensor_ripple": (0.0, 0.2),
    "sensor_ripple_period_nm": (2.0, 500.0),
    "vignetting": (0.0, 0.8),
    "field_colour": (-0.5, 0.5),
    "blur_px": (0.0, 10.0),
    "lateral_ca_px": (-10.0, 10.0),
    "ambient_lux": (0.0, 1000.0),
    "nonlinearity": (0.0, 0.2),
    "white_error": (-0.2, 0.2),
    "slit_flat_top": (0.0, 0.9),
    "slit_fwhm_slope": (-0.5, 0.5),
    "column_bow_nm": (-20.0, 20.0),
}


@dataclass(frozen=True)
class Realism:
    """The bench's imperfections (``[realism]`` table); every field 0 (the ideal twin) by default.

    See the module docstring for each key's meaning, its lab magnitude and the source of that magnitude.
    Ranges (a value outside is a one-line error naming the key): drifts per hour within +-0.2 (output) and
    +-500 K; stray light [0, 0.2]; off-state [0, 0.1]; ripples [0, 0.2] with periods [2, 500] nm; vignetting
    [0, 0.8]; field colour +-0.5; blur [0, 10] px; lateral colour +-10 px; ambient [0, 1000] lux; non-linearity
    [0, 0.2]; white error +-0.2; slit flat top [0, 0.9]; FWHM slope +-0.5 per 100 nm; bow +-20 nm.
    """

    lamp_output_drift_per_hour: float = 0.0
    lamp_cct_drift_K_per_hour: float = 0.0
    stray_light_fraction: float = 0.0
    dmd_off_state: float = 0.0
    grating_ripple: float = 0.0
    grating_ripple_period_nm: float = 37.0
    sensor_ripple: float = 0.0
    sensor_ripple_period_nm: float = 23.0
    vignetting: float = 0.0
    field_colour: float = 0.0
    blur_px: float = 0.0
    lateral_ca_px: float = 0.0
    ambient_lux: float = 0.0
    nonlinearity: float = 0.0
    white_error: float = 0.0
    slit_flat_top: float = 0.0
    slit_fwhm_slope: float = 0.0
    column_bow_nm: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            lo, hi = _RANGES[f.name]
            object.__setattr__(self, f.name, check_number(f"realism.{f.name}", getattr(self, f.name), low=lo, high=hi))

    @property
    def any(self) -> bool:
        """Whether any effect is on (periods alone do nothing)."""
        ideal = Realism()
        return any(getattr(self, f.name) != getattr(ideal, f.name) for f in fields(self) if "period" not in f.name)

    def only(self, name: str) -> "Realism":
        """The ideal bench with one effect kept at this value (the error budget's 'one effect alone')."""
        if name not in _RANGES:
            raise ValueError(f"unknown realism effect {name!r}; valid: {', '.join(_RANGES)}")
        keep = {name: getattr(self, name)}
        for period in ("grating_ripple_period_nm", "sensor_ripple_period_nm"):
            keep[period] = getattr(self, period)
        return replace(Realism(), **keep)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


#: The lab profile: every effect on at its typical magnitude (module docstring for the sources).
LAB = Realism(lamp_output_drift_per_hour=-0.005, lamp_cct_drift_K_per_hour=-20.0, stray_light_fraction=0.003,
              dmd_off_state=0.001, grating_ripple=0.015, sensor_ripple=0.02, vignetting=0.06, field_colour=0.03,
              blur_px=0.7, lateral_ca_px=0.6, ambient_lux=3.0, nonlinearity=0.01, white_error=-0.01,
              slit_flat_top=0.6, slit_fwhm_slope=0.08, column_bow_nm=1.5)

#: The time (s) between a calibration's end and a capture's start, per profile.
CAPTURE_DELAY_S = {"ideal": 0.0, "lab": 1800.0}


def profile_realism(profile: str) -> Realism:
    """The :class:`Realism` of a profile name ("ideal" or "lab")."""
    if profile not in PROFILES:
        raise ValueError(f"twin.profile must be one of {', '.join(PROFILES)}, got {profile!r}")
    return LAB if profile == "lab" else Realism()


@dataclass(frozen=True)
class Drift:
    """The change of the light since calibration (``[drift]`` table): time, not set-up, so it is left out of the
    rig fingerprint (a bundle stays valid; the drift is what capture must correct).

    Attributes
    ----------
    lamp_cct_K : float
        Change of the lamp's colour temperature, K, in [-1500, 1500] (a xenon arc changes by a few hundred K
        over its life; beyond that the lamp is another lamp).
    lamp_output : float
        Relative change of the lamp's output, in [-0.5, 0.5] (a lamp that lost half its output is replaced).
    cut_on_nm : float
        Shift of the light guide's cut-on edge, nm, in [-30, 30] (liquid guides solarize and warm up: a few nm).
    """

    lamp_cct_K: float = 0.0
    lamp_output: float = 0.0
    cut_on_nm: float = 0.0

    def __post_init__(self):
        check_number("drift.lamp_cct_K", self.lamp_cct_K, low=-1500, high=1500)
        check_number("drift.lamp_output", self.lamp_output, low=-0.5, high=0.5)
        check_number("drift.cut_on_nm", self.cut_on_nm, low=-30, high=30)
        for f in fields(self):
            object.__setattr__(self, f.name, float(getattr(self, f.name)))

    @property
    def any(self) -> bool:
        return any(getattr(self, f.name) != 0 for f in fields(self))

    def to_dict(self) -> dict:
        return asdict(self)
