"""The transfer paths of the linear map: the pinned, row-chunked path of discrete devices (forced here on every
device) against the direct path, and the choice of path by device and environment."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from specgpu.engine import runtime, transfer
from specgpu.engine.linear_map import apply_linear

# once per kernel variant, forced on each device present (tests/conftest.py kernel_variant)
pytestmark = pytest.mark.usefixtures("kernel_variant")


@pytest.mark.parametrize("layout", ["planar", "interleaved"])
@pytest.mark.parametrize("out_dtype", [np.float32, np.float16])
@pytest.mark.parametrize("chunk_rows", [1, 3, 1000])
def test_pinned_row_chunked_transfers_equal_the_direct_path(queue, monkeypatch, layout, out_dtype, chunk_rows):
    """The discrete-device path (pinned staging, row chunks on upload / compute / read-back queues), forced on
    any device: the same results and mask as the direct path, for chunks of one row, of an uneven number of rows
    and of the whole image, with per-frame dark, gain and saturation."""
    rng = np.random.default_rng(chunk_rows)
    K, B, shape = 5, 7, (11, 13)
    frames = rng.integers(0, 1000, (K, *shape), dtype=np.uint16)
    frames[1, 4, 5] = 1023
    dark = rng.uniform(0, 20, (K, *shape)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, shape).astype(np.float32)
    A = rng.normal(0, 1e-3, (B, K))
    kwargs = dict(out_dtype=out_dtype, layout=layout, saturation=1023, return_mask=True, device=queue)
    monkeypatch.setenv("SPECGPU_TRANSFER", "direct")
    direct = apply_linear(frames, A, dark, gain, **kwargs)
    monkeypatch.setenv("SPECGPU_TRANSFER", "pinned")
    row_bytes = shape[1] * B * np.dtype(out_dtype).itemsize
    monkeypatch.setattr(transfer, "CHUNK_BYTES", chunk_rows * row_bytes)
    pinned = apply_linear(frames, A, dark, gain, **kwargs)
    assert pinned.y.shape == direct.y.shape and pinned.y.dtype == direct.y.dtype
    np.testing.assert_array_equal(pinned.y, direct.y)
    np.testing.assert_array_equal(pinned.mask, direct.mask)
    assert pinned.mask.sum() > 0
    # the pinned result is a NumPy array like any other; its block returns to the pool when it is dropped
    pool = transfer.pinned_pool(runtime.get_queue(queue))
    held = pool.held_bytes()
    del pinned
    gc.collect()
    assert pool.held_bytes() > held


def test_transfer_mode_by_device_and_override(queue, monkeypatch):
    monkeypatch.delenv("SPECGPU_TRANSFER", raising=False)
    assert transfer.transfer_mode(queue.device) == ("pinned" if runtime.is_discrete(queue.device) else "direct")
    monkeypatch.setenv("SPECGPU_TRANSFER", "bogus")
    with pytest.raises(runtime.SpecgpuDeviceError, match=r"^SPECGPU_TRANSFER='bogus' is no transfer mode"):
        transfer.transfer_mode(queue.device)
    assert transfer.transfer_mode(queue.device, "Pinned") == "pinned"
