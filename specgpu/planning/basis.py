"""Reflectance databases and PCA basis tables (paper Section 4.A, eq. (5)).

The linear model of the paper writes a reflectance as ``S(lambda) = sum_j sigma_j S_j(lambda)`` with ``S_j`` the
principal components of a set of measured reflectances (the paper used 507 of them; five components hold
0.9974 of the variance). This module gathers the measured reflectances colour-science ships, plus user CSV
files, into a :class:`ReflectanceDatabase` on one wavelength grid, and turns it into a :class:`BasisTable`.

Training sets (:data:`REFLECTANCE_SETS`; all measured spectra, none synthetic):

- ColorChecker charts: ``"ColorChecker N Ohta"``, ``"BabelColor Average"``, ``"ISO 17321-1"`` (the same 24
  patches measured three times, see :data:`COLORCHECKER_24_SETS`) and ``"PMC"`` (30 patches);
- CIE test colour samples ``"CIE 1995 TCS"`` (14), ``"CIE 2024 TCS"`` (15), NIST colour quality scale samples
  ``"NIST CQS 7.4"`` and ``"NIST CQS 9.0"`` (15 each);
- ``"CIE 2017 CES"``: the 99 colour evaluation samples of the CIE 2017 colour fidelity index (the IES TM-30
  CES: measured spectra chosen from over 100 000 for uniform coverage of colour space; 5 nm table, 380-780 nm),
  through ``colour.quality.cfi2017.load_TCS_CIE2017``;
- ``"RAW to ACES v1"``: the 190 training reflectances of the Academy's rawtoaces (paint, skin, foliage, fabric,
  charts), through ``colour.characterisation.read_training_data_rawtoaces_v1``.

Keeping the evaluation chart out of the training set: exclude the chart by name *and* every set that holds the
same patches (:func:`evaluation_exclusions`), and drop any remaining spectrum closer than a tolerance to a test
spectrum (``exclude_similar_to``: the rawtoaces set, for one, contains ColorChecker-like patches).

PCA convention: **uncentred** by default, because the paper's projection ``sigma_j = integral S S_j`` (eq. (6))
reads the coefficients of ``S`` itself, so the model must be ``S = sum sigma_j S_j`` with no mean term (a mean
term would make recovery affine, ``y = A o + b``, which a projection sequence and ``apply_linear`` cannot
express). The uncentred first component of non-negative data is non-negative (Perron-Frobenius), which is why
the paper's symmetric design needs a single projection for it. The "variance" reported is then the share of the
second moment (energy) ``sum s_i^2 / sum_all s^2`` of the singular values; ``centred=True`` gives the textbook
PCA (mean removed, variance share) for comparison only.

File format shared by basis tables, plans and calibration bundles: ``.npz`` holding the arrays plus a JSON
``__meta__`` entry with the format name, version and a SHA-256 content hash of every array and of the metadata
(:func:`save_npz`, :func:`load_npz`). A file of another format or version, a truncated or edited file, is a
one-line ``ValueError`` naming the file.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

import colour
import colour.characterisation
import colour.quality
import numpy as np
from colour.quality.cfi2017 import load_TCS_CIE2017
from numpy.typing import ArrayLike

from specgpu.io.tables import load_npz, save_npz

__all__ = [
    "REFLECTANCE_SETS",
    "COLORCHECKER_24_SETS",
    "DEFAULT_WAVELENGTHS",
    "ReflectanceDatabase",
    "BasisTable",
    "load_reflectances",
    "read_reflectance_csv",
    "evaluation_exclusions",
    "pca_basis",
    "save_basis",
    "load_basis",
]

#: Default grid of the basis: 400-700 nm at 5 nm, the range the paper recovers.
DEFAULT_WAVELENGTHS = np.arange(400.0, 700.0 + 0.5, 5.0)

#: Maximum reflectance accepted from files (fluorescent whites slightly exceed 1).
MAX_REFLECTANCE = 1.5


def _colourchecker(name):
    def load():
        sds = colour.SDS_COLOURCHECKERS[name]
        return [(k, np.asarray(s.wavelengths, float), np.asarray(s.values, float)) for k, s in sds.items()]
    return load


def _quality(table, name):
    def load():
        sds = getattr(colour.quality, table)[name]
        return [(k, np.asarray(s.wavelengths, float), np.asarray(s.values, float)) for k, s in sds.items()]
    return load


def _cfi2017():
    msds = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
    wl = np.asarray(msds.wavelengths, float)
    return [(label, wl, np.asarray(msds.values[:, i], float)) for i, label in enumerate(msds.labels)]


def _rawtoaces():
    msds = colour.characterisation.read_training_data_rawtoaces_v1()
    wl = np.asarray(msds.wavelengths, float)
    return [(label, wl, np.asarray(msds.values[:, i], float)) for i, label in enumerate(msds.labels)]


#: Built-in training sets: name -> loader returning ``[(patch name, wavelengths nm, reflectance)]``.
REFLECTANCE_SETS = {
    "ColorChecker N Ohta": _colourchecker("ColorChecker N Ohta"),
    "BabelColor Average": _colourchecker("BabelColor Average"),
    "ISO 17321-1": _colourchecker("ISO 17321-1"),
    "PMC": _colourchecker("PMC"),
    "CIE 1995 TCS": _quality("SDS_TCS", "CIE 1995"),
    "CIE 2024 TCS": _quality("SDS_TCS", "CIE 2024"),
    "NIST CQS 7.4": _quality("SDS_VS", "NIST CQS 7.4"),
    "NIST CQS 9.0": _quality("SDS_VS", "NIST CQS 9.0"),
    "CIE 2017 CES": _cfi2017,
    "RAW to ACES v1": _rawtoaces,
}

#: Sets that are measurements of the same 24-patch ColorChecker: evaluating on one means excluding all.
COLORCHECKER_24_SETS = ("ColorChecker N Ohta", "BabelColor Average", "ISO 17321-1")


def _check_grid(wavelengths, name="wavelengths") -> np.ndarray:
    try:
        wl = np.asarray(wavelengths, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers in nm") from None
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError(f"{name} must be a 1-D grid of at least 2 wavelengths, got shape {wl.shape}")
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ValueError(f"{name} must be finite and strictly increasing")
    return wl


@dataclass(frozen=True)
class ReflectanceDatabase:
    """Measured reflectances on one wavelength grid.

    Attributes
    ----------
    wavelengths : numpy.ndarray
        (B,) strictly increasing wavelengths, nm.
    reflectance : numpy.ndarray
        (N, B) reflectance factors, float64, finite, in [0, 1.5].
    labels : tuple of str
        ``"<set>/<patch>"`` for each row.
    excluded : tuple of str
        Labels that were asked for but left out (excluded sets, spectra too close to a test spectrum,
        exact duplicates), for reports.
    """

    wavelengths: np.ndarray
    reflectance: np.ndarray
    labels: tuple
    excluded: tuple = ()

    def __post_init__(self):
        wl = _check_grid(self.wavelengths, "database wavelengths")
        r = np.asarray(self.reflectance, dtype=np.float64)
        if r.ndim != 2 or r.shape[1] != wl.size:
            raise ValueError(f"database reflectance must have shape (N, {wl.size}), got {r.shape}")
        if len(self.labels) != r.shape[0]:
            raise ValueError(f"database has {r.shape[0]} spectra but {len(self.labels)} labels")
        object.__setattr__(self, "wavelengths", wl)
        object.__setattr__(self, "reflectance", r)
        object.__setattr__(self, "labels", tuple(self.labels))
        object.__setattr__(self, "excluded", tuple(self.excluded))

    def __len__(self) -> int:
        return self.reflectance.shape[0]


def read_reflectance_csv(path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Read reflectances from a CSV file: first column wavelength (nm), one column per sample.

    An optional header row names the samples (``wavelength,red tile,blue tile``); without it the samples are
    named ``<file stem>:<column>``. Blank lines and lines starting with ``#`` are skipped.

    Returns
    -------
    list of (name, wavelengths, values)
        One entry per sample column; wavelengths strictly increasing (rows are sorted), values in [0, 1.5].

    Raises
    ------
    ValueError
        One line naming the file (and the row) for a missing file, ragged rows, non-numeric or non-finite cells,
        duplicated wavelengths, fewer than 2 rows or out-of-range reflectance.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: reflectance CSV not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read reflectance CSV ({exc.__class__.__name__})") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)
            and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ValueError(f"{path}: no data rows")
    names = None
    try:
        float(rows[0][0])
    except ValueError:
        names = [c.strip() for c in rows[0][1:]]
        rows = rows[1:]
    if len(rows) < 2:
        raise ValueError(f"{path}: needs at least 2 wavelength rows, got {len(rows)}")
    width = len(rows[0])
    if width < 2:
        raise ValueError(f"{path}: needs a wavelength column and at least one sample column")
    if names is not None and len(names) != width - 1:
        raise ValueError(f"{path}: header names {len(names)} samples but rows have {width - 1} value columns")
    data = np.empty((len(rows), width))
    for i, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"{path}: row {i + 1} has {len(row)} cells, expected {width}")
        try:
            data[i] = [float(c) for c in row]
        except ValueError:
            raise ValueError(f"{path}: row {i + 1} has a non-numeric cell: {row}") from None
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: NaN or infinite values")
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    if np.any(np.diff(data[:, 0]) <= 0):
        raise ValueError(f"{path}: duplicated wavelengths")
    vals = data[:, 1:]
    if vals.min() < 0 or vals.max() > MAX_REFLECTANCE:
        raise ValueError(f"{path}: reflectance must lie in [0, {MAX_REFLECTANCE}], "
                         f"got [{vals.min():g}, {vals.max():g}]")
    if names is None:
        names = [f"{path.stem}:{j + 1}" for j in range(width - 1)]
    return [(names[j], data[:, 0].copy(), vals[:, j].copy()) for j in range(width - 1)]


def evaluation_exclusions(chart: str) -> tuple[str, ...]:
    """The training sets to leave out when evaluating on ``chart``: the chart and every set of the same patches."""
    if chart in COLORCHECKER_24_SETS:
        return COLORCHECKER_24_SETS
    if chart not in REFLECTANCE_SETS:
        raise ValueError(f"unknown chart {chart!r}; valid: {', '.join(REFLECTANCE_SETS)}")
    return (chart,)


def load_reflectances(sets=None, *, wavelengths: ArrayLike | None = None, csv_files=(), exclude=(),
                      exclude_similar_to: ArrayLike | None = None,
                      similarity_tolerance: float = 0.01) -> ReflectanceDatabase:
    """Gather training reflectances on one grid.

    Parameters
    ----------
    sets : iterable of str, optional
        Names of :data:`REFLECTANCE_SETS` (all of them by default).
    wavelengths : array_like, optional
        Target grid, nm (default :data:`DEFAULT_WAVELENGTHS`, 400-700 nm at 5 nm). Spectra are linearly
        interpolated; a set that does not cover the grid is an error (no extrapolation).
    csv_files : iterable of path
        User CSV files (:func:`read_reflectance_csv`), added as sets named after the file.
    exclude : iterable of str
        Set names to leave out (e.g. :func:`evaluation_exclusions`).
    exclude_similar_to : array_like, (M, B), optional
        Test spectra on the same grid: any training spectrum within ``similarity_tolerance`` RMS of one is left
        out, so no copy of a test patch leaks into training through another set.
    similarity_tolerance : float
        RMS reflectance distance (>= 0) below which a training spectrum counts as a copy.

    Returns
    -------
    ReflectanceDatabase
        Exact duplicates (the same spectrum in two sets) kept once.
    """
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else _check_grid(wavelengths)
    names = list(REFLECTANCE_SETS) if sets is None else [str(s) for s in sets]
    for n in list(names) + [str(e) for e in exclude]:
        if n not in REFLECTANCE_SETS:
            raise ValueError(f"unknown reflectance set {n!r}; valid sets: {', '.join(REFLECTANCE_SETS)}")
    exclude = set(exclude)
    entries = []
    for n in names:
        if n not in exclude:
            entries.append((n, REFLECTANCE_SETS[n]()))
    for p in csv_files:
        entries.append((Path(p).stem, read_reflectance_csv(p)))
    rows, labels, dropped = [], [], [f"{n}/*" for n in names if n in exclude]
    for set_name, samples in entries:
        for patch, swl, val in samples:
            if swl[0] > wl[0] + 1e-9 or swl[-1] < wl[-1] - 1e-9:
                raise ValueError(f"reflectance set {set_name!r} covers {swl[0]:g}-{swl[-1]:g} nm, not the grid's "
                                 f"{wl[0]:g}-{wl[-1]:g} nm")
            rows.append(np.interp(wl, swl, val))
            labels.append(f"{set_name}/{patch}")
    if not rows:
        raise ValueError("no training reflectances left after the exclusions")
    r = np.array(rows)
    keep = np.ones(len(rows), bool)
    if exclude_similar_to is not None:
        test = np.asarray(exclude_similar_to, dtype=np.float64)
        if test.ndim != 2 or test.shape[1] != wl.size:
            raise ValueError(f"exclude_similar_to must have shape (M, {wl.size}), got {test.shape}")
        if not similarity_tolerance >= 0:
            raise ValueError(f"similarity_tolerance must be >= 0, got {similarity_tolerance!r}")
        dist = np.sqrt(np.mean((r[:, None, :] - test[None]) ** 2, axis=-1)).min(axis=1)
        keep &= dist >= similarity_tolerance
    # Exact duplicates (aliases, re-issued tables) would weight one spectrum twice.
    _, first = np.unique(np.round(r, 10), axis=0, return_index=True)
    unique = np.zeros(len(rows), bool)
    unique[first] = True
    dropped += [labels[i] for i in range(len(rows)) if not (keep[i] and unique[i])]
    keep &= unique
    if not keep.any():
        raise ValueError("no training reflectances left after the exclusions")
    return ReflectanceDatabase(wl, r[keep], tuple(np.array(labels)[keep]), tuple(dropped))


@dataclass(frozen=True)
class BasisTable:
    """Principal components of a reflectance database.

    Attributes
    ----------
    wavelengths : numpy.ndarray
        (B,) nm.
    functions : numpy.ndarray
        (B, n) basis functions as columns, orthonormal under the plain dot product over the grid
        (``functions.T @ functions = I``); sign fixed so the first is non-negative (uncentred) and every other
        has its largest-magnitude value positive.
    singular_values : numpy.ndarray
        (n,) singular values of the (centred or not) training matrix, decreasing.
    mean : numpy.ndarray
        (B,) mean removed before the decomposition (zeros when uncentred).
    centred : bool
    n_training : int
        Number of training spectra.
    source : str
        Description of the training set (sets, exclusions).
    """

    wavelengths: np.ndarray
    functions: np.ndarray
    singular_values: np.ndarray
    mean: np.ndarray
    centred: bool
    n_training: int
    source: str = ""

    def __post_init__(self):
        for k in ("wavelengths", "functions", "singular_values", "mean"):
            if np.asarray(getattr(self, k)).dtype.kind not in "biuf":
                raise ValueError(f"basis {k} must hold real numbers, got dtype {np.asarray(getattr(self, k)).dtype}")
        wl = _check_grid(self.wavelengths, "basis wavelengths")
        f = np.asarray(self.functions, dtype=np.float64)
        if f.ndim != 2 or f.shape[0] != wl.size or f.shape[1] < 1:
            raise ValueError(f"basis functions must have shape ({wl.size}, n), got {f.shape}")
        s = np.asarray(self.singular_values, dtype=np.float64)
        if s.shape != (f.shape[1],) or not np.all(s >= 0) or not np.all(np.isfinite(f)) or not np.all(np.isfinite(s)):
            raise ValueError("basis singular values must be (n,) non-negative and the functions finite")
        mean = np.asarray(self.mean, dtype=np.float64)
        if mean.shape != wl.shape or not np.all(np.isfinite(mean)):
            raise ValueError(f"basis mean must be finite of shape {wl.shape}, got {mean.shape}")
        for k, v in (("wavelengths", wl), ("functions", f), ("singular_values", s), ("mean", mean)):
            object.__setattr__(self, k, v)

    @property
    def cumulative_variance(self) -> np.ndarray:
        """(n,) share of the training energy (uncentred) or variance (centred) held by the first 1..n components."""
        e = self.singular_values**2
        return np.cumsum(e) / e.sum()

    def first(self, m: int) -> np.ndarray:
        """(B, m) the first ``m`` basis functions."""
        if not isinstance(m, (int, np.integer)) or not 1 <= m <= self.functions.shape[1]:
            raise ValueError(f"m must be an integer in [1, {self.functions.shape[1]}], got {m!r}")
        return self.functions[:, :m]

    def project(self, reflectance: ArrayLike, m: int) -> np.ndarray:
        """Best m-term approximation (..., B) of reflectances on the basis grid (least squares)."""
        phi = self.first(m)
        r = np.asarray(reflectance, dtype=np.float64) - self.mean
        return r @ phi @ phi.T + self.mean


def pca_basis(database: ReflectanceDatabase, *, centred: bool = False) -> BasisTable:
    """Principal components of a reflectance database (see the module notes on centring).

    Parameters
    ----------
    database
        Training reflectances.
    centred
        Remove the mean first (textbook PCA). Default False: the paper's uncentred model.

    Returns
    -------
    BasisTable
        All ``min(N, B)`` components.
    """
    r = database.reflectance
    mean = r.mean(axis=0) if centred else np.zeros(r.shape[1])
    _, s, vt = np.linalg.svd(r - mean, full_matrices=False)
    f = vt.T.copy()
    for j in range(f.shape[1]):
        if j == 0 and not centred:
            sign = 1.0 if f[:, 0].sum() >= 0 else -1.0
        else:
            sign = 1.0 if f[np.argmax(np.abs(f[:, j])), j] >= 0 else -1.0
        f[:, j] *= sign
    if not centred:
        # Perron-Frobenius makes it non-negative; clear the rounding-level negatives so no light is asked for them.
        f[:, 0] = np.maximum(f[:, 0], 0.0)
        f[:, 0] /= np.linalg.norm(f[:, 0])
    sets = sorted({lab.split("/", 1)[0] for lab in database.labels})
    src = f"{len(database)} spectra from {', '.join(sets)}; {len(database.excluded)} excluded"
    return BasisTable(database.wavelengths, f, s, mean, bool(centred), len(database), src)


_BASIS_FORMAT = "specgpu.basis"
_BASIS_VERSION = 1


def save_basis(path: str | os.PathLike[str], table: BasisTable) -> str:
    """Save a basis table (versioned ``.npz``); return its content hash."""
    arrays = {"wavelengths": table.wavelengths, "functions": table.functions,
              "singular_values": table.singular_values, "mean": table.mean}
    meta = {"centred": table.centred, "n_training": int(table.n_training), "source": table.source}
    return save_npz(path, _BASIS_FORMAT, _BASIS_VERSION, arrays, meta)


def load_basis(path: str | os.PathLike[str]) -> BasisTable:
    """Load a basis table written by :func:`save_basis` (one-line ``ValueError`` naming the file if unusable)."""
    arrays, meta, _, _ = load_npz(path, _BASIS_FORMAT, (_BASIS_VERSION,))
    try:
        return BasisTable(arrays["wavelengths"], arrays["functions"], arrays["singular_values"], arrays["mean"],
                          bool(meta["centred"]), int(meta["n_training"]), str(meta.get("source", "")))
    except (KeyError, ValueError, TypeError, OverflowError) as exc:
        raise ValueError(f"{path}: invalid basis table ({exc})") from None
