"""ruff, as configured in pyproject.toml, finds nothing over the package, the tests and the tools."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def ruff_command() -> list[str]:
    """ruff from this interpreter's environment (the test extra), else from PATH; skip when neither has it."""
    try:
        from ruff.__main__ import find_ruff_bin

        return [find_ruff_bin()]
    except ImportError:
        found = shutil.which("ruff")
        if found is None:
            pytest.skip("ruff is not installed (the test extra has it)")
        return [found]


def test_ruff_finds_nothing():
    result = subprocess.run([*ruff_command(), "check", "--no-cache", "specgpu", "tests", "tools"], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_configuration_is_read_and_can_fail(tmp_path):
    """The check is not vacuous: an unused import and a line over 120 columns in a copied module are reported."""
    bad = tmp_path / "specgpu" / "bad.py"
    bad.parent.mkdir()
    bad.write_text('"""A module with faults."""\n\nimport os\n\nLONG = "' + "x" * 120 + '"\n')
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    result = subprocess.run([*ruff_command(), "check", "--no-cache", "--output-format", "concise", "specgpu"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1
    assert "F401" in result.stdout and "E501" in result.stdout
