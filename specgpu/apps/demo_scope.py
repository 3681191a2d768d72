"""What one ``specgpu demo`` runs (:class:`DemoScope`) and how long that will take (:func:`estimate_seconds`).

The quick demo (the default) runs the paper's plans, the best design of each sequence-time budget and the
moving scene (on a field of at most 320 x 240) on one profile with one noise draw; ``--full`` runs every row on
both profiles (the lab rig and the same rig without imperfections) with two draws. The estimate the demo prints
before it starts is a cost model counted from the sizes it will run (pixels, frames, designs, draws), each unit's
cost the CPU seconds it took on a 2-core x86 machine, scaled by a short timing of this machine's speed at that
moment (a busy machine estimates longer).
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from specgpu.planning.equal_time import EQUAL_TIME, row_name

__all__ = ["DemoScope", "demo_scope", "estimate_seconds", "estimate_steps", "StepClock", "announce",
           "machine_speed", "QUICK_EQUAL_TIME_ROWS", "QUICK_MOVING_SIZE"]

#: The quick demo's time-budgeted rows: the design of each budget (the lowest error within it).
QUICK_EQUAL_TIME_ROWS = ("optimal-9", "optimal-6", "optimal-3")
#: The quick demo's moving scene at most this field (width, height): its capture, motion estimate and truth cost
#: about 12 s of CPU at 640 x 480.
QUICK_MOVING_SIZE = (320, 240)

# The cost model: CPU seconds per unit (every thread of the process) on the reference machine (2 x86 cores), for
# a 640 x 480 rig and its 31-band chart where a cost scales with pixels; fitted to the steps' CPU seconds of quick
# demos at 640 x 480 (lab) and 320 x 240 (ideal), which report.json records beside the model's share.
_REFERENCE_PIXELS = 640 * 480
_COST = {
    "start": 1.0,  # the basis, the prior and its training set
    "calibration": 7.9,  # per rig: both feedback loops
    "load": 0.2,  # per rig: a calibration kept from an earlier run, loaded and checked
    "plan": 0.4,  # a paper plan (its basis projection, its illuminants fitted to the light, every frame at once)
    "budgeted": 4.5,  # a paper plan made again within a budget, with its estimator
    "design": 0.5,  # an optimal design (one start, 100 iterations)
    "bound": 0.7,  # per budget: the limit's search
    "frame": 0.15,  # a captured, corrected and recovered frame (per draw)
    "evaluation": 0.6,  # a recovery scored per patch and per pixel (per draw)
    "files": 0.85,  # a plan's files (cubes, maps, previews, its sequence uncompressed) and its sigma, first draw
    "led_row": 1.0,  # an LED row designed, captured and scored (per draw)
    "report": 0.6,  # a plan's share of the report page: its figures
    "report_pixels": 0.5,  # and its renderings and maps, which scale with pixels
    "moving": 11.0,  # the moving-scene section
}
#: The sequence time of the LED rig's rows (:data:`specgpu.apps.demo_lights.LED_BUDGET_MS`).
_LED_BUDGET_MS = 60.0
#: The speed probe's seconds on the reference machine when idle.
_PROBE_REFERENCE_S = 0.05


@dataclass(frozen=True)
class DemoScope:
    """What one demo run does.

    Attributes
    ----------
    full : bool
        Every row on every profile (``--full``), else the quick demo.
    profiles : tuple of str
        The profiles run, the main one first.
    methods : tuple of str
        The paper's plans (names of :data:`specgpu.apps.demo.DEMO_METHODS`).
    estimator_rows : tuple of str
        Rows beyond the paper without a time budget (names of :data:`specgpu.apps.demo.ESTIMATOR_ROWS`).
    equal_time_rows : tuple of str
        Rows of :data:`specgpu.planning.equal_time.EQUAL_TIME` made within their budget (row names there).
    draws : int
        Noise draws per plan and profile.
    pixels : int
        The camera's pixels.
    moving_size : (int, int)
        Width and height of the moving scene's field: the camera's, at most :data:`QUICK_MOVING_SIZE` in the
        quick demo.
    """

    full: bool
    profiles: tuple
    methods: tuple
    estimator_rows: tuple
    equal_time_rows: tuple
    draws: int
    pixels: int
    moving_size: tuple

    def equal_time_names(self) -> list[str]:
        """The equal-time plans' names (``<row>@<budget>ms``)."""
        return [row_name(n, T) for T, (_, rows) in EQUAL_TIME.items() for n in rows if n in self.equal_time_rows]

    def designs(self) -> int:
        """Optimal designs made per profile."""
        rows = [r for _, rows in EQUAL_TIME.values() for n, r in rows.items() if n in self.equal_time_rows]
        return (sum(name.startswith("optimal") for name in self.estimator_rows)
                + sum(method == "optimal" for method, _, _ in rows))

    def plans(self) -> int:
        """Plans measured per profile."""
        return len(self.methods) + len(self.estimator_rows) + len(self.equal_time_names())


