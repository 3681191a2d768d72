"""What a sequence decoder computes per sequence, decided once (:func:`outputs_for`, an :class:`Outputs`), and the
fused device launches that compute it from one sequence's frames (:class:`FusedLaunches`).

:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder` owns both: its device-resident mode (the stream's and
the batch's) runs the launches below on each sequence; its motion mode decodes the same outputs' rows in one
warped pass and takes CIELAB and dE from their XYZ by :func:`lab_and_delta_E`, the function the denoised launches
use too.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla
from numpy.typing import ArrayLike, DTypeLike

from specgpu import engine
from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS
from specgpu.engine.guided import guided_filter_device
from specgpu.engine.guided_variance import filtered_variance_device
from specgpu.engine.runtime import get_allocator
from specgpu.pipeline.denoise import stream_denoise
from specgpu.planning.noise import NoiseModel
from specgpu.planning.uncertainty import ambient_variance, constant_covariance, variance_rows

__all__ = ["STREAM_OUTPUTS", "ColourLaunch", "FusedLaunches", "Outputs", "lab_and_delta_E", "outputs_for"]

#: What a decoder can compute per sequence, and the channel count / dtype of each map.
STREAM_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")

#: Host-corrected frames (FusedLaunches.prepare_frames) mark a saturated sample with _PRECORRECT_MARK, far above
#: any corrected signal, and the kernels flag samples at or above _PRECORRECT_SATURATION.
_PRECORRECT_MARK = np.float32(3.0e38)
_PRECORRECT_SATURATION = 1.0e38


# ------------------------------------------------------------------------------------------------- the outputs

@dataclass(frozen=True, eq=False)
class Outputs:
    """The maps a decoder makes of each sequence and what they need of the plan (:func:`outputs_for`).

    Attributes
    ----------
    names : tuple of str
        Of :data:`STREAM_OUTPUTS`, canonical, each once.
    A : ndarray, (B, K) float64
        The plan's decoder.
    cube_dtype : numpy dtype
        Storage of the cube.
    method, illuminant, observer, integration
        Of dE, and of XYZ / Lab.
    basis, A_coefficients : ndarray or None
        With ``"coefficients"``: the plan's output basis U (B, m) and the rows S Vt (m, K) decoding into it.
    to_XYZ, white : ndarray or None
        With a colour output: the plan's outputs to XYZ (3, B) and the white of Lab and dE.
    reference : ndarray or None
        The dE reference, (3,) or (H, W, 3) float32; ``reference_single`` when one colour.
    noise : NoiseModel or None
        With a sigma output: the plan's noise model.
    denoise : dict or None
        The guided filter's set-up (:func:`specgpu.pipeline.denoise.stream_denoise`).
    """

    names: tuple
    A: np.ndarray
    cube_dtype: np.dtype
    method: str
    illuminant: object
    observer: object
    integration: str
    basis: np.ndarray | None = None
    A_coefficients: np.ndarray | None = None
    to_XYZ: np.ndarray | None = None
    white: np.ndarray | None = None
    reference: np.ndarray | None = None
    reference_single: bool = True
    noise: NoiseModel | None = None
    denoise: dict | None = None

    @property
    def sigmas_filtered(self) -> bool:
        """Sigma outputs carried through the guided filter of ``denoise``."""
        return bool(self.denoise and self.denoise["sigmas"])

    @property
    def M(self) -> np.ndarray | None:
        """(3, K) the composed decoder of XYZ, or None without a colour output."""
        return None if self.to_XYZ is None else self.to_XYZ @ self.A

    def shapes(self, height: int, width: int) -> dict[str, tuple[tuple, np.dtype]]:
        """Per output: its (H, W, C) or (H, W) shape and dtype; plus ``mask`` (H, W) uint8, bit 1 = saturated."""
        h, w = height, width
        out = {}
        for name in self.names:
            if name == "coefficients":
                out[name] = ((h, w, self.A_coefficients.shape[0]), np.dtype(np.float32))
            elif name == "cube":
                out[name] = ((h, w, self.A.shape[0]), self.cube_dtype)
            elif name in ("XYZ", "Lab"):
                out[name] = ((h, w, 3), np.dtype(np.float32))
            elif name == "sigma":
                out[name] = ((h, w, self.A.shape[0] + 1), np.dtype(np.float32))
            else:
                out[name] = ((h, w), np.dtype(np.float32))
        out["mask"] = ((h, w), np.dtype(np.uint8))
        return out

    def rows(self, A: ArrayLike | None = None) -> tuple[np.ndarray, dict[str, slice]]:
        """The linear outputs (coefficients, cube, XYZ for any colour output; and ``samples``, the frames' K samples,
        where the sigmas carried through the filter read the cube's slopes and the cube is no output with more bands
        than frames) stacked as the rows of one decoder
        (rows, K) and the slice of each: what one pass over the frames decodes (the warped pass's matrix); the
        plan's A alone when none is asked (its pass still says which pixels have samples). ``A``: a decoder
        (B, K) used instead of the plan's (a reference white's, for one sequence), the coefficients in the same
        basis."""
        if A is None:
            coefficients, cube, xyz = self.A_coefficients, self.A, self.M
        else:
            A = np.asarray(A, np.float64)
            coefficients = None if self.basis is None else self.basis.T @ A
            cube, xyz = A, None if self.to_XYZ is None else self.to_XYZ @ A
        rows, slices, at = [], {}, 0
        # the sigmas carried through the filter read the cube's slopes on the guide: where the cube is not asked for
        # and the frames are fewer than its bands, the frames' samples (K rows; the cube is the decoder times them)
        B, K = np.shape(cube)
        samples = np.eye(K) if self.sigmas_filtered and "cube" not in self.names and K < B else None
        for name, matrix in (("coefficients", coefficients), ("cube", cube), ("XYZ", xyz), ("samples", samples)):
            if matrix is not None and (name != "cube" or "cube" in self.names
                                       or (self.sigmas_filtered and samples is None)):
                slices[name] = slice(at, at + len(matrix))
                rows.append(np.asarray(matrix, np.float64))
                at += len(matrix)
        return (np.vstack(rows) if rows else cube), slices


def outputs_for(plan, names, *, frame_shape, reference=None, method: str = "CIE 2000", illuminant=None,
                observer=None, integration: str = "rectangle", cube_dtype: DTypeLike = np.float32,
                denoise=None) -> Outputs:
    """The outputs ``names`` of ``plan`` checked and prepared (the one place that decides them, whichever pass
    computes them).

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
    names : sequence of str
        Of :data:`STREAM_OUTPUTS`, any case. ``"coefficients"``: the m basis coefficients of each pixel in the
        plan's output basis U (B x m, orthonormal columns from the SVD of A; ``cube = coefficients @ U.T``).
        ``"cube"``: the B outputs of the plan. ``"XYZ"``, ``"Lab"``, ``"dE"``: colorimetry. ``"sigma"``: the standard
        deviation of each of the B outputs and their RMS (B + 1 channels, as ``specgpu recover --sigma``);
        ``"sigma_rms"``: the RMS channel alone; ``"dE_sigma"``: the first-order dE2000 standard deviation (as
        ``recover --delta-e-sigma``). The sigmas need the plan's noise model, which ``specgpu plan`` records.
    frame_shape : (int, int)
        (H, W) of the frames (a per-pixel dE reference is checked against it).
    reference : array_like, optional
        CIELAB reference of ``"dE"``: one colour (3,) or a per-pixel (H, W, 3) image. Required for ``"dE"``.
    method : str
        Colour difference, a name of ``DELTA_E_METHODS``.
    illuminant, observer : str, optional
        Of XYZ (Y = 1 for the perfect white), Lab and dE; resolved by the plan
        (:meth:`specgpu.planning.plans.Plan.resolve_illuminant`, ``resolve_observer``).
    integration : str
        ``"rectangle"`` or ``"ASTM E308"`` (:func:`specgpu.core.spectra.XYZ_weights`); the white of Lab and dE is
        the perfect diffuser integrated the same way (:meth:`specgpu.planning.plans.Plan.white_XYZ`).
    cube_dtype : float16 or float32
    denoise : (radius, eps), optional
        The guided filter (:func:`specgpu.pipeline.denoise.stream_denoise`).
    """
    names = tuple(dict.fromkeys(validate_method(name, {k: k for k in STREAM_OUTPUTS}, "stream output")
                                for name in names))
    if not names:
        raise ValueError(f"a stream needs at least one output of {', '.join(STREAM_OUTPUTS)}")
    A = np.asarray(plan.A, np.float64)
    cube_dtype = np.dtype(cube_dtype)
    if cube_dtype not in (np.dtype(np.float16), np.dtype(np.float32)):
        raise ValueError(f"cube_dtype must be float16 or float32, got {cube_dtype}")
    method = validate_method(method, DELTA_E_METHODS) if "dE" in names else method
    illuminant, observer = plan.resolve_illuminant(illuminant), plan.resolve_observer(observer)
    extra = {}
    if "coefficients" in names:
        # Coefficients in the plan's own output basis: A = U S Vt has rank m (a basis plan), so the m rows of
        # S Vt decode the coefficients and U rebuilds the cube exactly.
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        m = int(plan.params.get("m", np.sum(s > s[0] * 1e-9)))
        extra.update(basis=U[:, :m], A_coefficients=s[:m, None] * Vt[:m])
    if {"XYZ", "Lab", "dE", "dE_sigma"} & set(names):
        extra.update(to_XYZ=plan.outputs_to_XYZ(illuminant, observer, integration),
                     white=plan.white_XYZ(illuminant, observer, integration))
    sigmas = [name for name in names if name in ("sigma", "sigma_rms", "dE_sigma")]
    if sigmas:
        if "noise" not in plan.params:
            raise ValueError(f"the {sigmas[0]} output: the {plan.method} plan records no noise model, so it has no "
                             "sigma; re-plan it with specgpu plan --rig RIG.toml (the rig the calibration was made "
                             "on) to record one")
        extra["noise"] = NoiseModel.from_params(plan.params["noise"])
    if denoise is not None:
        extra["denoise"] = stream_denoise(plan, names, cube_dtype, denoise)
    if "dE" in names:
        if reference is None:
            raise ValueError("the dE output needs a reference (an L,a,b colour or a per-pixel Lab image)")
        ref = np.asarray(reference, np.float32)
        height, width = (int(s) for s in frame_shape)
        if ref.shape not in ((3,), (height, width, 3)):
            raise ValueError(f"the dE reference must be (3,) or ({height}, {width}, 3), got {ref.shape}")
        extra.update(reference=ref, reference_single=ref.shape == (3,))
    elif reference is not None:
        raise ValueError("a reference was given but dE is not among the outputs")
    return Outputs(names=names, A=A, cube_dtype=cube_dtype, method=method, illuminant=illuminant,
                   observer=observer, integration=integration, **extra)


class ColourLaunch:
    """CIELAB and dE (those of ``spec.names``) of decoded XYZ maps on the device, in one prepared launch (the XYZ
    read once, Lab written only when asked, dE straight from the Lab in registers): how the denoised launches
    (from the filtered XYZ) and the motion pass (from the warped XYZ) make them. Set up once per decoder; each
    sequence costs one enqueue, its outputs taken from the memory pool.

    Parameters
    ----------
    queue : pyopencl.CommandQueue
    spec : Outputs
        With a colour output (``Lab`` or ``dE``).
    reference : pyopencl.array.Array or None
        The dE reference on the device (flat), with ``dE``.
    n : int
        Pixels per map.
    """

    def __init__(self, queue, spec: Outputs, reference, n: int):
        self.queue, self.n = queue, int(n)
        self.names = tuple(name for name in ("Lab", "dE") if name in spec.names)
        if not self.names:
            raise ValueError("a colour launch needs the Lab or the dE output")
        de = "dE" in spec.names
        self.launch = engine.prepare_XYZ_to_delta_E(
            queue, spec.white, reference if de else None, n=self.n,
            method=spec.method if de else "CIE 2000", reference_single=spec.reference_single,
            write_Lab="Lab" in spec.names)
        self._reference = reference  # the launch points at its buffer: kept alive with it
        self._lock = threading.Lock()  # one kernel object: its arguments set and enqueued by one thread at a time

    def enqueue(self, XYZ) -> dict:
        """Enqueue the launch on the XYZ buffer (3n float32); returns the pooled device buffers by output name."""
        with self._lock:
            made = self.launch.enqueue(XYZ)
        return {name: made[key] for name, key in (("Lab", "Lab"), ("dE", "delta_E")) if key in made}


def lab_and_delta_E(colour: ColourLaunch, XYZ) -> dict:
    """CIELAB and dE of the XYZ buffer (3n float32, on the device) by the decoder's :class:`ColourLaunch`:
    the one place Lab and dE are made from decoded XYZ (the filtered or the warped). Returns the device buffers by
    output name."""
    return colour.enqueue(XYZ)


# ------------------------------------------------------------------------------------------------ the launches

class FusedLaunches:
    """A decoder's outputs as fused device launches: the plan's composed matrices, the calibration's dark and gain
    maps, the noise model's maps and the dE reference put on the device once, and the prepared launches each
    sequence is decoded by (what :class:`specgpu.pipeline.sequence_decoder.SequenceDecoder` runs in its
    device-resident mode).

    The variance of an output is linear in the frames' sample variances plus a constant
    (:func:`specgpu.planning.uncertainty.sigma_map`), so the linear kernel computes ``sigma`` with ``A o A / g`` as
    the matrix, each sample squared first for the light's fluctuation, and takes the square root of it plus the
    constant; ``dE_sigma`` takes the XYZ covariance's six entries by the linear kernel, then a small kernel
    propagating them with XYZ to dE2000 (as :func:`specgpu.planning.uncertainty.delta_E_sigma`).

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
    spec : Outputs
        The plan's outputs (:func:`outputs_for`).
    calibration : specgpu.calibration.bundle.CalibrationBundle
    corrections : specgpu.pipeline.sequence_decoder.Corrections
        What the frames need before the linear map: anything beyond a dark level and a per-pixel gain runs on the
        host (:meth:`prepare_frames`, the level subtracted there too) and the kernels take float32 frames with no
        dark.
    frame_shape : (int, int)
    queue : pyopencl.CommandQueue
    white_reference : specgpu.planning.correction.WhiteReference, optional
        Each sequence's decoder rescaled for the light's drift: every launch takes its matrix from it
        (:meth:`matrices`).
    """

    def __init__(self, plan, spec: Outputs, calibration, corrections, *, frame_shape, queue, white_reference=None):
        self.spec, self.queue, self.corrections = spec, queue, corrections
        self.white_reference = white_reference
        self.height, self.width = (int(s) for s in frame_shape)
        self.n = self.height * self.width
        self.K = spec.A.shape[1]
        dark = corrections.dark
        gain = live_gain(calibration.flat_field)  # NaN where a pixel has no response: its outputs NaN
        if tuple(np.shape(dark)) != (self.height, self.width):
            raise ValueError(f"calibration maps are {np.shape(dark)} but the frames are {self.height} x {self.width}")
        # a sample at the sensor's maximum code has no valid measurement: its pixel's outputs become NaN, as
        # pipeline.recover makes them (flagged by the first kernel of a sequence, applied on the host)
        self.saturation = float(calibration.max_code)
        self._prepared: dict = {}
        self._calibration = calibration
        self._ambient = corrections.ambient
        self.precorrect = corrections.host
        if self.precorrect:
            dark = np.zeros_like(corrections.dark)
            self.saturation = _PRECORRECT_SATURATION  # saturated samples are marked by prepare_frames
        self.dark = engine.to_device(queue, np.asarray(dark, np.float32).reshape(-1))
        self.gain = engine.to_device(queue, np.asarray(gain, np.float32).reshape(-1))
        if spec.noise is not None:  # the uncertainty outputs: the noise model's dark and gain maps
            g_e = spec.noise.gain_e_per_dn
            self.dark_var = engine.to_device(queue, (np.asarray(dark, np.float32) - np.float32(
                g_e * spec.noise.read_var_dn2)).reshape(-1))
            self.gain2 = engine.to_device(queue, (np.asarray(gain, np.float32) ** 2).reshape(-1))
            # the light's fluctuation at each frame's own signal (squared samples); a white reference's per-sequence
            # gains divide it out, as recover --white-roi's uncertainty does. With an ambient frame the frames
            # arrive above it (prepare_frames) and its plane holds its own variance sample (never squared).
            self.square = (spec.noise.light_square() if white_reference is None and spec.noise.light_rms > 0
                           else None)
            if self._ambient is not None:
                self.dark_var = None
                self.square = None if self.square is None else (self.square[0], 0.0, self._ambient)
            const = constant_covariance(plan)
            cv = np.diag(const).astype(np.float32)
            self.sigma_offsets = np.append(cv, np.float32(np.mean(cv, dtype=np.float64)))
            self.cov_pairs = [(i, j) for i in range(3) for j in range(i, 3)]
            if "dE_sigma" in spec.names:
                self.cov_constant = spec.to_XYZ @ const @ spec.to_XYZ.T  # (3, 3) what no frame shows
        #: Lab and dE computed after the filter from the filtered XYZ instead of in the fused colour kernel
        self._lab_from_filtered = bool(spec.denoise and spec.denoise["from_XYZ"])
        #: the sigma launches write variances, carried through the filter by :meth:`_denoised_sigmas`
        self._sigmas_filtered = bool(spec.denoise and spec.denoise["sigmas"])
        self._guide_launches: dict = {}
        self._colour = None  # the ColourLaunch of the filtered XYZ, made on first use
        self.reference_device = None if spec.reference is None else engine.to_device(queue,
                                                                                      spec.reference.reshape(-1))

    def matrices(self, A: ArrayLike) -> list[np.ndarray]:
        """The float32 matrix argument of each launch (in :meth:`_launches`' order) for the decoder ``A`` (B x K):
        what a per-sequence decoder (the white reference's) writes into the launches' matrix buffers."""
        return [engine.linear_matrix(*make(np.asarray(A, np.float64))) for make, _ in self._matrix_makers()]

    def _matrix_makers(self) -> list:
        """Per launch, in order: (a function of A giving (matrix, square-root offsets or None), launch kind). With
        the sigmas carried through the filter, each sigma launch writes its variance, and a launch of the same
        rows without the light's fluctuation (kind ``<kind>_own``) the pixels' own part."""
        makers = []
        filtered = self._sigmas_filtered
        if "coefficients" in self.spec.names:
            # U^T A: S Vt for the plan's own A; for a corrected decoder (A times a K x K map) its coefficients in
            # the same basis, whose columns span the corrected decoder's outputs too
            makers.append((lambda A: (self.spec.basis.T @ A, None), "coefficients"))
        if "cube" in self.spec.names:
            makers.append((lambda A: (A, None), "cube"))
        if "sigma" in self.spec.names:
            g_e = self.spec.noise.gain_e_per_dn

            def sigma_rows(A):
                sq = variance_rows(A, A, self._ambient)
                return np.vstack([sq, sq.mean(axis=0)]) / g_e, None if filtered else self.sigma_offsets
            makers.append((sigma_rows, "sigma"))
        if "sigma_rms" in self.spec.names:
            g_e = self.spec.noise.gain_e_per_dn
            makers.append((lambda A: (variance_rows(A, A, self._ambient).mean(axis=0, keepdims=True) / g_e,
                                      None if filtered else self.sigma_offsets[-1:]), "sigma_rms"))
        if "dE_sigma" in self.spec.names:
            g_e = self.spec.noise.gain_e_per_dn

            def cov_rows(A):
                MA = self.spec.to_XYZ @ A
                left = np.stack([MA[i] for i, _ in self.cov_pairs])
                right = np.stack([MA[j] for _, j in self.cov_pairs])
                return variance_rows(left, right, self._ambient) / g_e, None
            makers.append((cov_rows, "XYZ_cov"))
        if filtered:
            makers += [(make, f"{kind}_own") for make, kind in makers if kind in ("sigma", "sigma_rms", "XYZ_cov")]
            g_e = self.spec.noise.gain_e_per_dn
            row = self.spec.denoise["row"]
            # the unfiltered outputs whose slopes on the guide pass its noise, and the guide's own variance
            makers.append((lambda A: (np.vstack(self._slope_rows(A)), None), "slopes"))
            makers.append((lambda A: (variance_rows(row, row, self._ambient) / g_e, None), "guide_var"))
        if self.spec.M is not None:
            makers.append((lambda A: (self.spec.to_XYZ @ A, None), "colour"))
        return makers

    def _slope_rows(self, A) -> list:
        """The rows of the slope images the carried sigmas read: the B outputs (for ``sigma``, ``sigma_rms``),
        then X, Y, Z (for ``dE_sigma``)."""
        names = self.spec.names
        return ([np.asarray(A, np.float64)] if {"sigma", "sigma_rms"} & set(names) else []) + (
            [self.spec.to_XYZ @ np.asarray(A, np.float64)] if "dE_sigma" in names else [])

    @property
    def frames_dtype(self):
        """What the kernels read: the raw frames, or float32 when :meth:`prepare_frames` corrects them first."""
        return np.dtype(np.float32) if self.precorrect else None

    def prepare_frames(self, raw: ArrayLike) -> np.ndarray:
        """(K, H, W) float32 frames for the kernels when the calibration or plan needs host-side corrections
        (``precorrect``): the dark level (or the plan's ambient frame) subtracted, linearised and scaled by the
        per-pattern flat ratio exactly as :func:`specgpu.pipeline.recovery.recover` does; a sample at the sensor's
        maximum
        code is set to a marker the kernels flag as saturated."""
        raw = np.asarray(raw)
        level = self.corrections.level(raw)
        f = self.corrections.signal(raw, level)
        if self._ambient is not None and self.spec.noise is not None:
            # the ambient frame's plane (a zero column of the decoder) carries its own variance sample for the
            # uncertainty launches (estimators.frame_variance)
            f[self._ambient] = ambient_variance(level, self.corrections.dark, self.spec.noise)
        f[raw >= self._calibration.max_code] = _PRECORRECT_MARK
        return f

    def warm_up(self, dtype: DTypeLike = np.uint16) -> None:
        """Build every kernel and prime the memory pool on a blank sequence, so the clock of a stream never pays
        for a program build."""
        blank = cla.zeros(self.queue, (self.K * self.n,), np.dtype(dtype), allocator=get_allocator(self.queue))
        outs = self.enqueue(blank)
        self.queue.finish()
        del outs

    def _launches(self, dtype) -> list:
        """The stream's kernels for frames of ``dtype`` as prepared launches (built on first use, then reused:
        a sequence costs a few argument sets and enqueues, not the per-call planning of the engine's functions),
        each with the map from its outputs to the stream's output names."""
        launches = self._prepared.get(dtype)
        if launches is not None:
            return launches
        q, n = self.queue, self.n
        launches = []
        sat = {"want_mask": True, "saturation": self.saturation}  # asked of the first kernel only
        for make, kind in self._matrix_makers():
            if kind == "coefficients":
                launches.append((engine.prepare_linear(q, dtype, self.spec.A_coefficients, n=n, dark=self.dark,
                                                       gain=self.gain, out_layout=1, **sat),
                                 {"out": "coefficients", "mask": "mask"}))
            elif kind == "cube":
                launches.append((engine.prepare_linear(q, dtype, self.spec.A, n=n, dark=self.dark, gain=self.gain,
                                                       out_dtype=self.spec.cube_dtype, out_layout=1, **sat),
                                 {"out": "cube", "mask": "mask"}))
            elif kind == "slopes":
                launches.append((engine.prepare_linear(q, dtype, make(self.spec.A)[0], n=n, dark=self.dark,
                                                       gain=self.gain, out_layout=1, **sat),
                                 {"out": kind, "mask": "mask"}))
            elif kind in ("sigma", "sigma_rms", "XYZ_cov", "sigma_own", "sigma_rms_own", "XYZ_cov_own", "guide_var"):
                rows, offsets = make(self.spec.A)
                own = kind.endswith("_own") or kind == "guide_var"  # the pixels' own noise: no light's fluctuation
                launches.append((engine.prepare_linear(q, dtype, rows, n=n, dark=self.dark_var, gain=self.gain2,
                                                       out_layout=1, sqrt_offsets=None if own else offsets,
                                                       square=None if own else self.square, **sat),
                                 {"out": kind, "mask": "mask"}))
            else:
                # with Lab and dE made after the filter from the filtered XYZ, this pass writes XYZ alone
                reference = None if self._lab_from_filtered else self.reference_device
                launches.append((engine.prepare_frames_to_delta_E(
                    q, dtype, self.spec.M, self.spec.white, reference, n=n,
                    method=self.spec.method if "dE" in self.spec.names else "CIE 2000",
                    reference_single=self.spec.reference_single, dark=self.dark, gain=self.gain,
                    write_XYZ="XYZ" in self.spec.names or "dE_sigma" in self.spec.names or self._lab_from_filtered,
                    write_Lab="Lab" in self.spec.names and not self._lab_from_filtered,
                    **sat), {"XYZ": "XYZ", "Lab": "Lab", "delta_E": "dE", "mask": "mask"}))
            sat = {}
        if "dE_sigma" in self.spec.names:  # on the XYZ and XYZ_cov buffers of the launches above
            de_sigma = (engine.prepare_delta_E_sigma(q, self.spec.white, self.cov_constant, n=n),
                        {"dE_sigma": "dE_sigma"})
            if self._sigmas_filtered:  # after the filter, on the filtered XYZ (_denoised_sigmas)
                self._de_sigma = de_sigma[0]
            else:
                launches.append(de_sigma)
        self._prepared[dtype] = launches
        return launches

    def enqueue(self, frames: cla.Array, matrices=None) -> dict:
        """Enqueue every kernel on the K frames (flat device array); returns the flat device output buffers (pooled
        :class:`pyopencl.Buffer` objects) by output name and ``mask`` (bit 1: a frame at the saturation level).

        ``matrices``: a device buffer per launch holding :meth:`matrices` of this sequence's decoder (written
        before, on the same in-order queue), used instead of the plan's."""
        out = {}
        for i, (launch, names) in enumerate(self._launches(np.dtype(frames.dtype))):
            if "dE_sigma" in names:  # the last launch: XYZ and its covariance in, no matrix
                made = launch.enqueue(out["XYZ"], inputs={1: out["XYZ_cov"]})
            else:
                made = launch.enqueue(frames.data, None if matrices is None else matrices[i])
            for key, buf in made.items():
                out[names[key]] = buf
        if self.spec.denoise is not None:
            self._denoised(frames, out)
        return out

    def _denoised(self, frames: cla.Array, out: dict) -> None:
        """Replace the linear outputs in ``out`` by their guided filter (:mod:`specgpu.pipeline.denoise`), and Lab
        and dE by those of the filtered XYZ: the guide, the frames' sum above dark, by one more linear launch; its
        99th percentile read on the host (a blocking read of one plane) scales eps as ``recover --denoise`` does."""
        dtype = np.dtype(frames.dtype)
        launch = self._guide_launches.get(dtype)
        if launch is None:
            launch = engine.prepare_linear(self.queue, dtype, self.spec.denoise["row"], n=self.n, dark=self.dark,
                                           gain=self.gain, out_layout=1)
            self._guide_launches[dtype] = launch
        guide = cla.Array(self.queue, (self.height, self.width), np.float32, data=launch.enqueue(frames.data)["out"])
        level = float(np.nanpercentile(guide.get(), 99))
        for name, channels in self.spec.denoise["channels"].items():
            if name in out and level > 0:  # no light above dark: nothing to guide, the outputs stay as decoded
                image = cla.Array(self.queue, (self.height, self.width, channels), np.float32, data=out[name])
                # enqueued on the device, in place: no host round trip and no new buffer per sequence
                out[name] = guided_filter_device(self.queue, image, guide, self.spec.denoise["radius"],
                                                 self.spec.denoise["eps"] * level ** 2, out=image).data
        if self._lab_from_filtered:  # CIELAB and dE of the filtered XYZ, as recover --denoise computes them
            if self._colour is None:
                self._colour = ColourLaunch(self.queue, self.spec, self.reference_device, self.n)
            out.update(lab_and_delta_E(self._colour, out["XYZ"]))
        if self._sigmas_filtered:
            self._denoised_sigmas(out, guide, level)
        out["guide"] = guide.data  # kept with the sequence's buffers while the passes queued on it run

    def _denoised_sigmas(self, out: dict, guide: cla.Array, level: float) -> None:
        """The sigma outputs of the filtered maps, on the device: each launch's variance (``total``), the pixels'
        own part of it (``<kind>_own``), the unfiltered outputs' slopes and the guide's own variance carried
        through the filter (:func:`specgpu.engine.guided_variance.filtered_variance_device`; a saturated pixel adds
        nothing to its neighbours) plus the constant; ``dE_sigma`` from the filtered XYZ and the covariance carried
        so. With no light to guide the filter (``level`` 0: the maps stay as decoded) the variance as it is."""
        h, w, q = self.height, self.width, self.queue
        mask = cla.Array(q, (h, w), np.uint8, data=out["mask"])
        B = self.spec.A.shape[0]
        slopes = cla.Array(q, (h, w, sum(len(r) for r in self._slope_rows(self.spec.A))), np.float32,
                           data=out["slopes"])
        gvar = cla.Array(q, (h, w), np.float32, data=out["guide_var"])
        xyz = B if {"sigma", "sigma_rms"} & set(self.spec.names) else 0  # where X, Y, Z lie among the slopes
        rms = [(b, b, 1.0 / B) for b in range(B)]
        # per launch: its constant (a standard deviation), or none (a covariance), and each channel's slope terms
        kinds = {"sigma": (self.sigma_offsets, [[(b, b, 1.0)] for b in range(B)] + [rms]),
                 "sigma_rms": (self.sigma_offsets[-1:], [rms]),
                 "XYZ_cov": (None, [[(xyz + i, xyz + j, 1.0)] for i, j in self.cov_pairs])}
        for kind, (offset, terms) in kinds.items():
            if kind not in out:
                continue
            channels = len(terms)
            total = cla.Array(q, (h, w, channels), np.float32, data=out[kind])
            own = cla.Array(q, (h, w, channels), np.float32, data=out[f"{kind}_own"])
            if not level > 0:  # nothing filtered: no own part carried, the variance as it is
                own, gvar = own * np.float32(0), gvar * np.float32(0)
            out[kind] = filtered_variance_device(
                q, own, total, guide, self.spec.denoise["radius"], self.spec.denoise["eps"] * max(level, 1.0) ** 2,
                slopes=slopes, guide_var=gvar, terms=terms, offsets=offset, sqrt=offset is not None, mask=mask,
                mask_bits=int(Mask.SATURATED), out=total).data
            out[f"{kind}_own"] = own.data  # kept with the sequence's buffers until it has been read back
        if "dE_sigma" in self.spec.names:
            out.update(dE_sigma=self._de_sigma.enqueue(out["XYZ"], inputs={1: out["XYZ_cov"]})["dE_sigma"])
