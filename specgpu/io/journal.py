"""The capture journal read back: verify what an interrupted capture journaled and salvage it into a sequence.

:class:`specgpu.io.sequence.SequenceWriter` appends a checksummed line per frame of each complete sequence;
:func:`verify_journal` checks the lines, the records and the frame files they name without writing anything, and
:func:`salvage_sequence` writes ``sequence.json`` for the intact sequences (verify first, commit last).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import OpenImageIO as oiio

from specgpu.io.paths import atomic_path, error_of
from specgpu.io.sequence import (
    _FRAME_NAME,
    _FRAME_RE,
    JOURNAL_FILE,
    JOURNAL_FORMAT,
    SEQUENCE_FILE,
    SEQUENCE_FORMAT,
    SEQUENCE_VERSION,
    _is_int,
    _line_check,
    validate_sequence_document,
)

__all__ = ["verify_journal", "journal_header", "salvage_sequence"]


def _journal_line(raw: bytes, checked: bool = False):
    """A journal line parsed and verified: (object, None), or (None, why it cannot be trusted). In a journal whose
    header carries a checksum (``checked``) every line must carry one: a flipped bit in the key ``check`` itself
    leaves a line without it. A line of a journal from a writer before checksums is taken as it is; its frames are
    still verified."""
    try:
        line = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None, "not valid JSON"
    if not isinstance(line, dict):
        return None, "not a JSON object"
    if "check" in line and line["check"] != _line_check(line):
        return None, "its checksum does not match its content"
    if checked and "check" not in line:
        return None, "its checksum is missing"
    return line, None


def _frame_shape(path: Path):
    """(height, width) of a frame file from its header, or None when it cannot be read as an image."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        error_of(oiio)  # clear the library's pending error
        return None
    try:
        spec = inp.spec()
        return spec.height, spec.width
    finally:
        inp.close()


