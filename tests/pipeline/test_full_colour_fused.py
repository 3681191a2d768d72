"""The colour after the filter in one launch (CIELAB and dE2000 of decoded XYZ:
:class:`specgpu.pipeline.decoder_outputs.ColourLaunch`) against colour-science on XYZ with NaN and flagged pixels,
and the stream's full case (motion, denoise, a reference white) whose XYZ and dE equal ``recover``'s."""

from __future__ import annotations

from pathlib import Path

import colour
import numpy as np
import pyopencl as cl
import pytest
from reference import sharma_pairs

from specgpu.engine import kernels
from specgpu.engine.runtime import get_queue
from specgpu.pipeline.decoder_outputs import ColourLaunch, Outputs, lab_and_delta_E

WHITE = np.array([0.9505, 1.0, 1.089], np.float64)


def spec(names, reference=None):
    """The :class:`Outputs` a colour launch reads: its names, white, method and dE reference."""
    ref = None if reference is None else np.asarray(reference, np.float32)
    return Outputs(names=tuple(names), A=np.eye(3), cube_dtype=np.dtype(np.float32), method="CIE 2000",
                   illuminant="D65", observer="CIE 1931 2 Degree Standard Observer", integration="rectangle",
                   white=WHITE, reference=ref, reference_single=ref is None or ref.shape == (3,))


