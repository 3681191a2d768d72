"""Versioned, hashed ``.npz`` tables: the file form of basis tables, calibration bundles and plans.

Each file holds its arrays and a ``__meta__`` JSON header (format name, version, SHA-256 of the content), so a
reader refuses another format, an unknown version or an edited / truncated file in one line naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from specgpu.io.npz import npz_members, savez_deflated
from specgpu.io.paths import atomic_path

__all__ = ["content_hash", "save_npz", "load_npz"]


def content_hash(arrays: dict, meta: dict) -> str:
    """SHA-256 (hex) of named arrays (name, dtype, shape, bytes, in name order) and JSON metadata."""
    h = hashlib.sha256()
    h.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_npz(path: str | os.PathLike[str], kind: str, version: int, arrays: dict, meta: dict,
             extra: dict | None = None) -> str:
    """Write a versioned, hashed ``.npz``; return the content hash.

    ``meta`` must be JSON-serializable; the hash covers it and every array. ``extra``: further header entries
    derived from the content (a plan's timing), for readers of the header alone; not hashed, ignored on load.
    """
    path = Path(path)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for k, v in arrays.items():
        if v.dtype == object:
            raise ValueError(f"{path}: array {k!r} is not numeric")
    digest = content_hash(arrays, meta)
    header = {"format": kind, "version": int(version), "hash": digest, "meta": meta}
    reserved = set(header) & set(extra or {})
    if reserved:
        raise ValueError(f"{path}: extra header entries may not replace {sorted(reserved)}")
    header.update(json.loads(json.dumps(extra or {})))
    # np.savez adds ".npz" to a name without it; write through a file object to keep the path as given, to a
    # temporary name renamed over the target at the end: an interrupted save never destroys a good file
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        savez_deflated(fh, {"__meta__": np.array(json.dumps(header)), **arrays})
    return digest


def load_npz(path: str | os.PathLike[str], kind: str, versions) -> tuple[dict, dict, int, str]:
    """Read a file written by :func:`save_npz`; check its format, version and hash.

    Returns
    -------
    arrays, meta, version, hash

    Raises
    ------
    ValueError
        One line naming the file: not found, not an npz, another format, an unknown version, or content that
        does not match its hash (truncated or edited).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: {kind} file not found")
    try:
        npz_members(path)  # the declared sizes, checked before any array is inflated
    except ValueError as exc:
        raise ValueError(str(exc).replace("truncated or corrupt .npz", f"corrupt {kind} file", 1)) from None
    try:
        with np.load(path, allow_pickle=False) as data:
            if "__meta__" not in data.files:
                raise ValueError(f"{path}: not a {kind} file (no __meta__ entry)")
            header = json.loads(str(data["__meta__"]))
            arrays = {k: np.array(data[k]) for k in data.files if k != "__meta__"}
    except ValueError as exc:
        msg = " ".join(str(exc).split())  # one line
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: corrupt {kind} file ({msg})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, json.JSONDecodeError,
            UnicodeDecodeError, SyntaxError, tokenize.TokenError, MemoryError, RuntimeError) as exc:
        # numpy parses a corrupt .npy header as a Python literal: its syntax errors, and a header declaring a huge
        # array, are corruption; so are the flags zipfile refuses (RuntimeError: "encrypted", unknown compression)
        raise ValueError(f"{path}: corrupt {kind} file ({exc.__class__.__name__})") from None
    if not isinstance(header, dict) or header.get("format") != kind:
        got = header.get("format") if isinstance(header, dict) else None
        raise ValueError(f"{path}: not a {kind} file (format {got!r})")
    version = header.get("version")
    if version not in tuple(versions):
        raise ValueError(f"{path}: unknown {kind} version {version!r}; this specgpu reads {tuple(versions)}")
    meta = header.get("meta")
    if not isinstance(meta, dict) or content_hash(arrays, meta) != header.get("hash"):
        raise ValueError(f"{path}: corrupt {kind} file (content does not match its hash)")
    return arrays, meta, int(version), str(header["hash"])
