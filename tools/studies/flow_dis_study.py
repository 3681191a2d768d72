"""Would OpenCV's DIS optical flow pay as a dense motion estimate? Its accuracy and cost on the moving twin.

The dense estimate the motion modes lack would register the frames lit by the same pattern in consecutive sequences
(same spectrum: brightness constancy holds, unlike between a sequence's own frames) and spread that displacement
over the sequence's frame times. This measures the first half: DIS flow (OpenCV's dense inverse search; frames
scaled to 8 bits, which is what it takes) from frame k of one sequence to frame k of the next, against the twin's
true displacement of the background and of a moving object, per pixel. No package of specgpu's depends on OpenCV:

    pip install opencv-python-headless          # about 50 MB
    PYTHONPATH=. python tools/studies/flow_dis_study.py --cases t1,t3,vib,object

At 640 x 480 with the symmetric-9 plan (tools/studies/motion_study.py's rig: paper noise, 200 fps).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

sys.path.insert(0, str(Path(__file__).resolve().parent))

from motion_study import CASES, twin_setup  # noqa: E402

from specgpu.rig.twin import TwinRig  # noqa: E402

try:
    import cv2
except ImportError:  # pragma: no cover - the study's own optional dependency
    sys.exit("tools/studies/flow_dis_study.py needs OpenCV: pip install opencv-python-headless")

PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}  # cv2.DISOPTICAL_FLOW_PRESET_*
BORDER = 30  # px left out at the field's edges (content enters and leaves there)


def eight_bit(frame, lo, hi):
    return np.clip((frame - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="t1,t3,vib,object", help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--presets", default="ultrafast,fast,medium")
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    args = ap.parse_args(argv)
    desc, _, plans, scene = twin_setup(args.small, "symmetric-9")
    plan = plans["symmetric-9"]
    K = plan.K
    h, w = desc.camera.roi_height, desc.camera.roi_width
    print(f"DIS flow (OpenCV {cv2.__version__}), frame k of a sequence to frame k of the next, {w} x {h}, "
          f"symmetric-9 (K = {K}); errors |flow - truth| px, median and 90th percentile over the pixels "
          f"{BORDER} px inside the field; ms per flow on one thread")
    print(f"{'motion':<34}{'preset':>10}{'background':>16}{'object':>16}{'ms':>7}")
    cv2.setNumThreads(1)
    for case in args.cases.split(","):
        label, motion = CASES[case]
        rig = TwinRig(replace(plan.rig_description(desc), motion=motion), scene=scene)
        rig.seed = 3
        rig.load_sequence(plan.patterns)
        frames = [rig.render(i % K, i, i * rig.frame_period_s)[0].astype(np.float32) for i in range(2 * K)]
        inside = np.zeros((h, w), bool)
        inside[BORDER:-BORDER, BORDER:-BORDER] = True
        truths = []  # per k: where a point of frame k is in frame K + k (background, object), and the object's pixels
        for k in range(K):
            pair = rig.motion_truth(np.array([k, K + k]) * rig.frame_period_s)  # relative to their mean time
            mask = rig.motion_truth(np.array([k]) * rig.frame_period_s)["object_mask"]  # at frame k's own time
            own = np.zeros((h, w), bool) if mask is None else mask > 0.99
            truths.append({
                "background": pair["displacement"][1] - pair["displacement"][0],
                "object": K * np.asarray(motion.object_velocity_px_per_frame, np.float64),
                # the object's own pixels away from its edge (where the flow mixes it with what it covers), and
                # the background: neither the object nor a 6 px ring about it
                "core": binary_erosion(own, iterations=6) & inside,
                "background_px": inside & (np.ones((h, w), bool) if mask is None else
                                           binary_erosion(~(mask > 0.01), iterations=6)),
            })
        for preset in args.presets.split(","):
            dis = cv2.DISOpticalFlow_create(PRESETS[preset])
            bg, ob, ms = [], [], []
            for k, truth in enumerate(truths):
                a, b = frames[k], frames[K + k]
                lo, hi = np.percentile(a, 0.5), np.percentile(a, 99.5)
                t0 = time.perf_counter()
                flow = dis.calc(eight_bit(a, lo, hi), eight_bit(b, lo, hi), None)
                ms.append((time.perf_counter() - t0) * 1e3)
                for part, px, out in (("background", "background_px", bg), ("object", "core", ob)):
                    if truth[px].any():
                        d = truth[part]
                        out.append(np.hypot(flow[..., 0] - d[0], flow[..., 1] - d[1])[truth[px]])
            bg = np.concatenate(bg)
            ob = np.concatenate(ob) if ob else None
            ob_text = "-" if ob is None else f"{np.median(ob):.3f} / {np.percentile(ob, 90):.2f}"
            print(f"{label:<34}{preset:>10}{np.median(bg):>9.3f} / {np.percentile(bg, 90):.2f}{ob_text:>16}"
                  f"{np.median(ms):>7.1f}")


if __name__ == "__main__":
    main()