def filtered_like_XYZ(n, seed=0):
    """(n, 3) float32 XYZ as a filter leaves them: colours across the gamut, dark ones below CIE's linear knee,
    NaN pixels (flagged: outside the field, inconsistent) and a pixel of each channel NaN alone."""
    rng = np.random.default_rng(seed)
    xyz = (rng.random((n, 3)) * WHITE * 1.05).astype(np.float32)
    xyz[:n // 20] *= np.float32(0.005)  # below (24/116)^3: the linear part of f(t)
    xyz[5:40:7] = np.nan
    xyz[41, 0] = xyz[42, 1] = xyz[43, 2] = np.nan
    return xyz


def run(names, xyz, reference):
    """The launch's outputs, read back, for XYZ ``xyz`` (n, 3) and the device reference."""
    q = get_queue(None)
    n = len(xyz)
    s = spec(names, None if reference is None else reference)
    ref_dev = None if reference is None else kernels.to_device(q, np.asarray(reference, np.float32).reshape(-1))
    launch = ColourLaunch(q, s, ref_dev, n)
    xyz_dev = kernels.to_device(q, np.ascontiguousarray(xyz).reshape(-1))
    made = lab_and_delta_E(launch, xyz_dev.data)
    out = {}
    for name, buf in made.items():
        out[name] = np.empty((n, 3) if name == "Lab" else (n,), np.float32)
        cl.enqueue_copy(q, out[name], buf)
    q.finish()
    return out


def colour_science(xyz, reference):
    """float64 Lab and dE2000 of ``xyz`` against ``reference`` by colour-science."""
    lab = colour.XYZ_to_Lab(xyz.astype(np.float64), colour.XYZ_to_xy(WHITE))
    return lab, colour.delta_E(np.broadcast_to(np.asarray(reference, np.float64), lab.shape), lab,
                               method="CIE 2000")


@pytest.mark.parametrize("per_pixel", [False, True])
def test_the_fused_colour_equals_colour_science_with_nan_pixels(per_pixel):
    n = 4099  # not a multiple of the work-item's 8 pixels: the last one is partial
    xyz = filtered_like_XYZ(n)
    rng = np.random.default_rng(1)
    reference = (np.column_stack([rng.random(n) * 100, rng.random((n, 2)) * 160 - 80]).astype(np.float32)
                 if per_pixel else np.array([50.0, 2.5, -3.0], np.float32))
    got = run(("XYZ", "Lab", "dE"), xyz, reference)
    lab, de = colour_science(xyz, reference)
    bad = ~np.isfinite(xyz).all(axis=-1)
    assert bad.sum() == 8
    # a NaN pixel is NaN in both maps, and only it
    np.testing.assert_array_equal(np.isnan(got["dE"]), bad)
    np.testing.assert_array_equal(np.isnan(got["Lab"]).any(axis=-1), bad)
    np.testing.assert_allclose(got["Lab"][~bad], lab[~bad], atol=2e-3, rtol=1e-5)
    np.testing.assert_allclose(got["dE"][~bad], de[~bad], atol=2e-3, rtol=1e-5)
    assert np.ptp(de[~bad]) > 40  # the pairs span near and far colours


def test_the_fused_colour_writes_only_what_is_asked():
    q = get_queue(None)
    ref = kernels.to_device(q, np.array([50.0, 0.0, 0.0], np.float32))
    only_dE = ColourLaunch(q, spec(("XYZ", "dE"), [50.0, 0.0, 0.0]), ref, 64)
    assert only_dE.names == ("dE",) and set(only_dE.launch.outputs) == {"delta_E"}
    only_Lab = ColourLaunch(q, spec(("XYZ", "Lab")), None, 64)
    assert only_Lab.names == ("Lab",) and set(only_Lab.launch.outputs) == {"Lab"}
    with pytest.raises(ValueError, match="Lab or the dE output"):
        ColourLaunch(q, spec(("XYZ",)), None, 64)
    # dE alone equals dE beside Lab, bit for bit: the Lab it is computed from is the same
    xyz = filtered_like_XYZ(1000, seed=3)
    alone = run(("dE",), xyz, np.array([60.0, -4.0, 9.0], np.float32))
    both = run(("Lab", "dE"), xyz, np.array([60.0, -4.0, 9.0], np.float32))
    np.testing.assert_array_equal(alone["dE"], both["dE"])
    lab_only = run(("Lab",), xyz, None)
    np.testing.assert_array_equal(lab_only["Lab"], both["Lab"])


def test_the_sharma_pairs_through_the_fused_colour():
    """Sharma, Wu and Dalal's published CIEDE2000 pairs: the second colour of each pair as XYZ (colour-science's,
    float64, then float32), its Lab and dE to the first by the one launch."""
    L1, L2, expected = sharma_pairs(Path(__file__).parents[1] / "data" / "ciede2000_sharma2005.csv")
    xyz = colour.Lab_to_XYZ(L2, colour.XYZ_to_xy(WHITE)).astype(np.float32)
    got = run(("Lab", "dE"), xyz, L1.astype(np.float32))
    lab = colour.XYZ_to_Lab(xyz.astype(np.float64), colour.XYZ_to_xy(WHITE))
    want = colour.delta_E(L1, lab, method="CIE 2000")
    # pairs on the formula's hue discontinuity (its +-180 degree rule) jump with a float32 step of their XYZ:
    # compared where a step of 1e-4 in a* or b* moves colour-science's dE2000 by less than 1e-3
    steady = np.ones(len(L1), bool)
    for step in ([0, 1e-4, 0], [0, -1e-4, 0], [0, 0, 1e-4], [0, 0, -1e-4]):
        steady &= np.abs(colour.delta_E(L1, lab + step, method="CIE 2000") - want) < 1e-3
    assert 28 <= steady.sum() < len(L1)
    np.testing.assert_allclose(got["dE"][steady], want[steady], atol=2e-4)
    np.testing.assert_allclose(got["dE"][steady], expected[steady], atol=2e-3)
    np.testing.assert_allclose(got["Lab"], L2, atol=2e-3)


# ------------------------------------------------------------------------------------ the full case, end to end

@pytest.fixture(scope="module")
def full_chart():
    """One sequence of the 7-band plan of a chart with a 0.99 white tile drifting (2, 1) px per frame, and the
    white tile's ROI at the reference time (found on the motion-compensated cube)."""
    from dataclasses import replace

    from moving_helpers import MOTION, moving_setup

    from specgpu.pipeline.sequence_decoder import SequenceDecoder
    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.rig.scene import colorchecker_scene

    desc, bundle, plan, _ = moving_setup()
    shot = capture_plan(replace(desc, motion=MOTION), plan, colorchecker_scene(240, 320, white_tile=0.99),
                        noise_seed=4, calibration=bundle)
    frames = shot.sequences[0].frames
    cube = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(frames)["cube"]
    white = np.all(np.abs(cube - 0.99) < 0.08, axis=-1) & (np.arange(240) < 40)[:, None]
    ys, xs = np.nonzero(white)
    x, y, w, h = int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)
    return frames, plan, bundle, f"{x + 2},{y + 2},{w - 4},{h - 4}"


