"""Measurement plans: the illuminant sequence to project and the decoder A that reads the frames back.

A :class:`Plan` is what the host decides before a capture: K DMD patterns (mirror
counts, within the light's limits), one exposure chosen so the brightest frame on a white uses most of the
camera's range, the decoder ``A`` (B x K) that :func:`specgpu.engine.linear_map.apply_linear` applies per pixel as
``y = A (o - dark) * gain``, what ``y`` means (reflectance at which wavelengths, or XYZ / camera RGB under which
illuminant and observer), and the hash of the calibration bundle whose model it was designed with.

Every plan is designed on the calibration's forward model (:class:`specgpu.calibration.bundle.CalibrationBundle`:
``O = F R``, F from the quantized patterns, the lamp, the slit and the V estimate), so the decoder accounts for
what the patterns really emit, not for what was asked of them. Methods (:data:`PLAN_METHODS`):

- ``narrowband`` (eq. (2)-(4)): K bands of ``bandwidth_nm`` at ``centres``, every mirror on; ``A = diag(1/c_i)``
  with ``c_i`` the model output of band i on a reflectance of 1 (eq. (3)). 31 bands at 10 nm or 61 at 5 nm.
- ``reciprocal``: the same bands, each column's level proportional to ``1 / (lamp V)`` with one common factor,
  so every band gives the same output on a white: the frame *is* the reflectance (``A`` is a multiple of I).
- ``biased`` (eq. (5), (6)): frames ``I_j V = S_j + K`` for the first m basis functions plus ``I_K V = K``;
  ``sigma_j = O_j / a_j - K O_K / a_K``. m + 1 frames.
- ``symmetric``: ``S_j = S_j+ - S_j-`` projected separately (the first function is non-negative: one frame);
  ``sigma_j = O_j+ / a_j+ - O_j- / a_j-``. 2m - 1 frames.
  For both basis designs, with ``D`` the paper's combination (m x K), ``A = Phi_out (D F Phi)^-1 D``: exactly the
  paper's decoder when the frames are ideal, and exact for every spectrum in the basis span when they are not
  (quantized mirrors, slit blur): ``D F Phi`` is the m x m matrix the ideal design makes the identity.
- ``tristimulus`` (eq. (7)-(11)): three frames with ``I V`` fitted (non-negative column levels, bounded least
  squares over the available column spectra) to ``E_T x``, ``E_T y``, ``E_T z`` for any illuminant and
  observer; ``A = diag(k)`` with k making a perfect white exact (``correction="diagonal"``, the paper's), or a
  full 3 x 3 exact on the span of a basis (``correction="span"``).
- ``camera``: a camera simulator: target responses ``E R_c`` (e.g. a real camera's RGB sensitivities that
  colour-science ships) under an illuminant, negative lobes split into two frames as in the symmetric design.
- ``steady``: one pattern emitting a target spectral irradiance (spectral rendering); ``A = 1 / c_white``.

Plans are saved as versioned, hashed ``.npz`` files (:func:`save_plan`); loading refuses an unknown version, a
corrupt file or, given the calibration, a plan made from another calibration (stale), each in one line naming the
file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from specgpu.calibration.bundle import DEFAULT_MAX_EXPOSURE_S
from specgpu.core.numerics import fit_levels
from specgpu.io.tables import content_hash, load_npz, save_npz
from specgpu.planning.basis import BasisTable
from specgpu.rig.scene import interpolation_matrix
from specgpu.core.spectra import DEFAULT_CMFS, OBSERVERS, XYZ_weights, resolve_cmfs, resolve_illuminant_sd

__all__ = [
    "Plan",
    "PLAN_METHODS",
    "make_plan",
    "plan_narrowband",
    "plan_reciprocal_narrowband",
    "plan_biased_basis",
    "plan_symmetric_basis",
    "plan_tristimulus",
    "plan_camera_simulator",
    "plan_steady_state",
    "save_plan",
    "load_plan",
    "camera_sensitivities",
]

PLAN_FORMAT = "specgpu.plan"
PLAN_VERSION = 1
OUTPUTS = ("reflectance", "XYZ", "RGB", "relative")


@dataclass(frozen=True)
class Plan:
    """An illuminant sequence and its decoder.

    Attributes
    ----------
    method : str
        Key of :data:`PLAN_METHODS` that made it.
    patterns : numpy.ndarray
        (K, C) int32 mirror counts in [0, rows].
    target_spectra : numpy.ndarray
        (K, G) the spectral irradiance (W m^-2 nm^-1, on ``light_wavelengths``) each frame was aimed at.
    light_wavelengths : numpy.ndarray
        (G,) nm.
    exposure_s : float
        Exposure of every frame, s (the twin and the paper's camera use one exposure per sequence; the patterns
        carry the per-frame intensity).
    A : numpy.ndarray
        (B, K) float64 decoder: ``y = A (o - dark) * gain``.
    output : str
        ``"reflectance"`` (B wavelengths), ``"XYZ"`` (Y = 1 for the perfect white), ``"RGB"`` (camera simulator,
        G = 1 for the perfect white) or ``"relative"`` (signal relative to a perfect white).
    output_wavelengths : numpy.ndarray
        (B,) nm for reflectance outputs, empty otherwise.
    output_labels : tuple of str
        A name per output (``"550nm"``, ``"X"`` ...).
    illuminant, observer : str
        For XYZ / RGB outputs: the illuminant and observer (or camera) they are for; empty otherwise.
    calibration : str
        Hash of the calibration bundle the plan was designed with.
    rows : int
        Mirrors per DMD column (the limit the patterns respect).
    min_exposure_s : float
        The light's switch time (the limit the exposure respects).
    expected_level : numpy.ndarray
        (K,) model output of each frame on a perfect white, as a fraction of the camera's range above dark.
    params : dict
        The method's parameters (plain data).
    """

    method: str
    patterns: np.ndarray
    target_spectra: np.ndarray
    light_wavelengths: np.ndarray
    exposure_s: float
    A: np.ndarray
    output: str
    output_wavelengths: np.ndarray
    output_labels: tuple
    illuminant: str
    observer: str
    calibration: str
    rows: int
    min_exposure_s: float
    expected_level: np.ndarray
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        for key in ("patterns", "A", "output_wavelengths", "target_spectra", "light_wavelengths", "expected_level"):
            if np.asarray(getattr(self, key)).dtype.kind not in "biuf":
                raise ValueError(f"plan {key} must hold real numbers, got dtype {np.asarray(getattr(self, key)).dtype}")
        for key in ("exposure_s", "min_exposure_s", "rows"):
            v = getattr(self, key)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(v) or (key == "rows" and (v != int(v) or v < 1)):
                raise ValueError(f"plan {key} must be a finite number{' >= 1' if key == 'rows' else ''}, got {v!r}")
        n = np.asarray(self.patterns)
        if n.ndim != 2 or n.shape[0] < 1:
            raise ValueError(f"plan patterns must be (K, columns), got shape {n.shape}")
        if not np.issubdtype(n.dtype, np.integer):
            if not np.all(np.isfinite(n)) or np.any(n != np.round(n)):
                raise ValueError("plan patterns must be integer mirror counts")
        if n.min() < 0 or n.max() > self.rows:
            raise ValueError(f"plan patterns must lie in [0, {self.rows}] mirrors, got [{n.min()}, {n.max()}]")
        k = n.shape[0]
        a = np.asarray(self.A, np.float64)
        if a.ndim != 2 or a.shape[1] != k or not np.all(np.isfinite(a)):
            raise ValueError(f"plan decoder A must be finite (B, K={k}), got shape {a.shape}")
        if a.size and np.max(np.abs(a)) > np.finfo(np.float32).max:  # the device computes in float32
            raise ValueError(f"plan decoder A must be finite in float32 (|A| <= 3.4e38), got {np.max(np.abs(a)):.3g}")
        if not (self.exposure_s >= self.min_exposure_s - 1e-12 and self.min_exposure_s > 0):
            raise ValueError(f"plan exposure {self.exposure_s * 1e6:.1f} us is below the light's switch time "
                             f"{self.min_exposure_s * 1e6:.0f} us")
        if self.output not in OUTPUTS:
            raise ValueError(f"plan output must be one of {', '.join(OUTPUTS)}, got {self.output!r}")
        ow = np.asarray(self.output_wavelengths, np.float64).reshape(-1)
        if self.output == "reflectance" and ow.size != a.shape[0]:
            raise ValueError(f"a reflectance plan needs {a.shape[0]} output wavelengths, got {ow.size}")
        if len(self.output_labels) != a.shape[0]:
            raise ValueError(f"plan has {a.shape[0]} outputs but {len(self.output_labels)} labels")
        ts = np.asarray(self.target_spectra, np.float64)
        lw = np.asarray(self.light_wavelengths, np.float64)
        if ts.shape != (k, lw.size):
            raise ValueError(f"plan target_spectra must be ({k}, {lw.size}), got {ts.shape}")
        lv = np.asarray(self.expected_level, np.float64).reshape(-1)
        if lv.shape != (k,):
            raise ValueError(f"plan expected_level must be ({k},), got {lv.shape}")
        for key, v in (("patterns", n.astype(np.int32)), ("A", a), ("output_wavelengths", ow),
                       ("target_spectra", ts), ("light_wavelengths", lw), ("expected_level", lv),
                       ("output_labels", tuple(str(x) for x in self.output_labels))):
            object.__setattr__(self, key, v)

    @property
    def K(self) -> int:
        """Number of frames (projections) per sequence."""
        return self.patterns.shape[0]

    def _arrays(self) -> dict:
        return {"patterns": self.patterns, "target_spectra": self.target_spectra,
                "light_wavelengths": self.light_wavelengths, "A": self.A,
                "output_wavelengths": self.output_wavelengths, "expected_level": self.expected_level}

    def _meta(self) -> dict:
        return json.loads(json.dumps({
            "method": self.method, "exposure_s": float(self.exposure_s), "output": self.output,
            "output_labels": list(self.output_labels), "illuminant": self.illuminant, "observer": self.observer,
            "calibration": self.calibration, "rows": int(self.rows), "min_exposure_s": float(self.min_exposure_s),
            "params": self.params}))

    @cached_property
    def hash(self) -> str:
        """Content hash (SHA-256 hex) that a capture records."""
        return content_hash(self._arrays(), self._meta())

    def rig_description(self, description):
        """The rig description to capture this plan with: the camera at the plan's exposure, its frame rate
        lowered if the exposure plus the light's switch time needs a longer period (never raised).

        Parameters
        ----------
        description : specgpu.rig.config.RigDescription

        Returns
        -------
        RigDescription
        """
        from dataclasses import replace

        cam = description.camera
        rate = min(cam.frame_rate_hz, 1.0 / (self.exposure_s + description.light.switch_time_s + 1e-6))
        return replace(description, camera=replace(cam, exposure_s=float(self.exposure_s), frame_rate_hz=rate))

    def outputs_to_XYZ(self, illuminant="D65", observer=None) -> np.ndarray:
        """(3, B) matrix C with XYZ = C . y for this plan's outputs y (Y = 1 for the white): the colour-matching
        weights of ``observer`` (None: :meth:`resolve_observer`'s default) under ``illuminant`` for reflectance
        outputs, the identity for a tristimulus plan made for the same illuminant and observer; any other output
        has no XYZ (ValueError)."""
        if self.output == "reflectance":
            return XYZ_weights(self.output_wavelengths, illuminant, self.resolve_observer(observer))
        if self.output == "XYZ":
            if self.illuminant and self.illuminant.lower() != str(illuminant).lower():
                raise ValueError(f"the plan measures XYZ under {self.illuminant}, not {illuminant}")
            self.resolve_observer(observer)  # refuses another observer than the plan's
            return np.eye(3)
        raise ValueError(f"a {self.output!r} plan ({self.method}) has no XYZ")

    @property
    def measured_illuminant(self) -> str:
        """The illuminant the plan's outputs themselves are relative to: a tristimulus (XYZ) or camera simulator
        (RGB) plan's own; empty for outputs that hold under any illuminant (reflectance, relative signal)."""
        return self.illuminant if self.output in ("XYZ", "RGB") else ""

    def resolve_illuminant(self, illuminant=None, *, name: str = "the plan") -> str:
        """The illuminant of the XYZ, Lab and dE made from this plan's outputs, and the one to record with them.

        Parameters
        ----------
        illuminant : str, optional
            The one asked for; None: the plan's own for a tristimulus or camera plan (:attr:`measured_illuminant`),
            D65 otherwise.
        name : str
            How an error names the plan (its file).

        Raises
        ------
        ValueError
            ``illuminant`` is not the one a tristimulus or camera plan measures under: its outputs would be
            labelled, converted and compared as if taken under another light.
        """
        own = self.measured_illuminant
        if illuminant is None:
            return own or "D65"
        illuminant = str(illuminant)
        if own and own.lower() != illuminant.lower():
            raise ValueError(f"{name} measures {self.output} under illuminant {own}, not {illuminant}: leave the "
                             f"illuminant out to use the plan's, or make a plan for {illuminant}")
        return own or illuminant

    @property
    def measured_observer(self) -> str:
        """The observer the plan's outputs themselves are for: a tristimulus (XYZ) plan's colour-matching
        functions, a camera simulator (RGB) plan's camera; empty for outputs that hold for any observer."""
        return self.observer if self.output in ("XYZ", "RGB") else ""

    def resolve_observer(self, observer=None, *, name: str = "the plan") -> str:
        """The observer of the XYZ, Lab and dE made from this plan's outputs (their reference white is that
        observer's), and the one to record with them; the counterpart of :meth:`resolve_illuminant`.

        Parameters
        ----------
        observer : str, optional
            The one asked for (a name of :data:`OBSERVERS`, in any case); None: the plan's own for a tristimulus
            or camera plan (:attr:`measured_observer`), the CIE 1931 2 degree observer otherwise.
        name : str
            How an error names the plan (its file).

        Raises
        ------
        ValueError
            ``observer`` is no observer with a white-point table, or not the one a tristimulus or camera plan
            measures for: its XYZ would be converted and compared against another observer's white.
        """
        own = self.measured_observer
        if observer is None:
            return own or DEFAULT_CMFS
        asked = str(observer)
        canonical = next((o for o in OBSERVERS if o.lower() == asked.lower()), None)
        if canonical is None:
            raise ValueError(f"observer {asked!r} is not one of {', '.join(OBSERVERS)}")
        if own and own.lower() != canonical.lower():
            raise ValueError(f"{name} measures {self.output} for the {own}, not the {canonical}: leave the "
                             f"observer out to use the plan's, or make a plan for the {canonical}")
        return own or canonical

    def check_calibration(self, bundle, name: str = "plan", calibration_name: str | None = None) -> None:
        """Refuse a plan designed with another calibration than ``bundle`` (stale plan); ``name`` and
        ``calibration_name`` are the files the message names."""
        if self.calibration != bundle.hash:
            current = f"{calibration_name} is" if calibration_name else "the current one is"
            raise ValueError(f"{name} is stale: made from calibration {self.calibration[:12]}, "
                             f"{current} {bundle.hash[:12]}; re-plan")


def save_plan(path, plan: Plan) -> str:
    """Save a plan as a versioned, hashed ``.npz``; return its hash (equal to ``plan.hash``)."""
    return save_npz(path, PLAN_FORMAT, PLAN_VERSION, plan._arrays(), plan._meta())


def load_plan(path, *, calibration=None) -> Plan:
    """Load a plan; refuse an unknown version, a corrupt file or (given the bundle) a stale plan, in one line
    naming the file."""
    arrays, meta, _, digest = load_npz(path, PLAN_FORMAT, (PLAN_VERSION,))
    try:
        meta = dict(meta)
        meta["output_labels"] = tuple(meta["output_labels"])
        plan = Plan(**arrays, **meta)
        same = plan.hash == digest  # the hash re-reads every field: a wrong type fails here too
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise ValueError(f"{path}: invalid plan ({exc})") from None
    if not same:
        raise ValueError(f"{path}: corrupt plan file (content does not match its hash)")
    A = np.asarray(plan.A, np.float64)
    if not np.all(np.isfinite(A)) or (A.size and np.max(np.abs(A)) > 1e30):
        raise ValueError(f"{path}: invalid plan: its decoder A holds NaN, inf or values beyond 1e30 (a hand-made "
                         "or broken plan); re-plan")
    if calibration is not None:
        plan.check_calibration(calibration, str(path))
    return plan


# ---- design helpers -------------------------------------------------------------------------------------------
def _on_grid(values, wavelengths, grid) -> np.ndarray:
    """Linear interpolation onto the light's grid, zero outside the given range (no light asked for there)."""
    return np.interp(grid, wavelengths, values, left=0.0, right=0.0)


def _quantize(levels, rows) -> np.ndarray:
    return np.clip(np.rint(np.asarray(levels) * rows), 0, rows).astype(np.int32)


def _design_frames(bundle, products) -> tuple[np.ndarray, np.ndarray]:
    """Patterns whose ``I V`` matches each non-negative (G,) product up to a scale, each using every mirror it
    can (its brightest column full); returns (patterns (K, C), target irradiance (K, G))."""
    pats, targets = [], []
    rho = bundle.responsivity
    for prod in products:
        if not np.any(prod > 0):
            raise ValueError("a frame's target response is zero everywhere")
        f = fit_levels(bundle.system_matrix, prod / prod.max(), upper=None)
        s = 1.0 / f.max()
        pats.append(_quantize(f * s, bundle.rows))
        with np.errstate(divide="ignore", invalid="ignore"):
            targets.append(np.where(rho > 0, prod / prod.max() * s / rho, 0.0))
    return np.array(pats), np.array(targets)


def _choose_exposure(bundle, patterns, level: float, max_exposure_s: float | None) -> tuple[float, np.ndarray]:
    """One exposure for the sequence: the brightest frame on a perfect white at ``level`` of the range above dark,
    within the light's switch time and the frame period; returns (exposure, per-frame levels)."""
    if not 0 < level <= 1:
        raise ValueError(f"level must lie in (0, 1], got {level!r}")
    per_s = bundle.forward_matrix(patterns, bundle.wavelengths, 1.0).sum(axis=1)  # DN/s on reflectance 1
    headroom = bundle.max_code - float(np.mean(bundle.dark))
    longest = DEFAULT_MAX_EXPOSURE_S if max_exposure_s is None else float(max_exposure_s)
    if not longest >= bundle.min_exposure_s:
        raise ValueError(f"max_exposure_s must be >= the light's switch time {bundle.min_exposure_s:g} s")
    t = min(max(level * headroom / per_s.max(), bundle.min_exposure_s), longest)
    levels = per_s * t / headroom
    if levels.max() > 1.0:
        raise ValueError(f"even the light's shortest exposure ({bundle.min_exposure_s * 1e6:.0f} us) saturates a white "
                         f"with these patterns ({levels.max():.2f} x the camera's range): lower the illuminance")
    return t, levels


def _band_masks(bundle, centres, bandwidth):
    cw = bundle.column_wavelengths
    masks = np.stack([np.abs(cw - c) < bandwidth / 2 for c in centres])
    empty = np.flatnonzero(~masks.any(axis=1))
    if empty.size:
        raise ValueError(f"band at {centres[empty[0]]:g} nm holds no DMD column (bandwidth {bandwidth:g} nm)")
    return masks


def _check_centres(centres, step, bandwidth, start, stop):
    if centres is None:
        if not step > 0:
            raise ValueError(f"step_nm must be > 0, got {step!r}")
        centres = np.arange(start, stop + step / 2, step)
    c = np.asarray(centres, np.float64).reshape(-1)
    if c.size < 1 or not np.all(np.isfinite(c)) or np.any(np.diff(c) <= 0):
        raise ValueError("centres must be finite and strictly increasing (nm)")
    bw = float(step if bandwidth is None else bandwidth)
    if not bw > 0:
        raise ValueError(f"bandwidth_nm must be > 0, got {bandwidth!r}")
    return c, bw


def _base(bundle, method, patterns, targets, A, level, max_exposure_s, **kw) -> Plan:
    t, levels = _choose_exposure(bundle, patterns, level, max_exposure_s)
    A = np.asarray(A, np.float64) / t  # A was designed per second of exposure
    kw["params"] = {**kw.get("params", {}), "max_frame_rate_hz": 1.0 / (t + bundle.min_exposure_s)}
    return Plan(method=method, patterns=patterns, target_spectra=targets, light_wavelengths=bundle.wavelengths,
                exposure_s=t, A=A, calibration=bundle.hash, rows=bundle.rows, min_exposure_s=bundle.min_exposure_s,
                expected_level=levels, **kw)


# ---- narrowband ----------------------------------------------------------------------------------------------
def plan_narrowband(bundle, *, centres=None, step_nm: float = 10.0, bandwidth_nm: float | None = None,
                    start_nm: float = 400.0, stop_nm: float = 700.0, level: float = 0.9,
                    max_exposure_s: float | None = None) -> Plan:
    """Narrow-band sequence (eq. (2)-(4)): every mirror on in the columns within ``bandwidth_nm / 2`` of each centre.

    Parameters
    ----------
    bundle : CalibrationBundle
    centres : array_like, optional
        Band centres, nm (default ``start_nm`` to ``stop_nm`` every ``step_nm``: 31 bands at 10 nm, 61 at 5).
    step_nm, bandwidth_nm : float
        Spacing and full width of the bands, nm (width defaults to the spacing).
    level : float
        Fraction of the range above dark the brightest frame reaches on a perfect white, (0, 1].
    max_exposure_s : float, optional
        Longest exposure, s (default :data:`DEFAULT_MAX_EXPOSURE_S`). The capture runs at a frame rate of at
        most ``1 / (exposure + switch time)``, recorded as ``params["max_frame_rate_hz"]``.

    Returns
    -------
    Plan
        ``A = diag(1 / c_i)``, output reflectance at the centres.
    """
    c, bw = _check_centres(centres, step_nm, bandwidth_nm, start_nm, stop_nm)
    masks = _band_masks(bundle, c, bw)
    patterns = np.where(masks, bundle.rows, 0).astype(np.int32)
    return _narrow(bundle, "narrowband", c, bw, patterns, level, max_exposure_s)


def _narrow(bundle, method, c, bw, patterns, level, max_exposure_s):
    resp = bundle.forward_matrix(patterns, bundle.wavelengths, 1.0).sum(axis=1)  # c_i per second, eq. (3)
    if np.any(resp <= 0):
        raise ValueError(f"band at {c[np.argmin(resp)]:g} nm gives no camera signal in the calibration model")
    targets = bundle.emitted(patterns)
    return _base(bundle, method, patterns, targets, np.diag(1.0 / resp), level, max_exposure_s,
                 output="reflectance", output_wavelengths=c, output_labels=tuple(f"{x:g}nm" for x in c),
                 illuminant="", observer="", params={"bandwidth_nm": bw, "centres_nm": c.tolist()})


def plan_reciprocal_narrowband(bundle, *, centres=None, step_nm: float = 10.0, bandwidth_nm: float | None = None,
                               start_nm: float = 400.0, stop_nm: float = 700.0, level: float = 0.9,
                               max_exposure_s: float | None = None) -> Plan:
    """Narrow bands shaped as ``1 / (lamp V)`` (eq. (4), last remark): each column's level is a common factor
    over its response, so every band gives the same output on a white and the frame reads the reflectance.

    The common factor is the largest that keeps every column within its mirrors (the weakest column full).
    Parameters as :func:`plan_narrowband`.
    """
    c, bw = _check_centres(centres, step_nm, bandwidth_nm, start_nm, stop_nm)
    masks = _band_masks(bundle, c, bw)
    col_resp = bundle.system_matrix.sum(axis=0)  # DN/s per full column on reflectance 1
    used = masks.any(axis=0)
    if np.any(col_resp[used] <= 0):
        raise ValueError("a band column gives no camera signal in the calibration model")
    # Each column contributes a common amount; a band of fewer columns gets proportionally more per column, so
    # every band (25 or 26 columns at 10 nm) gives the same total.
    with np.errstate(divide="ignore"):
        share = np.where(masks, 1.0 / (col_resp * masks.sum(axis=1, keepdims=True)), 0.0)
    levels = share / share.max()
    patterns = _quantize(levels, bundle.rows)
    return _narrow(bundle, "reciprocal", c, bw, patterns, level, max_exposure_s)


# ---- basis designs --------------------------------------------------------------------------------------------
def _basis_functions(basis: BasisTable, m: int):
    if not isinstance(basis, BasisTable):
        raise TypeError(f"basis must be a BasisTable, not {type(basis).__name__}")
    if basis.centred:
        raise ValueError("basis plans need an uncentred basis (a mean term would make recovery affine)")
    return basis.first(m)


def _basis_plan(bundle, basis, m, method, frames, D_rows, output_wavelengths, level, max_exposure_s, extra):
    """frames: list of (B,) non-negative spectra on the basis grid; D_rows: function(a) -> (m, K) combination."""
    wl = basis.wavelengths
    phi = basis.first(m)
    grid = bundle.wavelengths
    products = [_on_grid(f, wl, grid) for f in frames]
    patterns, targets = _design_frames(bundle, products)
    F = bundle.forward_matrix(patterns, wl, 1.0)  # (K, B) per second
    # a_k: the scale by which frame k realizes its spectrum (least-squares projection of its model row on it).
    a = np.array([F[k] @ frames[k] / (frames[k] @ frames[k]) for k in range(len(frames))])
    D = D_rows(a)
    G = D @ F @ phi  # (m, m): the identity for ideal frames
    cond = np.linalg.cond(G)
    if not cond < 1e8:
        raise ValueError(f"{method}: the projections do not determine the {m} coefficients (condition {cond:.1e})")
    ow = wl if output_wavelengths is None else np.asarray(output_wavelengths, np.float64).reshape(-1)
    if ow.min() < wl[0] - 1e-9 or ow.max() > wl[-1] + 1e-9:
        raise ValueError(f"output_wavelengths must lie within the basis range {wl[0]:g}-{wl[-1]:g} nm")
    phi_out = interpolation_matrix(ow, wl) @ phi
    A = phi_out @ np.linalg.solve(G, D)
    params = {"m": int(m), "basis_source": basis.source, "cumulative_variance": float(basis.cumulative_variance[m - 1]),
              **extra}
    return _base(bundle, method, patterns, targets, A, level, max_exposure_s, output="reflectance",
                 output_wavelengths=ow, output_labels=tuple(f"{x:g}nm" for x in ow), illuminant="", observer="",
                 params=params)


def plan_symmetric_basis(bundle, basis: BasisTable, *, m: int = 5, output_wavelengths=None, level: float = 0.9,
                         max_exposure_s: float | None = None) -> Plan:
    """Symmetric basis design (eq. (5), (6)): ``S_j = S_j+ - S_j-``, 2m - 1 frames (one for the non-negative S_1).

    Parameters
    ----------
    bundle : CalibrationBundle
    basis : BasisTable
        Uncentred basis; its grid is the design grid.
    m : int
        Basis functions used, >= 1 (paper: 5).
    output_wavelengths : array_like, optional
        Where to output reflectance (default the basis grid), within the basis range.
    level, max_exposure_s
        As :func:`plan_narrowband`.
    """
    phi = _basis_functions(basis, m)
    frames, where = [phi[:, 0].clip(0, None)], [(0, 1.0)]
    if np.any(phi[:, 0] < -1e-12):
        frames.append((-phi[:, 0]).clip(0, None))
        where.append((0, -1.0))
    for j in range(1, m):
        for sign in (1.0, -1.0):
            part = (sign * phi[:, j]).clip(0, None)
            if np.any(part > 0):
                frames.append(part)
                where.append((j, sign))

    def D_rows(a):
        D = np.zeros((m, len(frames)))
        for k, (j, sign) in enumerate(where):
            D[j, k] = sign / a[k]
        return D

    return _basis_plan(bundle, basis, m, "symmetric", frames, D_rows, output_wavelengths, level, max_exposure_s,
                       {"frames": [[int(j), float(s)] for j, s in where]})


def plan_biased_basis(bundle, basis: BasisTable, *, m: int = 5, output_wavelengths=None, level: float = 0.9,
                      max_exposure_s: float | None = None) -> Plan:
    """Biased basis design (eq. (5), (6)): frames ``S_j + K`` (K the smallest bias making every function
    non-negative) and one bias frame ``K``: m + 1 frames. Parameters as :func:`plan_symmetric_basis`."""
    phi = _basis_functions(basis, m)
    bias = float(max(0.0, (-phi).max()))
    frames = [phi[:, j] + bias for j in range(m)]
    frames = [np.clip(f, 0.0, None) for f in frames]
    frames.append(np.full(phi.shape[0], 1.0))

    def D_rows(a):
        D = np.zeros((m, m + 1))
        for j in range(m):
            D[j, j] = 1.0 / a[j]
            D[j, m] = -bias / a[m]
        return D

    return _basis_plan(bundle, basis, m, "biased", frames, D_rows, output_wavelengths, level, max_exposure_s,
                       {"bias": bias})


# ---- response designs: tristimulus and camera simulator ----------------------------------------------------------
def _illuminant_on(illuminant, grid):
    sd = resolve_illuminant_sd(illuminant)
    return np.interp(grid, sd.wavelengths, sd.values, left=0.0, right=0.0), getattr(sd, "name", str(illuminant))


def _response_plan(bundle, method, responses, W, labels, output, illuminant, observer, correction, basis, m,
                   level, max_exposure_s, params):
    """responses: (P, G) signed target products I V; W: (P, G) weights giving the ideal outputs from a
    reflectance on the light grid. Negative lobes get their own frame (symmetric split)."""
    grid = bundle.wavelengths
    frames, where = [], []
    for p, r in enumerate(responses):
        for sign in (1.0, -1.0):
            part = np.clip(sign * r, 0.0, None)
            if part.max() > 1e-9 * np.abs(r).max():
                frames.append(part)
                where.append((p, sign))
    patterns, targets = _design_frames(bundle, frames)
    F = bundle.forward_matrix(patterns, grid, 1.0)  # (K, G) per second
    a = np.array([F[k] @ frames[k] / (frames[k] @ frames[k]) for k in range(len(frames))])
    D = np.zeros((len(responses), len(frames)))
    for k, (p, sign) in enumerate(where):
        D[p, k] = sign / a[k]
    if correction == "diagonal":
        white = np.ones(grid.size)
        k = (W @ white) / (D @ F @ white)
        A = k[:, None] * D
    elif correction == "span":
        if basis is None:
            raise ValueError("correction='span' needs a basis")
        if basis.centred:
            raise ValueError("correction='span' needs an uncentred basis")
        phi = interpolation_matrix(grid, basis.wavelengths) @ basis.first(m)  # constant beyond the basis range
        phi = phi * basis.singular_values[:m]  # weight components by their share of the training energy
        DFphi = D @ F @ phi
        A = (W @ phi) @ np.linalg.pinv(DFphi) @ D
    else:
        raise ValueError(f"correction must be one of diagonal, span, got {correction!r}")
    params = {**params, "correction": correction, "frames": [[int(p), float(s)] for p, s in where]}
    if correction == "span":
        params["m"] = int(m)
    return _base(bundle, method, patterns, targets, A, level, max_exposure_s, output=output,
                 output_wavelengths=np.zeros(0), output_labels=labels, illuminant=illuminant, observer=observer,
                 params=params)


def plan_tristimulus(bundle, *, illuminant="D65", cmfs=DEFAULT_CMFS, correction: str = "diagonal",
                     basis: BasisTable | None = None, m: int = 3, level: float = 0.9,
                     max_exposure_s: float | None = None) -> Plan:
    """Tristimulus imager (eq. (7)-(11)): three frames with ``I_x V = E_T x``, ``I_y V = E_T y``, ``I_z V = E_T z``.

    Parameters
    ----------
    bundle : CalibrationBundle
    illuminant : str or colour.SpectralDistribution
        E_T: any of ``colour.SDS_ILLUMINANTS`` (``"D65"``, ``"A"`` ...) or a spectrum.
    cmfs : str or colour.MultiSpectralDistributions
        Observer.
    correction : {"diagonal", "span"}
        ``"diagonal"``: ``A = diag(k)``, k making the perfect white exact (the paper's). ``"span"``: the 3 x 3
        least-squares decoder over the first ``m`` functions of ``basis`` (weighted by their energy): exact on
        their span when m = 3.
    basis, m
        For ``"span"``.
    level, max_exposure_s
        As :func:`plan_narrowband`.

    Returns
    -------
    Plan
        Output ``"XYZ"`` with Y = 1 for the perfect white, over the light's wavelength range (colour-science's
        ``sd_to_XYZ`` with the observer trimmed to that range, divided by 100).
    """
    grid = bundle.wavelengths
    E, name = _illuminant_on(illuminant, grid)
    cm = resolve_cmfs(cmfs)
    xyz = np.stack([np.interp(grid, cm.wavelengths, cm.values[:, i], left=0.0, right=0.0) for i in range(3)])
    W = XYZ_weights(grid, illuminant, cm)
    return _response_plan(bundle, "tristimulus", E * xyz, W, ("X", "Y", "Z"), "XYZ", str(name), cm.name,
                          correction, basis, m, level, max_exposure_s, {})


def camera_sensitivities(name: str):
    """RGB sensitivities colour-science ships (``colour.MSDS_CAMERA_SENSITIVITIES``), by name."""
    import colour

    table = colour.MSDS_CAMERA_SENSITIVITIES
    if name not in table:
        raise ValueError(f"unknown camera {name!r}; valid cameras: {', '.join(table)}")
    return table[name]


def plan_camera_simulator(bundle, *, camera="Nikon 5100 (NPL)", illuminant="D65", correction: str = "diagonal",
                          basis: BasisTable | None = None, m: int = 3, level: float = 0.9,
                          max_exposure_s: float | None = None) -> Plan:
    """Camera simulator: frames with ``I V = E R_c`` for a camera's response functions R_c under illuminant E,
    so the monochrome rig records what that camera would (negative lobes, if any, split into two frames).

    Parameters
    ----------
    camera : str or colour.MultiSpectralDistributions
        A name of ``colour.MSDS_CAMERA_SENSITIVITIES`` or any multi-spectral response set.
    illuminant, correction, basis, m, level, max_exposure_s
        As :func:`plan_tristimulus`.

    Returns
    -------
    Plan
        Output ``"RGB"``, normalized so the perfect white has G = 1 (the second channel).
    """
    import colour

    msds = camera_sensitivities(camera) if isinstance(camera, str) else camera
    if not isinstance(msds, colour.MultiSpectralDistributions):
        raise TypeError(f"camera must be a name or colour.MultiSpectralDistributions, not {type(camera).__name__}")
    grid = bundle.wavelengths
    E, name = _illuminant_on(illuminant, grid)
    vals = np.asarray(msds.values, np.float64)
    R = np.stack([np.interp(grid, msds.wavelengths, vals[:, i], left=0.0, right=0.0) for i in range(vals.shape[1])])
    resp = E * R
    dl = float(grid[1] - grid[0])
    ref = resp[min(1, len(resp) - 1)].sum() * dl
    if not ref > 0:
        raise ValueError("camera responses under the illuminant are zero over the light's range")
    W = resp * dl / ref
    labels = tuple(str(x) for x in msds.labels)
    return _response_plan(bundle, "camera", resp, W, labels, "RGB", str(name), str(msds.name), correction, basis,
                          m, level, max_exposure_s, {})


# ---- steady state ----------------------------------------------------------------------------------------------
def plan_steady_state(bundle, spectrum, wavelengths=None, *, fit: str = "scale", level: float = 0.9,
                      max_exposure_s: float | None = None) -> Plan:
    """One pattern emitting a target spectral irradiance, every frame (spectral rendering, paper Section 3).

    Parameters
    ----------
    spectrum : array_like or colour.SpectralDistribution or str
        Target spectral irradiance (W m^-2 nm^-1) on ``wavelengths``; an illuminant name is taken from
        ``colour.SDS_ILLUMINANTS`` (relative, use ``fit="scale"``).
    fit : {"scale", "absolute"}
        ``"scale"``: the largest multiple of the target the lamp can give; ``"absolute"``: as given (clipped
        where the lamp cannot).

    Returns
    -------
    Plan
        K = 1, ``A = 1 / c_white``: output ``"relative"``, the signal relative to a perfect white under it.
    """
    grid = bundle.wavelengths
    if isinstance(spectrum, str) or hasattr(spectrum, "values"):
        if wavelengths is not None:
            raise ValueError("wavelengths must not be given with a named or colour spectrum")
        target, name = _illuminant_on(spectrum, grid)
    else:
        s = np.asarray(spectrum, np.float64)
        w = grid if wavelengths is None else np.asarray(wavelengths, np.float64)
        if s.ndim != 1 or s.shape != w.shape or np.any(s < 0) or not np.all(np.isfinite(s)):
            raise ValueError(f"spectrum must be finite, non-negative and match wavelengths {w.shape}")
        target, name = _on_grid(s, w, grid), "custom"
    if not target.max() > 0:
        raise ValueError("spectrum is zero over the light's range")
    if fit == "scale":
        f = fit_levels(bundle.column_matrix, target / target.max(), upper=None)
        scale = 1.0 / f.max()
        f, target = f * scale, target / target.max() * scale
    elif fit == "absolute":
        f = fit_levels(bundle.column_matrix, target)
    else:
        raise ValueError(f"fit must be one of scale, absolute, got {fit!r}")
    patterns = _quantize(f, bundle.rows)[None]
    resp = bundle.forward_matrix(patterns, grid, 1.0).sum()
    if not resp > 0:
        raise ValueError("the steady illuminant gives no camera signal in the calibration model")
    return _base(bundle, "steady", patterns, target[None], np.array([[1.0 / resp]]), level, max_exposure_s,
                 output="relative", output_wavelengths=np.zeros(0), output_labels=("relative",),
                 illuminant=str(name), observer="", params={"fit": fit})


#: Plan methods by name.
PLAN_METHODS = {
    "narrowband": plan_narrowband,
    "reciprocal": plan_reciprocal_narrowband,
    "biased": plan_biased_basis,
    "symmetric": plan_symmetric_basis,
    "tristimulus": plan_tristimulus,
    "camera": plan_camera_simulator,
    "steady": plan_steady_state,
}


def make_plan(method: str, bundle, *args, **kwargs) -> Plan:
    """Make a plan by method name (a key of :data:`PLAN_METHODS`); unknown names list the valid ones."""
    if method not in PLAN_METHODS:
        raise ValueError(f"unknown plan method {method!r}; valid methods: {', '.join(PLAN_METHODS)}")
    return PLAN_METHODS[method](bundle, *args, **kwargs)
