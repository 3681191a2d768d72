"""The measurement plan (:class:`Plan`): the illuminant sequence to project and the decoder A that reads the
frames back, its file (:func:`save_plan`, :func:`load_plan`) and the design helpers every method shares.

A :class:`Plan` is what the host decides before a capture: K DMD patterns (mirror
counts, within the light's limits), one exposure chosen so the brightest frame on a white uses most of the
camera's range, the decoder ``A`` (B x K) that :func:`specgpu.engine.linear_map.apply_linear` applies per pixel as
``y = A (o - dark) * gain``, what ``y`` means (reflectance at which wavelengths, or XYZ / camera RGB under which
illuminant and observer), and the hash of the calibration bundle whose model it was designed with.

Every plan is designed on the calibration's forward model (:class:`specgpu.calibration.bundle.CalibrationBundle`:
``O = F R``, F from the quantized patterns, the lamp, the slit and the V estimate), so the decoder accounts for
what the patterns really emit, not for what was asked of them. The methods live one family per module
(:mod:`~specgpu.planning.narrowband`, :mod:`~specgpu.planning.basis_plans`, :mod:`~specgpu.planning.response`,
:mod:`~specgpu.planning.design`) and are made by name through :func:`specgpu.planning.registry.make_plan`.

Plans are saved as versioned, hashed ``.npz`` files (:func:`save_plan`); loading refuses an unknown version, a
corrupt file or, given the calibration, a plan made from another calibration (stale), each in one line naming the
file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from specgpu.calibration.bundle import DEFAULT_MAX_EXPOSURE_S
from specgpu.core.numerics import fit_levels
from specgpu.core.spectra import DEFAULT_CMFS, OBSERVERS, XYZ_weights, resolve_integration, white_point_XYZ
from specgpu.core.validate import BadArgument
from specgpu.io.tables import content_hash, load_npz, save_npz

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.rig.config import RigDescription

__all__ = ["Plan", "PLAN_FORMAT", "PLAN_VERSION", "OUTPUTS", "save_plan", "load_plan"]

#: The file format identifier of a saved plan (its ``.npz`` metadata).
PLAN_FORMAT = "specgpu.plan"
PLAN_VERSION = 1
OUTPUTS = ("reflectance", "XYZ", "RGB", "relative")


@dataclass(frozen=True)
class Plan:
    """An illuminant sequence and its decoder.

    Made by :func:`specgpu.planning.registry.make_plan` (or a method's ``plan_*`` function), saved by
    :func:`save_plan`; frozen, with every array checked and normalized on construction.

    Attributes
    ----------
    method : str
        Key of :data:`specgpu.planning.registry.PLAN_METHODS` that made it.
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

    Examples
    --------
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.planning import make_plan
    >>> from specgpu.rig import load_rig
    >>> plan = make_plan("narrowband", oracle_calibration(load_rig()), step_nm=20.0)
    >>> plan.K, plan.A.shape, plan.output
    (16, (16, 16), 'reflectance')
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

    @property
    def frame_period_s(self) -> float:
        """Shortest frame period the plan runs at, s: its exposure plus the light's switch time, or the camera's
        shortest frame period (read-out) where the design recorded it (``params["min_frame_period_s"]``) and it
        is longer."""
        floor = float(self.params.get("min_frame_period_s", 0.0) or 0.0)
        return max(float(self.exposure_s) + float(self.min_exposure_s), floor)

    @property
    def sequence_s(self) -> float:
        """Time one sequence of the plan takes, s: K frame periods (every frame, ambient and probes included)."""
        return self.K * self.frame_period_s

    @property
    def timing(self) -> dict:
        """Exposure, frame period and sequence time (s), sequences per second and, for a plan designed within a
        time budget, the budget (plain data; :func:`save_plan` writes it beside the hashed content)."""
        out = {"exposure_s": float(self.exposure_s), "frame_period_s": self.frame_period_s,
               "sequence_s": self.sequence_s, "sequences_per_s": 1.0 / self.sequence_s, "frames": self.K}
        if "sequence_budget_s" in self.params:
            out["sequence_budget_s"] = float(self.params["sequence_budget_s"])
        return out

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

    def rig_description(self, description: RigDescription):
        """The rig description to capture this plan with: the camera at the plan's exposure, its frame rate
        lowered if the exposure plus the light's switch time needs a longer period; a plan designed within a
        sequence-time budget runs at its own :attr:`frame_period_s` (within the camera's fastest rate), so a
        sequence takes the time it was designed for.

        Parameters
        ----------
        description : specgpu.rig.config.RigDescription

        Returns
        -------
        RigDescription
        """
        cam = description.camera
        rate = min(cam.frame_rate_hz, 1.0 / (self.exposure_s + description.light.switch_time_s + 1e-6))
        if "sequence_budget_s" in self.params:  # a plan designed within a time budget runs at its own rate
            rate = min(cam.max_frame_rate_hz, 1.0 / (self.frame_period_s + 1e-6))
        return replace(description, camera=replace(cam, exposure_s=float(self.exposure_s), frame_rate_hz=rate))

    def outputs_to_XYZ(self, illuminant: str = "D65", observer=None, integration: str = "rectangle") -> np.ndarray:
        """(3, B) matrix C with XYZ = C . y for this plan's outputs y (Y = 1 for the white): the colour-matching
        weights of ``observer`` (None: :meth:`resolve_observer`'s default) under ``illuminant`` on the output
        wavelengths, integrated by ``integration`` (:func:`specgpu.core.spectra.XYZ_weights`) for reflectance
        outputs; the identity for a tristimulus plan made for the same illuminant and observer (its frames
        integrate by the rectangle rule on the light's grid, so another integration is refused); any other output
        has no XYZ (ValueError). Its white is :meth:`white_XYZ`."""
        integration = resolve_integration(integration)
        if self.output == "reflectance":
            return XYZ_weights(self.output_wavelengths, illuminant, self.resolve_observer(observer),
                               integration=integration)
        if self.output == "XYZ":
            if self.illuminant and self.illuminant.lower() != str(illuminant).lower():
                raise ValueError(f"the plan measures XYZ under {self.illuminant}, not {illuminant}")
            self.resolve_observer(observer)  # refuses another observer than the plan's
            if integration != "rectangle":
                raise ValueError(f"a {self.method} plan measures XYZ integrated by the rectangle rule on the light's "
                                 f"grid, not by {integration}; leave the integration out")
            return np.eye(3)
        raise ValueError(f"a {self.output!r} plan ({self.method}) has no XYZ")

    def white_XYZ(self, illuminant: str = "D65", observer=None, integration: str = "rectangle") -> np.ndarray:
        """(3,) the reference white of the XYZ :meth:`outputs_to_XYZ` gives: the perfect diffuser integrated with
        the same weights (:func:`specgpu.core.spectra.white_point_XYZ` on the output wavelengths, or on the light's
        grid for a tristimulus plan, whose frames were made for those weights), so a perfect white's Lab is
        (100, 0, 0). Refuses what :meth:`outputs_to_XYZ` refuses."""
        self.outputs_to_XYZ(illuminant, observer, integration)
        grid = self.output_wavelengths if self.output == "reflectance" else self.light_wavelengths
        return white_point_XYZ(illuminant, self.resolve_observer(observer), wavelengths=grid,
                               integration=integration)

    @property
    def measured_illuminant(self) -> str:
        """The illuminant the plan's outputs themselves are relative to: a tristimulus (XYZ) or camera simulator
        (RGB) plan's own; empty for outputs that hold under any illuminant (reflectance, relative signal)."""
        return self.illuminant if self.output in ("XYZ", "RGB") else ""

    def resolve_illuminant(self, illuminant: str | None = None, *, name: str = "the plan") -> str:
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

    def resolve_observer(self, observer: str | None = None, *, name: str = "the plan") -> str:
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
            raise BadArgument(f"observer {asked!r} is not one of {', '.join(OBSERVERS)}")
        if own and own.lower() != canonical.lower():
            raise ValueError(f"{name} measures {self.output} for the {own}, not the {canonical}: leave the "
                             f"observer out to use the plan's, or make a plan for the {canonical}")
        return own or canonical

    def check_calibration(self, bundle: CalibrationBundle, name: str = "plan",
                          calibration_name: str | None = None) -> None:
        """Refuse a plan designed with another calibration than ``bundle`` (stale plan); ``name`` and
        ``calibration_name`` are the files the message names."""
        if self.calibration != bundle.hash:
            current = f"{calibration_name} is" if calibration_name else "the current one is"
            raise ValueError(f"{name} is stale: made from calibration {self.calibration[:12]}, "
                             f"{current} {bundle.hash[:12]}; re-plan")


def save_plan(path: str | os.PathLike[str], plan: Plan) -> str:
    """Save a plan as a versioned, hashed ``.npz`` (format ``"specgpu.plan"``).

    Parameters
    ----------
    path : str or os.PathLike
        The file to write.
    plan : Plan

    Returns
    -------
    str
        The plan's content hash (equal to ``plan.hash``), which a capture records.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.planning import load_plan, make_plan, save_plan
    >>> from specgpu.rig import load_rig
    >>> plan = make_plan("narrowband", oracle_calibration(load_rig()), step_nm=20.0)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "plan.npz"
    >>> save_plan(path, plan) == plan.hash == load_plan(path).hash
    True
    """
    return save_npz(path, PLAN_FORMAT, PLAN_VERSION, plan._arrays(), plan._meta(), extra={"timing": plan.timing})


def load_plan(path: str | os.PathLike[str], *, calibration: CalibrationBundle | None = None) -> Plan:
    """Load a plan saved by :func:`save_plan`.

    Parameters
    ----------
    path : str or os.PathLike
        The plan file.
    calibration : CalibrationBundle, optional
        Given, a plan designed with another calibration is refused as stale.

    Returns
    -------
    Plan
        The plan, its content hash checked against the one stored in the file.

    Raises
    ------
    ValueError
        An unknown version, a corrupt or invalid file, or a stale plan, in one line naming the file.

    Examples
    --------
    A plan loads against the calibration it was designed with, and is refused against any other:

    >>> import tempfile, pathlib
    >>> from specgpu import calibration, planning, rig
    >>> mine = calibration.oracle_calibration(rig.load_rig())
    >>> bands = pathlib.Path(tempfile.mkdtemp()) / "bands.npz"
    >>> _ = planning.save_plan(bands, planning.make_plan("narrowband", mine, step_nm=20.0))
    >>> planning.load_plan(bands, calibration=mine).method
    'narrowband'
    >>> brighter = calibration.oracle_calibration(rig.rig_from_dict({"light": {"illuminance_lux": 2000.0}}))
    >>> planning.load_plan(bands, calibration=brighter)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ValueError: ...bands.npz is stale: made from calibration ..., the current one is ...; re-plan
    """
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
    products = [np.asarray(prod, np.float64) for prod in products]
    for prod in products:
        if not np.any(prod > 0):
            raise ValueError("a frame's target response is zero everywhere")
    # every frame's fit at once: the fits share the system matrix's products
    levels = fit_levels(bundle.system_matrix, np.stack([prod / prod.max() for prod in products], axis=1),
                        upper=None) if products else np.zeros((bundle.system_matrix.shape[1], 0))
    for prod, f in zip(products, levels.T):
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
    whole = bundle.whole_periods(t)  # an LED's PWM or the OL490's grey levels are exact over whole periods only
    if whole > longest * (1 + 1e-9):
        raise ValueError(f"the light's level period ({whole * 1e3:.3f} ms) is longer than the longest exposure "
                         f"allowed ({longest * 1e3:.3f} ms): allow a longer exposure or fewer grey bits")
    t = whole
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
