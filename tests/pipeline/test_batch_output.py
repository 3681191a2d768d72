"""Reading a `specgpu batch` output (specgpu.pipeline.batch_output): the computed sequences as the batch wrote them,
and one-line refusals for a sequence not computed yet, a missing chunk, another format or version."""

from __future__ import annotations

import json

import numpy as np
import pytest
from capture_helpers import write_chart_capture
from zarr_helpers import damaged_copy

from specgpu.pipeline import read_capture, recover
from specgpu.pipeline.batch import prepare_batch, process_sequences
from specgpu.pipeline.batch_output import open_batch_output


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A capture of 3 sequences and its batch output (cube, XYZ) with sequences 0 and 2 computed."""
    root = tmp_path_factory.mktemp("batch-output")
    seq = write_chart_capture(root, "seq", sequences=3, noise_seed=3)
    folder = read_capture(seq)
    job, _ = prepare_batch(seq, folder.plan, folder.calibration, root / "out.zarr", outputs=("cube", "XYZ"))
    assert not any(r.get("error") for r in process_sequences(job, [0, 2]))
    return folder, root / "out.zarr"


def test_computed_sequences_read_as_recovered_and_the_others_are_refused(made):
    folder, out = made
    batch = open_batch_output(out)
    assert batch.sequences == 3 and batch.pending == [1] and batch.missing("cube") == []
    np.testing.assert_allclose(batch.read("cube", 2), recover(folder, sequence=2), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError) as refused:  # zarr alone reads it as NaN
        batch.read("XYZ", 1)
    assert str(refused.value) == (f"{out}/XYZ: sequence 1 is not computed yet (the batch stopped before it; run "
                                  "the same specgpu batch again to resume it)")
    with pytest.raises(ValueError, match=r"out\.zarr/XYZ: sequence 1 is not computed yet"):
        batch.read("XYZ", slice(0, 3))
    np.testing.assert_array_equal(batch.read("XYZ", slice(2, 3))[0], batch.read("XYZ", 2))


def test_a_computed_sequence_whose_chunk_is_gone_is_damage(made, tmp_path):
    _, out = made
    bad = open_batch_output(damaged_copy(out, tmp_path / "bad.zarr", missing=[("cube", 2)]))
    assert bad.missing("cube") == [2] and bad.missing("XYZ") == []
    with pytest.raises(ValueError, match=r"bad\.zarr/cube: sequence 2 is committed but its chunk .* is missing"):
        bad.read("cube", 2)


def test_what_is_not_a_batch_output_is_one_line(made, tmp_path):
    folder, out = made
    with pytest.raises(FileNotFoundError, match="nothing.zarr: batch output not found"):
        open_batch_output(tmp_path / "nothing.zarr")
    (tmp_path / "plain").mkdir()
    with pytest.raises(ValueError, match="plain: not a zarr v3 batch output"):
        open_batch_output(tmp_path / "plain")
    old = damaged_copy(out, tmp_path / "old.zarr")
    doc = json.loads((old / "zarr.json").read_text())
    doc["attributes"]["version"] = 1
    (old / "zarr.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"old\.zarr: batch output version 1 is not supported \(this specgpu reads"):
        open_batch_output(old)
    doc["attributes"]["format"] = "specgpu.recording"
    (old / "zarr.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"old\.zarr: not a specgpu batch output \(format 'specgpu.recording'\)"):
        open_batch_output(old)
