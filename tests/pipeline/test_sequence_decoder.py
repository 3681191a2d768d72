"""One sequence decoder: what a (calibration, plan) pair asks of the frames is decided by ``corrections_for`` alone,
and recover, the stream's device decoder and the motion-compensated decoder all take it from there."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from specgpu import engine
from specgpu.calibration.bundle import oracle_calibration
from specgpu.core.numerics import live_gain
from specgpu.engine.linear_map import apply_linear
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.denoise import sequence_guide
from specgpu.pipeline.recovery import recover, uncertainty
from specgpu.pipeline.sequence_decoder import SequenceDecoder, corrections_for
from specgpu.planning.correction import with_ambient_frame
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription

H, W = 240, 320
DESC = RigDescription(camera=CameraParameters(roi_width=W, roi_height=H))


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def plan(bundle):
    return make_plan("narrowband", bundle, step_nm=50.0)


@pytest.fixture(scope="module")
def tilted(bundle):
    """A calibration that measured a sensor compression and a wavelength-dependent flat field."""
    tilt = np.linspace(-1.0, 1.0, W, dtype=np.float32)[None, :]
    flats = np.stack([bundle.flat_field * (1 + 0.04 * s * tilt) for s in (-1.0, 1.0)])
    return replace(bundle, flat_fields=flats, flat_wavelengths=np.array([450.0, 650.0]),
                   reports={**bundle.reports, "linearity_c_per_dn2": 4e-8})


def frames_for(plan, bundle, sequences=2, seed=1) -> np.ndarray:
    """(S, K, H, W) uint16 frames well above the dark level and below saturation."""
    rng = np.random.default_rng(seed)
    dark = np.asarray(bundle.dark_at(plan.exposure_s), np.float32)
    top = float(bundle.max_code) - float(dark.max())
    signal = rng.uniform(0.1 * top, 0.9 * top, (sequences, plan.K, H, W)).astype(np.float32)
    return np.round(dark[None, None] + signal).astype(np.uint16)


def test_corrections_are_decided_by_the_pair(bundle, plan, tilted):
    bare = corrections_for(bundle, plan)
    assert not bare.host and not bare.per_sequence and bare.ambient is None and bare.ratio is None
    np.testing.assert_array_equal(bare.dark, bundle.dark_at(plan.exposure_s))
    flat = corrections_for(tilted, replace(plan, calibration=tilted.hash))
    assert flat.host and not flat.per_sequence and flat.linearize and flat.ratio.shape == (plan.K, H, W)
    ambient = corrections_for(bundle, with_ambient_frame(plan))
    assert ambient.host and ambient.per_sequence and ambient.ambient == plan.K
    white = corrections_for(bundle, plan, white_roi="10,10,20,20")
    assert white.per_sequence and not white.host


def test_every_decoder_takes_its_corrections_from_the_pair(bundle, plan, tilted):
    queue = engine.get_queue()
    for cal, p in ((bundle, plan), (tilted, replace(plan, calibration=tilted.hash)),
                   (bundle, with_ambient_frame(plan))):
        expected = corrections_for(cal, p).host
        stream = SequenceDecoder(p, cal, ("cube",), frame_shape=(H, W), device=queue)
        assert stream.precorrect == stream.corrections.host == expected
    moving = SequenceDecoder(replace(plan, calibration=tilted.hash), tilted, ("cube",), motion="global")
    assert moving.corrections.host and moving.motion == "global"


def test_recover_maps_the_signal_above_the_dark_once(tilted, plan):
    """Host-corrected frames go to the linear map as the signal above the dark level, with no dark: the level is
    subtracted once, not added back for the map to subtract again."""
    p = replace(plan, calibration=tilted.hash)
    frames = frames_for(p, tilted, sequences=1)
    y = recover(SequenceFolder(Path("mem"), frames, p, tilted, [], {}), sequence=0)
    corr = corrections_for(tilted, p)
    signal = corr.signal(frames[0])
    expected = (frames[0].astype(np.float32) - corr.dark[None]) * corr.ratio
    np.testing.assert_allclose(signal, tilted.linearize(frames[0].astype(np.float32) - corr.dark[None]) * corr.ratio,
                               rtol=1e-6)
    assert np.abs(signal - expected).max() > 0  # the linearisation is applied
    direct = np.asarray(apply_linear(signal, p.A, None, live_gain(tilted.flat_field)))
    np.testing.assert_array_equal(y, direct)


def test_recover_refuses_a_white_reflectance_without_its_white(bundle, plan):
    folder = SequenceFolder(Path("mem"), frames_for(plan, bundle), plan, bundle, [], {})
    with pytest.raises(ValueError, match="--white-reflectance needs --white-roi"):
        recover(folder, white_reflectance=0.9)
    with pytest.raises(ValueError, match="--white-reflectance needs --white-roi"):
        uncertainty(folder, white_reflectance=0.9)


@pytest.mark.parametrize("motion", ["none", "global"])
def test_a_sequence_out_of_range_is_one_line_naming_the_folder(bundle, plan, motion):
    folder = SequenceFolder(Path("seq-folder"), frames_for(plan, bundle), plan, bundle, [], {})
    for call in (lambda: recover(folder, sequence=2, motion=motion),
                 lambda: SequenceDecoder(plan, bundle, motion=motion).picked(folder.frames, -1, folder.path),
                 lambda: sequence_guide(folder, sequence=5)):
        with pytest.raises(ValueError, match=r"^sequence -?\d+ is out of range: seq-folder holds 2$"):
            call()


def test_averaged_sequences_decode_as_their_mean(bundle, plan):
    frames = frames_for(plan, bundle, sequences=3, seed=4)
    folder = SequenceFolder(Path("mem"), frames, plan, bundle, [], {})
    mean = apply_linear(frames.mean(axis=0, dtype=np.float32), plan.A, bundle.dark_at(plan.exposure_s),
                        live_gain(bundle.flat_field))
    np.testing.assert_allclose(recover(folder), mean, rtol=1e-6, atol=1e-7)


def test_the_pipeline_has_one_decoder_class():
    """Every command decodes through SequenceDecoder: no second decoder class computes the outputs another way."""
    import ast

    root = Path(__file__).resolve().parents[2] / "specgpu" / "pipeline"
    decoders = sorted(node.name for path in root.glob("*.py") for node in ast.walk(ast.parse(path.read_text()))
                      if isinstance(node, ast.ClassDef) and node.name.endswith("Decoder"))
    assert decoders == ["SequenceDecoder"]


def test_the_device_mode_maps_equal_recover_with_the_saturated_pixels_nan(bundle, plan, tilted):
    """The device-resident mode's maps of host frames (fused launches, host corrections first where the pair asks
    for them) equal recover's decoding of the same sequence, NaN where a frame saturated."""
    for cal, p in ((bundle, plan), (tilted, replace(plan, calibration=tilted.hash))):
        frames = frames_for(p, cal, sequences=1, seed=5)
        frames[0, 1, 7, 11] = cal.max_code
        want = recover(SequenceFolder(Path("mem"), frames, p, cal, [], {}), sequence=0)
        dec = SequenceDecoder(p, cal, ("cube", "XYZ"))
        maps = dec.maps(frames[0])
        assert set(maps) == {"cube", "XYZ", "mask"} and maps["cube"].dtype == np.float32
        assert maps["mask"][7, 11] & 1 and np.isnan(maps["cube"][7, 11]).all() and np.isnan(want[7, 11]).all()
        np.testing.assert_allclose(maps["cube"], want, rtol=1e-5, atol=1e-6)
        assert np.isfinite(maps["cube"]).sum() == np.isfinite(want).sum() == want.size - want.shape[-1]


