"""Image sizes as ``specgpu bench`` takes them (``--sizes``, ``--stream-size``): ``"WxH,WxH"``."""

from __future__ import annotations

import re

__all__ = ["parse_sizes"]

_SIZE = re.compile(r"\s*([0-9]+)\s*[xX]\s*([0-9]+)\s*", re.ASCII)


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """Image sizes from a comma-separated ``"WxH,WxH"`` list.

    Parameters
    ----------
    text : str
        For example ``"640x480,2048x2048"``; ``X`` and spaces around the numbers are accepted.

    Returns
    -------
    list of (int, int)
        (width, height) pairs, both >= 1, in the order given.

    Raises
    ------
    ValueError
        Naming the first token that is not ``WxH`` with positive integers.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"no image size given in {text!r}: expected e.g. '640x480,2048x2048'")
    sizes = []
    for token in text.split(","):
        match = _SIZE.fullmatch(token)
        if match is None:
            raise ValueError(f"bad image size {token!r}: expected WxH with positive integers, e.g. '640x480'")
        width, height = int(match.group(1)), int(match.group(2))
        if width < 1 or height < 1:
            raise ValueError(f"bad image size {token!r}: width and height must be at least 1")
        sizes.append((width, height))
    return sizes
