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


def test_plan_for_denoise_records_it_and_recover_warns_without_the_filter(files):
    d, rig, cal = files
    out = run("plan", "optimal", "--frames", "4", "--calib", cal, "--rig", rig, "--out", d / "o.npz",
              "--sequence-ms", "40", "--no-ambient", "--denoise").output
    assert "where recover --denoise --denoise-radius 2 flattens the noise" in out
    plan = load_plan(d / "o.npz")
    assert plan.params["denoise"]["radius"] == 2 and plan.params["denoise"]["variance_reduction"] > 50
    assert plan.params["expected"]["rmse_at_decoder_noise"] < plan.params["expected"]["rmse"]
    run("capture", "--rig", rig, "--plan", d / "o.npz", "--calib", cal, "--scene", "colorchecker", "--out",
        d / "seq", "--sequences", "1")
    plain = run("recover", d / "seq", "--out", d / "plain.npz")
    assert "designed for --denoise --denoise-radius 2" in plain.stderr
    other = run("recover", d / "seq", "--out", d / "r3.npz", "--denoise", "--denoise-radius", "3")
    assert "designed for --denoise-radius 2, filtered here with 3" in other.stderr
    same = run("recover", d / "seq", "--out", d / "r2.npz", "--denoise")
    assert "designed for" not in same.stderr


def test_plan_for_denoise_needs_a_decoder_with_a_noise_model(files):
    d, rig, cal = files
    one_line_error(run("plan", "hadamard", "--bands", "7", "--calib", cal, "--rig", rig, "--out", d / "hd.npz",
                       "--denoise", ok=False), "--estimator wiener")
    assert not (d / "hd.npz").exists()
    run("plan", "hadamard", "--bands", "7", "--calib", cal, "--rig", rig, "--out", d / "hw.npz", "--denoise",
        "--estimator", "wiener", "--no-ambient")
    plan = load_plan(d / "hw.npz")
    assert plan.params["denoise"]["radius"] == 2 and "decoder_noise" in plan.params


def test_an_optimal_plan_without_a_budget_says_its_sequence_time_and_the_option(files):
    """Without --sequence-ms the optimal design takes the longest useful exposures: a one-line note on stderr
    gives its sequence time and points to --sequence-ms; with a budget, no note."""
    d, rig, cal = files
    free = run("plan", "optimal", "--frames", "3", "--calib", cal, "--rig", rig, "--out", d / "of.npz",
               "--no-ambient")
    plan = load_plan(d / "of.npz")
    notes = [line for line in free.stderr.splitlines() if line.startswith("note: no --sequence-ms")]
    assert len(notes) == 1
    assert f"{plan.exposure_s * 1e3:.1f} ms a frame, {plan.sequence_s * 1e3:.0f} ms a sequence" in notes[0]
    assert notes[0].endswith("--sequence-ms T designs within T ms a sequence")
    capped = run("plan", "optimal", "--frames", "3", "--calib", cal, "--rig", rig, "--out", d / "oc.npz",
                 "--no-ambient", "--sequence-ms", "60")
    assert "--sequence-ms" not in capped.stderr and load_plan(d / "oc.npz").sequence_s <= 0.060 * (1 + 1e-9)
