"""Helpers the file-format tests share: one-line error checks, small cubes, raw EXR channels, oiiotool."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

# OpenImageIO's own command-line tool: the console script next to this interpreter (the wheel installs it), or PATH.
OIIOTOOL = next((str(p) for p in (Path(sys.executable).parent / "oiiotool",) if p.exists()), None) or \
    shutil.which("oiiotool")


def raises_one_line(exc_type, match):
    """pytest.raises that also checks the message is one line."""

    class _Ctx:
        def __enter__(self):
            self.ctx = pytest.raises(exc_type, match=match)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.ctx.__exit__(*exc)
            assert "\n" not in str(self.info.value), str(self.info.value)
            return out

    return _Ctx()


def cube_data(h=6, w=5, b=4, seed=0):
    return np.random.default_rng(seed).random((h, w, b)).astype(np.float32)


def write_exr_channels(path, names, data, attributes=None):
    """An EXR written straight through OpenImageIO with the given channel names (any order)."""
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    spec.channelnames = tuple(names)
    for k, v in (attributes or {}).items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data, np.float32))
    out.close()


def no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if ".tmp" in p.name]
