"""Small zarr outputs made in-process (no CLI, no Dask cluster): a recording of the stream's default outputs, a
batch output of some of its sequences, and damaged copies of either."""

from __future__ import annotations

import shutil
from pathlib import Path

from stream_helpers import shared_stream_setup

from specgpu.io.recording import ZarrRecorder
from specgpu.pipeline import Stream
from specgpu.pipeline.batch import prepare_batch, process_sequences
from specgpu.planning import save_plan

#: What ``specgpu stream --out`` records by default.
DEFAULT_OUTPUTS = ("coefficients", "XYZ", "dE")


def default_recording(root, *, sequences: int = 3, frames: bool = False):
    """The chart streamed on the 320 x 240 twin (symmetric plan, 10 nm outputs) into ``root / "rec.zarr"`` as
    ``specgpu stream --out`` records it by default: coefficients with the plan's basis, XYZ and dE, the plan copied
    beside them (``frames``: the raw frames too). Returns (setup, recording path)."""
    setup = shared_stream_setup(320, 240, sequences=sequences, output_step_nm=10.0)
    path = Path(root) / "rec.zarr"
    stream = Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=DEFAULT_OUTPUTS,
                    reference=setup.reference, policy="block")
    recorder = ZarrRecorder(path, setup.plan, frames=frames, basis=stream.decoder.basis,
                            metadata={"scene": "colorchecker", "illuminant": "D65"})
    stream.sinks.append(recorder)
    report = stream.run()
    assert report.sequences_out == sequences and recorder.committed == sequences
    save_plan(path / "plan.npz", setup.plan)
    return setup, path


def batch_output(setup, source, out, computed):
    """``specgpu batch`` of recording ``source`` (with raw frames) into ``out`` (cube, XYZ, dE), with only the
    sequences ``computed`` done, as a batch stopped before the others leaves it. Returns ``out``."""
    job, _ = prepare_batch(source, setup.plan, setup.bundle, out, outputs=("cube", "XYZ", "dE"),
                           reference=setup.reference)
    records = process_sequences(job, computed)
    assert not any(r.get("error") for r in records), records
    return Path(out)


def damaged_copy(source, dest, *, missing=(), corrupt=()):
    """A copy of the zarr output ``source`` at ``dest`` with the chunks ``missing`` ((array, sequence) pairs)
    deleted and one byte of each of ``corrupt`` flipped; returns ``dest``."""
    shutil.copytree(source, dest)
    for name, i in missing:
        shutil.rmtree(dest / name / "c" / str(i))
    for name, i in corrupt:
        chunk = next(p for p in (dest / name / "c" / str(i)).rglob("*") if p.is_file())
        data = bytearray(chunk.read_bytes())
        data[len(data) // 2] ^= 0xFF
        chunk.write_bytes(bytes(data))
    return dest


def disk_full_after(monkeypatch, n_sequences: int, array: str = "XYZ"):
    """Every write of ``array`` after its first ``n_sequences`` fails as a full disk does."""
    import os

    from specgpu.io import recording

    real = recording.write_chunk
    count = [0]

    def write(path, parts, **kwargs):
        if f"{os.sep}{array}{os.sep}" in path:
            count[0] += 1
            if count[0] > n_sequences:
                raise OSError(28, "No space left on device")
        return real(path, parts, **kwargs)

    monkeypatch.setattr(recording, "write_chunk", write)
