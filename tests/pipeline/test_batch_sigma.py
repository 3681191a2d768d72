"""The uncertainty outputs of ``specgpu batch`` (``sigma``, ``sigma_rms``, ``dE_sigma``): equal to the stream's and
to recover's for the same frames, still, moving (``--motion global``), denoised, denoised with a reference white,
and moving with the denoise and a white that moves with the scene; written like the other outputs (float32, one
chunk per sequence, channels, units, NaN where the mask says why), resumed, refused in one line where a
combination cannot give them, and checked when read back.

Every stream and batch here runs on 160 x 120 frames (:mod:`batch_sigma_helpers`)."""

from __future__ import annotations

import functools
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from batch_sigma_helpers import DENOISE, OUTPUTS, SEQUENCES, SIGMAS, rendered, streamed, white_roi, window_twin
from zarr_helpers import damaged_copy

from specgpu.core.mask import Mask
from specgpu.io.recording import open_recording
from specgpu.pipeline import batch
from specgpu.pipeline.batch import prepare_batch, process_sequences
from specgpu.pipeline.batch_output import open_batch_output
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.outputs import delta_E_sigma_map, sigma_with_rms
from specgpu.pipeline.recovery import recover, to_XYZ, uncertainty

#: (motion, denoise, a reference white in the field: with motion, one moving with the scene)
CASES = {"still": ("none", None, False), "global": ("global", None, False), "denoise": ("none", DENOISE, False),
         "denoise-white": ("none", DENOISE, True), "global-denoise-white": ("global", DENOISE, True)}


@pytest.fixture(scope="module")
def twin():
    """:func:`batch_sigma_helpers.window_twin`: the plan, calibration and scene of the 160 x 120 window."""
    return window_twin()


@pytest.fixture(scope="module")
def cases(twin, tmp_path_factory):
    """``case(name)``: a recording of :data:`SEQUENCES` sequences streamed with the case's options (raw frames and
    the stream's :data:`OUTPUTS`), the batch output of it with the same options (computed in this process, as a
    worker computes it), the options and the recorded frames; each made once."""
    root = tmp_path_factory.mktemp("batch-sigma")

    @functools.cache
    def case(name):
        motion, denoise, white = CASES[name]
        frames, infos, light = rendered(twin, moving=motion != "none")
        _, plan, bundle, _ = twin
        options = {"motion": motion, "denoise": denoise,
                   "white": None if not white else (white_roi(plan, bundle, frames[:plan.K]), None, "scene")}
        rec = streamed(root / f"{name}.zarr", plan, bundle, frames, infos, light, **options)
        out = root / f"{name}-out.zarr"
        job, todo = prepare_batch(rec, plan, bundle, out, outputs=OUTPUTS, **options)
        assert todo.tolist() == list(range(SEQUENCES))
        assert not any(r.get("error") for r in process_sequences(job, todo))
        return rec, out, options, frames

    return case


def assert_close_nan(a, b, **tol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), **tol)


def recovered_sigmas(plan, bundle, frames, *, motion, denoise, white) -> dict:
    """``recover --sigma --delta-e-sigma`` (with the options) of one sequence's ``frames``: its sigma map (with the
    RMS) and dE_sigma, as recover writes them."""
    folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
    kw = {"sequence": 0, "motion": motion, "denoise": denoise}
    if white is not None:
        kw.update(white_roi=white[0], white_moves=white[2])
    cube = recover(folder, **kw)
    sigma, cov = uncertainty(folder, illuminant="D65", **kw)
    return {"sigma": sigma_with_rms(sigma, plan.output_labels)[0],
            "dE_sigma": delta_E_sigma_map(to_XYZ(cube, plan), cov, plan.white_XYZ("D65"))}


# ------------------------------------------------------------------------------------ equal to stream and recover

@pytest.mark.parametrize("name", list(CASES))
def test_the_batch_sigmas_equal_the_streams(cases, name):
    """The batch decodes through the stream's decoder with the same options: every output, the sigmas included,
    equals what the stream recorded of the same frames, to float rounding (NaN at the same pixels)."""
    rec, out, _, _ = cases(name)
    streamed_maps, batch_maps = open_recording(rec), open_batch_output(out)
    assert batch_maps.pending == []
    for output in OUTPUTS:
        want, got = streamed_maps.read(output, slice(None)), batch_maps.read(output, slice(None))
        assert got.dtype == np.float32 and got.shape == want.shape
        assert_close_nan(got, want, rtol=1e-5, atol=1e-7)
    sigma = batch_maps.read("sigma", slice(None))
    assert np.isfinite(sigma).mean() > 0.6 and np.nanmin(sigma) > 0  # maps of numbers, not of NaN or zeros
    np.testing.assert_array_equal(sigma[..., -1], batch_maps.read("sigma_rms", slice(None)))


