"""Calibrations of the twin kept on disk and reused: the same rig calibrated with the same options by the same
code gives the same bundle, so a program that calibrates a twin again and again (the demo, each run) loads the
bundle it saved the first time instead of running both feedback loops again.

A bundle is filed under its **key** (:func:`calibration_key`): a SHA-256 of the whole rig description, the
procedure's options and seed, the bundle format's version and the source of the rooms a calibration of the twin
runs (``core``, ``rig``, ``calibration``), so a change to any of them makes a new key and the old file is never
read again. A file found under its key is loaded with every check of
:func:`~specgpu.calibration.bundle.load_calibration` (format, version, content hash, the rig's fingerprint); one
that fails them is calibrated again and replaced. Folders searched: those the caller names (the demo: its output
folder) and the user's cache folder (:func:`user_cache_dir`: ``$SPECGPU_CACHE_DIR``, else
``$XDG_CACHE_HOME/specgpu``, else ``~/.cache/specgpu``; ``SPECGPU_CACHE_DIR=""`` turns it off).
"""

from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path

from specgpu.calibration.bundle import CALIBRATION_VERSION, CalibrationBundle, load_calibration, save_calibration
from specgpu.calibration.procedure import calibrate
from specgpu.rig.config import RigDescription

__all__ = ["calibration_key", "calibration_file", "cached_calibration", "find_calibration", "user_cache_dir",
           "CACHE_ENV"]

#: The environment variable naming the user's cache folder (empty: no user cache).
CACHE_ENV = "SPECGPU_CACHE_DIR"
#: The rooms whose source a calibration of the twin runs: their code is part of the key.
_ROOMS = ("core", "rig", "calibration")


@lru_cache(maxsize=1)
def _code_digest() -> str:
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for room in _ROOMS:
        for path in sorted((package / room).glob("*.py")):
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def calibration_key(description: RigDescription, **options) -> str:
    """SHA-256 (hex) naming one calibration of the twin: the whole rig ``description`` (its exposure, noise seed,
    the bench's imperfections and drift included), the keyword ``options`` of
    :func:`~specgpu.calibration.procedure.calibrate` as given (``seed`` and the rest; a default spelt out makes
    another key than the same default left out, which costs one calibration more, never a wrong bundle), the
    bundle format's version and the calibrating code."""
    rig = {**description.to_dict(), "realism": description.realism.to_dict(), "drift": description.drift.to_dict(),
           "motion": description.motion.to_dict(), "capture_delay_s": description.capture_delay_s}
    key = {"rig": rig, "seed": description.seed, "options": options,
           "format_version": CALIBRATION_VERSION, "code": _code_digest()}
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()


def user_cache_dir() -> Path | None:
    """The user's cache folder for calibrations: ``$SPECGPU_CACHE_DIR`` when set (None when set empty), else
    ``$XDG_CACHE_HOME/specgpu``, else ``~/.cache/specgpu``."""
    if CACHE_ENV in os.environ:
        value = os.environ[CACHE_ENV].strip()
        return Path(value).expanduser() if value else None
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "specgpu"


def _file(folder: Path, key: str) -> Path:
    return Path(folder) / f"calibration-{key[:24]}.npz"


def calibration_file(description: RigDescription, folder, **options) -> Path:
    """The file in ``folder`` that keeps the calibration of ``description`` with ``options`` (:func:`cached_calibration`
    writes it there, :func:`find_calibration` reads it), whether or not it exists yet."""
    return _file(Path(folder), calibration_key(description, **options))


def _folders(folders, user_cache: bool) -> list[Path]:
    out = [Path(f) for f in folders]
    user = user_cache_dir() if user_cache else None
    return out + ([user] if user is not None and user not in out else [])


def find_calibration(description: RigDescription, folders=(), *, user_cache: bool = True,
                     **options) -> tuple[CalibrationBundle, Path] | None:
    """The bundle saved for this calibration (:func:`calibration_key`) in ``folders`` or the user's cache, and
    its file; None when no folder holds one that passes every check of
    :func:`~specgpu.calibration.bundle.load_calibration` (such a file is left for :func:`cached_calibration` to
    replace)."""
    key = calibration_key(description, **options)
    for folder in _folders(folders, user_cache):
        path = _file(folder, key)
        if path.is_file():
            try:
                return load_calibration(path, rig=description), path
            except (ValueError, OSError):
                continue
    return None


def cached_calibration(description: RigDescription, folders=(), *, user_cache: bool = True,
                       **options) -> tuple[CalibrationBundle, Path | None]:
    """:func:`~specgpu.calibration.procedure.calibrate` ``(description, **options)``, or the bundle it made
    before, kept in ``folders`` or the user's cache (:func:`user_cache_dir`; off with ``user_cache=False``).

    Returns
    -------
    (CalibrationBundle, Path or None)
        The bundle, and the file it was loaded from (None: calibrated now, then saved into every folder that can
        be written; a folder that cannot, such as a read-only cache, is passed over).
    """
    found = find_calibration(description, folders, user_cache=user_cache, **options)
    if found is not None:
        return found
    bundle = calibrate(description, **options)
    key = calibration_key(description, **options)
    for folder in _folders(folders, user_cache):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            save_calibration(_file(folder, key), bundle)
        except OSError:
            continue
    return bundle, None
