"""Shared fixtures: every test that takes ``queue`` runs once per OpenCL device present."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

from specgpu.engine.runtime import SpecgpuDeviceError, get_queue, list_devices

# Kernel builds make the first example of a property test slow; CI runs fewer examples, and the same ones every
# run (derandomized: each test's seed is fixed by the test itself), so a failure in CI reproduces anywhere.
settings.register_profile("default", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow],
                          derandomize=True, database=None, print_blob=True)
PROFILE = "ci" if os.environ.get("CI") else "default"
settings.load_profile(PROFILE)


def pytest_report_header(config):
    """Say in the header how the property tests draw their examples, so a run's log tells how to repeat it."""
    if settings.default.derandomize:
        return f"hypothesis: profile {PROFILE!r}, derandomized (a seed fixed per test: each run draws alike)"
    return f"hypothesis: profile {PROFILE!r}, random examples (CI=1 draws the fixed ones CI runs)"


def _devices():
    try:
        return list_devices()
    except SpecgpuDeviceError:
        return []


DEVICES = _devices()


@pytest.fixture(scope="session", params=DEVICES, ids=[f"{d.selector}:{d.name}" for d in DEVICES])
def queue(request):
    """A command queue on each OpenCL device present (PoCL's CPU device at least)."""
    return get_queue(request.param.device)


@pytest.fixture(params=["cpu", "gpu"])
def kernel_variant(request, monkeypatch):
    """Runs a test once per kernel variant (specgpu.engine.runtime.VARIANTS), forced on whatever device runs it: CI runs
    the GPU kernels on PoCL and the CPU kernels on a GPU."""
    monkeypatch.setenv("SPECGPU_VARIANT", request.param)
    return request.param
