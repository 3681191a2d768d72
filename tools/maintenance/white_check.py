"""The Lab of a perfect white through every path, on every kind of grid, under every illuminant colour-science has,
for both observers, and ASTM E308 against colour-science's ``sd_to_XYZ(method="ASTM E308")``.

Per (grid, integration, observer): the largest |Lab - (100, 0, 0)| over the illuminants through the host path
(``reflectance_to_XYZ`` then ``XYZ_to_Lab`` with the grid's white), the fused device pass (``frames_to_delta_E``,
its Lab and dE2000 against (100, 0, 0)) and the stream's decoder (a narrowband plan's frames of the perfect white,
under a few illuminants); then the largest |XYZ - colour-science's| (0-1 scale) of ASTM E308 on random spectra.
Run from the repository root:

    PYTHONPATH=. python tools/maintenance/white_check.py
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import colour
import numpy as np
import pyopencl as cl

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu import engine  # noqa: E402
from specgpu.calibration.bundle import oracle_calibration  # noqa: E402
from specgpu.core.spectra import OBSERVERS, XYZ_weights  # noqa: E402
from specgpu.engine.colorimetry import XYZ_to_Lab, frames_to_delta_E, reflectance_to_XYZ  # noqa: E402
from specgpu.pipeline.sequence_decoder import SequenceDecoder  # noqa: E402
from specgpu.planning.registry import make_plan  # noqa: E402
from specgpu.rig import CameraParameters, RigDescription  # noqa: E402

ASTM_GRIDS = [np.arange(400.0, 701.0, 1.0), np.arange(380.0, 781.0, 5.0), np.arange(400.0, 701.0, 10.0),
              np.arange(400.0, 701.0, 20.0), np.arange(340.0, 831.0, 10.0)]
GRIDS = [*ASTM_GRIDS, np.arange(403.0, 698.0, 7.0), np.arange(420.0, 680.1, 2.5)]
NEUTRAL = np.array([100.0, 0.0, 0.0])


def grid_name(w) -> str:
    return f"{w[0]:g}-{w[-1]:g} nm / {w[1] - w[0]:g}"


def paths(w, integration, observer, queue) -> tuple[float, float]:
    """Worst |Lab - (100, 0, 0)| over colour-science's illuminants: host path, fused pass (Lab or dE2000)."""
    host = fused = 0.0
    colours = dict(observer=observer, wavelengths=w, integration=integration)
    for illuminant in sorted(colour.SDS_ILLUMINANTS):
        XYZ = reflectance_to_XYZ(np.ones(w.size), w, illuminant, observer, integration=integration, device=queue)
        host = max(host, float(np.abs(XYZ_to_Lab(XYZ, illuminant, device=queue, **colours) - NEUTRAL).max()))
        C = XYZ_weights(w, illuminant, observer, integration=integration)
        res = frames_to_delta_E(np.ones((1, 1, 1), np.float32), np.ones((w.size, 1)), NEUTRAL, C=C,
                                illuminant=illuminant, return_Lab=True, device=queue, **colours)
        fused = max(fused, float(np.abs(res.Lab - NEUTRAL).max()), float(res.delta_E.max()))
    return host, fused


def decoder(queue) -> float:
    """Worst |Lab - (100, 0, 0)| and dE2000 of the stream's decoder on a white scene (a 20 nm narrowband plan)."""
    bundle = oracle_calibration(RigDescription(camera=CameraParameters(roi_width=320, roi_height=240)))
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    signal = bundle.forward_matrix(plan.patterns, plan.light_wavelengths, plan.exposure_s).sum(axis=1)
    frames = (bundle.dark_at(plan.exposure_s)[None] + signal[:, None, None] / bundle.flat_field[None])
    worst = 0.0
    for integration in ("rectangle", "ASTM E308"):
        for observer in OBSERVERS:
            for illuminant in ("D65", "A", "D50", "E", "FL2", "FL11", "LED-B5", "ISO 7589 Photoflood"):
                dec = SequenceDecoder(plan, bundle, ("Lab", "dE"), frame_shape=bundle.frame_shape, device=queue,
                                      reference=NEUTRAL, illuminant=illuminant, observer=observer,
                                      integration=integration)
                out = dec.enqueue(engine.to_device(queue, frames.astype(np.float32).reshape(-1)))
                for name, (shape, dtype) in dec.shapes().items():
                    got = np.empty(shape, dtype)
                    cl.enqueue_copy(queue, got, out[name])
                    worst = max(worst, float(np.abs(got - (NEUTRAL if name == "Lab" else 0.0)).max()))
    return worst


def astm(observer) -> float:
    """Largest |XYZ - colour-science's ASTM E308 XYZ| (0-1 scale) over grids, illuminants and random spectra."""
    worst = 0.0
    rng = np.random.default_rng(0)
    for w in ASTM_GRIDS:
        R = rng.uniform(0.0, 1.0, (4, w.size))
        for illuminant in ("D65", "A", "D50", "FL2", "FL11", "LED-B5"):
            W = XYZ_weights(w, illuminant, observer, integration="ASTM E308")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                want = np.array([colour.sd_to_XYZ(colour.SpectralDistribution(r, w), colour.MSDS_CMFS[observer],
                                                  colour.SDS_ILLUMINANTS[illuminant], method="ASTM E308")
                                 for r in R]) / 100.0
            worst = max(worst, float(np.abs(R @ W.T - want).max()))
    return worst


def main() -> None:
    queue = engine.get_queue()
    n = len(colour.SDS_ILLUMINANTS)
    print(f"worst |Lab - (100, 0, 0)| of a perfect white over {n} illuminants (float32 device paths)")
    print(f"{'grid':<22} {'integration':<11} {'observer':<8} {'host':>9} {'fused':>9}")
    for w in GRIDS:
        for integration in ("rectangle", "ASTM E308") if any(w is g for g in ASTM_GRIDS) else ("rectangle",):
            for observer in OBSERVERS:
                host, fused = paths(w, integration, observer, queue)
                short = "2 deg" if "1931" in observer else "10 deg"
                print(f"{grid_name(w):<22} {integration:<11} {short:<8} {host:>9.2e} {fused:>9.2e}")
    print(f"stream decoder, white scene, worst |Lab - (100, 0, 0)| or dE2000: {decoder(queue):.2e}")
    for observer in OBSERVERS:
        print(f"ASTM E308 vs colour-science sd_to_XYZ, {observer}: max |dXYZ| = {astm(observer):.2e}")


if __name__ == "__main__":
    main()
