"""``specgpu demo``'s moving-scene section (:func:`moving_section`): the paper's symmetric-9 at 200 fps on the
natural scene, still and translating 3 px per frame (2.4 across, 1.8 down), recovered as it is and motion
compensated (:func:`specgpu.pipeline.moving_scores.compare_motion`): per-pixel RMSE and dE2000 over the field
and within 3 px of the scene's edges, and the three error maps on one scale.

The rig is the demo's with every imperfection off at 200 fps and the twin's own (oracle) calibration, so the
section isolates motion; ``tools/studies/motion_study.py`` runs every motion case with more plans and draws.
"""

from __future__ import annotations

import html
from dataclasses import replace

import numpy as np

from specgpu.apps.report_figures import common_scale, figure_png, map_figure
from specgpu.apps.report_html import card_grid, cell, figure_card, html_table
from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.moving_scores import RECOVERIES, compare_motion
from specgpu.planning import make_plan
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import natural_scene

__all__ = ["MOVING_MOTION", "moving_section", "moving_lines", "moving_html"]

#: The section's motion: a translation of 3 px per frame.
MOVING_MOTION = MotionParameters(velocity_px_per_frame=(2.4, 1.8))
_FRAME_RATE_HZ = 200.0
_EXPOSURE_S = 0.0049  # 200 fps less the light's 80 us switch time (and a margin)
_MAP_LABEL = "RMSE per pixel (reflectance, 400-700 nm)"


def moving_section(description, basis, *, seed: int = 0, size: tuple[int, int] | None = None) -> dict:
    """The section's figures on ``description`` (the demo's rig with its imperfections off) at 200 fps: ``rows``
    (recovery -> scores), ``maps`` (recovery -> per-pixel RMSE), the flagged share, the largest error of the
    estimated displacement (px), the compensation's seconds, and what was run. ``size``: (width, height) of the
    camera's ROI for the section (default the rig's)."""
    camera = replace(description.camera, frame_rate_hz=_FRAME_RATE_HZ, exposure_s=_EXPOSURE_S)
    if size is not None:
        camera = replace(camera, roi_width=int(size[0]), roi_height=int(size[1]))
    desc = replace(description, camera=camera)
    bundle = oracle_calibration(desc)
    plan = make_plan("symmetric", bundle, basis, m=5, output_wavelengths=np.arange(400.0, 701.0, 10.0),
                     max_exposure_s=_EXPOSURE_S)
    scene = natural_scene(desc.camera.roi_height, desc.camera.roi_width)
    run = compare_motion(desc, bundle, plan, scene, MOVING_MOTION, seed)
    sequence_ms = plan.K / plan.rig_description(desc).camera.frame_rate_hz * 1e3
    return {"rows": {k: run[k] for k in RECOVERIES}, "maps": run["maps"], "flagged": run["flagged"],
            "shift_error_px": run["shift_error_px"], "seconds": run["seconds"],
            "setup": f"symmetric-9 at {_FRAME_RATE_HZ:g} fps ({sequence_ms:.0f} ms a sequence) on the "
                     f"{scene.name} scene, {desc.camera.roi_width} x {desc.camera.roi_height}, translating 3 px "
                     "per frame; paper noise, imperfections off, the twin's own calibration"}


def moving_lines(section: dict) -> list[str]:
    """The section as text lines for the terminal."""
    lines = ["", f"Moving scene: {section['setup']}",
             f"{'':<12}{'RMSE field':>12}{'RMSE edges':>12}{'dE00 field':>12}{'dE00 edges':>12}"]
    for kind, r in section["rows"].items():
        lines.append(f"{kind:<12}{r['rmse_field']:>12.4f}{r['rmse_edge']:>12.4f}{r['dE_field']:>12.2f}"
                     f"{r['dE_edge']:>12.2f}")
    ratio = section["rows"]["compensated"]["rmse_field"] / section["rows"]["still"]["rmse_field"]
    lines.append(f"compensated / still RMSE {ratio:.2f}; {section['flagged'] * 100:.1f} % of the field flagged "
                 f"(seen outside it by some frame: NaN, never a wrong spectrum); displacement error <= "
                 f"{section['shift_error_px']:.3f} px; compensation {section['seconds']:.2f} s")
    return lines


def moving_html(section: dict) -> str:
    """The section for the report page: its table and the three error maps on one colour scale."""
    rows = [[kind, cell(r["rmse_field"], 4), cell(r["rmse_edge"], 4), cell(r["dE_field"]), cell(r["dE_edge"])]
            for kind, r in section["rows"].items()]
    table = html_table(["recovery", "RMSE field", "RMSE within 3 px of edges", "ΔE00 field",
                        "ΔE00 within 3 px of edges"], rows,
                       caption=f"per-pixel means over the pixels all three recover; {section['flagged'] * 100:.1f} % "
                               "of the field flagged (seen outside it by some frame: NaN, never a wrong spectrum)")
    vmax = common_scale(list(section["maps"].values()))
    cards = [figure_card(figure_png(map_figure(m, vmax=vmax, label=_MAP_LABEL, title=kind)),
                         f"{kind}: per-pixel RMSE (grey: flagged, not scored)")
             for kind, m in section["maps"].items()]
    return (f"<h2>A moving scene</h2><p>{html.escape(section['setup'])}: the still scene, the moving one decoded as "
            "it is (every frame sees a different part of the scene: colour fringes at each edge), and motion "
            "compensated (each frame's displacement estimated from the frames and undone in the decoding pass)."
            f"</p>{table}{card_grid(cards)}")
