"""The tables of a rig TOML read into the rig's parameter dataclasses, one parser for every table."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

__all__ = ["build_table"]

#: (table, key) of the keys naming a file (a built-in name otherwise), resolved against the rig file's folder.
_PATH_KEYS = {("light", "lamp"), ("light", "spectra"), ("camera", "sensitivity")}


def build_table(cls, table: dict, section: str, source: str, base: Path | None = None):
    """The dataclass ``cls`` from a TOML table: every key one of its fields, each value of its default's type
    (true / false for a flag, a number, an integer, a string, a list of as many numbers), file paths resolved
    against ``base``; any error is one line naming ``source`` and ``section.key``."""
    if not isinstance(table, dict):
        raise ValueError(f"{source}: [{section}] must be a table, got {table!r}")
    valid = {f.name: f for f in fields(cls)}
    kwargs = {}
    for key, value in table.items():
        if key not in valid:
            raise ValueError(f"{source}: unknown key {section}.{key}; valid keys: {', '.join(valid)}")
        default = valid[key].default
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{source}: {section}.{key} must be true or false, got {value!r}")
        elif isinstance(value, bool):
            kind = {int: "an integer", float: "a number", str: "a string"}.get(type(default), "a list")
            raise ValueError(f"{source}: {section}.{key} must be {kind}, got {value!r}")
        if isinstance(default, str):
            if not isinstance(value, str):
                raise ValueError(f"{source}: {section}.{key} must be a string, got {value!r}")
            named = value in ("xenon", "kinoton-75p", "cmos")
            if (section, key) in _PATH_KEYS and base is not None and value and not named:
                p = Path(value)
                value = str(p if p.is_absolute() else base / p)
                if not Path(value).is_file():
                    raise ValueError(f"{source}: {section}.{key} file not found: {value!r}")
        elif default == ():  # a list of any length (one value per LED, say)
            numbers = isinstance(value, list) and all(
                isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)
            if not numbers:
                raise ValueError(f"{source}: {section}.{key} must be a list of numbers, got {value!r}")
            value = tuple(float(c) for c in value)
        elif isinstance(default, tuple):
            if (not isinstance(value, list) or len(value) != len(default)
                    or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in value)):
                raise ValueError(f"{source}: {section}.{key} must be a list of {len(default)} numbers, got {value!r}")
            value = tuple(value)
        elif isinstance(default, int) and not isinstance(default, bool):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if not isinstance(value, int):
                raise ValueError(f"{source}: {section}.{key} must be an integer, got {value!r}")
        elif isinstance(default, float):
            if not isinstance(value, (int, float)):
                raise ValueError(f"{source}: {section}.{key} must be a number, got {value!r}")
            value = float(value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None
