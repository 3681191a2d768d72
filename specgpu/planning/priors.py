"""Training priors: the second-order statistics of reflectances (:class:`Prior`) the Wiener decoder and the
optimal design learn from, the training spectra they come from (colour-science's sets minus a held-out chart, and
the user's files), a smoothness prior for users with no training set, and the subspace bound of a training set.

The prior holds the training spectra's second moment ``S = E[r r^T]`` and mean ``mu``. The second moment, not the
covariance: the decoder has no offset term (``apply_linear`` has none), so the best *linear* map through the origin
is ``A = W S F^T (F S F^T + N)^-1``, the LMMSE estimate without intercept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from specgpu.io.npz import npz_members
from specgpu.planning.basis import (
    DEFAULT_WAVELENGTHS,
    MAX_REFLECTANCE,
    REFLECTANCE_SETS,
    evaluation_exclusions,
    load_reflectances,
    pca_basis,
    read_reflectance_csv,
)

__all__ = ["HELD_OUT_CHART", "Prior", "prior_from_spectra", "read_training", "held_out_spectra", "training_database",
           "held_out_basis", "training_spectra", "default_prior", "smooth_prior", "subspace_bound"]

#: The colour-science set held out of training to evaluate the estimators and designs on (14 Munsell chips of
#: the CIE 1995 colour rendering test samples: in neither the default training nor the ColorChecker).
HELD_OUT_CHART = "CIE 1995 TCS"


@dataclass(frozen=True)
class Prior:
    """Second-order statistics of training reflectances on a grid.

    Attributes
    ----------
    wavelengths : (B,) nm
    moment : (B, B) ``E[r r^T]`` (uncentred)
    mean : (B,) ``E[r]``
    n : number of training spectra
    source : description for reports
    """

    wavelengths: np.ndarray
    moment: np.ndarray
    mean: np.ndarray
    n: int
    source: str = ""


def prior_from_spectra(reflectance: ArrayLike, wavelengths: ArrayLike, source: str = "") -> Prior:
    """The prior of (N, B) training spectra on ``wavelengths``; an empty set is a one-line error."""
    r = np.asarray(reflectance, np.float64)
    wl = np.asarray(wavelengths, np.float64).reshape(-1)
    if r.ndim != 2 or r.shape[1] != wl.size:
        raise ValueError(f"training spectra must be (N, {wl.size}), got shape {r.shape}")
    if r.shape[0] == 0:
        raise ValueError(f"the training set is empty{f' ({source})' if source else ''}: give at least one spectrum")
    if not np.all(np.isfinite(r)):
        raise ValueError("training spectra must be finite")
    return Prior(wl, r.T @ r / r.shape[0], r.mean(axis=0), int(r.shape[0]), source)


def read_training(path, wavelengths) -> tuple[np.ndarray, list]:
    """Training spectra from a file, on ``wavelengths``: a CSV
    (:func:`specgpu.planning.basis.read_reflectance_csv`) or an ``.npz`` with ``wavelengths`` (B,) and
    ``reflectance`` (N, B). Returns ((N, B), labels); one-line errors."""
    path = Path(path)
    wl = np.asarray(wavelengths, np.float64)
    if path.suffix.lower() == ".npz":
        if not path.is_file():
            raise ValueError(f"{path}: training file not found")
        npz_members(path)  # the declared sizes, checked before any array is inflated
        try:
            with np.load(path, allow_pickle=False) as data:
                swl = np.asarray(data["wavelengths"], np.float64).reshape(-1)
                r = np.asarray(data["reflectance"], np.float64)
        except KeyError as exc:
            raise ValueError(f"{path}: training npz needs 'wavelengths' and 'reflectance' arrays ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - any unreadable file is one line naming it
            raise ValueError(f"{path}: cannot read training npz ({exc.__class__.__name__})") from None
        r = r.reshape(-1, swl.size) if r.ndim == 1 else r
        if r.ndim != 2 or r.shape[1] != swl.size or swl.size < 2 or np.any(np.diff(swl) <= 0):
            raise ValueError(f"{path}: reflectance must be (N, {swl.size}) on increasing wavelengths")
        if not np.all(np.isfinite(r)) or r.size and (r.min() < 0 or r.max() > MAX_REFLECTANCE):
            raise ValueError(f"{path}: reflectance must be finite and in [0, {MAX_REFLECTANCE}]")
        samples = [(f"{path.stem}:{i + 1}", swl, r[i]) for i in range(r.shape[0])]
    else:
        samples = read_reflectance_csv(path)
    if not samples:
        raise ValueError(f"{path}: the training file holds no spectra")
    out = []
    for name, swl, val in samples:
        if swl[0] > wl[0] + 1e-9 or swl[-1] < wl[-1] - 1e-9:
            raise ValueError(f"{path}: spectrum {name!r} covers {swl[0]:g}-{swl[-1]:g} nm, not {wl[0]:g}-{wl[-1]:g} nm")
        out.append(np.interp(wl, swl, val))
    return np.array(out), [f"{path.stem}/{s[0]}" for s in samples]


def held_out_spectra(chart: str = HELD_OUT_CHART, wavelengths=None) -> tuple[list, np.ndarray, np.ndarray]:
    """(names, wavelengths, (N, B) spectra) of a colour-science set, on its own grid clipped to 380-780 nm
    (``wavelengths`` None) or interpolated onto ``wavelengths``."""
    if chart not in REFLECTANCE_SETS:
        raise ValueError(f"unknown chart {chart!r}; valid: {', '.join(REFLECTANCE_SETS)}")
    samples = REFLECTANCE_SETS[chart]()
    swl = samples[0][1]
    wl = swl[(swl >= 380) & (swl <= 780)] if wavelengths is None else np.asarray(wavelengths, np.float64)
    return [s[0] for s in samples], wl, np.array([np.interp(wl, s[1], s[2]) for s in samples])


def training_database(chart: str = HELD_OUT_CHART, wavelengths=None):
    """colour-science's reflectance sets minus ``chart`` (every set of the same patches, and any spectrum within
    0.01 RMS of one of its patches), on ``wavelengths`` (default 400-700 nm at 5 nm)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, np.float64)
    _, _, test = held_out_spectra(chart, wl)
    return load_reflectances(wavelengths=wl, exclude=evaluation_exclusions(chart), exclude_similar_to=test)