def verify_journal(directory, group: int) -> tuple[dict, dict]:
    """Verify what an interrupted capture journaled, without writing anything: every whole sequence of ``group``
    frames whose journal lines are intact (their checksums agree), whose records are valid and in capture order,
    and whose frame files are present, match their journaled sizes and checksums and have the journaled shape.

    Returns
    -------
    doc : dict
        The ``sequence.json`` document of the intact sequences (validated), its metadata holding ``salvaged``.
    info : dict
        ``frames_journaled``, ``frames_kept``, ``sequences``, ``sequences_journaled``, ``left_out`` (one
        ``{"sequence", "first_file", "last_file", "reason"}`` per sequence not kept, 0-based in capture order),
        ``kept_sequences`` (the capture-order index of each sequence kept, in the index's order),
        ``stopped`` (the reasons in one line, or None) and ``frames_unindexed`` (frame files outside the index).

    Raises
    ------
    ValueError
        One line naming the file: no journal, a journal that is not specgpu's or whose header (the plan it names)
        is damaged, or no complete intact sequence (with the first reason).
    """
    directory = Path(directory)
    journal = directory / JOURNAL_FILE
    header, lines = _read_journal(directory)
    group = int(group)
    entries, damaged = {}, []  # frame index -> [(line number, entry)]; line numbers that cannot be trusted
    n_lines = 0
    for number, raw in enumerate(lines[1:], start=2):
        if not raw.strip():
            continue
        n_lines += 1
        entry, why = _journal_line(raw, checked="check" in header)
        m = _FRAME_INDEX.match(entry["file"]) if entry is not None and isinstance(entry.get("file"), str) else None
        if m is None:
            damaged.append((number, why or "not a frame record"))
            continue
        entries.setdefault(int(m.group(1)), []).append((number, entry))
    last = max(entries) if entries else -1
    n_sequences = max(last // group + 1, n_lines // group) if group > 0 else 0
    kept, left_out, shape, last_id = [], [], None, -1
    for s in range(n_sequences):
        first, stop = s * group, (s + 1) * group
        found = [entries.get(i, []) for i in range(first, stop)]
        reason = None
        if any(len(f) > 1 for f in found):
            reason = "the journal lists one of its frames twice"
        elif not all(found):
            missing = [_FRAME_NAME.format(first + j) for j, f in enumerate(found) if not f]
            before = max((n for i, f in entries.items() if i < first for n, _ in f), default=1)
            after = min((n for i, f in entries.items() if i >= stop for n, _ in f), default=len(lines) + 1)
            bad = [f"line {n} ({why})" for n, why in damaged if before < n < after]
            if s == n_sequences - 1 and not bad and stop > last + 1 >= first:
                reason = (f"incomplete: the last {last + 1 - first} frame(s) of a sequence of {group} (the capture "
                          "stopped while writing it)")
            else:
                reason = (f"no intact journal record of {', '.join(missing[:3])}"
                          f"{' and more' if len(missing) > 3 else ''}"
                          + (f"; damaged journal {', '.join(bad)}" if bad else ""))
        chunk = [f[0] for f in found] if reason is None else []
        if reason is None:
            reason = _sequence_problem(directory, [e for _, e in chunk], first, shape, last_id, journal)
        if reason is not None:
            left_out.append({"sequence": s, "first_file": _FRAME_NAME.format(first),
                             "last_file": _FRAME_NAME.format(stop - 1), "reason": reason})
            continue
        shape = (chunk[0][1]["height"], chunk[0][1]["width"])
        last_id = chunk[-1][1]["frame_id"]
        kept.extend(e for _, e in chunk)
    stopped = "; ".join(f"sequence {x['sequence']}: {x['reason']}" for x in left_out) or None
    if not kept:
        raise ValueError(f"{directory}: no complete, intact sequence to salvage "
                         f"({left_out[0]['reason'] if left_out else 'nothing journaled'})")
    frames = [{k: v for k, v in e.items() if k not in ("height", "width", "check")} for e in kept]
    names = {e["file"] for e in frames}
    gone = {x["sequence"] for x in left_out}
    info = {"frames_journaled": n_lines, "frames_kept": len(kept), "sequences": len(kept) // group,
            "kept_sequences": [s for s in range(n_sequences) if s not in gone],
            "sequences_journaled": n_sequences, "left_out": left_out, "stopped": stopped,
            "frames_unindexed": sum(1 for p in directory.iterdir() if _FRAME_RE.match(p.name) and p.name not in names)}
    meta = {k: v for k, v in (header.get("header") or {}).items()}
    meta["salvaged"] = info
    doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": header.get("plan_hash"),
           "height": shape[0], "width": shape[1], "dtype": "uint16", "n_frames": len(frames), "frames": frames,
           "metadata": meta}
    return validate_sequence_document(doc, journal), info


_FRAME_INDEX = re.compile(r"^frame_(\d{6,})\.tif$")


def journal_header(directory) -> dict:
    """The verified first line of a capture folder's journal: ``plan_hash`` (the plan the frames were captured
    with) and ``header`` (the capture's own, e.g. ``plan_method`` and ``K``). Raises as :func:`verify_journal`."""
    return _read_journal(directory)[0]


def _read_journal(directory: Path) -> tuple[dict, list[bytes]]:
    journal = Path(directory) / JOURNAL_FILE
    if (Path(directory) / SEQUENCE_FILE).exists():
        raise FileExistsError(f"{directory}: already holds {SEQUENCE_FILE}; nothing to salvage")
    if not journal.is_file():
        raise ValueError(f"{directory}: no capture journal ({JOURNAL_FILE}); nothing of it can be indexed")
    lines = journal.read_bytes().split(b"\n")
    header, why = _journal_line(lines[0])
    if header is None:
        raise ValueError(f"{journal}: corrupt at line 1, its header ({why}): the plan the frames were captured "
                         "with cannot be verified, so none of them is indexed")
    if header.get("format") != JOURNAL_FORMAT or not isinstance(header.get("plan_hash"), str):
        raise ValueError(f"{journal}: not a specgpu capture journal")
    return header, lines


