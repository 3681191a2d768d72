"""Where a batch's frames come from and what makes two batches the same: the recording and sequence-folder
sources (:func:`open_source`), and the identity a batch output records so that a resumed batch continues only the
same batch (:func:`reference_label`, the one-line refusal naming the first option that differs).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from specgpu.core.spectra import DEFAULT_CMFS
from specgpu.core.validate import check_sequence
from specgpu.io.recording import chunk_keys, open_recording, patterns_hash
from specgpu.io.sequence import check_frame_files, read_frames
from specgpu.pipeline.capture_folder import read_capture_header

__all__ = ["open_source", "reference_label"]


# ---------------------------------------------------------------------------------------------------- sources


class _RecordingSource:
    """Raw frames of a zarr recording (``specgpu stream --frames``)."""

    def __init__(self, path):
        self.path = Path(path)
        self.rec = open_recording(path)
        if self.rec.sequences == 0:
            raise ValueError(f"{self.path}: holds no committed sequence (status {self.rec.attrs.get('status')!r}"
                             + (f": {self.rec.attrs['error']}" if self.rec.attrs.get("error") else "") + ")")
        if not self.rec.attrs.get("frames") or "frames" not in self.rec.group:
            raise ValueError(f"{self.path}: the recording has no raw frames to re-process "
                             "(record them with specgpu stream --frames)")
        self.sequences = self.rec.sequences
        self.K = self.rec.K
        arr = self.rec.group["frames"]
        shape = arr.shape
        if len(shape) != 4 or shape[1] != self.K or tuple(arr.chunks) != (1, *shape[1:]):
            raise ValueError(f"{self.path}/frames: shape {tuple(shape)} in chunks {tuple(arr.chunks)} is not "
                             f"(time, {self.K} patterns, y, x) in one chunk per sequence")
        self.height, self.width = int(shape[2]), int(shape[3])
        said = (self.rec.attrs.get("height"), self.rec.attrs.get("width"))
        if said != (None, None) and said != (self.height, self.width):
            raise ValueError(f"{self.path}/frames: frames are {self.height} x {self.width} but the recording says "
                             f"{said[0]} x {said[1]}")
        self.patterns_hash = self.rec.attrs.get("patterns_hash")
        self.plan_hash = self.rec.attrs.get("plan_hash")
        self.default_calibration = self.path / "calibration.npz"
        self._id = None

    @property
    def content_id(self) -> str:
        """The recording's ``recording_id`` with the CRC32C trailer of each committed frames chunk (4 bytes read
        per chunk, no pixel): another recording put at this path, or a frames chunk replaced, changes it. A
        committed sequence whose chunk is missing is a one-line error here, before any work."""
        if self._id is None:
            missing = self.rec.missing("frames")
            if missing:
                self.rec.read("frames", missing[0])  # the one-line error naming the recording and sequence
            arr = self.rec.group["frames"]
            digest = hashlib.sha256(f"{self.rec.attrs.get('recording_id')}|{self.sequences}".encode())
            for i in range(self.sequences):
                chunk = self.path / "frames" / chunk_keys(arr, i)[0]
                try:
                    with open(chunk, "rb") as fh:
                        fh.seek(-4, os.SEEK_END)
                        digest.update(fh.read(4))
                except OSError as exc:
                    raise ValueError(f"{self.path}/frames: sequence {i}: chunk {chunk.name} unreadable "
                                     f"({type(exc).__name__})") from None
            self._id = digest.hexdigest()
        return self._id

    def frames(self, i: int) -> np.ndarray:
        return self.rec.read("frames", i)

    def frame_ids(self) -> np.ndarray:
        return self.rec.read("frame_id", slice(0, self.sequences))

    def times(self) -> np.ndarray:
        return self.rec.read("time", slice(0, self.sequences))


class _FolderSource:
    """The sequences of a sequence folder (``specgpu capture``): ``sequence.json``, the plan and calibration
    checked once per process, the frames read (and checked against their checksums) one sequence at a time, so
    memory does not grow with the capture."""

    def __init__(self, path):
        self.path = Path(path)
        self.records, self.meta, plan, _ = read_capture_header(path)
        check_frame_files(self.path, self.records)  # every listed frame there at its size, no pixel read
        self.K = plan.K
        self.sequences = len(self.records) // self.K
        self.height, self.width = int(self.meta["height"]), int(self.meta["width"])
        self.patterns_hash = patterns_hash(plan)
        self.plan_hash = plan.hash
        self.default_calibration = self.path / "calibration.npz"

    @property
    def content_id(self) -> str:
        """The frames' names, sizes and SHA-256 checksums (from ``sequence.json``; each frame read is checked
        against its own): another capture put at this path changes it."""
        digest = hashlib.sha256(f"{self.plan_hash}|{self.height}x{self.width}".encode())
        for r in self.records:
            digest.update(f"|{r['file']}:{r['bytes']}:{r['sha256']}".encode())
        return digest.hexdigest()

    def frames(self, i: int) -> np.ndarray:
        check_sequence(i, self.sequences, self.path)
        return read_frames(self.path, self.records, self.meta, i * self.K, (i + 1) * self.K)

    def frame_ids(self) -> np.ndarray:
        return np.array([r["frame_id"] for r in self.records], np.int64).reshape(self.sequences, self.K)

    def times(self) -> np.ndarray:
        return np.array([r["timestamp_s"] for r in self.records], np.float64)[::self.K]


def open_source(path):
    """A zarr recording with raw frames, or a sequence folder; one-line errors naming the path."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no recording or sequence folder there")
    if (path / "sequence.json").is_file():
        return _FolderSource(path)
    if (path / "zarr.json").is_file():
        return _RecordingSource(path)
    raise ValueError(f"{path}: neither a zarr recording (zarr.json) nor a sequence folder (sequence.json)")



