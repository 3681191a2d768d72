"""Fuzzed readers: every file specgpu reads, corrupted every way hypothesis can think of.

Each reader gets valid files mutated by truncation, bit flips, garbage bytes and wholly random bytes, and, for
structured formats, documents whose fields carry wrong types, wrong values and huge sizes. Every input must give
either a valid object or a one-line ``ValueError`` / ``FileNotFoundError`` that names the file: never another
exception, a traceback of a library, a hang, or (for formats that carry a checksum) a silently different value.

Run with ``--hypothesis-show-statistics`` to see how many examples each reader was given.
"""

from __future__ import annotations

import json
import math
import os
import signal
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.calibration.bundle import (
    CALIBRATION_FORMAT,
    CALIBRATION_VERSION,
    load_calibration,
    oracle_calibration,
    save_calibration,
)
from specgpu.io import sequence as io_sequence
from specgpu.io.npz import read_spectrum_csv
from specgpu.io.tables import content_hash, save_npz
from specgpu.planning import PLAN_FORMAT, load_plan, plan_narrowband, save_plan
from specgpu.planning.basis import BasisTable, load_basis, read_reflectance_csv, save_basis
from specgpu.planning.plans import PLAN_VERSION
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription, _toml_value, load_rig

# a complex array read as real with its imaginary part dropped is a silent wrong value
pytestmark = pytest.mark.filterwarnings("error::numpy.exceptions.ComplexWarning")

#: SPECGPU_FUZZ_SCALE=10 runs ten times the examples (a longer fuzzing session), 0.1 a tenth (a quick look).
SCALE = float(os.environ.get("SPECGPU_FUZZ_SCALE", "1"))


def fuzz(examples: int):
    return settings(max_examples=max(1, round(examples * SCALE)), deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


HANG_S = 60  # one example taking longer than this is a hang


@contextmanager
def no_hang(seconds: int = HANG_S):
    def alarm(signum, frame):
        raise AssertionError(f"reader hung for more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def read_or_refuse(reader, path: Path, *args, **kwargs):
    """``reader(path)``; None when it refused with a one-line ValueError / FileNotFoundError naming ``path``.
    Any other exception propagates (and fails the test)."""
    with no_hang():
        try:
            return reader(path, *args, **kwargs)
        except (ValueError, FileNotFoundError) as exc:
            msg = str(exc)
            assert "\n" not in msg and "\r" not in msg, f"not one line: {msg!r}"
            assert str(path) in msg or path.name in msg, f"names no file: {msg!r}"
            assert type(exc).__name__ not in ("UnicodeDecodeError", "JSONDecodeError"), msg
            return None


# ---- byte-level mutations ----------------------------------------------------------------------------------------
@st.composite
def mutated(draw, original: bytes):
    """``original`` truncated, bit-flipped, overwritten with garbage, with garbage inserted, or replaced."""
    n = len(original)
    kind = draw(st.sampled_from(["truncate", "flip", "overwrite", "insert", "random", "empty-tail"]))
    data = bytearray(original)
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, n - 1))])
    if kind == "flip":
        for pos in draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=8)):
            data[pos] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    if kind == "overwrite":
        pos = draw(st.integers(0, n - 1))
        blob = draw(st.binary(min_size=1, max_size=64))
        data[pos: pos + len(blob)] = blob
        return bytes(data[: max(n, pos + len(blob))])
    if kind == "insert":
        pos = draw(st.integers(0, n))
        return bytes(data[:pos]) + draw(st.binary(min_size=1, max_size=64)) + bytes(data[pos:])
    if kind == "empty-tail":  # a disk that filled up: the tail is zeros
        pos = draw(st.integers(0, n - 1))
        return bytes(data[:pos]) + bytes(n - pos)
    return draw(st.binary(max_size=2 * n))


