"""``specgpu plan --sequence-ms``: the plan states its exposure, frame period and sequence time, keeps the budget
with the ambient frame it adds, and a budget too short for the frames is one line."""

import pytest
from cli_helpers import RIG, one_line_error, run

from specgpu.calibration.bundle import oracle_calibration, save_calibration
from specgpu.planning import load_plan
from specgpu.rig.config import load_rig


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("budget")
    rig = d / "rig.toml"
    rig.write_text(RIG)
    cal = d / "cal.npz"
    save_calibration(cal, oracle_calibration(load_rig(rig)))
    return d, rig, cal


def test_plan_within_a_budget_with_its_ambient_frame(files):
    d, rig, cal = files
    out = run("plan", "hadamard", "--bands", "7", "--calib", cal, "--rig", rig, "--out", d / "h.npz",
              "--sequence-ms", "50", "--ambient").output
    assert "ms per sequence (budget 50 ms)" in out and "frame period" in out
    plan = load_plan(d / "h.npz")
    assert plan.K == 8 and plan.sequence_s <= 0.050 * (1 + 1e-9)
    assert plan.frame_period_s >= load_rig(rig).camera.min_frame_period_s


def test_plan_without_a_budget_states_its_time(files):
    d, rig, cal = files
    out = run("plan", "hadamard", "--bands", "7", "--calib", cal, "--rig", rig, "--out", d / "free.npz",
              "--no-ambient").output
    plan = load_plan(d / "free.npz")
    assert f"{plan.sequence_s * 1e3:.1f} ms per sequence" in out and "(budget" not in out


def test_a_budget_too_short_is_one_line(files):
    d, rig, cal = files
    one_line_error(run("plan", "symmetric", "--calib", cal, "--rig", rig, "--out", d / "s.npz", "--sequence-ms",
                       "10", ok=False), "cannot hold", "at least")
    assert not (d / "s.npz").exists()
