"""The twin workload the stream's tests replay: a longer recording begins with the sequences a shorter one holds,
which is what lets the suite record it once (tests/stream_helpers.py) and hand each test the sequences it asks."""

import numpy as np
import pytest
from stream_helpers import RECORDED, shared_stream_setup

from specgpu.pipeline.twin_replay import stream_setup


def test_the_shared_recording_holds_what_a_recording_of_fewer_sequences_records():
    own = stream_setup(320, 240, sequences=1, output_step_nm=10.0)
    shared = shared_stream_setup(sequences=1)
    K = own.plan.K
    assert shared.frames.shape == own.frames.shape == (K, 240, 320)
    np.testing.assert_array_equal(shared.frames, own.frames)
    assert [(i.frame_id, i.pattern_index, i.timestamp_s) for i in shared.infos] == \
        [(i.frame_id, i.pattern_index, i.timestamp_s) for i in own.infos]
    assert shared.bundle.hash == own.bundle.hash and shared.plan.hash == own.plan.hash
    np.testing.assert_array_equal(shared.reference, own.reference)
    longer = shared_stream_setup(sequences=RECORDED)
    assert longer.frames.shape[0] == RECORDED * K and not np.array_equal(longer.frames[K:2 * K], own.frames)


def test_the_shared_recording_is_read_only_and_each_caller_replays_its_own_light():
    a, b = shared_stream_setup(sequences=2), shared_stream_setup(sequences=2)
    with pytest.raises(ValueError, match="read-only"):
        a.frames[0, 0, 0] = 0
    assert a.light is not b.light and a.infos is not b.infos
    with pytest.raises(ValueError, match=r"sequences must lie in \[1, 4\]"):
        shared_stream_setup(sequences=RECORDED + 1)