def save(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# ---- fixtures: one valid file of each kind -----------------------------------------------------------------------
H, W = 240, 320
DESC = RigDescription(camera=CameraParameters(roi_width=W, roi_height=H))


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


class Valid(dict):
    def __repr__(self):  # keep hypothesis' failure reports short
        return f"<valid files in {self['dir']}>"


@pytest.fixture(scope="module")
def files(tmp_path_factory, bundle):
    """Valid files of every kind, written once; tests copy their bytes, never write here."""
    d = tmp_path_factory.mktemp("valid")
    rng = np.random.default_rng(1)
    cube = rng.uniform(0, 1, (6, 7, 4)).astype(np.float32)
    io.write_cube(d / "cube.exr", cube, [450.0, 500.0, 550.0, 600.5], metadata={"k": 1.5})
    io.write_cube(d / "cube.npz", cube, [450.0, 500.0, 550.0, 600.5])
    io.write_map(d / "xyz.exr", rng.uniform(0, 1, (5, 3, 3)), "XYZ")
    frames = rng.integers(0, 65536, (3, 4, 5), dtype=np.uint16)
    records = [dict(frame_id=i, pattern_index=i % 2, exposure_s=0.01, timestamp_s=0.005 * i) for i in range(3)]
    io.write_sequence(d / "seq", frames, records, plan_hash="abc123")
    save_calibration(d / "calib.npz", bundle)
    save_plan(d / "plan.npz", plan_narrowband(bundle))
    wl = np.arange(400.0, 701.0, 50.0)
    basis = BasisTable(wl, rng.normal(size=(wl.size, 2)), np.array([2.0, 1.0]), np.zeros(wl.size), False, 10, "t")
    save_basis(d / "basis.npz", basis)
    (d / "lamp.csv").write_text("wavelength,power\n400,0.5\n500,1.0\n600,0.7\n700,0.2\n")
    (d / "refl.csv").write_text("wavelength,red,blue\n400,0.1,0.5\n500,0.2,0.4\n600,0.6,0.1\n")
    (d / "rig.toml").write_text("[camera]\nroi_width = 320\nroi_height = 240\nexposure_s = 0.01\n\n"
                                "[light]\ncolumns = 1024\n\n[twin]\nseed = 3\n\n[faults]\ndrop_rate = 0.01\n")
    return Valid({"dir": d, "frames": frames, "cube": cube})


# ---- spectral EXR and npz cubes, EXR maps ------------------------------------------------------------------------
@fuzz(150)
@given(data=st.data())
def test_fuzz_spectral_exr(files, tmp_path, data):
    blob = data.draw(mutated((files["dir"] / "cube.exr").read_bytes()))
    path = save(tmp_path / "f.exr", blob)
    got = read_or_refuse(io.read_cube, path)
    if got is not None:
        cube, wl, meta = got
        assert cube.dtype == np.float32 and cube.ndim == 3 and cube.shape[2] == wl.size
        assert np.all(np.diff(wl) > 0) and np.all(np.isfinite(wl)) and isinstance(meta, dict)


@fuzz(100)
@given(data=st.data())
def test_fuzz_exr_map(files, tmp_path, data):
    blob = data.draw(mutated((files["dir"] / "xyz.exr").read_bytes()))
    path = save(tmp_path / "m.exr", blob)
    got = read_or_refuse(io.read_map, path, "XYZ")
    if got is not None:
        assert got[0].shape[2] == 3 and got[1] == ("X", "Y", "Z")


@fuzz(100)
@given(data=st.data())
def test_fuzz_npz_cube(files, tmp_path, data):
    blob = data.draw(mutated((files["dir"] / "cube.npz").read_bytes()))
    path = save(tmp_path / "c.npz", blob)
    got = read_or_refuse(io.read_cube, path)
    if got is not None:
        assert got[0].ndim == 3 and got[0].shape[2] == got[1].size


NAMES = st.one_of(st.text(max_size=20), st.sampled_from(["T.550nm", "T.0nm", "T.nan nm", "T.1e400nm", "T.550,0nm",
                                                          "T.0Hz", "T.5e-300nm", "T.545THz", "S0.550nm", "T.550.5nm"]))
META_TEXT = st.one_of(st.text(max_size=30), st.just("[1, 2]"), st.just('{"a": NaN}'), st.just("null"),
                      st.just('{"a": 1e999}'), st.just("{" * 5000 + "}" * 5000))


@fuzz(120)
@given(names=st.lists(NAMES, min_size=1, max_size=5, unique=True), meta=st.one_of(st.none(), META_TEXT),
       shape=st.tuples(st.integers(1, 4), st.integers(1, 4)))
def test_fuzz_exr_channels_and_header(tmp_path, names, meta, shape):
    """Structured fields of a well-formed EXR: odd channel names and a broken metadata attribute."""
    names = [n for n in names if n and "\x00" not in n]
    assume(names)
    path = tmp_path / "s.exr"
    from specgpu.io.exr import write_exr
    try:
        write_exr(path, np.ones((*shape, len(names)), np.float32), names,
                  attributes=None if meta is None else {"specgpu:metadata": meta})
    except ValueError:
        assume(False)  # OpenEXR refused the names: nothing to read
    got = read_or_refuse(io.read_cube, path)
    if got is not None:
        cube, wl, meta_out = got
        assert np.all(np.isfinite(wl)) and np.all(wl > 0) and np.all(np.diff(wl) > 0)
        assert cube.shape == (*shape, wl.size) and isinstance(meta_out, dict)
    got = read_or_refuse(io.read_map, path)
    if got is not None:
        assert got[0].shape[:2] == shape


# ---- sequence folders: sequence.json and TIFF frames ---------------------------------------------------------------
def copy_sequence(files, tmp_path) -> Path:
    seq = tmp_path / "seq"
    seq.mkdir(exist_ok=True)
    for f in (files["dir"] / "seq").iterdir():
        (seq / f.name).write_bytes(f.read_bytes())
    return seq


def read_sequence_checked(files, seq):
    """A sequence that reads must be exactly the frames written (every frame carries a SHA-256)."""
    got = read_or_refuse(io.read_sequence, seq)
    if got is not None:
        frames, records, meta = got
        assert frames.shape[1:] == (meta["height"], meta["width"]) and len(records) == frames.shape[0]
    return got


@fuzz(150)
@given(data=st.data())
def test_fuzz_sequence_json_bytes(files, tmp_path, data):
    seq = copy_sequence(files, tmp_path)
    index = seq / "sequence.json"
    save(index, data.draw(mutated(index.read_bytes())))
    got = read_or_refuse(io.read_sequence_header, seq)
    if got is not None:
        read_sequence_checked(files, seq)


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
                    lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=5), kids, max_size=3),
                    max_leaves=8)