def _sequence_problem(directory: Path, chunk: list, first: int, shape, last_id: int, journal: Path) -> str | None:
    """Why a whole journaled sequence (its ``chunk`` of records, frame ``first`` on) cannot be kept, or None."""
    try:
        validate_sequence_document(
            {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": "journal", "height": 1, "width": 1,
             "dtype": "uint16", "frames": [{k: v for k, v in e.items() if k not in ("height", "width", "check")}
                                           for e in chunk]}, journal)
    except ValueError as error:
        return f"an invalid journal record ({str(error).split(': ', 1)[-1]})"
    for j, e in enumerate(chunk):
        h, w = e.get("height"), e.get("width")
        if not (_is_int(h) and _is_int(w) and h >= 1 and w >= 1):
            return f"{e['file']}: its journal record has no valid height and width"
        if e["pattern_index"] != j:
            return f"{e['file']}: pattern {e['pattern_index']} where the sequence's pattern {j} belongs"
    if chunk[0]["frame_id"] <= last_id:
        return f"{chunk[0]['file']}: frame id {chunk[0]['frame_id']} is not after the previous sequence's {last_id}"
    for e in chunk:
        problem = _journaled_frame_problem(directory, e)
        if problem is not None:
            return problem
        actual = _frame_shape(directory / e["file"])
        if actual is None:
            return f"{e['file']} cannot be read as an image"
        if actual != (e["height"], e["width"]):
            return (f"{e['file']} is {actual[0]} x {actual[1]} pixels but its journal record says {e['height']} x "
                    f"{e['width']}")
        if shape is not None and actual != tuple(shape):
            return f"{e['file']} is {actual[0]} x {actual[1]} pixels, the sequences kept {shape[0]} x {shape[1]}"
    return None


def _journaled_frame_problem(directory: Path, entry) -> str | None:
    """Why a journaled frame cannot be kept (missing, or its bytes differ from the journal), or None."""
    path = directory / Path(entry["file"]).name
    try:
        raw = path.read_bytes()
    except OSError:
        return f"{path.name} is missing"
    if len(raw) != entry.get("bytes") or hashlib.sha256(raw).hexdigest() != entry.get("sha256"):
        return f"{path.name} does not match its journaled checksum"
    return None


def salvage_sequence(directory: str | os.PathLike[str], group: int, *, metadata: dict | None = None, check=None,
                     confirm=None) -> dict:
    """Index what an interrupted capture journaled: write ``sequence.json`` for every whole sequence of ``group``
    frames that :func:`verify_journal` finds intact; the others are left out, each with its reason (in the
    returned ``left_out`` and in ``sequence.json``'s ``metadata.salvaged``).

    Verify first, commit last: ``check(doc)`` (the caller's checks of the document, e.g. its plan) runs before
    anything is written; ``sequence.json`` is written atomically, then ``confirm()`` (reading the folder back)
    runs, and only once it passes is the journal removed. Any failure leaves the folder as it was (journal kept,
    no ``sequence.json``), so salvage can be run again. No frame file is deleted.

    Returns
    -------
    dict
        See :func:`verify_journal` (``info``).

    Raises
    ------
    ValueError
        See :func:`verify_journal`; whatever ``check`` or ``confirm`` raise.
    """
    directory = Path(directory)
    doc, info = verify_journal(directory, group)
    if metadata:
        doc["metadata"] = {**doc["metadata"], **metadata, "salvaged": info}
    if check is not None:
        check(doc)
    index = directory / SEQUENCE_FILE
    with atomic_path(index) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=1, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
    if confirm is not None:
        try:
            confirm()
        except BaseException:
            index.unlink(missing_ok=True)  # not readable after all: back to the journal, to be salvaged again
            raise
    (directory / JOURNAL_FILE).unlink(missing_ok=True)
    return info