@pytest.mark.parametrize("name", ["still", "denoise-white", "global-denoise-white"])
def test_the_batch_sigmas_equal_recovers(twin, cases, name):
    """Sequence 1 of the batch against ``recover --sigma --delta-e-sigma`` of its frames with the same options."""
    _, plan, bundle, _ = twin
    _, out, options, frames = cases(name)
    want = recovered_sigmas(plan, bundle, frames[plan.K:2 * plan.K], **options)
    got = open_batch_output(out)
    assert_close_nan(got.read("sigma", 1), want["sigma"], rtol=1e-4, atol=1e-7)
    ok = np.isfinite(want["dE_sigma"])
    np.testing.assert_array_equal(np.isfinite(got.read("dE_sigma", 1)), ok)
    np.testing.assert_allclose(got.read("dE_sigma", 1)[ok], want["dE_sigma"][ok], rtol=1e-3, atol=1e-5)


def test_the_sigma_arrays_say_what_they_hold_and_the_mask_says_where_they_are_nan(twin, cases):
    _, plan, _, _ = twin
    _, out, _, _ = cases("global")
    group = open_batch_output(out).group
    B, (h, w) = plan.A.shape[0], (120, 160)
    assert group["sigma"].shape == (SEQUENCES, h, w, B + 1) and group["sigma"].chunks == (1, h, w, B + 1)
    attrs = dict(group["sigma"].attrs)
    assert attrs["channels"] == [f"sigma_{label}" for label in plan.output_labels] + ["sigma_rms"]
    assert attrs["units"] == "reflectance factor" and "mask" in attrs["missing"]
    assert tuple(group["sigma"].metadata.dimension_names) == ("time", "y", "x", "sigma_channel")
    assert tuple(group["sigma_rms"].metadata.dimension_names) == ("time", "y", "x")
    assert dict(group["dE_sigma"].attrs)["units"] == "CIEDE2000"
    assert group["mask"].dtype == np.uint8 and group["mask"].shape == (SEQUENCES, h, w)
    assert dict(group["mask"].attrs)["flags"]["OUTSIDE"] == int(Mask.OUTSIDE)
    mask = group["mask"][:]
    flagged = (mask & ~np.uint8(Mask.LAYER)) != 0
    assert 0.02 < flagged.mean() < 0.3  # the drift leaves a border seen outside the field
    for name in SIGMAS:
        np.testing.assert_array_equal(np.isnan(group[name][:]).reshape(SEQUENCES, h, w, -1).any(axis=-1), flagged)


# ------------------------------------------------------------------------------------------------- resuming

def test_an_interrupted_batch_resumes_and_keeps_the_sigmas_it_wrote(twin, cases, tmp_path, monkeypatch):
    """A disk that fails while writing sequence 1's sigma stops the batch with sequence 0 done; run again, only
    sequence 1 is computed, sequence 0's sigma chunk is left as it was, and both equal the stream's."""
    _, plan, bundle, _ = twin
    rec, _, _, _ = cases("still")
    out = tmp_path / "out.zarr"
    real = batch.write_sequence_chunk

    def full_disk(array, index, value, **kwargs):
        if array.basename == "sigma" and index == 1:
            raise OSError(28, "No space left on device")
        return real(array, index, value, **kwargs)

    job, todo = prepare_batch(rec, plan, bundle, out, outputs=OUTPUTS)
    monkeypatch.setattr(batch, "write_sequence_chunk", full_disk)
    records = process_sequences(job, todo)
    monkeypatch.setattr(batch, "write_sequence_chunk", real)
    assert "error" not in records[0] and records[1]["error"] == f"{out}/sigma: writing sequence 1 failed " \
                                                                "(No space left on device)"
    assert open_batch_output(out).pending == [1]
    chunk = next(p for p in (out / "sigma" / "c" / "0").rglob("*") if p.is_file())
    kept = (chunk.read_bytes(), chunk.stat().st_mtime_ns)
    job, todo = prepare_batch(rec, plan, bundle, out, outputs=OUTPUTS)
    assert todo.tolist() == [1]
    assert not any(r.get("error") for r in process_sequences(job, todo))
    assert (chunk.read_bytes(), chunk.stat().st_mtime_ns) == kept
    done, streamed_maps = open_batch_output(out), open_recording(rec)
    assert done.pending == []
    for name in SIGMAS:
        assert_close_nan(done.read(name, slice(None)), streamed_maps.read(name, slice(None)), rtol=1e-5, atol=1e-7)


def test_resuming_with_another_white_of_dE_sigma_is_refused(twin, cases, tmp_path):
    """dE_sigma depends on the illuminant of XYZ: an output of it alone resumes only under the same one."""
    _, plan, bundle, _ = twin
    rec, _, _, _ = cases("still")
    out = tmp_path / "out.zarr"
    prepare_batch(rec, plan, bundle, out, outputs=("dE_sigma",))
    with pytest.raises(ValueError) as refused:
        prepare_batch(rec, plan, bundle, out, outputs=("dE_sigma",), illuminant="A")
    assert str(refused.value) == (f"{out}: holds a batch made with --illuminant D65, this run gives A; resume only "
                                  "the same batch, or choose a new --out")