HUGE = st.sampled_from([0, -1, 2**31, 2**40, 2**63, 2**64, 100000, 1e300, float("nan"), float("inf"), "1", True,
                        None, [], {}])


@fuzz(300)
@given(data=st.data())
def test_fuzz_sequence_json_fields(files, tmp_path, data):
    """One or a few fields of a valid document replaced by values of the wrong type, wrong value or huge size."""
    seq = copy_sequence(files, tmp_path)
    index = seq / "sequence.json"
    doc = json.loads(index.read_text())
    for _ in range(data.draw(st.integers(1, 3))):
        value = data.draw(st.one_of(JSON, HUGE))
        if data.draw(st.booleans()):
            key = data.draw(st.sampled_from(sorted(doc) + ["extra"]))
            if data.draw(st.integers(0, 9)) == 0:
                doc.pop(key, None)
            else:
                doc[key] = value
        elif isinstance(doc.get("frames"), list) and doc["frames"] and isinstance(doc["frames"][0], dict):
            rec = doc["frames"][data.draw(st.integers(0, len(doc["frames"]) - 1))]
            if isinstance(rec, dict):
                rec[data.draw(st.sampled_from(sorted(rec) + ["extra"]))] = value
    try:
        text = json.dumps(doc, allow_nan=data.draw(st.booleans()))
    except ValueError:
        text = json.dumps(doc)
    index.write_text(text)
    got = read_or_refuse(io.read_sequence_header, seq)
    if got is not None:
        records, meta = got
        assert all(isinstance(r["frame_id"], int) and r["frame_id"] >= 0 for r in records)
        assert all(math.isfinite(r["exposure_s"]) and r["exposure_s"] > 0 for r in records)
        assert meta["height"] >= 1 and meta["width"] >= 1
        read_sequence_checked(files, seq)


@fuzz(150)
@given(data=st.data())
def test_fuzz_tiff_frame(files, tmp_path, data):
    """A corrupted frame: refused by size or checksum; without the checksum, by the TIFF decoder, or read as a
    frame of the right shape and type."""
    seq = copy_sequence(files, tmp_path)
    frame = seq / "frame_000001.tif"
    save(frame, data.draw(mutated(frame.read_bytes())))
    got = read_or_refuse(io.read_sequence, seq)
    if got is not None:  # the checksum held: the bytes are those written
        assert np.array_equal(got[0], files["frames"])
    # the TIFF decoder alone (a sequence.json rewritten to the new size and hash)
    got = read_or_refuse(io_sequence._read_tiff, frame, (4, 5))
    if got is not None:
        assert got.shape == (4, 5) and got.dtype == np.uint16


