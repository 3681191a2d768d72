"""The spectral rendering projector of the paper's section 3 on the digital twin.

Produces CIE A, D65, a phosphor white LED and an RGB-mixing LED near 6500 K with the programmable light, closing
the loop on the spectroradiometer; prints produced-vs-target RMSE, xy, CCT and CRI beside the targets (and the
paper's RMSE for A and D65); writes sRGB renderings of the chart and a natural scene under each illuminant and
the metamer map between the two LEDs (same white point) as PNG.

    PYTHONPATH=. python tools/studies/projector_study.py [--out projector] [--iterations 40]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from specgpu import io
from specgpu.apps import paper
from specgpu.pipeline import projector as render
from specgpu.rig.scene import colorchecker_scene, natural_scene


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="projector", help="folder for the PNG renderings")
    ap.add_argument("--iterations", type=int, default=40, help="loop (b) adjustment bound")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    print("projector: target vs produced (spectroradiometer), RMSE on the CIE scale (100 at 560 nm)")
    print(f"{'target':<10}{'RMSE':>7}{'400-700':>8}{'rel.':>8}{'iter':>6}{'conv':>6}   "
          f"{'xy target':>16} {'xy produced':>16}"
          f"{'CCT t':>8}{'CCT p':>8}{'Ra t':>7}{'Ra p':>7}  paper RMSE")
    for name in render.PROJECTOR_TARGETS:
        r = render.project(name, max_iterations=args.iterations)
        t, p = r.target_colour, r.produced_colour
        ref = paper.PROJECTOR_RMSE.get(name, "-")
        print(f"{name:<10}{r.rmse:7.2f}{r.rmse_400_700:8.2f}{r.relative_rmse:8.4f}{r.loop['iterations']:6d}{str(r.loop['converged']):>6}"
              f"   ({t['xy'][0]:.4f}, {t['xy'][1]:.4f}) ({p['xy'][0]:.4f}, {p['xy'][1]:.4f})"
              f"{t['CCT_K']:8.0f}{p['CCT_K']:8.0f}{t['CRI_Ra']:7.1f}{p['CRI_Ra']:7.1f}  {ref}")

    scenes = {"chart": colorchecker_scene(240, 320), "natural": natural_scene(240, 320)}
    for scene_name, scene in scenes.items():
        for name in render.PROJECTOR_TARGETS:
            rgb = render.render_scene(scene, name)
            io.write_png(out / f"{scene_name}-{name.replace(' ', '-')}.png",
                         np.round(rgb * 255).astype(np.uint8), {"specgpu:illuminant": name})
        dE = render.metamer_map(scene, "LED white", "LED RGB")
        io.write_delta_E_png(out / f"{scene_name}-metamer-LEDs.png", dE, vmax=10.0)
        masks = list(scene.masks.values())
        patch = f"; per patch max {max(float(dE[m].mean()) for m in masks):.2f}" if masks else ""
        print(f"metamer map {scene_name}, white LED vs RGB LED (same white point): dE2000 mean {float(dE.mean()):.2f}, "
              f"max {float(dE.max()):.2f}{patch}")
    print(f"wrote {out}/")


if __name__ == "__main__":
    main()
