"""The stream's twin workload (:func:`specgpu.pipeline.twin_replay.stream_setup`) made once per test session and
shared by every file that streams it: calibrating the twin and recording the chart cost seconds each time."""

from __future__ import annotations

import copy
import functools
from dataclasses import replace

from specgpu.pipeline.twin_replay import stream_setup

#: the most sequences a test asks of the shared recording
RECORDED = 4


@functools.cache
def _recording(width: int, height: int, output_step_nm: float, white_tile: float | None):
    setup = stream_setup(width, height, sequences=RECORDED, output_step_nm=output_step_nm, white_tile=white_tile)
    setup.frames.setflags(write=False)  # shared by every test of the session: a test that writes to it fails
    setup.reference.setflags(write=False)
    return setup


def shared_stream_setup(width: int = 320, height: int = 240, *, sequences: int, output_step_nm: float = 10.0,
                        white_tile: float | None = None):
    """``stream_setup(width, height, sequences=sequences, output_step_nm=..., white_tile=...)``, made once per
    session: the first ``sequences`` of one recording of :data:`RECORDED` sequences (the twin records each sequence
    after the one before from one seeded draw, so these are the frames a recording of ``sequences`` holds). The
    frames and the reference are read-only; the light, whose replay position a stream advances, is each caller's
    own copy."""
    if not 1 <= sequences <= RECORDED:
        raise ValueError(f"sequences must lie in [1, {RECORDED}], got {sequences}")
    full = _recording(int(width), int(height), float(output_step_nm), white_tile)
    n = sequences * full.plan.K
    return replace(full, frames=full.frames[:n], infos=list(full.infos[:n]), light=copy.deepcopy(full.light))
