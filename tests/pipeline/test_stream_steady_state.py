"""The stream's per-sequence path in a steady state: after the first sequence nothing is built and nothing taken
from the system, every full-quality option at once (``--motion global --denoise --white-roi``); the checked warped
pass on the device equal to the host's check; the stream's full-quality maps equal to ``recover``'s."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from stream_helpers import shared_stream_setup

from specgpu.engine import warp_map
from specgpu.engine.runtime import get_allocator, get_queue, program_cache_size
from specgpu.motion.residual import residual_check
from specgpu.pipeline import moving_layers
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.recovery import recover
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.stream import Stream
from specgpu.rig.scene import white_tile_roi

DENOISE = (2, 1e-4)


@pytest.fixture(scope="module")
def setup():
    return shared_stream_setup(320, 240, sequences=3, white_tile=0.99)


def drifting(setup, index: int) -> np.ndarray:
    """Sequence ``index`` of the recording with frame k moved (k, k // 3) px: a scene that moves."""
    K = setup.plan.K
    seq = setup.frames[index * K:(index + 1) * K]
    return np.stack([np.roll(seq[k], (k // 3, k), axis=(0, 1)) for k in range(K)])


def full_decoder(setup, outputs=("coefficients", "XYZ", "dE")):
    h, w = setup.frames.shape[1:]
    return SequenceDecoder(setup.plan, setup.bundle, outputs, reference=setup.reference, frame_shape=(h, w),
                           white_roi=white_tile_roi(h, w), denoise=DENOISE, motion="global")


def test_a_second_sequence_builds_and_allocates_nothing(setup, monkeypatch):
    made = []
    init = warp_map.PreparedWarp.__init__

    def counted(self, *args, **kw):
        made.append(1)
        init(self, *args, **kw)

    monkeypatch.setattr(warp_map.PreparedWarp, "__init__", counted)
    dec = full_decoder(setup)
    pool = get_allocator(get_queue())
    dec.maps(drifting(setup, 0))
    programs, managed, set_up = program_cache_size(), pool.managed_bytes, len(made)
    assert set_up >= 1  # the first sequence made its passes
    for i in (1, 2):
        maps = dec.maps(drifting(setup, i))
        assert np.isfinite(maps["XYZ"]).mean() > 0.5
    assert program_cache_size() == programs, "a kernel was built after the first sequence"
    assert len(made) == set_up, "a warped pass was set up again after the first sequence"
    assert pool.managed_bytes == managed, "the memory pool took memory from the system after the first sequence"


def test_the_check_on_the_device_equals_the_hosts(setup, monkeypatch):
    """The checked warped pass (outputs, mask, the residual's flags) bit for bit as with the chi2 on the host."""
    frames = drifting(setup, 1)
    plan, bundle = setup.plan, setup.bundle
    kw = dict(dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field, saturation=float(bundle.max_code),
              residual=residual_check(plan, bundle))
    got = recover_moving(frames, plan.A, **kw)
    monkeypatch.setattr(moving_layers, "warped_checked", lambda *a, **k: None)  # the host's check
    want = recover_moving(frames, plan.A, **kw)
    np.testing.assert_array_equal(got.mask, want.mask)
    np.testing.assert_array_equal(got.y, want.y)
    assert np.count_nonzero(got.mask & 8) > 0  # the check had something to flag (the rolled frames' wrapped edge)


def test_full_quality_stream_equals_recover(setup):
    """Coefficients, XYZ and dE of the stream with --motion global --denoise --white-roi against ``recover`` of
    the same frames with the same options (XYZ from its filtered cube; dE checked where both are finite)."""
    h, w = setup.frames.shape[1:]
    roi = white_tile_roi(h, w)
    kept = []

    def keep(result):
        kept.append(({k: np.array(v) for k, v in result.arrays.items()}, np.array(result.frames)))

    Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=("cube", "XYZ", "dE"),
           reference=setup.reference, cube_dtype=np.float32, policy="block", sinks=[keep], motion="global",
           denoise=DENOISE, white_roi=roi).run()
    assert len(kept) == 3
    for maps, frames in kept[:2]:
        folder = SequenceFolder(Path("mem"), frames[None], setup.plan, setup.bundle, [], {})
        want = recover(folder, sequence=0, motion="global", denoise=DENOISE, white_roi=roi)
        np.testing.assert_array_equal(np.isnan(maps["cube"]), np.isnan(want))
        np.testing.assert_allclose(np.nan_to_num(maps["cube"]), np.nan_to_num(want), rtol=1e-4, atol=1e-5)
        assert np.isfinite(want).all(axis=-1).mean() > 0.9
