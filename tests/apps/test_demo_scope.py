"""What ``specgpu demo`` runs, quick and ``--full``, and the estimate it prints before it starts."""

from __future__ import annotations

from dataclasses import replace

import pytest

from specgpu.apps.demo import DEMO_METHODS, ESTIMATOR_ROWS, demo_profiles, scope_of
from specgpu.apps.demo_scope import QUICK_EQUAL_TIME_ROWS, announce, estimate_seconds, machine_speed
from specgpu.planning.equal_time import EQUAL_TIME


def test_the_quick_demo_runs_the_paper_plans_and_each_budgets_design_on_one_profile_once():
    profiles = demo_profiles()
    scope = scope_of(profiles)
    assert scope.profiles == ("lab",) and scope.draws == 1 and not scope.full
    assert scope.methods == tuple(DEMO_METHODS) and scope.estimator_rows == ()
    assert scope.equal_time_names() == ["optimal-9@60ms", "optimal-6@40ms", "optimal-3@20ms"]
    assert scope.plans() == len(DEMO_METHODS) + 3 and scope.designs() == 3
    assert set(QUICK_EQUAL_TIME_ROWS) <= {n for _, rows in EQUAL_TIME.values() for n in rows}


def test_the_full_demo_runs_every_row_on_both_profiles_twice():
    scope = scope_of(demo_profiles(), full=True)
    every = [n for _, rows in EQUAL_TIME.values() for n in rows]
    assert scope.profiles == ("lab", "ideal") and scope.draws == 2 and scope.full
    assert scope.estimator_rows == ESTIMATOR_ROWS and len(scope.equal_time_names()) == len(every) == 8
    assert scope.plans() == len(DEMO_METHODS) + len(ESTIMATOR_ROWS) + 8
    assert scope.designs() == 3 + 3  # optimal-9/6/3 beyond the paper, and each budget's
    assert scope_of(demo_profiles(), full=True, draws=5).draws == 5 and scope_of(demo_profiles(), draws=3).draws == 3


def test_the_estimate_counts_the_sizes_run():
    profiles = demo_profiles()
    quick, full = scope_of(profiles), scope_of(profiles, full=True)
    assert 10 < estimate_seconds(quick) < 90  # the quick demo: about a minute on the reference machine
    assert estimate_seconds(full) > 3 * estimate_seconds(quick)
    lab = profiles["lab"]
    small = {"lab": replace(lab, camera=replace(lab.camera, roi_width=320, roi_height=240))}
    assert scope_of(small).pixels == 320 * 240 and estimate_seconds(scope_of(small)) < estimate_seconds(quick)
    assert estimate_seconds(scope_of(profiles, draws=2)) > estimate_seconds(quick)
    assert estimate_seconds(quick, speed=3.0) == pytest.approx(3 * estimate_seconds(quick))


def test_the_announcement_says_what_runs_and_how_long_quick_and_full():
    profiles = demo_profiles()
    quick = scope_of(profiles)
    line = announce(quick, speed=2.0, full_scope=scope_of(profiles, full=True))
    assert line.startswith("demo: lab profile, 8 plans, 1 noise draw, a moving scene: about ")
    assert f"about {estimate_seconds(quick, speed=2.0):.0f} s" in line and "--full" in line
    assert "\n" not in line


def test_a_machine_slower_than_the_reference_estimates_longer_and_a_faster_one_no_shorter():
    import time

    assert machine_speed(lambda: time.sleep(0.2)) == pytest.approx(0.2 / 0.05, rel=0.5)
    assert machine_speed(lambda: None) == 1.0