# ---- versioned, hashed bundles -------------------------------------------------------------------------------------
LOADERS = {"calib.npz": load_calibration, "plan.npz": load_plan, "basis.npz": load_basis}
FORMATS = {"calib.npz": (CALIBRATION_FORMAT, CALIBRATION_VERSION), "plan.npz": (PLAN_FORMAT, PLAN_VERSION),
           "basis.npz": ("specgpu.basis", 1)}


@fuzz(200)
@given(data=st.data(), name=st.sampled_from(sorted(LOADERS)))
def test_fuzz_bundle_bytes(files, tmp_path, data, name):
    """Any change to a bundle's bytes is refused (the content hash), or leaves the content as saved."""
    original = files["dir"] / name
    path = save(tmp_path / name, data.draw(mutated(original.read_bytes())))
    got = read_or_refuse(LOADERS[name], path)
    if got is not None:  # the bytes changed where they do not count (zip metadata): the content is the same
        if name == "basis.npz":
            assert np.array_equal(got.functions, load_basis(original).functions)
        else:
            assert got.hash == LOADERS[name](original).hash


def _bad_array(data, arr: np.ndarray):
    kind = data.draw(st.sampled_from(["nan", "inf", "huge", "negative", "shape", "empty", "dtype", "scalar", "str"]))
    a = np.array(arr, copy=True)
    if kind in ("nan", "inf", "huge", "negative") and a.size and a.dtype.kind == "f" and a.dtype.itemsize >= 4:
        flat = a.reshape(-1)
        with np.errstate(over="ignore"):  # "huge" in a float32 field is inf, as a file could hold
            flat[data.draw(st.integers(0, flat.size - 1))] = {"nan": np.nan, "inf": np.inf, "huge": 1e300,
                                                              "negative": -1e30}[kind]
        return a
    if kind == "shape" and a.ndim:
        return a[..., : max(0, a.shape[-1] - data.draw(st.integers(1, 3)))]
    if kind == "empty":
        return np.zeros((0,) * max(a.ndim, 1), a.dtype)
    if kind == "dtype":
        dtype = np.dtype(data.draw(st.sampled_from([np.int8, np.complex128, np.bool_, np.float16])))
        if a.dtype.kind == "c" and dtype.kind != "c":  # an earlier mutation made it complex: drop the imaginary
            a = a.real  # part here, or the cast warns (an error in this module)
        try:
            with np.errstate(all="ignore"):
                return a.astype(dtype)
        except (TypeError, ValueError):  # an earlier mutation made it text
            return a
    if kind == "scalar":
        return np.array(data.draw(st.floats()))
    return np.array(data.draw(st.text(max_size=5)))


def test_ci_draws_the_same_examples_every_run(pytestconfig):
    """The "ci" profile is derandomized (a fixed seed per test) and the header says which profile ran."""
    ci = settings.get_profile("ci")
    assert ci.derandomize and ci.database is None and ci.print_blob
    headers = pytestconfig.hook.pytest_report_header(config=pytestconfig, start_path=pytestconfig.rootpath)
    ours = [h for h in headers if isinstance(h, str) and h.startswith("hypothesis: profile ")]
    assert len(ours) == 1
    assert ("derandomized" in ours[0]) == settings.default.derandomize


class Scripted:
    """Stands for hypothesis's ``data``: each draw returns the next scripted value."""

    def __init__(self, *values):
        self._values = list(values)

    def draw(self, strategy):
        return self._values.pop(0)


@pytest.mark.parametrize("dtype", [np.int8, np.bool_, np.float16, np.complex128])
def test_a_complex_field_mutated_again_to_another_dtype_is_drawn_without_a_warning(dtype):
    """Two mutations of one field (complex, then another dtype) draw a wrong-typed array, not a ComplexWarning."""
    got = _bad_array(Scripted("dtype", dtype), np.array([1.5 + 2.0j, -3.0 + 1.0j]))
    assert got.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(got, np.array([1.5 + 2.0j, -3.0 + 1.0j]).astype(dtype) if dtype is np.complex128
                                  else np.array([1.5, -3.0]).astype(dtype))


