"""Frame sequence folders: 16-bit TIFF frames and ``sequence.json``, written last, and the capture journal's lines.

``sequence.json`` (format ``specgpu.sequence``, version 1) lists per frame its file, frame id, pattern index,
exposure, timestamp, size and SHA-256, plus the plan hash (:func:`validate_sequence_document`).
:func:`write_sequence` and :class:`SequenceWriter` write a folder (frames first, the document last, atomically, so a
folder without one is an incomplete capture and readers refuse it); with a journal, :meth:`SequenceWriter.commit`
appends checksummed lines for each complete sequence (:mod:`specgpu.io.journal` reads them back).
:func:`read_sequence`, :func:`read_sequence_header` and :func:`read_frames` read a folder, checking each frame's size
and checksum.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from numpy.typing import ArrayLike

from specgpu.core.text import one_line
from specgpu.io.metadata import _metadata_json
from specgpu.io.paths import atomic_path, error_of, os_error, write_failed

__all__ = [
    "SEQUENCE_FORMAT", "SEQUENCE_VERSION", "SEQUENCE_FILE", "JOURNAL_FILE", "JOURNAL_FORMAT",
    "validate_sequence_document", "write_sequence", "SequenceWriter", "read_sequence_header", "read_sequence",
    "check_frame_files", "read_frames", "capture_hash"
]

# ---- frame sequences -----------------------------------------------------------------------------------------------
SEQUENCE_FORMAT = "specgpu.sequence"
SEQUENCE_VERSION = 1
SEQUENCE_FILE = "sequence.json"
_FRAME_NAME = "frame_{:06d}.tif"
_FRAME_RE = re.compile(r"^frame_\d{6,}\.tif$")
_RECORD_FIELDS = ("frame_id", "pattern_index", "exposure_s", "timestamp_s")


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _roi_inside(roi, width: int, height: int) -> bool:
    """Whether ``roi`` (``"X,Y,W,H"`` or four integers) is a region of at least one pixel inside the frame."""
    parts = roi.split(",") if isinstance(roi, str) else roi
    if not isinstance(parts, list) or len(parts) != 4:
        return False
    try:
        x, y, w, h = (int(p.strip()) if isinstance(p, str) else p for p in parts)
    except ValueError:
        return False
    if not all(_is_int(v) for v in (x, y, w, h)):
        return False
    return w >= 1 and h >= 1 and x >= 0 and y >= 0 and x + w <= width and y + h <= height


def validate_sequence_document(doc, path="sequence.json") -> dict:
    """Check a parsed ``sequence.json`` and return it normalized (plain Python ints, floats and strings).

    The document (format ``specgpu.sequence``, version 1)::

        {"format": "specgpu.sequence", "version": 1, "plan_hash": str (non-empty),
         "height": int >= 1, "width": int >= 1, "dtype": "uint16",
         "frames": [{"file": "frame_000000.tif", "frame_id": int >= 0 (strictly increasing),
                     "pattern_index": int >= 0, "exposure_s": float > 0, "timestamp_s": finite float (s),
                     "bytes": int >= 0, "sha256": 64 hex digits}, ...]  (at least one; files unique plain names),
         "n_frames": len(frames) (optional), "metadata": {...}  (optional JSON object; its "white_roi", the
         reference white recover uses, "X,Y,W,H" inside the frame)}

    Extra keys in a frame record are kept (a newer writer's additions), so are unknown top-level keys.

    Raises
    ------
    ValueError
        One line that starts with ``path`` and names the field, e.g.
        ``"seq/sequence.json: frames[3].frame_id must be an integer >= 0, got -1"``.
    """
    where = str(path)

    def fail(msg):
        raise ValueError(f"{where}: {msg}")

    if not isinstance(doc, dict):
        fail(f"must hold a JSON object, got {type(doc).__name__}")
    if doc.get("format") != SEQUENCE_FORMAT:
        fail(f"not a specgpu frame sequence (format {doc.get('format')!r}, expected {SEQUENCE_FORMAT!r})")
    version = doc.get("version")
    if not _is_int(version):
        fail(f"version must be an integer, got {version!r}")
    if version != SEQUENCE_VERSION:
        fail(f"unknown format version {version} (this specgpu reads version {SEQUENCE_VERSION})")
    plan_hash = doc.get("plan_hash")
    if not isinstance(plan_hash, str) or not plan_hash:
        fail(f"plan_hash must be a non-empty string, got {plan_hash!r}")
    dims = {}
    for key in ("height", "width"):
        v = doc.get(key)
        if not _is_int(v) or v < 1:
            fail(f"{key} must be an integer >= 1, got {v!r}")
        dims[key] = int(v)
    if doc.get("dtype") != "uint16":
        fail(f"dtype must be 'uint16', got {doc.get('dtype')!r}")
    metadata = doc.get("metadata", {})
    if not isinstance(metadata, dict):
        fail(f"metadata must be a JSON object, got {type(metadata).__name__}")
    roi = metadata.get("white_roi")
    if roi is not None and not _roi_inside(roi, dims["width"], dims["height"]):  # recover and the report use it
        fail(f"metadata.white_roi must be X,Y,W,H in whole pixels inside the {dims['width']} x {dims['height']} "
             f"frame, got {roi!r}")
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        fail("frames must be a non-empty list")
    if "n_frames" in doc and (not _is_int(doc["n_frames"]) or doc["n_frames"] != len(frames)):
        fail(f"n_frames is {doc['n_frames']!r} but {len(frames)} frame(s) are listed")
    records, files, last_id = [], set(), -1
    for i, rec in enumerate(frames):
        at = f"frames[{i}]"
        if not isinstance(rec, dict):
            fail(f"{at} must be an object, got {type(rec).__name__}")
        missing = [k for k in ("file", *_RECORD_FIELDS, "bytes", "sha256") if k not in rec]
        if missing:
            fail(f"{at} lacks {', '.join(missing)}")
        name = rec["file"]
        if not isinstance(name, str) or not name or name != Path(name).name or name in (".", "..") or "\\" in name:
            fail(f"{at}.file must be a plain file name inside the folder, got {name!r}")
        if name in files:
            fail(f"{at}.file {name!r} is listed twice")
        files.add(name)
        fid = rec["frame_id"]
        if not _is_int(fid) or fid < 0:
            fail(f"{at}.frame_id must be an integer >= 0, got {fid!r}")
        if fid <= last_id:
            fail(f"{at}.frame_id {fid} must be greater than the previous frame's {last_id} (capture order)")
        last_id = int(fid)
        pat = rec["pattern_index"]
        if not _is_int(pat) or pat < 0:
            fail(f"{at}.pattern_index must be an integer >= 0, got {pat!r}")
        exp = rec["exposure_s"]
        if not _is_number(exp) or not math.isfinite(exp) or exp <= 0:
            fail(f"{at}.exposure_s must be a finite number > 0 (s), got {exp!r}")
        ts = rec["timestamp_s"]
        if not _is_number(ts) or not math.isfinite(ts):
            fail(f"{at}.timestamp_s must be a finite number (s), got {ts!r}")
        size = rec["bytes"]
        if not _is_int(size) or size < 0:
            fail(f"{at}.bytes must be an integer >= 0, got {size!r}")
        digest = rec["sha256"]
        if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
            fail(f"{at}.sha256 must be 64 lowercase hex digits, got {digest!r}")
        out = dict(rec)
        out.update(file=name, frame_id=int(fid), pattern_index=int(pat), exposure_s=float(exp),
                   timestamp_s=float(ts), bytes=int(size), sha256=digest)
        records.append(out)
    result = dict(doc)
    result.update(version=int(version), plan_hash=plan_hash, dtype="uint16", metadata=metadata, frames=records,
                  **dims)
    return result


def _record_of(rec, i: int, directory: Path) -> dict:
    """One capture record (a mapping or an object such as capture.driver.FrameInfo) as plain data."""
    if isinstance(rec, Mapping):
        get = rec.get
    else:
        def get(key, default=None):
            return getattr(rec, key, default)
    out = {}
    for key in _RECORD_FIELDS:
        v = get(key)
        if v is None:
            raise ValueError(f"{directory}: record {i} lacks {key} (records need {', '.join(_RECORD_FIELDS)})")
        out[key] = v.item() if isinstance(v, np.generic) else v
    return out


def _frame_array(frame, i: int, directory: Path, shape) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{directory}: frame {i} must have shape (H, W), got {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{directory}: frame {i} has shape {arr.shape}, the first frame {shape}")
    if arr.dtype != np.uint16:
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{directory}: frame {i} must be uint16 (16-bit DN), got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise ValueError(f"{directory}: frame {i} values must lie in 0-65535, got {arr.min()}-{arr.max()}")
        arr = arr.astype(np.uint16)
    return np.ascontiguousarray(arr[..., None])


#: The frames' TIFF compressions: ``zip`` (deflate, lossless: a frame of a lit scene, its noise included, in about
#: four fifths of its size) or ``none`` (a fortieth of the CPU time, for frames written to be looked at).
TIFF_COMPRESSIONS = ("zip", "none")


def _write_tiff(path: Path, frame: np.ndarray, compression: str = "zip") -> tuple[int, str]:
    h, w, _ = frame.shape
    spec = oiio.ImageSpec(w, h, 1, "uint16")
    spec.attribute("compression", compression)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create("tiff")
        if out is None or not out.open(str(tmp), spec):
            raise write_failed(path, tmp, "TIFF", oiio.geterror())
        try:
            if not out.write_image(frame):  # a full disk: "TIFFWriteScanline failed", its cause found here
                raise write_failed(path, tmp, "TIFF", out.geterror())
        finally:
            closed = out.close()
        if not closed:
            raise write_failed(path, tmp, "TIFF", out.geterror() or oiio.geterror() or "closing it failed")
        raw = tmp.read_bytes()
    return len(raw), hashlib.sha256(raw).hexdigest()


def write_sequence(directory: str | os.PathLike[str], frames: ArrayLike, records=None, plan_hash: str = "", *,
                   metadata: dict | None = None,
                   overwrite: bool = False) -> Path:
    """Write a captured frame sequence: 16-bit TIFF frames and ``sequence.json``, the JSON last.

    Parameters
    ----------
    directory : str or os.PathLike
        Target folder (created if needed).
    frames : array_like or iterable
        (N, H, W) uint16 frames (DN), or an iterable of (H, W) frames (written as they come, e.g. from the
        assembler), or a :class:`specgpu.capture.assemble.Sequence` (its records are used when ``records`` is
        None). Other integer dtypes are accepted when their values fit 0-65535.
    records : sequence
        One per frame, in capture order: mappings or objects (e.g. :class:`specgpu.capture.driver.FrameInfo`)
        with ``frame_id`` (int >= 0, increasing), ``pattern_index`` (int >= 0), ``exposure_s`` (s, > 0) and
        ``timestamp_s`` (s) — what ``Sequence.frame_records()`` returns.
    plan_hash : str
        Hash of the plan the capture ran (a capture records its plan's hash).
    metadata : mapping, optional
        JSON-serialisable extras (rig, scene, ...), stored under ``"metadata"``.
    overwrite : bool
        Replace a complete sequence already in ``directory``: its ``sequence.json`` is removed first, so the
        folder never looks complete while it is rewritten (the old sequence is gone from then on, even if this
        write fails). Leftover ``frame_*.tif`` of an interrupted write (no ``sequence.json``) are always
        replaced.

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    FileExistsError
        ``directory`` already holds a sequence and ``overwrite`` is False.
    ValueError
        One line naming the folder: frames of different shapes or non-16-bit values, a record count that does
        not match the frames, invalid records or plan hash. Frames written by this call are removed and no
        ``sequence.json`` is written.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_sequence, write_sequence
    >>> records = [{"frame_id": i, "pattern_index": i, "exposure_s": 0.01, "timestamp_s": 0.02 * i}
    ...            for i in range(3)]
    >>> folder = write_sequence(pathlib.Path(tempfile.mkdtemp()) / "seq", np.zeros((3, 4, 5), np.uint16),
    ...                         records, plan_hash="0123abcd")
    >>> frames, records_back, meta = read_sequence(folder)
    >>> frames.shape, meta["n_frames"], meta["plan_hash"], records_back[2]["timestamp_s"]
    ((3, 4, 5), 3, '0123abcd', 0.04)
    """
    directory = Path(directory)
    if hasattr(frames, "frame_records") and hasattr(frames, "frames"):  # a capture.assemble.Sequence
        records = frames.frame_records() if records is None else records
        frames = frames.frames
    if records is None:
        raise ValueError(f"{directory}: records are required (frame_id, pattern_index, exposure_s, timestamp_s)")
    _check_plan_hash(directory, plan_hash)
    meta_text = _metadata_json(directory, metadata)
    records = [_record_of(r, i, directory) for i, r in enumerate(records)]
    if records:  # check the records before any pixel is written (placeholders for what the frames will give)
        validate_sequence_document(
            {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": plan_hash, "height": 1,
             "width": 1, "dtype": "uint16",
             "frames": [{"file": _FRAME_NAME.format(i), **r, "bytes": 0, "sha256": "0" * 64}
                        for i, r in enumerate(records)]}, directory / SEQUENCE_FILE)
    writer = SequenceWriter(directory, plan_hash, overwrite=overwrite)
    try:
        for i, frame in enumerate(frames):
            if i >= len(records):
                raise ValueError(f"{directory}: more frames than records ({len(records)})")
            writer.add(frame, records[i])
        if writer.n_frames != len(records):
            raise ValueError(f"{directory}: {writer.n_frames} frame(s) but {len(records)} record(s)")
        return writer.close(None if meta_text is None else json.loads(meta_text))
    except BaseException:
        writer.abort()
        raise


def _check_plan_hash(directory: Path, plan_hash) -> None:
    if not isinstance(plan_hash, str) or not plan_hash:
        raise ValueError(f"{directory}: plan_hash must be a non-empty string, got {plan_hash!r}")


class SequenceWriter:
    """Write a frame sequence one frame at a time (a long capture never holds its frames in memory):
    :meth:`add` each frame with its record as it arrives, then :meth:`close` writes ``sequence.json``, last;
    :meth:`abort` removes the frames written. Until :meth:`close` returns, the folder never reads as complete.

    With ``journal``, :meth:`commit` appends the records of the frames added since the last commit to
    :data:`JOURNAL_FILE` and syncs it (a capture commits each complete sequence), so a process killed before
    :meth:`close` leaves its frames indexed: :func:`salvage_sequence` turns them into a readable sequence.

    Parameters
    ----------
    directory, plan_hash, overwrite
        As :func:`write_sequence`; the folder checks (not a folder, a sequence already there) happen here,
        before any frame is written, and leftover frames of an interrupted write are removed.
    journal : dict, optional
        Keep the journal; this JSON object (for example the capture's metadata and K) is its first line.
    compression : str
        The frames' TIFF compression, one of :data:`TIFF_COMPRESSIONS` (any TIFF reader reads either).
    """

    def __init__(self, directory: str | os.PathLike[str], plan_hash: str, *, overwrite: bool = False,
                 journal: dict | None = None, compression: str = "zip"):
        if compression not in TIFF_COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(TIFF_COMPRESSIONS)}, got {compression!r}")
        self.compression = compression
        directory = self.directory = Path(directory)
        _check_plan_hash(directory, plan_hash)
        self.plan_hash = plan_hash
        index = self.index = directory / SEQUENCE_FILE
        if directory.exists() and not directory.is_dir():
            raise ValueError(f"{directory}: exists and is not a folder")
        if index.exists():
            if not overwrite:
                raise FileExistsError(f"{directory}: already holds a frame sequence (pass overwrite=True to replace "
                                      "it)")
            index.unlink()
        directory.mkdir(parents=True, exist_ok=True)
        for stale in directory.iterdir():  # frames of an interrupted or replaced write
            if _FRAME_RE.match(stale.name) or (stale.name.startswith(".frame_") and ".tmp" in stale.name):
                stale.unlink()
        self.entries: list[dict] = []
        self.written: list[Path] = []
        self.shape = None
        self.committed = 0
        self.journal = directory / JOURNAL_FILE if journal is not None else None
        if self.journal is not None:
            header = {"format": JOURNAL_FORMAT, "plan_hash": plan_hash, "header": journal}
            _append_synced(self.journal, [header], fresh=True)

    @property
    def n_frames(self) -> int:
        return len(self.entries)

    def add(self, frame, record) -> None:
        """Write one (H, W) frame (uint16 DN, or integers in 0-65535) with its capture record."""
        i = len(self.entries)
        rec = _record_of(record, i, self.directory)
        arr = _frame_array(frame, i, self.directory, self.shape)
        self.shape = arr.shape[:2]
        name = _FRAME_NAME.format(i)
        self.written.append(self.directory / name)
        try:
            size, digest = _write_tiff(self.directory / name, arr, self.compression)
        except OSError as exc:  # disk full, folder gone: one line naming the frame
            if str(self.directory / name) in str(exc):
                raise
            raise os_error(self.directory / name, exc) from None
        self.entries.append({"file": name, **rec, "bytes": size, "sha256": digest})

    def commit(self) -> None:
        """Journal the frames added since the last commit (appended and synced; nothing without ``journal``)."""
        if self.journal is not None and self.committed < len(self.entries):
            shape = {"height": int(self.shape[0]), "width": int(self.shape[1])}
            _append_synced(self.journal, [{**e, **shape} for e in self.entries[self.committed:]])
        self.committed = len(self.entries)

    def truncate(self, n_frames: int) -> None:
        """Keep only the first ``n_frames`` frames: the files of the later ones (a sequence cut short) are removed."""
        for path in self.written[n_frames:]:
            path.unlink(missing_ok=True)
        del self.entries[n_frames:], self.written[n_frames:]
        self.committed = min(self.committed, n_frames)

    def close(self, metadata: dict | None = None) -> Path:
        """Validate the whole document and write ``sequence.json`` (atomically, synced); return the folder."""
        meta_text = _metadata_json(self.directory, metadata)
        if not self.entries:
            raise ValueError(f"{self.directory}: no frames to write")
        doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": self.plan_hash,
               "height": int(self.shape[0]), "width": int(self.shape[1]), "dtype": "uint16",
               "n_frames": len(self.entries), "frames": self.entries,
               "metadata": {} if meta_text is None else json.loads(meta_text)}
        doc = validate_sequence_document(doc, self.index)
        with atomic_path(self.index) as tmp:
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(doc, fh, indent=1, allow_nan=False)
                fh.write("\n")
                fh.flush()
                os.fsync(fh.fileno())
        if self.journal is not None:
            self.journal.unlink(missing_ok=True)
        return self.directory

    def abort(self) -> None:
        """Remove the frames this writer wrote and its journal (no ``sequence.json`` is written)."""
        for p in self.written:
            p.unlink(missing_ok=True)
        self.written = []
        if self.journal is not None:
            self.journal.unlink(missing_ok=True)


JOURNAL_FILE = ".specgpu-capture-journal.jsonl"
JOURNAL_FORMAT = "specgpu.capture-journal"


def _line_check(line: dict) -> str:
    """The checksum a journal line carries (``check``): SHA-256 of its other fields in canonical JSON, 16 hex
    digits. One flipped byte anywhere in the line (a value, a key, the checksum itself) makes it disagree."""
    body = {k: v for k, v in line.items() if k != "check"}
    text = json.dumps(body, sort_keys=True, allow_nan=False, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _append_synced(path: Path, lines, *, fresh: bool = False) -> None:
    """Append JSON lines, each with its checksum, to ``path`` (create or replace it with ``fresh``) and sync them
    to the disk."""
    try:
        with open(path, "w" if fresh else "a", encoding="utf-8") as fh:
            for line in lines:
                fh.write(json.dumps({**line, "check": _line_check(line)}, allow_nan=False) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        raise os_error(path, exc) from None


def read_sequence_header(directory: str | os.PathLike[str]) -> tuple[list[dict], dict]:
    """Read and validate only ``sequence.json`` of a sequence folder (no pixels).

    Returns
    -------
    records : list of dict
        Per frame, in capture order: ``file``, ``frame_id``, ``pattern_index``, ``exposure_s``, ``timestamp_s``,
        ``bytes``, ``sha256``.
    meta : dict
        ``format``, ``version``, ``plan_hash``, ``height``, ``width``, ``dtype``, ``n_frames``, ``metadata``.

    Raises
    ------
    FileNotFoundError
        The folder does not exist.
    ValueError
        One line naming the file: no ``sequence.json`` (an incomplete or interrupted capture), invalid JSON, or
        a document :func:`validate_sequence_document` rejects.
    """
    directory = Path(directory)
    if not directory.exists():
        raise FileNotFoundError(f"{directory}: sequence folder not found")
    if not directory.is_dir():
        raise ValueError(f"{directory}: not a folder (a frame sequence is a folder with {SEQUENCE_FILE})")
    index = directory / SEQUENCE_FILE
    if not index.is_file():
        raise ValueError(f"{index}: missing; {directory} is not a complete frame sequence (an interrupted write "
                         "leaves no sequence.json)")
    try:
        doc = json.loads(index.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"{index}: corrupt (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{index}: corrupt JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    doc = validate_sequence_document(doc, index)
    records = doc.pop("frames")
    doc["n_frames"] = len(records)
    return records, doc


def _read_tiff(path: Path, shape) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: truncated or corrupt TIFF ({one_line(error_of(oiio))})")
    try:
        spec = inp.spec()
        if inp.format_name() != "tiff" or spec.nchannels != 1 or str(spec.format) != "uint16":
            raise ValueError(f"{path}: frame must be a 1-channel 16-bit TIFF, got {inp.format_name()} "
                             f"{spec.nchannels} channel(s) {spec.format}")
        if (spec.height, spec.width) != tuple(shape):
            raise ValueError(f"{path}: frame is {spec.height} x {spec.width}, sequence.json says "
                             f"{shape[0]} x {shape[1]}")
        data = inp.read_image(0, 0, 0, 1, "uint16")
        err = error_of(inp)
        if data is None or err or data.size != shape[0] * shape[1]:
            raise ValueError(f"{path}: truncated or corrupt TIFF ({one_line(err or 'no pixel data')})")
    finally:
        inp.close()
    return data.reshape(shape)


def read_sequence(directory: str | os.PathLike[str], *, verify: bool = True) -> tuple[np.ndarray, list[dict], dict]:
    """Read a frame sequence folder written by :func:`write_sequence`.

    Parameters
    ----------
    directory : str or os.PathLike
        The folder.
    verify : bool
        Check each frame file's SHA-256 against ``sequence.json`` (catches corruption that keeps the size);
        sizes are always checked.

    Returns
    -------
    frames : numpy.ndarray
        (N, H, W) uint16 frames (DN), in capture order.
    records : list of dict
        Per frame (see :func:`read_sequence_header`).
    meta : dict
        ``plan_hash``, ``height``, ``width``, ``n_frames``, ``format``, ``version``, ``metadata``.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: see :func:`read_sequence_header`; a listed frame missing, truncated (size
        differs), corrupt (checksum or decoding) or of the wrong shape or type.

    Examples
    --------
    A folder written by :func:`write_sequence` reads back frame for frame:

    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_sequence, write_sequence
    >>> seq = pathlib.Path(tempfile.mkdtemp()) / "two"
    >>> stamps = [dict(frame_id=f, pattern_index=f, exposure_s=0.005, timestamp_s=f / 100) for f in (0, 1)]
    >>> _ = write_sequence(seq, np.full((2, 3, 4), 7, np.uint16), stamps, plan_hash="feed")
    >>> frames, _, header = read_sequence(seq)
    >>> int(frames.sum()), header["height"], header["width"]
    (168, 3, 4)
    """
    directory = Path(directory)
    records, meta = read_sequence_header(directory)
    shape = (meta["height"], meta["width"])
    frames = None  # allocated once the first frame has shown that the header's size is real
    for i, rec in enumerate(records):
        frame = _read_listed_frame(directory, i, rec, shape, verify)
        if frames is None:
            try:
                frames = np.empty((len(records), *shape), dtype=np.uint16)
            except (MemoryError, ValueError):
                raise ValueError(f"{directory / SEQUENCE_FILE}: {len(records)} frames of {shape[0]} x {shape[1]} "
                                 f"pixels ({len(records) * shape[0] * shape[1] * 2 / 2**30:.1f} GiB) do not fit "
                                 "in memory") from None
        frames[i] = frame
    return frames, records, meta


def _check_listed_frame(directory: Path, i: int, rec: dict) -> Path:
    """The file of frame ``i`` listed in ``sequence.json``, there and of the listed size."""
    path = directory / rec["file"]
    if not path.is_file():
        raise ValueError(f"{path}: frame {i} (frame id {rec['frame_id']}) listed in {SEQUENCE_FILE} is missing")
    size = path.stat().st_size
    if size != rec["bytes"]:
        raise ValueError(f"{path}: truncated or altered frame: {size} bytes, {SEQUENCE_FILE} says {rec['bytes']}")
    return path


def _read_listed_frame(directory: Path, i: int, rec: dict, shape, verify: bool) -> np.ndarray:
    path = _check_listed_frame(directory, i, rec)
    if verify:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != rec["sha256"]:
            raise ValueError(f"{path}: corrupt frame: SHA-256 differs from {SEQUENCE_FILE}")
    return _read_tiff(path, shape)


def check_frame_files(directory, records) -> None:
    """Every frame listed in ``sequence.json`` (``records``, from :func:`read_sequence_header`) is there with its
    listed size: what a reader checks before any work, without reading pixels (a one-line error naming the
    file)."""
    directory = Path(directory)
    for i, rec in enumerate(records):
        _check_listed_frame(directory, i, rec)


def read_frames(directory, records, meta, start: int, stop: int, *, verify: bool = True) -> np.ndarray:
    """Frames ``start:stop`` of a sequence folder whose header :func:`read_sequence_header` returned
    (``records``, ``meta``), each checked as :func:`read_sequence` checks it: (stop - start, H, W) uint16. Reading
    a folder a sequence at a time keeps memory to one sequence however long the capture."""
    directory = Path(directory)
    shape = (meta["height"], meta["width"])
    if not 0 <= start <= stop <= len(records):
        raise ValueError(f"{directory}: frames {start}:{stop} are out of range ({len(records)} listed)")
    out = np.empty((stop - start, *shape), dtype=np.uint16)
    for j, i in enumerate(range(start, stop)):
        out[j] = _read_listed_frame(directory, i, records[i], shape, verify)
    return out


def capture_hash(records) -> str:
    """A capture's identity: SHA-256 over its frames' own SHA-256 digests, in capture order (``records`` from
    :func:`read_sequence_header`). A copy of the folder keeps it; any other capture, or the same one recaptured
    with other noise, has another. What a recovery records, so its scores can be checked against the right
    truth.

    Examples
    --------
    >>> capture_hash([{"sha256": "0" * 64}]) == capture_hash([{"sha256": "0" * 64}]) != capture_hash([])
    True
    """
    digest = hashlib.sha256()
    for rec in records:
        digest.update(str(rec["sha256"]).encode("ascii"))
    return digest.hexdigest()
