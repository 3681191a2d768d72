"""Does ``specgpu stream --view`` keep the stream's rate? The same twin stream (paced at the camera's frame rate,
the chart, symmetric-9 by default) run without and with the napari view, alternately, and the median rate and
drops of each printed, with their ratio.

    PYTHONPATH=. xvfb-run -a python tools/benchmarks/stream_view_check.py --seconds 10 --runs 3

Needs the viewer extra and a display with OpenGL (a desktop, or Xvfb with Mesa). The view closes itself when the
stream ends.
"""

from __future__ import annotations

import argparse
import statistics

from specgpu.apps.live_view import run_with_view
from specgpu.calibration import calibrate
from specgpu.hardware.drivers import open_rig_driver
from specgpu.pipeline.recovery import default_basis
from specgpu.pipeline.stream import Stream
from specgpu.planning import make_plan
from specgpu.rig.config import rig_from_dict
from specgpu.rig.scene import colorchecker_scene


def one_run(description, plan, bundle, scene, outputs, seconds, view):
    driver = open_rig_driver(description, plan, hardware=None, scene=scene, calibration=bundle, seed=1, pacing="paced")
    stream = Stream(driver, plan, bundle, outputs=outputs, policy="drop_newest", reference=None)
    if view:
        report = run_with_view(stream, seconds, wavelengths=plan.output_wavelengths, close_when_done=True)
    else:
        report = stream.run(seconds)
    a = report.assembly
    return report.sequences_per_s, report.frames_per_s, a.dropped + report.ring.dropped


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--outputs", default="cube,XYZ")
    args = parser.parse_args(argv)
    description = rig_from_dict({}, source="<paper rig, 640 x 480>")
    bundle = calibrate(description, seed=0)
    plan = make_plan("symmetric", bundle, default_basis(), m=5)
    scene = colorchecker_scene(description.camera.roi_height, description.camera.roi_width)
    outputs = args.outputs.split(",")
    rows = {False: [], True: []}
    for _ in range(args.runs):
        for view in (False, True):
            rows[view].append(one_run(description, plan, bundle, scene, outputs, args.seconds, view))
            print(f"{'view   ' if view else 'no view'}: {rows[view][-1][0]:.2f} sequences/s, "
                  f"{rows[view][-1][1]:.1f} frames/s, drops {rows[view][-1][2]}", flush=True)
    plain = statistics.median(r[0] for r in rows[False])
    viewed = statistics.median(r[0] for r in rows[True])
    print(f"{description.camera.roi_width} x {description.camera.roi_height}, {plan.method} K={plan.K}, outputs "
          f"{args.outputs}, {args.seconds:g} s x {args.runs}: median {plain:.2f} sequences/s without the view, "
          f"{viewed:.2f} with it (ratio {viewed / plain:.3f}); drops without {sum(r[2] for r in rows[False])}, "
          f"with {sum(r[2] for r in rows[True])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
