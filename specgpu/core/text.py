"""Text helpers shared by every room: a library's error message collapsed to one line."""

from __future__ import annotations

__all__ = ["one_line"]


def one_line(text: str, limit: int = 240) -> str:
    """Collapse a (possibly multi-line, repeated) library error message to one short line."""
    seen = []
    for line in str(text).splitlines():
        line = " ".join(line.split())
        if line and line not in seen:
            seen.append(line)
    out = "; ".join(seen) or "unknown error"
    return out if len(out) <= limit else out[: limit - 3] + "..."

