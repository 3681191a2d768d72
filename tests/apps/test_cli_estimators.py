"""The estimator options through the CLI: plan --estimator / --training / optimal / hadamard, recover --sigma and
--delta-e-sigma, and their one-line refusals."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import calibrated_rig, one_line_error, run

from specgpu import io


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("est")
    calibrated_rig(d)
    run("plan", "narrowband", "--step-nm", 20, "--estimator", "wiener", "--rig", d / "rig.toml", "--calib",
        d / "calib.npz", "--out", d / "nb.npz")
    run("capture", "--rig", d / "rig.toml", "--plan", d / "nb.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seq", "--sequences", 2, "--seed", 3)
    return d


def test_plan_records_the_estimator(work):
    from specgpu.planning import load_plan

    plan = load_plan(work / "nb.npz")
    assert plan.params["estimator"] == "wiener" and plan.params["expected"]["rmse"] > 0
    assert set(plan.params["noise"]) == {"gain_e_per_dn", "read_var_dn2", "light_rms"}


def test_recover_sigma_maps(work, tmp_path):
    out = run("recover", work / "seq", "--out", tmp_path / "c.exr", "--sigma", tmp_path / "s.exr",
              "--delta-e-sigma", tmp_path / "d.exr").output
    assert "s.exr" in out and "d.exr" in out
    sig, names, _ = io.read_map(tmp_path / "s.exr")
    assert names[0] == "sigma_400nm" and names[-1] == "sigma_rms" and sig.shape == (240, 320, 17)
    assert np.all(sig[100:140, 100:200] > 0) and np.all(sig[100:140, 100:200] < 0.1)
    np.testing.assert_allclose(sig[..., -1], np.sqrt((sig[..., :-1] ** 2).mean(axis=-1)), rtol=1e-5)
    des, names, _ = io.read_map(tmp_path / "d.exr")
    assert names == ("dE2000_sigma",) and np.all(np.isfinite(des[100:140, 100:200]))
    assert 0 < np.median(des) < 5


def test_sigma_refused_without_a_noise_model(work, tmp_path):
    """A plan made for a custom rig's calibration without --rig has no noise model: --sigma says so, in one line,
    and writes nothing."""
    run("plan", "narrowband", "--step-nm", 30, "--calib", work / "calib.npz", "--out", tmp_path / "p.npz")
    run("capture", "--rig", work / "rig.toml", "--plan", tmp_path / "p.npz", "--calib", work / "calib.npz",
        "--scene", "white", "--out", tmp_path / "seq")
    one_line_error(run("recover", tmp_path / "seq", "--out", tmp_path / "c.exr", "--sigma", tmp_path / "s.exr",
                       ok=False), "no noise model")
    assert not (tmp_path / "c.exr").exists() and not (tmp_path / "s.exr").exists()


def test_plan_refusals(work, tmp_path):
    base = ("plan", "optimal", "--calib", work / "calib.npz", "--rig", work / "rig.toml", "--out", tmp_path / "o.npz",
            "--frames", 3)
    one_line_error(run(*base, "--training-only", ok=False), "training set is empty")
    one_line_error(run(*base, "--training", tmp_path / "missing.csv", ok=False), "missing.csv")
    one_line_error(run("plan", "hadamard", "--bands", 12, "--calib", work / "calib.npz", "--rig", work / "rig.toml",
                       "--out", tmp_path / "h.npz", ok=False), "hadamard bands")
    one_line_error(run("plan", "narrowband", "--estimator", "wiener", "--calib", work / "calib.npz", "--out",
                       tmp_path / "n.npz", ok=False), "give that rig's description with --rig")
    assert not (tmp_path / "o.npz").exists()