def test_the_full_case_gives_xyz_and_dE_equal_to_recover(full_chart):
    """Motion, denoise and a reference white with coefficients, XYZ and dE: the decoder's XYZ and dE (the colour
    launched on the filtered XYZ, read back once) equal ``recover``'s cube through XYZ and Lab to dE2000."""
    from specgpu.engine.colorimetry import delta_E
    from specgpu.pipeline.capture_folder import SequenceFolder
    from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ
    from specgpu.pipeline.sequence_decoder import SequenceDecoder

    frames, plan, bundle, roi = full_chart
    reference = [50.0, 0.0, 0.0]
    dec = SequenceDecoder(plan, bundle, ("coefficients", "XYZ", "dE"), reference=reference, motion="global",
                          denoise=(2, 1e-4), white_roi=roi)
    maps = dec.maps(frames)
    assert maps["white_gains"] is not None
    want = recover(SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {}), sequence=0, motion="global",
                   denoise=(2, 1e-4), white_roi=roi)
    XYZ = to_XYZ(want, plan)
    dE = delta_E(np.array(reference, np.float32), to_Lab(XYZ, plan))
    for got, expected in ((maps["XYZ"], XYZ), (maps["dE"], dE)):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
        assert 0 < np.isnan(got).mean() < 0.2  # the border seen outside the field: NaN alike
    ok = np.isfinite(dE)
    np.testing.assert_allclose(maps["XYZ"][ok], XYZ[ok], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(maps["dE"][ok], dE[ok], atol=1e-2)
    assert maps["dE"].dtype == np.float32 and maps["dE"].shape == frames.shape[1:]
    assert dE[ok].max() - dE[ok].min() > 20  # a chart: the colours differ
    # the coefficients rebuild the cube recover gives
    np.testing.assert_allclose((maps["coefficients"] @ dec.basis.T)[ok], want[ok], rtol=1e-4, atol=1e-4)


def test_a_white_that_rescales_the_columns_reuses_the_plan_rows(full_chart, monkeypatch):
    """A reference white's decoder that is the plan's with its columns divided by the gains (no colour change of
    the light) gets its pass rows from the plan's, made once, with the same columns divided; the guide's row stays
    the plan's; any other decoder has its rows rebuilt."""
    from specgpu.pipeline.decoder_outputs import Outputs
    from specgpu.pipeline.denoise import warped_guide_row
    from specgpu.pipeline.sequence_decoder import SequenceDecoder

    _, plan, bundle, roi = full_chart
    dec = SequenceDecoder(plan, bundle, ("coefficients", "XYZ", "dE"), reference=[50.0, 0.0, 0.0],
                          motion="global", denoise=(2, 1e-4), white_roi=roi)
    made = []
    rows = Outputs.rows
    monkeypatch.setattr(Outputs, "rows", lambda self, A=None: made.append(A) or rows(self, A))
    for seed in range(3):
        g = np.random.default_rng(seed).uniform(0.9, 1.1, plan.K)
        A = plan.A / g[None, :]
        got = dec.white_rows(A, g)
        want = np.vstack([rows(dec.spec, A)[0], warped_guide_row(plan)])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
        np.testing.assert_array_equal(got[-1], warped_guide_row(plan).reshape(-1))
    assert len(made) == 1  # the plan's rows, once
    other = plan.A * np.linspace(0.8, 1.2, plan.A.shape[0])[:, None]  # a colour change: its rows rebuilt
    np.testing.assert_allclose(dec.white_rows(other, np.ones(plan.K)),
                               np.vstack([rows(dec.spec, other)[0], warped_guide_row(plan)]), rtol=1e-12)
    assert len(made) == 2


def test_the_moving_maps_are_views_of_the_filtered_rows_not_copies(full_chart):
    """Without a colour output the filtered coefficients and XYZ are handed to the sink as views of the one array
    the filter made (no per-sequence copy of each); with dE the XYZ the colour launch reads is made contiguous once
    and the coefficients stay a view."""
    from specgpu.pipeline.sequence_decoder import SequenceDecoder

    frames, plan, bundle, _ = full_chart
    plain = SequenceDecoder(plan, bundle, ("coefficients", "XYZ"), motion="global", denoise=(2, 1e-4)).maps(frames)
    assert np.may_share_memory(plain["coefficients"], plain["XYZ"])  # slices of one array
    coloured = SequenceDecoder(plan, bundle, ("coefficients", "XYZ", "dE"), reference=[50.0, 0.0, 0.0],
                               motion="global", denoise=(2, 1e-4)).maps(frames)
    assert coloured["XYZ"].flags.c_contiguous and not np.may_share_memory(coloured["coefficients"], coloured["XYZ"])
    assert coloured["coefficients"].base is not None
    for name in ("coefficients", "XYZ"):
        np.testing.assert_array_equal(np.isnan(plain[name]), np.isnan(coloured[name]))
        ok = np.isfinite(plain[name])
        np.testing.assert_array_equal(plain[name][ok], coloured[name][ok])
