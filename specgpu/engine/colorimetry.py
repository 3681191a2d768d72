"""Device-backed colorimetry: reflectance -> XYZ -> CIELAB -> colour difference, NumPy in / NumPy out.

Every function takes NumPy arrays (returned results are NumPy) or :class:`pyopencl.array.Array` inputs
(results stay on that device, so work can chain without transfers). Channels are on the last axis and
results are float32. Names and conventions follow colour-science:

- XYZ is in the domain [0, 1] with Y = 1 for the perfect reflecting diffuser under the illuminant
  (colour-science's ``sd_to_XYZ`` reports the same values scaled by 100), integrated by the rectangle rule on
  the cube's own grid (nothing outside it), or with ASTM E308's tables (``integration="ASTM E308"``);
- CIELAB has L* in [0, 100] for 0 <= Y <= Yn; the white (Xn, Yn, Zn) of a named illuminant is
  :func:`specgpu.core.spectra.white_point_XYZ`'s, the perfect diffuser integrated with the same weights as the
  XYZ (give the XYZ's ``wavelengths`` and ``integration``), so a perfect white is exactly (100, 0, 0);
- ``delta_E(Lab_1, Lab_2, method)``: ``Lab_1`` is the reference (only CIE 1994 is asymmetric).

Non-finite input is not an error for pixel data: a NaN or inf in a pixel gives a non-finite result in that
pixel only (NaN in, NaN out; inf may come out as inf or NaN), never a finite wrong value and never a
change in neighbouring pixels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.spectra import DEFAULT_CMFS, XYZ_weights, white_point_XYZ
from specgpu.core.validate import (
    as_float32,
    check_band_wavelengths,
    check_frames,
    check_last_axis,
    check_matrix,
    is_device_array,
    validate_method,
)
from specgpu.engine import kernels
from specgpu.engine.runtime import get_queue

__all__ = [
    "DELTA_E_METHODS",
    "XYZ_to_Lab",
    "delta_E",
    "reflectance_to_XYZ",
    "frames_to_delta_E",
    "FusedResult",
]

#: Colour-difference formulae by name (colour-science's names; the short aliases are accepted too).
DELTA_E_METHODS = {
    "CIE 1976": "CIE 1976",
    "CIE 1994": "CIE 1994",
    "CIE 2000": "CIE 2000",
    "cie1976": "CIE 1976",
    "cie1994": "CIE 1994",
    "cie2000": "CIE 2000",
}


def _result(dev, shape, on_device: bool):
    dev = dev.reshape(shape)
    return dev if on_device else dev.get()


def XYZ_to_Lab(XYZ: ArrayLike, illuminant: str = "D65", *, observer: str = DEFAULT_CMFS,
               wavelengths: ArrayLike | None = None,
               integration: str = "rectangle", device=None):
    """CIE XYZ -> CIE L*a*b* on the device.

    Parameters
    ----------
    XYZ : array_like or pyopencl.array.Array, (..., 3)
        Tristimulus values, domain [0, 1] (Y = 1 for the reference white).
    illuminant : str, colour.SpectralDistribution or array_like
        Reference white: a name of ``colour.SDS_ILLUMINANTS`` or a spectrum, whose white is the perfect diffuser
        integrated as the XYZ was (:func:`specgpu.core.spectra.white_point_XYZ`); or the white outright as
        chromaticity xy (2,) or XYZ (3,).
    observer : str
        Observer (colour-matching functions) of the XYZ.
    wavelengths : array_like, (B,), optional
        The grid the XYZ was integrated on (:func:`reflectance_to_XYZ`'s); None: 360-780 nm at 1 nm.
    integration : str
        How the XYZ was integrated: ``"rectangle"`` or ``"ASTM E308"``.
    device : optional
        Explicit device, queue or selector (see :mod:`specgpu.engine.runtime`).

    Returns
    -------
    ndarray or pyopencl.array.Array, (..., 3), float32
        L* in [0, 100], a* and b* roughly [-128, 127] for real colours.

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.engine import XYZ_to_Lab
    >>> Lab = XYZ_to_Lab(np.array([[0.20654008, 0.12197225, 0.05136952]]), [0.3127, 0.3290])
    >>> Lab.shape, Lab.dtype
    ((1, 3), dtype('float32'))
    >>> Lab.astype(float).round(2).tolist()
    [[41.53, 52.64, 26.92]]

    A perfect white on a 10 nm grid, with the white of that grid:

    >>> from specgpu.engine import reflectance_to_XYZ
    >>> wavelengths = np.arange(400, 701, 10)
    >>> XYZ = reflectance_to_XYZ(np.ones(31), wavelengths)
    >>> (XYZ_to_Lab(XYZ, wavelengths=wavelengths).astype(float).round(3) + 0.0).tolist()
    [100.0, 0.0, 0.0]
    """
    XYZ = check_last_axis(XYZ, "XYZ")
    white = white_point_XYZ(illuminant, observer, wavelengths=wavelengths, integration=integration)
    queue = get_queue(device, like=(XYZ,))
    n = int(np.prod(XYZ.shape[:-1], dtype=np.int64))
    lab = kernels.launch_XYZ_to_Lab(queue, kernels.to_device(queue, XYZ.reshape(-1)), white, n=n)
    return _result(lab, XYZ.shape, is_device_array(XYZ))


def delta_E(Lab_1: ArrayLike, Lab_2: ArrayLike, method: str = "CIE 2000", *, device=None):
    """Colour difference between two CIELAB images, or an image and one colour, on the device.

    Parameters
    ----------
    Lab_1, Lab_2 : array_like or pyopencl.array.Array, (..., 3)
        CIELAB values; either may be a single colour (3,) broadcast against the other. ``Lab_1`` is the
        reference (it sets the weights of CIE 1994).
    method : str
        ``"CIE 1976"``, ``"CIE 1994"`` (graphic arts: kL = 1, K1 = 0.045, K2 = 0.015) or ``"CIE 2000"``
        (kL = kC = kH = 1), case-insensitive.

    Returns
    -------
    ndarray or pyopencl.array.Array, (...,), float32
        Non-negative differences.

    Examples
    --------
    A reference colour against an image of two pixels (the first of Sharma, Wu and Dalal's CIEDE2000 pairs):

    >>> import numpy as np
    >>> from specgpu.engine import delta_E
    >>> Lab = np.array([[50.0, 0.0, -82.7485], [50.0, 3.0, -79.7751]])
    >>> delta_E([50.0, 2.6772, -79.7751], Lab).astype(float).round(4).tolist()
    [2.0425, 0.1783]
    >>> float(delta_E([50.0, 0.0, 0.0], [50.0, 3.0, 4.0], method="CIE 1976"))
    5.0
    """
    method = validate_method(method, DELTA_E_METHODS)
    Lab_1 = check_last_axis(Lab_1, "Lab_1")
    Lab_2 = check_last_axis(Lab_2, "Lab_2")
    single1, single2 = Lab_1.ndim == 1, Lab_2.ndim == 1
    if not single1 and not single2 and Lab_1.shape != Lab_2.shape:
        raise ValueError(f"Lab_1 {Lab_1.shape} and Lab_2 {Lab_2.shape} must have the same shape, or one be (3,)")
    shape = Lab_2.shape[:-1] if single1 else Lab_1.shape[:-1]
    queue = get_queue(device, like=(Lab_1, Lab_2))
    n = int(np.prod(shape, dtype=np.int64))
    # Two single colours are one pixel: the first read as an image of one, the second broadcast.
    de = kernels.launch_delta_E(queue, kernels.to_device(queue, Lab_1.reshape(-1)),
                                kernels.to_device(queue, Lab_2.reshape(-1)), method=method, n=n,
                                single1=single1 and not single2, single2=single2)
    return _result(de, shape, is_device_array(Lab_1) or is_device_array(Lab_2))


def reflectance_to_XYZ(R: ArrayLike, wavelengths: ArrayLike, illuminant: str = "D65", cmfs=DEFAULT_CMFS, *,
                       integration: str = "rectangle",
                       device=None):
    """Spectral reflectance -> CIE XYZ under ``illuminant`` for the ``cmfs`` observer, on the device.

    The weights are :func:`specgpu.core.spectra.XYZ_weights`': colour-science's ``msds_to_XYZ_integration`` ones
    (rectangle rule on the grid, nothing outside it) or its ASTM E308 ones, computed in float64 on the host; the
    device applies them to every pixel. Their white is :func:`XYZ_to_Lab`'s for the same ``wavelengths`` and
    ``integration``.

    Parameters
    ----------
    R : array_like or pyopencl.array.Array, (..., B)
        Reflectance factors, nominally [0, 1].
    wavelengths : array_like, (B,)
        Evenly spaced, increasing band centres in nm.
    illuminant : str or colour.SpectralDistribution
    cmfs : str or colour.MultiSpectralDistributions
    integration : str
        ``"rectangle"`` (default) or ``"ASTM E308"`` (colour-science's ``sd_to_XYZ(method="ASTM E308")``; grids
        of 1, 5, 10 or 20 nm only).

    Returns
    -------
    ndarray or pyopencl.array.Array, (..., 3), float32
        XYZ with Y = 1 for the perfect reflecting diffuser.

    Examples
    --------
    The perfect reflecting diffuser and a 50 % grey on a 10 nm grid:

    >>> import numpy as np
    >>> from specgpu.engine import reflectance_to_XYZ
    >>> wavelengths = np.arange(400, 701, 10)
    >>> R = np.stack([np.ones(31), np.full(31, 0.5)])
    >>> reflectance_to_XYZ(R, wavelengths).astype(float).round(3).tolist()
    [[0.949, 1.0, 1.087], [0.475, 0.5, 0.544]]
    """
    R = as_float32(R, "R")
    if R.ndim == 0:
        raise ValueError("R must have bands on its last axis, got a scalar")
    w = check_band_wavelengths(wavelengths, R.shape[-1])
    W = check_matrix(XYZ_weights(w, illuminant, cmfs, integration=integration), "XYZ weights")
    queue = get_queue(device, like=(R,))
    n = int(np.prod(R.shape[:-1], dtype=np.int64))
    frames = kernels.to_device(queue, R.reshape(-1))
    xyz, _ = kernels.launch_linear(queue, frames, W, n=n, in_layout=1, out_layout=1)
    return _result(xyz, (*R.shape[:-1], 3), is_device_array(R))


class FusedResult(NamedTuple):
    """Results of :func:`frames_to_delta_E` when intermediates are asked for (None where not)."""

    delta_E: object
    XYZ: object
    Lab: object
    mask: object


def frames_to_delta_E(frames: ArrayLike, A: ArrayLike, reference: ArrayLike, *, C: ArrayLike | None = None,
                      illuminant: str = "D65", observer: str = DEFAULT_CMFS,
                      wavelengths: ArrayLike | None = None, integration: str = "rectangle",
                      method: str = "CIE 2000", dark: ArrayLike | None = None,
                      gain: ArrayLike | None = None, saturation: float | None = None, return_XYZ: bool = False,
                      return_Lab: bool = False, return_mask: bool = False, device=None):
    """Frames -> XYZ -> Lab -> colour difference against a reference, fused in one device pass.

    XYZ = M (o - dark) * gain per pixel with M = C . A (3 x K, composed on the host), then CIELAB for the
    ``illuminant`` white, then ``delta_E(reference, Lab, method)``. No intermediate is stored unless asked for.

    Parameters
    ----------
    frames : array_like or pyopencl.array.Array, (K, H, W) or (K, N)
        uint8, uint16 or float32 frames of one illumination sequence.
    A : array_like, (B, K) or (3, K)
        Decoder from frames to the B outputs; when ``C`` is None it must already give XYZ (3 x K).
    reference : array_like, (3,) or (H, W, 3)
        Reference CIELAB colour, or a per-pixel reference image.
    C : array_like, (3, B), optional
        Outputs -> XYZ (for example :func:`specgpu.core.spectra.XYZ_weights` for spectral outputs).
    illuminant, observer, wavelengths, integration
        Reference white of the Lab conversion (see :func:`XYZ_to_Lab`): give the grid and integration ``C``'s
        weights were made with, so a perfect white is (100, 0, 0).
    method : str
        Colour-difference formula (see :func:`delta_E`).
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted from every frame (or per frame), in frame units.
    gain : array_like, (H, W), optional
        Per-pixel gain (flat field) applied after the matrix; NaN marks a pixel with no response (outputs NaN).
    saturation : float, optional
        Sensor maximum code for the mask (default: the dtype's maximum for integer frames; none for float).
    return_XYZ, return_Lab, return_mask : bool
        Also return these intermediates; the mask is uint8, 1 = a frame at ``saturation``,
        2 = a non-finite frame sample (OR-ed).

    Returns
    -------
    delta_E : ndarray, (H, W), float32
        When no intermediate is asked for; otherwise a :class:`FusedResult` (delta_E, XYZ, Lab, mask).

    Examples
    --------
    Thirty-one narrowband frames of a 50 % grey (an ideal decoder: A is the identity, C the XYZ weights)
    against the CIELAB colour of a 40 % grey:

    >>> import numpy as np
    >>> from specgpu.core import XYZ_weights
    >>> from specgpu.engine import XYZ_to_Lab, frames_to_delta_E, reflectance_to_XYZ
    >>> wavelengths = np.arange(400, 701, 10)
    >>> frames = np.full((31, 2, 2), 0.5, np.float32)
    >>> reference = XYZ_to_Lab(reflectance_to_XYZ(np.full(31, 0.4), wavelengths), wavelengths=wavelengths)
    >>> dE = frames_to_delta_E(frames, np.eye(31), reference, C=XYZ_weights(wavelengths), wavelengths=wavelengths)
    >>> dE.shape, dE.dtype, bool(np.allclose(dE, dE[0, 0]))
    ((2, 2), dtype('float32'), True)
    >>> result = frames_to_delta_E(frames, np.eye(31), reference, C=XYZ_weights(wavelengths), return_Lab=True)
    >>> result.Lab.shape, result.XYZ is None
    ((2, 2, 3), True)
    """
    method = validate_method(method, DELTA_E_METHODS)
    frames, K = check_frames(frames)
    spatial = tuple(frames.shape[1:])
    if C is None:
        M = check_matrix(A, "A", columns=K, rows=3)
    else:
        A = check_matrix(A, "A", columns=K)
        Cm = check_matrix(C, "C", columns=A.shape[0], columns_from="A (rows)")
        if Cm.shape[0] != 3:
            raise ValueError(f"C must map the outputs to XYZ (3 rows), got shape {Cm.shape}")
        M = check_matrix(np.asarray(Cm, np.float64) @ np.asarray(A, np.float64), "C . A", rows=3)
    reference = check_last_axis(reference, "reference")
    if reference.ndim > 1 and reference.shape[:-1] != spatial:
        raise ValueError(f"reference has shape {reference.shape}, expected (3,) or {(*spatial, 3)}")
    white = white_point_XYZ(illuminant, observer, wavelengths=wavelengths, integration=integration)
    on_device = is_device_array(frames)
    queue = get_queue(device, like=(frames, reference, dark, gain))
    dark_dev, dark_per_frame = kernels.pixel_map(queue, dark, "dark", spatial, K)
    gain_dev = kernels.gain_map(queue, gain, spatial)
    if saturation is None and frames.dtype.kind == "u":
        saturation = float(np.iinfo(frames.dtype).max)
    n = int(np.prod(spatial, dtype=np.int64))
    out = kernels.launch_frames_to_delta_E(
        queue, kernels.to_device(queue, frames.reshape(-1)), M, white,
        kernels.to_device(queue, reference.reshape(-1)), n=n, method=method,
        reference_single=reference.ndim == 1, dark=dark_dev, dark_per_frame=dark_per_frame, gain=gain_dev,
        write_XYZ=return_XYZ, write_Lab=return_Lab, want_mask=return_mask, saturation=saturation,
    )
    de = _result(out.delta_E, spatial, on_device)
    if not (return_XYZ or return_Lab or return_mask):
        return de
    return FusedResult(
        delta_E=de,
        XYZ=_result(out.XYZ, (*spatial, 3), on_device) if return_XYZ else None,
        Lab=_result(out.Lab, (*spatial, 3), on_device) if return_Lab else None,
        mask=_result(out.mask, spatial, on_device) if return_mask else None,
    )