def test_an_output_made_without_a_mask_resumes_without_one(twin, cases, tmp_path):
    import shutil

    _, plan, bundle, _ = twin
    rec, _, _, _ = cases("still")
    out = tmp_path / "out.zarr"
    prepare_batch(rec, plan, bundle, out, outputs=("sigma_rms",))
    shutil.rmtree(out / "mask")  # as a batch output made before the mask was written
    job, todo = prepare_batch(rec, plan, bundle, out, outputs=("sigma_rms",))
    assert not job.mask and todo.tolist() == [0, 1]
    assert not any(r.get("error") for r in process_sequences(job, todo))
    assert not (out / "mask").exists()
    np.testing.assert_array_equal(open_batch_output(out).read("sigma_rms", 0), open_recording(rec).read("sigma_rms", 0))


# ---------------------------------------------------------------------------------------------------- refusals

def test_a_combination_that_cannot_give_a_sigma_is_refused_in_one_line_before_any_output(twin, cases, tmp_path):
    _, plan, bundle, _ = twin
    rec, _, _, _ = cases("still")
    out = tmp_path / "out.zarr"
    bare = replace(plan, params={k: v for k, v in plan.params.items() if k != "noise"})
    refusals = [((bare, ("cube", "dE_sigma")), {}, "the dE_sigma output: the narrowband plan records no noise model, "
                                                   "so it has no sigma; re-plan it with specgpu plan --rig RIG.toml"),
                ((plan, ("sigma",)), {"denoise": (5, 1e-4)}, "--denoise-radius 5: the sigma maps are carried through "
                                                             "the filter up to radius 4"),
                ((bare, ("sigma_rms",)), {"motion": "global", "denoise": DENOISE},
                 "the sigma_rms output: the narrowband plan records no noise model")]
    for (p, outputs), options, message in refusals:
        with pytest.raises(ValueError) as refused:
            prepare_batch(rec, p, bundle, out, outputs=outputs, **options)
        assert str(refused.value).startswith(message) and "\n" not in str(refused.value)
        assert not out.exists()


# ---------------------------------------------------------------------------------------------- reading it back

def test_the_validator_refuses_a_corrupt_sigma_array(cases, tmp_path):
    _, out, _, _ = cases("still")

    def edited(name, change):
        copy = damaged_copy(out, tmp_path / f"{name}.zarr")
        meta = copy / "sigma" / "zarr.json"
        doc = json.loads(meta.read_text())
        change(doc)
        meta.write_text(json.dumps(doc))
        return copy

    def fewer_channels(doc):
        doc["attributes"]["channels"] = doc["attributes"]["channels"][:-1]

    def float64(doc):
        doc["data_type"] = "float64"

    def no_channel_axis(doc):
        doc["shape"], doc["chunk_grid"]["configuration"]["chunk_shape"] = doc["shape"][:3], doc["shape"][:3]
        doc["dimension_names"] = doc["dimension_names"][:3]

    def one_channel_short(doc):
        doc["shape"][-1] -= 1
        doc["chunk_grid"]["configuration"]["chunk_shape"][-1] -= 1
        doc["attributes"]["channels"] = doc["attributes"]["channels"][1:]

    for name, change, message in [
            ("fewer", fewer_channels, r"fewer\.zarr/sigma: its channels .* do not name its 8 channels \(sigma_"),
            ("wide", float64, r"wide\.zarr/sigma: is float64, a batch output's sigma is float32"),
            ("flat", no_channel_axis, r"flat\.zarr/sigma: has 3 dimensions, a batch output's sigma has 4"),
            ("short", one_channel_short, r"short\.zarr/sigma: holds 7 channels for 7 cube outputs")]:
        with pytest.raises(ValueError, match=message) as refused:
            open_batch_output(edited(name, change))
        assert "\n" not in str(refused.value)
    gone = open_batch_output(damaged_copy(out, tmp_path / "gone.zarr", missing=[("sigma", 1)]))
    assert gone.missing("sigma") == [1]
    with pytest.raises(ValueError, match=r"gone\.zarr/sigma: sequence 1 is committed but its chunk"):
        gone.read("sigma", 1)
    bad = open_batch_output(damaged_copy(out, tmp_path / "bad.zarr", corrupt=[("dE_sigma", 0)]))
    with pytest.raises(ValueError, match=r"bad\.zarr/dE_sigma: corrupt or unreadable chunk at sequence 0"):
        bad.read("dE_sigma", 0)


@pytest.mark.parametrize("name", ["still", "denoise"])
def test_a_device_without_shared_memory_copies_the_same_sigmas(twin, cases, tmp_path, name):
    """On a device whose memory is not the host's the results are copied back instead of mapped (a GPU): the
    sigmas, and the mask, are those of the mapped path."""
    from specgpu.pipeline.batch import _decoder, _worker_state

    _, plan, bundle, _ = twin
    rec, mapped, options, _ = cases(name)
    out = tmp_path / "copied.zarr"
    job, todo = prepare_batch(rec, plan, bundle, out, outputs=OUTPUTS, **options)
    state, _ = _worker_state(job)
    _decoder(job, state)
    state._zero_copy = False
    assert not any(r.get("error") for r in process_sequences(job, todo))
    copied, want = open_batch_output(out), open_batch_output(mapped)
    for output in (*SIGMAS, "mask"):
        np.testing.assert_array_equal(copied.read(output, slice(None)), want.read(output, slice(None)))