def test_the_outputs_are_decided_once_for_every_mode(bundle, plan):
    """The device-resident and the motion mode check their outputs in the same place, with the same words."""
    for motion in ("none", "global"):
        with pytest.raises(ValueError, match="the dE output needs a reference"):
            SequenceDecoder(plan, bundle, ("cube", "dE"), motion=motion)
        with pytest.raises(ValueError, match=r"the dE reference must be \(3,\) or \(240, 320, 3\), got \(2, 3\)"):
            SequenceDecoder(plan, bundle, ("dE",), motion=motion, reference=np.zeros((2, 3)))
        with pytest.raises(ValueError, match="cube_dtype must be float16 or float32"):
            SequenceDecoder(plan, bundle, ("cube",), motion=motion, cube_dtype=np.float64)
    moving = SequenceDecoder(plan, bundle, ("coefficients", "cube", "XYZ", "Lab"), motion="global")
    still = SequenceDecoder(plan, bundle, ("coefficients", "cube", "XYZ", "Lab"))
    assert moving.shapes() == still.shapes()
    rows, slices = moving.rows, moving.slices
    np.testing.assert_array_equal(rows[slices["coefficients"]], still.spec.A_coefficients)
    np.testing.assert_array_equal(rows[slices["cube"]], plan.A)
    np.testing.assert_allclose(rows[slices["XYZ"]], plan.outputs_to_XYZ("D65") @ plan.A, rtol=1e-12)
    with pytest.raises(ValueError, match="the device launches need outputs and no motion mode"):
        moving.enqueue(None)


@pytest.mark.parametrize("outputs", [(), ("cube",)])
def test_what_motion_cannot_compensate_is_refused_alike_in_every_mode(bundle, plan, outputs):
    """recover's decoder and the stream's and batch's refuse a reference white outside the frame or where it moves
    unknown, in the same words, naming the option; a plan with an ambient frame they take (its frame warped)."""
    assert SequenceDecoder(with_ambient_frame(plan), bundle, outputs, motion="affine").motion == "affine"
    with pytest.raises(ValueError, match=r"--white-roi-moves"):
        SequenceDecoder(plan, bundle, outputs, motion="global", white_roi="10,10,20,20", white_moves="sideways")
    folder = SequenceFolder(Path("mem"), frames_for(plan, bundle, sequences=1), plan, bundle, [], {})
    with pytest.raises(ValueError, match=r"^--white-roi 9000,10,20,20 lies outside"):
        recover(folder, motion="global", white_roi="9000,10,20,20")