def save_stored(path: Path, kind: str, version: int, arrays: dict, meta: dict) -> Path:
    """What :func:`save_npz` writes (the header with the content hash, every array), as a foreign writer may write
    it: the members stored, not deflated. The loaders read either; deflating the calibration's two frame-sized
    float maps (a quarter of a second) is otherwise what most of the fuzz of fields spends its time on. Refuses
    what ``save_npz`` refuses (object arrays, metadata that is not JSON)."""
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    if any(v.dtype == object for v in arrays.values()):
        raise ValueError(f"{path}: an array is not numeric")
    header = {"format": kind, "version": int(version), "hash": content_hash(arrays, meta), "meta": meta}
    with open(path, "wb") as fh:
        np.savez(fh, __meta__=np.array(json.dumps(header)), **arrays)
    return path


def _fields(files, name):
    with np.load(files["dir"] / name, allow_pickle=False) as z:
        header = json.loads(str(z["__meta__"]))
        arrays = {k: np.array(z[k]) for k in z.files if k != "__meta__"}
    return arrays, dict(header["meta"])


@pytest.fixture(scope="module")
def fields(files):
    """Each bundle's arrays (read-only) and metadata, read once: an example mutates copies of the two dicts."""
    read = {name: _fields(files, name) for name in LOADERS}
    for arrays, _ in read.values():
        for a in arrays.values():
            a.setflags(write=False)
    return read


@pytest.mark.parametrize("name", sorted(LOADERS))
def test_a_bundle_saved_with_stored_members_loads_as_saved(files, tmp_path, name):
    """The fuzz of fields below writes its bundles with :func:`save_stored`: unchanged, each loads as the file
    ``save_npz`` wrote (so its examples reach the checks of the fields, not a refusal of the writer)."""
    arrays, meta = _fields(files, name)
    path = save_stored(tmp_path / name, *FORMATS[name], arrays, meta)
    with np.load(path, allow_pickle=False) as z:  # really stored: no member deflated
        assert {info.compress_type for info in z.zip.infolist()} == {0}
    got, want = LOADERS[name](path), LOADERS[name](files["dir"] / name)
    if name == "basis.npz":
        np.testing.assert_array_equal(got.functions, want.functions)
    else:
        assert got.hash == want.hash


@fuzz(200)
@given(data=st.data(), name=st.sampled_from(sorted(LOADERS)))
def test_fuzz_bundle_fields(fields, tmp_path, data, name):
    """Bundles with a valid hash whose arrays or metadata carry wrong types, values or shapes (a hand-made or
    foreign file): a valid object or one line naming the file."""
    arrays, meta = (dict(d) for d in fields[name])
    for _ in range(data.draw(st.integers(1, 2))):
        if data.draw(st.booleans()):
            key = data.draw(st.sampled_from(sorted(arrays)))
            if data.draw(st.integers(0, 9)) == 0:
                del arrays[key]
            else:
                arrays[key] = _bad_array(data, arrays[key])
        else:
            key = data.draw(st.sampled_from(sorted(meta) + ["extra"]))
            meta[key] = data.draw(st.one_of(JSON, HUGE))
    fmt, version = FORMATS[name]
    path = tmp_path / name
    try:
        save_stored(path, fmt, version, arrays, json.loads(json.dumps(meta)))
    except (ValueError, TypeError):
        assume(False)  # not even writable (object arrays, NaN in the JSON metadata ...)
    got = read_or_refuse(LOADERS[name], path)
    if got is not None and name == "calib.npz":
        for key, value in vars(got).items():
            if isinstance(value, np.ndarray) and value.dtype.kind == "f":
                assert np.all(np.isfinite(value)), f"{key} accepted with non-finite values"


# ---- rig TOML ----------------------------------------------------------------------------------------------------
@fuzz(200)
@given(data=st.data())
def test_fuzz_rig_toml_bytes(files, tmp_path, data):
    path = save(tmp_path / "rig.toml", data.draw(mutated((files["dir"] / "rig.toml").read_bytes())))
    got = read_or_refuse(load_rig, path)
    if got is not None:
        assert isinstance(got, RigDescription)


