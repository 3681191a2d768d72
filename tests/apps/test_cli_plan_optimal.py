"""``specgpu plan optimal``'s refusals through the command line: an objective no design can reach and an empty
training set, each one ``Error:`` line naming its cause, with a failing exit status and no plan written."""

from __future__ import annotations

from cli_helpers import one_line_error, run
from estimator_helpers import DESC  # the planning tests' rig; the bundle fixture is its oracle (tests/apps/conftest.py)


def test_cli_plan_optimal_refusals(tmp_path, bundle):
    from specgpu.calibration.bundle import save_calibration
    from specgpu.rig.config import dump_rig

    cal, rig = tmp_path / "cal.npz", tmp_path / "rig.toml"
    save_calibration(cal, bundle)
    rig.write_text(dump_rig(DESC))  # the bundle is the oracle of DESC: describe that rig to the command
    base = ("plan", "optimal", "--calib", cal, "--out", tmp_path / "o.npz", "--frames", 3, "--rig", rig)
    one_line_error(run(*base, "--target", "0.0001", ok=False), "objective unreachable", "above the target 0.0001")
    one_line_error(run(*base, "--training-only", ok=False), "the training set is empty")
    assert not (tmp_path / "o.npz").exists()
