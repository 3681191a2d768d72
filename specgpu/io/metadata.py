"""The caller's metadata as exact JSON, stored in file headers (EXR, PNG, ENVI) and in ``sequence.json``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from specgpu.core.text import one_line

_META_ATTRIBUTE = "specgpu:metadata"  # header attribute holding the caller's metadata as JSON (exact floats)


# ---- metadata ------------------------------------------------------------------------------------------------------
def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def _metadata_json(path, metadata) -> str | None:
    if metadata is None:
        return None
    if not isinstance(metadata, Mapping):
        raise ValueError(f"{path}: metadata must be a mapping of str to JSON values, got {type(metadata).__name__}")
    try:
        return json.dumps(dict(metadata), default=_json_default, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: metadata must be JSON-serialisable with finite numbers "
                         f"({one_line(str(exc))})") from None


def _metadata_from(path, attributes: dict) -> dict:
    text = attributes.get(_META_ATTRIBUTE)
    if text is None:
        return {}
    try:
        meta = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: header attribute {_META_ATTRIBUTE!r} is not valid JSON "
                         f"({one_line(str(exc))})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: header attribute {_META_ATTRIBUTE!r} must hold a JSON object")
    return meta