RIG_KEYS = {
    "camera": ["roi_width", "roi_height", "exposure_s", "bit_depth", "sensitivity", "frame_rate_hz", "typo"],
    "light": ["columns", "rows", "wavelength_min_nm", "wavelength_max_nm", "lamp", "spot_centre_mm", "typo"],
    "twin": ["seed", "pacing", "typo"],
    "faults": ["drop_rate", "duplicate_rate", "missed_trigger_rate", "jitter_s", "typo"],
    "scene": ["source", "typo"],
    "spectroradiometer": ["step_nm", "bandwidth_nm", "noise_rms", "typo"],
    "hardware": ["light", "camera", "nested"],
    "bogus": ["x"],
}
TOML_VALUE = st.one_of(st.integers(-2**70, 2**70), st.floats(), st.booleans(), st.text(max_size=12),
                       st.lists(st.one_of(st.integers(-5, 5), st.floats()), max_size=3),
                       st.sampled_from([0, -1, 2**31, 10**9, 1e300, 1e-300, "lamp.csv", "../../etc/passwd", "nan"]))


def _toml(value) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return _toml_value(value)


@fuzz(300)
@given(tables=st.dictionaries(st.sampled_from(sorted(RIG_KEYS)), st.data(), min_size=1, max_size=3),
       data=st.data())
def test_fuzz_rig_toml_fields(files, tmp_path, tables, data):
    """Known and unknown keys with values of every type and size: a valid rig or one line naming the file."""
    (tmp_path / "lamp.csv").write_bytes((files["dir"] / "lamp.csv").read_bytes())
    lines = []
    for table in tables:
        lines.append(f"[{table}]")
        for key in data.draw(st.lists(st.sampled_from(RIG_KEYS[table]), max_size=3, unique=True)):
            lines.append(f"{key} = {_toml(data.draw(TOML_VALUE))}")
    path = tmp_path / "rig.toml"
    path.write_text("\n".join(lines) + "\n")
    got = read_or_refuse(load_rig, path)
    if got is not None:
        assert got.camera.roi_width >= 1 and got.camera.roi_height >= 1
        assert math.isfinite(got.camera.exposure_s) and got.camera.exposure_s > 0


# ---- CSV spectra ---------------------------------------------------------------------------------------------------
CSV_CELL = st.one_of(st.floats(), st.integers(-10**6, 10**6), st.sampled_from(["", "nan", "x", "1e999", "-0", " "]))


@fuzz(200)
@given(data=st.data())
def test_fuzz_spectrum_csv(files, tmp_path, data):
    if data.draw(st.booleans()):
        blob = data.draw(mutated((files["dir"] / "lamp.csv").read_bytes()))
    else:
        rows = data.draw(st.lists(st.lists(CSV_CELL, min_size=1, max_size=3), max_size=6))
        blob = "\n".join(",".join(str(c) for c in r) for r in rows).encode()
    path = save(tmp_path / "curve.csv", blob)
    got = read_or_refuse(read_spectrum_csv, path)
    if got is not None:
        wl, values = got
        assert wl.size == values.size >= 2 and np.all(np.diff(wl) > 0) and np.all(np.isfinite(values))


@fuzz(200)
@given(data=st.data())
def test_fuzz_reflectance_csv(files, tmp_path, data):
    if data.draw(st.booleans()):
        blob = data.draw(mutated((files["dir"] / "refl.csv").read_bytes()))
    else:
        rows = data.draw(st.lists(st.lists(CSV_CELL, min_size=1, max_size=3), max_size=6))
        blob = "\n".join(",".join(str(c) for c in r) for r in rows).encode()
    path = save(tmp_path / "refl.csv", blob)
    got = read_or_refuse(read_reflectance_csv, path)
    if got is not None:
        for _, wl, values in got:
            assert wl.size == values.size >= 2 and np.all(np.diff(wl) > 0)
            assert np.all((values >= 0) & (values <= 1.5))


@fuzz(100)
@given(data=st.data())
def test_fuzz_lamp_csv_through_the_rig(files, tmp_path, data):
    """A corrupted CSV curve named in a rig TOML: the rig loads or refuses naming a file."""
    blob = data.draw(mutated((files["dir"] / "lamp.csv").read_bytes()))
    save(tmp_path / "lamp.csv", blob)
    path = tmp_path / "rig.toml"
    path.write_text('[light]\nlamp = "lamp.csv"\n')
    with no_hang():
        try:
            load_rig(path)
        except ValueError as exc:
            assert "\n" not in str(exc) and ("lamp.csv" in str(exc) or "rig.toml" in str(exc)), str(exc)


