"""The device decoder of a stream: a plan's matrices, the calibration's dark and gain maps and the dE reference,
put on the device once, and the fused kernel launches each sequence of frames is decoded by.

:class:`StreamDecoder` is the engine of the stream; :mod:`specgpu.pipeline.stream` runs it on sequences as they
arrive, :mod:`specgpu.pipeline.batch` on recorded ones.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pyopencl.array as cla
from numpy.typing import ArrayLike, DTypeLike

from specgpu import engine
from specgpu.core.numerics import live_gain
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS
from specgpu.engine.guided import guided_filter
from specgpu.engine.runtime import get_allocator
from specgpu.pipeline.denoise import stream_denoise
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.correction import WhiteReference
from specgpu.planning.noise import NoiseModel
from specgpu.planning.uncertainty import ambient_variance, constant_covariance, variance_rows

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["STREAM_OUTPUTS", "StreamDecoder"]

#: What a stream can compute per sequence, and the channel count / dtype of each map.
STREAM_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")


# ------------------------------------------------------------------------------------------------- the decoder

#: Host-corrected frames (StreamDecoder.prepare_frames) mark a saturated sample with _PRECORRECT_MARK, far above
#: any corrected signal, and the kernels flag samples at or above _PRECORRECT_SATURATION.
_PRECORRECT_MARK = np.float32(3.0e38)
_PRECORRECT_SATURATION = 1.0e38


class StreamDecoder:
    """The host-side planning of a stream: matrices, dark and gain maps and the reference, on the device once.

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
        Decoder A (B x K) and what it outputs (reflectance or XYZ).
    calibration : specgpu.calibration.bundle.CalibrationBundle
        Dark frame at the plan's exposure and flat field (the same ones ``specgpu recover`` applies).
    outputs : sequence of str
        Any of :data:`STREAM_OUTPUTS`. ``"coefficients"``: the m basis coefficients of each pixel in the plan's
        output basis U (B x m, orthonormal columns from the SVD of A; ``cube = coefficients @ U.T``).
        ``"cube"``: the B outputs of the plan. ``"XYZ"``, ``"Lab"``, ``"dE"``: the fused colorimetric pass.
        ``"sigma"``: the standard deviation of each of the B outputs and their RMS (B + 1 channels, as
        ``specgpu recover --sigma``): the variance is linear in the frames' sample variances plus a constant
        (:func:`specgpu.planning.uncertainty.sigma_map`), so the linear kernel computes it with ``A o A / g`` as the
        matrix, each sample squared first for the light's fluctuation, and takes the square root of it plus the
        constant. ``"sigma_rms"``: the RMS channel alone (one
        row of the same map: B times fewer bytes written than ``"sigma"``). ``"dE_sigma"``: the first-order dE2000
        standard deviation (as ``recover --delta-e-sigma``): the XYZ covariance's six entries by the linear
        kernel, then a small kernel propagating them with XYZ to dE2000 (as
        :func:`specgpu.planning.uncertainty.delta_E_sigma`). Both need the plan's noise model, which ``specgpu plan``
        records
        (given ``--rig`` for a calibration made on a custom rig).
    reference : array_like, optional
        CIELAB reference of ``"dE"``: one colour (3,) or a per-pixel (H, W, 3) image. Required for ``"dE"``.
    method : str
        Colour difference, a name of ``DELTA_E_METHODS`` (default ``"CIE 2000"``).
    illuminant : str, optional
        Illuminant of XYZ (Y = 1 for the perfect white), Lab and dE; default the plan's own for a tristimulus or
        camera plan, D65 otherwise (:meth:`specgpu.planning.plans.Plan.resolve_illuminant`, which refuses another than a
        tristimulus plan measures under).
    observer : str, optional
        Observer of XYZ, Lab and dE (its white); default the plan's own for a tristimulus plan, the CIE 1931 2
        degree observer otherwise (:meth:`specgpu.planning.plans.Plan.resolve_observer`, which refuses another than a
        tristimulus plan's).
    integration : str
        How reflectance outputs are integrated to XYZ: ``"rectangle"`` (default) or ``"ASTM E308"``
        (:func:`specgpu.core.spectra.XYZ_weights`); the white of Lab and dE is the perfect diffuser integrated the
        same way (:meth:`specgpu.planning.plans.Plan.white_XYZ`), so a white scene decodes to (100, 0, 0).
    cube_dtype : float16 or float32
        Storage of the cube (float16 halves the memory traffic of the widest output).
    frame_shape : (int, int)
        (H, W) of the frames.
    queue : pyopencl.CommandQueue
    white_roi : str or (x, y, w, h), optional
        A reference white in the field (``specgpu recover --white-roi``): each sequence's decoder is rescaled for
        the light's drift since calibration (:class:`specgpu.planning.correction.WhiteReference`), and every launch of
        the sequence gets its matrix from the corrected decoder (:meth:`matrices`).
    white_reflectance : float or path, optional
        The white's reflectance (0.99 by default); only with ``white_roi``.
    """

    def __init__(self, plan: Plan, calibration: CalibrationBundle, outputs, *, frame_shape, queue, reference=None,
                 method: str = "CIE 2000",
                 illuminant=None, observer: str | None = None, cube_dtype: DTypeLike = np.float16, white_roi=None,
                 white_reflectance=None, denoise=None, integration: str = "rectangle"):
        # canonical names (the check is case-insensitive), each once
        outputs = tuple(dict.fromkeys(validate_method(name, {k: k for k in STREAM_OUTPUTS}, "stream output")
                                      for name in outputs))
        if not outputs:
            raise ValueError(f"a stream needs at least one output of {', '.join(STREAM_OUTPUTS)}")
        self.outputs = outputs
        self.plan = plan
        self.queue = queue
        self.height, self.width = (int(s) for s in frame_shape)
        self.n = self.height * self.width
        self.K = plan.K
        A = np.asarray(plan.A, np.float64)
        self.cube_dtype = np.dtype(cube_dtype)
        if self.cube_dtype not in (np.dtype(np.float16), np.dtype(np.float32)):
            raise ValueError(f"cube_dtype must be float16 or float32, got {self.cube_dtype}")
        self.method = validate_method(method, DELTA_E_METHODS) if "dE" in outputs else method
        self.illuminant = illuminant = plan.resolve_illuminant(illuminant)
        self.observer = observer = plan.resolve_observer(observer)
        # what the calibration and plan ask of the frames before the linear map (the sensor's linearisation, the
        # per-pattern flat field, a plan's ambient frame subtracted instead of the dark level): none of them is
        # linear in one per-pixel map, so they run on the host (prepare_frames), the level subtracted there too,
        # and the kernels take float32 frames with no dark
        self.sequence = SequenceDecoder(plan, calibration, white_roi=white_roi, white_reflectance=white_reflectance,
                                        device=queue)
        self.corrections = corrections = self.sequence.corrections
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
        self.A = A
        self.basis = None
        self.A_coefficients = None
        if "coefficients" in outputs:
            # Coefficients in the plan's own output basis: A = U S Vt has rank m (a basis plan), so the m rows of
            # S Vt decode the coefficients and U rebuilds the cube exactly.
            U, s, Vt = np.linalg.svd(A, full_matrices=False)
            m = int(plan.params.get("m", np.sum(s > s[0] * 1e-9)))
            self.basis = U[:, :m]
            self.A_coefficients = s[:m, None] * Vt[:m]
        colour = {"XYZ", "Lab", "dE", "dE_sigma"} & set(outputs)
        self.M = None
        self.to_XYZ = None
        self.white = None
        self.reference = None
        self.reference_single = True
        if colour:
            self.to_XYZ = plan.outputs_to_XYZ(illuminant, observer, integration)
            self.M = self.to_XYZ @ A
            self.white = plan.white_XYZ(illuminant, observer, integration)
        # the white reference: parsed and checked now (an ROI outside the frame is refused before any streaming)
        self.white_reference = None
        if white_roi is not None:
            self.white_reference = WhiteReference(plan, calibration, white_roi, white_reflectance,
                                                  frame_shape=(self.height, self.width))
        # the uncertainty outputs: the noise model's dark and gain maps (estimators._noise_products)
        self.noise = None
        if {"sigma", "sigma_rms", "dE_sigma"} & set(outputs):
            if "noise" not in plan.params:
                raise ValueError(f"the {plan.method} plan records no noise model, so it has no sigma; re-plan it "
                                 "with specgpu plan --rig RIG.toml (the rig the calibration was made on) to record one")
            self.noise = NoiseModel.from_params(plan.params["noise"])
            g_e = self.noise.gain_e_per_dn
            self.dark_var = engine.to_device(queue, (np.asarray(dark, np.float32) - np.float32(
                g_e * self.noise.read_var_dn2)).reshape(-1))
            self.gain2 = engine.to_device(queue, (np.asarray(gain, np.float32) ** 2).reshape(-1))
            # the light's fluctuation at each frame's own signal (squared samples); a white reference's per-sequence
            # gains divide it out, as recover --white-roi's uncertainty does. With an ambient frame the frames
            # arrive above it (prepare_frames) and its plane holds its own variance sample (never squared).
            self.square = (self.noise.light_square() if self.white_reference is None and self.noise.light_rms > 0
                           else None)
            if self._ambient is not None:
                self.dark_var = None
                self.square = None if self.square is None else (self.square[0], 0.0, self._ambient)
            const = constant_covariance(plan)
            cv = np.diag(const).astype(np.float32)
            self.sigma_offsets = np.append(cv, np.float32(np.mean(cv, dtype=np.float64)))
            self.cov_pairs = [(i, j) for i in range(3) for j in range(i, 3)]
            if "dE_sigma" in outputs:
                self.cov_constant = self.to_XYZ @ const @ self.to_XYZ.T  # (3, 3) what no frame shows
        self.denoise = None if denoise is None else stream_denoise(plan, outputs, self.cube_dtype, denoise)
        #: Lab and dE computed after the filter from the filtered XYZ instead of in the fused colour kernel
        self._lab_from_filtered = bool(self.denoise and self.denoise["from_XYZ"])
        self._guide_launches: dict = {}
        if "dE" in outputs:
            if reference is None:
                raise ValueError("the dE output needs a reference (an L,a,b colour or a per-pixel Lab image)")
            ref = np.asarray(reference, np.float32)
            if ref.shape == (3,):
                self.reference_single = True
            elif ref.shape == (self.height, self.width, 3):
                self.reference_single = False
            else:
                raise ValueError(f"the dE reference must be (3,) or ({self.height}, {self.width}, 3), got {ref.shape}")
            self.reference = engine.to_device(queue, ref.reshape(-1))
        elif reference is not None:
            raise ValueError("a reference was given but dE is not among the outputs")

    def shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """Per output: its (H, W, C) or (H, W) shape and dtype; plus ``mask`` (H, W) uint8, bit 1 = saturated."""
        h, w = self.height, self.width
        out = {}
        for name in self.outputs:
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

    def device_shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """The maps read back from the device (:meth:`shapes`); :meth:`enqueue` may return more buffers (those
        ``dE_sigma`` is computed from), which stay on the device."""
        return self.shapes()

    def matrices(self, A: ArrayLike) -> list[np.ndarray]:
        """The float32 matrix argument of each launch (in :meth:`_launches`' order) for the decoder ``A`` (B x K):
        what a per-sequence decoder (the white reference's) writes into the launches' matrix buffers."""
        return [engine.linear_matrix(*make(np.asarray(A, np.float64))) for make, _ in self._matrix_makers()]

    def _matrix_makers(self) -> list:
        """Per launch, in order: (a function of A giving (matrix, square-root offsets or None), launch kind)."""
        makers = []
        if "coefficients" in self.outputs:
            # U^T A: S Vt for the plan's own A; for a corrected decoder (A times a K x K map) its coefficients in
            # the same basis, whose columns span the corrected decoder's outputs too
            makers.append((lambda A: (self.basis.T @ A, None), "coefficients"))
        if "cube" in self.outputs:
            makers.append((lambda A: (A, None), "cube"))
        if "sigma" in self.outputs:
            g_e = self.noise.gain_e_per_dn

            def sigma_rows(A):
                sq = variance_rows(A, A, self._ambient)
                return np.vstack([sq, sq.mean(axis=0)]) / g_e, self.sigma_offsets
            makers.append((sigma_rows, "sigma"))
        if "sigma_rms" in self.outputs:
            g_e = self.noise.gain_e_per_dn
            makers.append((lambda A: (variance_rows(A, A, self._ambient).mean(axis=0, keepdims=True) / g_e,
                                      self.sigma_offsets[-1:]), "sigma_rms"))
        if "dE_sigma" in self.outputs:
            g_e = self.noise.gain_e_per_dn

            def cov_rows(A):
                MA = self.to_XYZ @ A
                left = np.stack([MA[i] for i, _ in self.cov_pairs])
                right = np.stack([MA[j] for _, j in self.cov_pairs])
                return variance_rows(left, right, self._ambient) / g_e, None
            makers.append((cov_rows, "XYZ_cov"))
        if self.M is not None:
            makers.append((lambda A: (self.to_XYZ @ A, None), "colour"))
        return makers

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
        if self._ambient is not None and self.noise is not None:
            # the ambient frame's plane (a zero column of the decoder) carries its own variance sample for the
            # uncertainty launches (estimators.frame_variance)
            f[self._ambient] = ambient_variance(level, self.corrections.dark, self.noise)
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
                launches.append((engine.prepare_linear(q, dtype, self.A_coefficients, n=n, dark=self.dark,
                                                       gain=self.gain, out_layout=1, **sat),
                                 {"out": "coefficients", "mask": "mask"}))
            elif kind == "cube":
                launches.append((engine.prepare_linear(q, dtype, self.A, n=n, dark=self.dark, gain=self.gain,
                                                       out_dtype=self.cube_dtype, out_layout=1, **sat),
                                 {"out": "cube", "mask": "mask"}))
            elif kind in ("sigma", "sigma_rms", "XYZ_cov"):
                rows, offsets = make(self.A)
                launches.append((engine.prepare_linear(q, dtype, rows, n=n, dark=self.dark_var, gain=self.gain2,
                                                       out_layout=1, sqrt_offsets=offsets, square=self.square,
                                                       **sat),
                                 {"out": kind, "mask": "mask"}))
            else:
                # with Lab and dE made after the filter from the filtered XYZ, this pass writes XYZ alone
                launches.append((engine.prepare_frames_to_delta_E(
                    q, dtype, self.M, self.white, None if self._lab_from_filtered else self.reference, n=n,
                    method=self.method if "dE" in self.outputs else "CIE 2000",
                    reference_single=self.reference_single, dark=self.dark, gain=self.gain,
                    write_XYZ="XYZ" in self.outputs or "dE_sigma" in self.outputs or self._lab_from_filtered,
                    write_Lab="Lab" in self.outputs and not self._lab_from_filtered,
                    **sat), {"XYZ": "XYZ", "Lab": "Lab", "delta_E": "dE", "mask": "mask"}))
            sat = {}
        if "dE_sigma" in self.outputs:  # on the XYZ and XYZ_cov buffers of the launches above
            launches.append((engine.prepare_delta_E_sigma(q, self.white, self.cov_constant, n=n),
                             {"dE_sigma": "dE_sigma"}))
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
        if self.denoise is not None:
            self._denoised(frames, out)
        return out

    def _denoised(self, frames: cla.Array, out: dict) -> None:
        """Replace the linear outputs in ``out`` by their guided filter (:mod:`specgpu.pipeline.denoise`), and Lab
        and dE by those of the filtered XYZ: the guide, the frames' sum above dark, by one more linear launch; its
        99th percentile read on the host (a blocking read of one plane) scales eps as ``recover --denoise`` does."""
        dtype = np.dtype(frames.dtype)
        launch = self._guide_launches.get(dtype)
        if launch is None:
            launch = engine.prepare_linear(self.queue, dtype, self.denoise["row"], n=self.n, dark=self.dark,
                                           gain=self.gain, out_layout=1)
            self._guide_launches[dtype] = launch
        guide = cla.Array(self.queue, (self.height, self.width), np.float32, data=launch.enqueue(frames.data)["out"])
        level = float(np.nanpercentile(guide.get(), 99))
        for name, channels in self.denoise["channels"].items():
            if name in out and level > 0:  # no light above dark: nothing to guide, the outputs stay as decoded
                image = cla.Array(self.queue, (self.height, self.width, channels), np.float32, data=out[name])
                out[name] = guided_filter(image, guide, radius=self.denoise["radius"],
                                          eps=self.denoise["eps"] * level ** 2).data
        if self._lab_from_filtered:  # CIELAB and dE of the filtered XYZ, as recover --denoise computes them
            xyz = cla.Array(self.queue, (3 * self.n,), np.float32, data=out["XYZ"])
            lab = engine.launch_XYZ_to_Lab(self.queue, xyz, self.white, n=self.n)
            if "Lab" in self.outputs:
                out["Lab"] = lab.data
            if "dE" in self.outputs:
                out["dE"] = engine.launch_delta_E(self.queue, self.reference, lab, method=self.method, n=self.n,
                                                  single1=self.reference_single).data


