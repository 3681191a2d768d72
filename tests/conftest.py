"""Shared fixtures: every test that takes ``queue`` runs once per OpenCL device present; ``dask_scheduler`` points
Dask at one worker process kept for the whole session."""

from __future__ import annotations

import logging
import os

import pytest
from hypothesis import HealthCheck, settings

from specgpu.core.numerics import one_blas_thread
from specgpu.engine.runtime import SpecgpuDeviceError, get_queue, list_devices

# as every specgpu command does: the suite's small host matrices on one BLAS thread (on busy cores OpenBLAS's
# threads spin waiting on each other), set before any worker process is started so that it inherits it
one_blas_thread()

# Kernel builds make the first example of a property test slow; CI runs fewer examples, and the same ones every
# run (derandomized: each test's seed is fixed by the test itself), so a failure in CI reproduces anywhere.
settings.register_profile("default", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow],
                          derandomize=True, database=None, print_blob=True)
PROFILE = "ci" if os.environ.get("CI") else "default"
settings.load_profile(PROFILE)


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker more than the cores this process may use (at most four, ``--maxprocesses``). Part of
    the suite waits rather than computes (paced streams, subprocesses killed at a lock, a Dask worker's start), so
    on two cores three workers keep them busy: the whole default suite took 7 min 33 s against 8 min 17 s with
    two, the same CPU time."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 1


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


@pytest.fixture(scope="session")
def dask_cluster():
    """One Dask ``LocalCluster`` for the session, started by the first test that asks: one worker process with one
    thread, as ``specgpu batch`` starts by default (starting one, and the worker's OpenCL context, costs seconds).
    Its worker keeps each batch's state under that batch's own key, as on any long-lived scheduler."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        yield cluster


@pytest.fixture
def dask_scheduler(dask_cluster):
    """Dask's ``scheduler-address`` set to the session's cluster for one test: a batch given no scheduler of its
    own (``specgpu batch`` without ``--scheduler``, ``run_batch`` without ``client``) runs there."""
    import dask
    from distributed import Client

    with Client(dask_cluster) as client:  # a worker an earlier test lost is restarted by its nanny: wait for it
        client.wait_for_workers(1, timeout=120)
    with dask.config.set({"scheduler-address": dask_cluster.scheduler_address}):
        yield dask_cluster.scheduler_address
