"""Plans within a sequence-time budget: every method's designed plan keeps its budget (ambient and probe frames
included), the timing the plan states and its file records, the refusal of a budget too short for the frames, the
photon-limited optimal design's gradient and its gain over the paper's design at equal time."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import specgpu.planning as E
from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning import design as D
from specgpu.planning.budget import budget_plan
from specgpu.planning.correction import with_ambient_frame
from specgpu.planning.priors import held_out_basis
from specgpu.planning.timing import exposure_within
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
FLOOR = DESC.camera.min_frame_period_s


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def prior():
    return E.default_prior()


@pytest.fixture(scope="module")
def basis():
    return held_out_basis()


def noise_at(t):
    return E.NoiseModel.from_rig(DESC, t)


def _method_args(method, basis, prior):
    if method in ("biased", "symmetric"):
        return (basis,), {"m": 5}
    if method == "narrowband":
        return (), {"step_nm": 30.0}
    if method == "hadamard":
        return (), {"bands": 7}
    if method == "tristimulus":
        return (), {"illuminant": "D65"}
    return (prior, noise_at), {"frames": 4, "starts": 1, "iterations": 40}


@pytest.mark.parametrize("method", ["narrowband", "biased", "symmetric", "tristimulus", "hadamard", "optimal"])
@pytest.mark.parametrize("sequence_ms", [25.0, 60.0, 400.0])
def test_every_designed_plan_keeps_its_budget(bundle, basis, prior, method, sequence_ms):
    args, kw = _method_args(method, basis, prior)
    T = sequence_ms / 1e3
    plan = budget_plan(method, bundle, T, *args, min_frame_period_s=FLOOR, extra_frames=1, **kw)
    plan = with_ambient_frame(plan)  # the frame the budget left room for
    assert plan.sequence_s <= T * (1 + 1e-9)
    assert plan.frame_period_s >= max(plan.exposure_s + bundle.min_exposure_s, FLOOR) - 1e-12
    assert plan.sequence_s == pytest.approx(plan.K * plan.frame_period_s)
    assert plan.params["sequence_budget_s"] == T and plan.expected_level.max() <= 0.9 + 1e-9
    # captured at its own rate: the rig's frame period is the plan's, within the camera's fastest
    cam = plan.rig_description(DESC).camera
    assert plan.K / cam.frame_rate_hz <= T * (1 + 1e-6) + plan.K * 2e-6
    assert cam.exposure_s + DESC.light.switch_time_s <= 1.0 / cam.frame_rate_hz


def test_a_short_budget_caps_the_exposure_and_a_long_one_leaves_it(bundle, basis):
    free = E.make_plan("symmetric", bundle, basis, m=5)
    long = budget_plan("symmetric", bundle, 10.0, basis, m=5, min_frame_period_s=FLOOR)
    np.testing.assert_array_equal(long.patterns, free.patterns)
    assert long.exposure_s == free.exposure_s
    short = budget_plan("symmetric", bundle, free.sequence_s / 2, basis, m=5, min_frame_period_s=FLOOR)
    assert short.exposure_s < free.exposure_s and short.expected_level.max() < free.expected_level.max()


@settings(max_examples=60, deadline=None)
@given(T=st.floats(1e-4, 10.0), k=st.integers(1, 64), floor=st.floats(0.0, 0.02))
def test_exposure_within_fits_or_refuses_in_one_line(T, k, floor):
    switch = 80e-6
    try:
        t = exposure_within(T, k, switch, floor)
    except ValueError as exc:
        assert "\n" not in str(exc) and "cannot hold" in str(exc)
        assert T < k * max(2 * switch, floor) * (1 + 1e-6)
        return
    assert t >= switch and k * max(t + switch, floor) <= T * (1 + 1e-9)


def test_too_short_a_budget_is_one_line_naming_the_least(bundle, basis):
    with pytest.raises(ValueError, match=r"cannot hold 9 frames.*at least") as info:
        budget_plan("symmetric", bundle, 0.009, basis, m=5, min_frame_period_s=FLOOR)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="sequence time must be"):
        exposure_within(float("nan"), 3, 80e-6)


def test_timing_is_in_the_file_header_and_old_readers_still_load(tmp_path, bundle):
    plan = budget_plan("hadamard", bundle, 0.05, bands=7, min_frame_period_s=FLOOR)
    path = tmp_path / "p.npz"
    assert E.save_plan(path, plan) == plan.hash
    with np.load(path) as data:
        header = json.loads(str(data["__meta__"]))
    assert header["timing"]["sequence_s"] == pytest.approx(plan.sequence_s)
    assert header["timing"]["sequence_budget_s"] == 0.05 and header["timing"]["frames"] == 7
    loaded = E.load_plan(path)  # the header's extra entry is not hashed content
    assert loaded.hash == plan.hash and loaded.timing == plan.timing


def test_photon_limited_gradient_matches_finite_differences(bundle, prior):
    Sb = D._system_on(bundle, prior.wavelengths)
    cap = 0.9 * (bundle.max_code - float(np.mean(bundle.dark)))
    # reach the objective through a 2-frame, one-start, zero-iteration design's own function: compare J at x and
    # x + h d against the analytic directional derivative, on both sides of the cap
    n = noise_at(0.005)
    rng = np.random.default_rng(1)
    C = Sb.shape[0]
    x = rng.uniform(0.2, 1.0, (2, C))
    white = Sb.sum(axis=1)
    for t in (0.5 * cap / (x @ white).max(), 3.0 * cap / (x @ white).min()):  # under and over the cap
        def J(xx):
            s = xx @ white
            c = np.where(t * s > cap, cap / s, t)
            return D.wiener_objective(c[:, None] * (xx @ Sb), prior, n, np.eye(Sb.shape[1]))[0]
        d = rng.normal(size=x.shape)
        h = 1e-6
        numeric = (J(x + h * d) - J(x - h * d)) / (2 * h)
        s = x @ white
        lit = t * s > cap
        c = np.where(lit, cap / s, t)
        dc = np.where(lit, cap / s ** 2, 0.0)
        g = x @ Sb
        _, dF = D.wiener_objective(c[:, None] * g, prior, n, np.eye(Sb.shape[1]))
        dg = c[:, None] * dF - (dc * np.einsum("kb,kb->k", dF, g))[:, None]
        assert numeric == pytest.approx(float(((dg @ Sb.T) * d).sum()), rel=1e-4)


def test_optimal_beats_the_paper_at_equal_time(bundle, basis, prior):
    T = 0.06
    opt = budget_plan("optimal", bundle, T, prior, noise_at, frames=9, starts=1, iterations=100,
                      min_frame_period_s=FLOOR)
    sym = budget_plan("symmetric", bundle, T, basis, m=5, min_frame_period_s=FLOOR)
    wie = E.with_estimator(sym, bundle, "wiener", prior=prior, noise=noise_at(sym.exposure_s))
    assert opt.sequence_s <= T * (1 + 1e-9) and wie.sequence_s <= T * (1 + 1e-9)
    assert opt.params["expected"]["rmse"] < 0.8 * wie.params["expected"]["rmse"]
    longer = budget_plan("optimal", bundle, 4 * T, prior, noise_at, frames=9, starts=1, iterations=100,
                         min_frame_period_s=FLOOR)
    assert longer.params["expected"]["rmse"] < opt.params["expected"]["rmse"]  # more time, more light, less error