def demo_scope(profiles: dict, *, full: bool = False, draws: int | None = None, methods=(),
               estimator_rows=()) -> DemoScope:
    """The scope of a demo on ``profiles`` (label -> RigDescription, main first: :func:`specgpu.apps.demo.
    demo_profiles`): the quick demo runs the main profile only, ``methods``, no ``estimator_rows`` and
    :data:`QUICK_EQUAL_TIME_ROWS`, one draw; ``full`` every profile and row, two draws. ``draws`` overrides."""
    main = next(iter(profiles.values()))
    width, height = main.camera.roi_width, main.camera.roi_height
    if not full:
        width, height = min(width, QUICK_MOVING_SIZE[0]), min(height, QUICK_MOVING_SIZE[1])
    every_row = tuple(n for _, rows in EQUAL_TIME.values() for n in rows)
    return DemoScope(full=bool(full), profiles=tuple(profiles) if full else tuple(profiles)[:1],
                     methods=tuple(methods), estimator_rows=tuple(estimator_rows) if full else (),
                     equal_time_rows=tuple(dict.fromkeys(every_row)) if full else QUICK_EQUAL_TIME_ROWS,
                     draws=int(draws) if draws is not None else (2 if full else 1),
                     pixels=main.camera.roi_width * main.camera.roi_height, moving_size=(width, height))


def _frames(scope: DemoScope, frames_per_plan: dict) -> int:
    """Frames captured per profile and draw, an ambient frame per plan included."""
    names = [*scope.methods, *scope.estimator_rows, *scope.equal_time_names()]
    return sum(frames_per_plan.get(name.split("@")[0], 9) + 1 for name in names)


#: Frames per sequence of each plan (before the ambient frame), for the estimate only.
_FRAMES = {"narrowband": 31, "biased": 6, "symmetric": 9, "tristimulus-D65": 3, "tristimulus-A": 3,
           "wiener-9": 9, "optimal-9": 9, "optimal-6": 6, "optimal-3": 3, "symmetric-9": 9, "biased-6": 6,
           "wiener-6": 6}


def _probe():
    """A short workload of one thread (no BLAS, whose thread count varies): three sorts of a million floats."""
    x = np.random.default_rng(0).random(1_000_000)
    for _ in range(3):
        np.sort(x)


def machine_speed(probe=None, *, repeats: int = 3) -> float:
    """How much slower than the reference machine (idle) this one runs now: ``probe`` (default a short NumPy
    workload, about 0.05 s there) timed against its reference time, the quickest of ``repeats`` runs; at least 1
    (a faster machine is not promised a shorter run).

    The quickest run, not one run: a single 50 ms run that meets a moment of another process's work, or of a
    virtual machine's host taking the CPU, read 2.4 times the demo's real time. Sustained load slows every run
    and still lengthens the estimate."""
    probe = _probe if probe is None else probe
    best = math.inf
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        probe()
        best = min(best, time.perf_counter() - t0)
    return max(1.0, best / _PROBE_REFERENCE_S)


