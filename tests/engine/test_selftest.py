"""The golden regression suite: it passes on every device, and it can fail."""

from __future__ import annotations

import json

import numpy as np
import pytest

from specgpu.engine.selftest import CASES, compare, golden_path, load_golden, run_selftest


def test_every_kernel_reproduces_the_golden_set(queue):
    report = run_selftest(device=queue)
    assert report.passed, report.format(verbose=True)
    assert set(report.kernels()) == {"linear", "xyz_to_lab", "delta_e", "fused", "guided"}
    assert len(report.cases) == len(CASES)
    assert "PASS: every kernel reproduces the golden set" in report.format()


def _rewrite(tmp_path, mutate):
    """A copy of the golden file with ``mutate(manifest, arrays)`` applied."""
    manifest, arrays = load_golden()
    flat = {f"{case}/{name}": value for case, d in arrays.items() for name, value in d.items()}
    mutate(manifest, flat)
    path = tmp_path / "golden.npz"
    np.savez(path, _manifest=np.array(json.dumps(manifest)), **flat)
    return path


def test_a_wrong_expectation_fails_that_kernel_only(queue, tmp_path):
    def perturb(manifest, flat):
        flat["xyz_to_lab_d65/expected_Lab"] = flat["xyz_to_lab_d65/expected_Lab"] + 2e-4  # twice the tolerance

    report = run_selftest(device=queue, path=_rewrite(tmp_path, perturb))
    assert not report.passed
    assert report.failed_kernels() == ["xyz_to_lab"]
    assert "FAIL xyz_to_lab_d65" in report.format()


def test_a_missing_case_fails(queue, tmp_path):
    def drop(manifest, flat):
        manifest["cases"] = [c for c in manifest["cases"] if c["name"] != "delta_e_cie2000_sharma2005"]

    report = run_selftest(device=queue, path=_rewrite(tmp_path, drop))
    assert not report.passed and "delta_e" in report.failed_kernels()


def test_corrupt_or_foreign_golden_file_is_a_clear_error(tmp_path):
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(golden_path().read_bytes()[:1000])
    with pytest.raises(ValueError, match=f"golden set {truncated} is unreadable"):
        load_golden(truncated)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, _manifest=np.array(json.dumps({"format": "other", "version": 3})))
    with pytest.raises(ValueError, match="expected specgpu-golden version 1"):
        load_golden(foreign)


def test_compare_requires_non_finite_in_place():
    assert compare("y", np.array([1.0, np.nan]), np.array([1.0, np.nan]), "abs") == (0.0, "")
    err, message = compare("y", np.array([1.0, 2.0]), np.array([1.0, np.nan]), "abs")
    assert err == float("inf") and "non-finite" in message
    assert compare("y", np.array([110.0]), np.array([100.0]), "range")[0] == pytest.approx(0.1)
    assert compare("m", np.array([1, 0], np.uint8), np.array([1, 2], np.uint8), "abs")[0] == 1