def held_out_basis(chart: str = HELD_OUT_CHART):
    """The uncentred PCA basis of :func:`training_database` (the paper's basis methods, for the same chart)."""
    return pca_basis(training_database(chart))


def training_spectra(chart: str = HELD_OUT_CHART, wavelengths=None, *, training_files=(),
                     builtin: bool = True) -> np.ndarray:
    """(N, B) training spectra: :func:`training_database` (``builtin``) plus the user's files, on ``wavelengths``."""
    return _training(chart, wavelengths, training_files, builtin)[0]


def _training(chart, wavelengths, training_files, builtin):
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, np.float64)
    rows, source = [], []
    if builtin:
        db = training_database(chart, wl)
        rows.append(db.reflectance)
        source.append(f"colour-science sets without {chart} ({len(db)} spectra)")
    for p in training_files:
        r, lab = read_training(p, wl)
        rows.append(r)
        source.append(f"{Path(p).name} ({len(lab)} spectra)")
    r = np.concatenate(rows) if rows else np.zeros((0, wl.size))
    return r, wl, "; ".join(source) or "no training files"


def default_prior(chart: str = HELD_OUT_CHART, wavelengths: ArrayLike | None = None, *, training_files=(),
                  builtin: bool = True) -> Prior:
    """Every reflectance set colour-science ships minus ``chart`` (and every set of the same patches, and any
    spectrum within 0.01 RMS of one of its patches), plus the user's training files; on ``wavelengths``
    (default 400-700 nm at 5 nm). ``builtin=False`` uses the files alone (none: a one-line error)."""
    r, wl, source = _training(chart, wavelengths, training_files, builtin)
    return prior_from_spectra(r, wl, source)



def smooth_prior(wavelengths: ArrayLike, *, correlation_nm: float = 40.0, level: float = 0.4,
                 spread: float = 0.25) -> Prior:
    """A prior with no training set: a flat level (RMS ``level``) plus a smooth variation (RMS ``spread``,
    squared-exponential correlation over ``correlation_nm``): second moment ``level^2 11^T + spread^2 K``."""
    wl = np.asarray(wavelengths, np.float64).reshape(-1)
    for name, v in (("correlation_nm", correlation_nm), ("level", level), ("spread", spread)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"smooth {name} must be finite and > 0, got {v!r}")
    K = np.exp(-0.5 * ((wl[:, None] - wl[None, :]) / correlation_nm) ** 2)
    return Prior(wl, level ** 2 + spread ** 2 * K, np.full(wl.size, level), 1,
                 f"smooth prior ({correlation_nm:g} nm correlation)")



def subspace_bound(training, test, K: int, *, centred: bool = False) -> float:
    """The noise-free linear bound with K measurements learnt from ``training`` (N, B), on ``test`` (M, B): the
    RMSE of the test spectra's orthogonal projection onto the training's best K-dimensional subspace (the top K
    eigenvectors of its second moment; ``centred``: of its covariance, about its mean, i.e. an affine decoder).
    No linear decoder of K noise-free measurements designed on that training set does better on ``test`` than a
    projection onto the subspace it would learn, and the best the training set can teach is its own top K."""
    tr = np.asarray(training, np.float64)
    te = np.asarray(test, np.float64)
    if tr.ndim != 2 or te.ndim != 2 or tr.shape[1] != te.shape[1]:
        raise ValueError(f"training and test must be (N, B) and (M, B) on one grid, got {tr.shape} and {te.shape}")
    if not (isinstance(K, (int, np.integer)) and 1 <= K <= tr.shape[1]):
        raise ValueError(f"K must be an integer in [1, {tr.shape[1]}], got {K!r}")
    mu = tr.mean(axis=0) if centred else np.zeros(tr.shape[1])
    X = tr - mu
    U = np.linalg.eigh(X.T @ X)[1][:, ::-1][:, :K]
    e = (te - mu) - (te - mu) @ U @ U.T
    return float(np.sqrt(np.mean(e ** 2)))