def estimate_steps(scope: DemoScope, *, speed: float = 1.0, calibrated: int = 0) -> dict[str, float]:
    """Seconds each step of the demo of ``scope`` takes (the steps :class:`StepClock` records): the cost model
    counted from its sizes, times ``speed`` (:func:`machine_speed`); ``calibrated``: the rigs whose calibration
    is kept from an earlier run (loaded, not made; the main profile's first, then the others, the LED rig's last).
    """
    scale = scope.pixels / _REFERENCE_PIXELS
    n = len(scope.profiles)
    plans = scope.plans()
    bounds = len(EQUAL_TIME) if scope.equal_time_rows else 0
    budgeted = len(scope.equal_time_names()) - sum(name.startswith("optimal") for name in scope.equal_time_rows)
    made = plans - scope.designs() - budgeted
    led_rows = sum(name in scope.equal_time_rows for name in EQUAL_TIME[_LED_BUDGET_MS][1])
    rigs = n + (1 if led_rows else 0)
    to_make = max(0, rigs - int(calibrated))
    steps = {
        "start": _COST["start"],
        "calibration": (to_make * _COST["calibration"] + (rigs - to_make) * _COST["load"]) * scale,
        "planning": n * (made * _COST["plan"] + budgeted * _COST["budgeted"] + scope.designs() * _COST["design"])
        + bounds * _COST["bound"],
        "measuring": n * scope.draws * (_frames(scope, _FRAMES) * _COST["frame"] + plans * _COST["evaluation"])
        * scale + plans * _COST["files"] * scale,
        # the LED rig: its 60 ms rows designed and measured as the DMD's
        "led": scope.draws * led_rows * _COST["led_row"] * scale,
        "moving": _COST["moving"] * scope.moving_size[0] * scope.moving_size[1] / _REFERENCE_PIXELS,
        "report": plans * (_COST["report"] + _COST["report_pixels"] * scale),
    }
    return {step: cost * speed for step, cost in steps.items()}


def estimate_seconds(scope: DemoScope, *, speed: float = 1.0, calibrated: int = 0) -> float:
    """Seconds the demo of ``scope`` takes: the sum of :func:`estimate_steps`."""
    return sum(estimate_steps(scope, speed=speed, calibrated=calibrated).values())


class StepClock:
    """CPU and wall seconds a run spends in each of its steps (a step may be entered several times): ``with
    clock("planning"): ...``. CPU seconds are the process's, every thread's (the OpenCL device's included)."""

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self.wall: dict[str, float] = {}

    @contextmanager
    def __call__(self, step: str):
        cpu, wall = time.process_time(), time.perf_counter()
        try:
            yield
        finally:
            self.cpu[step] = self.cpu.get(step, 0.0) + time.process_time() - cpu
            self.wall[step] = self.wall.get(step, 0.0) + time.perf_counter() - wall

    def steps(self, estimate: dict | None = None) -> dict:
        """step -> ``{"cpu_s", "wall_s"}`` of every step entered, and ``"estimate_s"``, the step's share of
        ``estimate`` (:func:`estimate_steps`) where given."""
        out = {}
        for step in {**(estimate or {}), **self.cpu}:
            row = {"cpu_s": self.cpu.get(step, 0.0), "wall_s": self.wall.get(step, 0.0)}
            if estimate is not None and step in estimate:
                row["estimate_s"] = float(estimate[step])
            out[step] = row
        return out


def announce(scope: DemoScope, *, speed: float | None = None, full_scope: DemoScope | None = None,
             calibrated: int = 0) -> str:
    """The line the demo prints before it starts: what it runs and about how long it takes (and ``--full``'s
    time when ``full_scope`` is given); ``calibrated``: :func:`estimate_steps`'."""
    speed = machine_speed() if speed is None else speed
    what = (f"{', '.join(scope.profiles)} profile{'s' if len(scope.profiles) > 1 else ''}, {scope.plans()} plans, "
            f"{scope.draws} noise draw{'s' if scope.draws > 1 else ''}, a moving scene")
    line = f"demo: {what}: about {estimate_seconds(scope, speed=speed, calibrated=calibrated):.0f} s"
    if full_scope is not None:
        n = len(full_scope.profiles)
        line += f" (--full: every row on {n} profile{'s' if n > 1 else ''}, about " \
                f"{estimate_seconds(full_scope, speed=speed, calibrated=calibrated):.0f} s)"
    return line