# ---- what the fuzzing found, pinned ------------------------------------------------------------------------------
def test_binary_rig_toml_names_the_file(tmp_path):
    path = save(tmp_path / "rig.toml", b"\x80\x81[camera]\n")
    with pytest.raises(ValueError, match=r"rig\.toml: invalid TOML \(not UTF-8"):
        load_rig(path)


def test_sequence_json_with_a_huge_width_names_the_file(files, tmp_path):
    seq = copy_sequence(files, tmp_path)
    doc = json.loads((seq / "sequence.json").read_text())
    doc["width"] = doc["height"] = 100000  # 60 GB of frames: refused by the first frame, before any allocation
    (seq / "sequence.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"frame_000000\.tif: frame is 4 x 5, sequence.json says 100000 x 100000"):
        io.read_sequence(seq)


def test_corrupt_zip_stream_in_a_bundle_names_the_file(files, tmp_path):
    raw = bytearray((files["dir"] / "basis.npz").read_bytes())
    start = raw.index(b"__meta__.npy") + len(b"__meta__.npy") + 20  # inside the first member's deflate stream
    raw[start: start + 16] = bytes(16)
    path = save(tmp_path / "basis.npz", bytes(raw))
    with pytest.raises(ValueError, match=r"basis\.npz: corrupt specgpu\.basis file"):
        load_basis(path)
    path = save(tmp_path / "cube.npz", (files["dir"] / "cube.npz").read_bytes()[:60] + bytes(400))
    with pytest.raises(ValueError, match=r"cube\.npz: truncated or corrupt"):
        io.read_cube(path)


def _resaved(files, tmp_path, name, **changes):
    with np.load(files["dir"] / name, allow_pickle=False) as z:
        header = json.loads(str(z["__meta__"]))
        arrays = {k: np.array(z[k]) for k in z.files if k != "__meta__"}
    meta = dict(header["meta"])
    for key, value in changes.items():
        (arrays if key in arrays else meta)[key] = value(arrays[key]) if callable(value) else value
    fmt, version = FORMATS[name]
    save_npz(tmp_path / name, fmt, version, arrays, meta)
    return tmp_path / name


@pytest.mark.parametrize("change, message", [
    ({"dark": lambda d: np.full_like(d, -1e30)}, "dark must lie in 0-"),
    ({"dark_rate_dn_per_s": None}, "dark_rate_dn_per_s must be a finite number"),
    ({"column_wavelengths": lambda c: np.where(np.arange(c.size) == 3, np.nan, c)}, "column_wavelengths"),
    ({"responsivity": lambda r: r.astype(np.complex128)}, "responsivity must hold real numbers"),
    # all zero: every plan from it would divide by zero (an SVD that does not converge), so the file is refused
    ({"responsivity": np.zeros_like}, "responsivity is zero at every wavelength"),
    ({"column_power": np.zeros_like}, "column_power is zero at every column"),
    ({"responsivity": lambda r: np.where(np.arange(r.size) == 7, np.inf, r)}, "responsivity must be (G="),
])
def test_hand_made_calibration_with_bad_values_is_refused(files, tmp_path, change, message):
    path = _resaved(files, tmp_path, "calib.npz", **change)
    with pytest.raises(ValueError, match=r"calib\.npz: invalid calibration bundle") as exc:
        load_calibration(path)
    assert message in str(exc.value)


def test_plan_whose_decoder_overflows_float32_is_refused(files, tmp_path):
    path = _resaved(files, tmp_path, "plan.npz", A=lambda a: np.where(a == a.flat[0], 1e300, a))
    with pytest.raises(ValueError, match=r"plan\.npz: invalid plan \(plan decoder A must be finite in float32"):
        load_plan(path)


def test_exr_channel_named_with_a_newline_gives_one_line(tmp_path):
    from specgpu.io.exr import write_exr

    write_exr(tmp_path / "n.exr", np.ones((1, 1, 1), np.float32), ["a\nb"])
    with pytest.raises(ValueError) as exc:
        io.read_cube(tmp_path / "n.exr")
    assert "\n" not in str(exc.value) and "n.exr: no reflective spectral channels" in str(exc.value)
