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


def test_one_probe_run_slowed_by_a_passing_load_does_not_lengthen_the_estimate():
    import time

    pauses = iter([0.3, 0.1, 0.3])  # the second run alone meets a quiet machine
    assert machine_speed(lambda: time.sleep(next(pauses))) == pytest.approx(0.1 / 0.05, rel=0.5)
    pauses = iter([0.3])
    assert machine_speed(lambda: time.sleep(next(pauses)), repeats=1) == pytest.approx(0.3 / 0.05, rel=0.5)


def test_the_estimate_is_the_sum_of_its_steps_and_kept_calibrations_cost_a_load():
    from specgpu.apps.demo_scope import estimate_steps

    quick = scope_of(demo_profiles())
    steps = estimate_steps(quick)
    assert set(steps) == {"start", "calibration", "planning", "measuring", "led", "moving", "report"}
    assert sum(steps.values()) == pytest.approx(estimate_seconds(quick))
    assert all(seconds > 0 for seconds in steps.values())
    # the lab rig and the LED rig: two calibrations to make, or one, or two loads
    one, both = estimate_steps(quick, calibrated=1), estimate_steps(quick, calibrated=2)
    assert steps["calibration"] > one["calibration"] > both["calibration"] > 0
    assert both["calibration"] < 0.1 * steps["calibration"]
    assert {k: v for k, v in both.items() if k != "calibration"} == {k: v for k, v in steps.items()
                                                                     if k != "calibration"}
    line = announce(quick, speed=1.0, calibrated=2)
    assert f"about {estimate_seconds(quick, calibrated=2):.0f} s" in line


def test_the_step_clock_adds_up_each_steps_cpu_and_wall_seconds():
    import time

    from specgpu.apps.demo_scope import StepClock

    clock = StepClock()
    for _ in range(2):
        with clock("busy"):
            t0 = time.process_time()
            while time.process_time() - t0 < 0.05:
                pass
    with clock("idle"):
        time.sleep(0.1)
    steps = clock.steps({"busy": 3.0, "never": 1.0})
    assert steps["busy"]["cpu_s"] >= 0.1 and steps["busy"]["wall_s"] >= steps["busy"]["cpu_s"] * 0.9
    assert steps["idle"]["wall_s"] >= 0.1 and steps["idle"]["cpu_s"] < 0.05
    assert steps["busy"]["estimate_s"] == 3.0 and "estimate_s" not in steps["idle"]
    assert steps["never"] == {"cpu_s": 0.0, "wall_s": 0.0, "estimate_s": 1.0}
