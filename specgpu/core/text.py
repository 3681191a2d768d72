"""Text helpers shared by every room: a library's error message collapsed to one line."""

from __future__ import annotations

__all__ = ["one_line", "short_list"]


def one_line(text: str, limit: int = 240) -> str:
    """Collapse a (possibly multi-line, repeated) library error message to one short line."""
    seen = []
    for line in str(text).splitlines():
        line = " ".join(line.split())
        if line and line not in seen:
            seen.append(line)
    out = "; ".join(seen) or "unknown error"
    return out if len(out) <= limit else out[: limit - 3] + "..."



def short_list(items, head: int = 3, sep: str = ", ") -> str:
    """``items`` joined by ``sep``, the middle elided when there are more than ``head + 1``: ``c0, c1, c2, ...,
    c319 (320)``, so a message naming hundreds of channels stays one short line."""
    items = [str(v) for v in items]
    if len(items) <= head + 1:
        return sep.join(items)
    return sep.join(items[:head]) + f"{sep}...{sep}{items[-1]} ({len(items)})"