# -------------------------------------------------------------------------------------------------- identity

#: identity attribute -> (what it is called on the command line, how its value is shown in a refusal)
_IDENTITY_NAMES = {
    "format": ("the output format", str), "version": ("the batch format version", str),
    "source": ("SOURCE", str),
    "source_id": ("SOURCE's content (recording id and frame checksums)", lambda v: str(v)[:12]),
    "source_plan_hash": ("SOURCE's plan", lambda v: str(v)[:12]), "sequences": ("SOURCE's sequence count", str),
    "plan_hash": ("--plan", lambda v: str(v)[:12]), "calibration": ("--calib", lambda v: str(v)[:12]),
    "outputs": ("--outputs", lambda v: ",".join(v) if isinstance(v, list) else str(v)),
    "illuminant": ("--illuminant", str), "observer": ("--observer", str), "method": ("--method", str),
    "integration": ("--integration", str),
    "reference_sha256": ("--delta-e-ref", None), "denoise": ("--denoise", str), "motion": ("--motion", str),
    "white_roi": ("--white-roi", str), "white_reflectance": ("--white-reflectance", str),
    "white_roi_moves": ("--white-roi-moves", str),
}


def reference_label(reference) -> str | None:
    """How a dE reference is shown: ``L,a,b`` when it is one colour, else a per-pixel map by checksum."""
    if reference is None:
        return None
    ref = np.asarray(reference, np.float32)
    flat = ref.reshape(-1, ref.shape[-1]) if ref.ndim > 1 else ref.reshape(1, -1)
    if np.all(flat == flat[0]):
        return ",".join(f"{float(v):g}" for v in flat[0])
    return f"a per-pixel Lab map {_reference_hash(ref)[:12]}"


def _reference_hash(reference) -> str | None:
    if reference is None:
        return None
    ref = np.ascontiguousarray(np.asarray(reference, np.float32))
    return hashlib.sha256(repr(ref.shape).encode() + ref.tobytes()).hexdigest()


def _identity_mismatch(out: Path, attrs: dict, identity: dict) -> str | None:
    """One line naming the first identity entry ``out`` was made with that differs from this run's, with both
    values; None when it is the same batch."""
    for key, value in identity.items():
        old = attrs.get(key)
        if key == "observer" and key not in attrs and attrs.get("illuminant") is not None:
            old = DEFAULT_CMFS  # made before the observer was recorded: its colours are the 2 degree observer's
        if old == value:
            continue
        if key == "reference_sha256":
            name, was, now = "--delta-e-ref", attrs.get("delta_e_ref"), identity.get("delta_e_ref")
        elif key == "delta_e_ref":
            continue  # the label: the checksum decides
        else:
            name, show = _IDENTITY_NAMES.get(key, (key, str))
            was, now = (show(old) if old is not None else None), show(value)
        return (f"{out}: holds a batch made with {name} {was if was is not None else '(none)'}, this run gives "
                f"{now if now is not None else '(none)'}; resume only the same batch, or choose a new --out")
    return None
