"""napari's own screenshot of ``specgpu view``: the viewer on a cube, sequence folder or recording with the
spectrum widget showing one pixel's spectrum (or a region's mean +- std) against the truth.

    PYTHONPATH=. xvfb-run -a python tools/maintenance/screenshot_viewer.py REC.zarr --pixel 190,230 --colors 256 \
        --out docs/viewer-screenshot.png
    PYTHONPATH=. xvfb-run -a python tools/maintenance/screenshot_viewer.py REC.zarr --region 150,180,40,40 --out \
        viewer-region.png

Needs the viewer extra (pip install 'specgpu[viewer]') and a display with OpenGL (a desktop, or Xvfb with Mesa:
Debian's xvfb and libgl1-mesa-dri packages). Prints what the widget shows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("path", type=Path)
    parser.add_argument("--pixel", default=None, metavar="Y,X", help="Show this pixel's spectrum.")
    parser.add_argument("--region", default=None, metavar="Y,X,H,W", help="Draw this rectangle and show its spectrum.")
    parser.add_argument("--sequence", type=int, default=0, help="The time step (sequence) to show.")
    parser.add_argument("--out", type=Path, default=Path("viewer-screenshot.png"))
    parser.add_argument("--size", default="1500,860", metavar="W,H", help="Window size (px).")
    parser.add_argument("--colors", type=int, default=0, metavar="N",
                        help="Save the picture with a palette of N colours (a smaller PNG for the docs; 0: as taken).")
    args = parser.parse_args(argv)

    import napari

    from specgpu.apps.viewer_layers import read_layers
    from specgpu.apps.viewer_widget import SpectrumWidget, add_layers

    viewer = napari.Viewer(title=f"specgpu view {args.path}", show=True)
    add_layers(viewer, read_layers(args.path))
    widget = SpectrumWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Spectrum", area="right")
    w, h = (int(v) for v in args.size.split(","))
    viewer.window.resize(w, h)
    if viewer.dims.ndim == 4:
        viewer.dims.set_point(1, args.sequence)
    spectrum = widget.probe.layer("spectrum")
    point = list(viewer.dims.point)
    if args.region:
        y, x, rh, rw = (float(v) for v in args.region.split(","))
        viewer.add_shapes([np.array([[y, x], [y, x + rw], [y + rh, x + rw], [y + rh, x]])], shape_type="rectangle",
                          name="region", edge_color="cyan", face_color="transparent", edge_width=2)
        widget.on_region()
    elif args.pixel:
        y, x = (float(v) for v in args.pixel.split(","))
        viewer.cursor.position = tuple(point[:-2]) + (y, x)
        widget.on_move()
        viewer.add_points([[y, x]], size=8, face_color="transparent", border_color="cyan", name="pixel")
    if spectrum is not None:
        viewer.layers.selection.active = spectrum
    print(widget.status.text())
    from qtpy.QtWidgets import QApplication

    for _ in range(5):  # let the dock and the plot lay out before the picture
        QApplication.processEvents()
    viewer.reset_view()
    QApplication.processEvents()
    viewer.screenshot(str(args.out), canvas_only=False, flash=False)
    if args.colors:
        from PIL import Image

        picture = Image.open(args.out).convert("RGB")
        picture.quantize(colors=args.colors, method=Image.Quantize.MEDIANCUT,
                         dither=Image.Dither.NONE).save(args.out, optimize=True)
    print(f"wrote {args.out}")
    viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
