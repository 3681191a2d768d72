"""The digital twin's headline figures: SNR (paper Section 2.F), DMD round trip, fault-drill counts.

Usage: PYTHONPATH=. python tools/studies/twin_figures.py [--seeds N] [--drill-frames N]

- sensor and temporal SNR measured like the paper (R, G, B at 90 fps on a reference white, mean / std of 100
  repeats), at 640 x 480 for seed 0 and at 320 x 240 over N seeds (the light's fluctuation is common to a frame,
  so one 100-repeat run has sampling spread);
- spectrum -> DMD pattern -> spectrum relative RMSE for CIE A, D65, an equal-energy white and narrow bands;
- a fault drill: random drops, duplicates and missed triggers through twin -> ring buffer -> assembler, injected
  against counted.
(Render speed: tools/benchmarks/twin_speed.py.)
"""

from __future__ import annotations

import argparse

import colour
import numpy as np

from specgpu.capture import capture_sequences, open_driver
from specgpu.rig import CameraParameters, FaultRates, FaultSchedule, ProgrammableLight, RigDescription, TwinRig
from specgpu.rig.twin import measure_snr


def snr(seeds: int) -> None:
    full = measure_snr(seed=0)
    print(f"SNR 640x480 seed 0: sensor {full.sensor_db:.2f} dB (paper 44.2), temporal {full.temporal_db:.2f} dB "
          f"(paper 39.1); per channel temporal "
          + ", ".join(f"{k} {v:.2f}" for k, v in full.temporal_db_per_channel.items()))
    desc = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    runs = [measure_snr(desc, seed=s) for s in range(seeds)]
    t = np.array([r.temporal_db for r in runs])
    s = np.array([r.sensor_db for r in runs])
    print(f"SNR 320x240 over {seeds} seeds: sensor {s.mean():.2f} +- {s.std(ddof=1):.2f} dB, "
          f"temporal {t.mean():.2f} +- {t.std(ddof=1):.2f} dB")
    fast = measure_snr(desc, frame_rate_hz=400.0, level=0.15)
    slow = measure_snr(desc, frame_rate_hz=90.0, level=0.15)
    print(f"SNR at 15 % of full well: 90 fps temporal {slow.temporal_db:.2f} dB, 400 fps {fast.temporal_db:.2f} dB")


def round_trip() -> None:
    light = ProgrammableLight()
    wl = light.wavelengths
    inner = (wl >= 390) & (wl <= 770)
    targets = {
        "CIE A": np.interp(wl, colour.SDS_ILLUMINANTS["A"].wavelengths, colour.SDS_ILLUMINANTS["A"].values),
        "CIE D65": np.interp(wl, colour.SDS_ILLUMINANTS["D65"].wavelengths, colour.SDS_ILLUMINANTS["D65"].values),
        "equal energy": np.ones_like(wl),
    }
    for c in (450, 550, 650):
        targets[f"narrow band {c} nm (10 nm FWHM)"] = np.exp(-0.5 * ((wl - c) / (10 / 2.3548)) ** 2)
    for name, t in targets.items():
        fit = light.spectrum_to_pattern(t, fit="scale")
        e = fit.emitted - fit.target
        inner_rel = np.sqrt(np.mean(e[inner] ** 2)) / fit.target.max()
        print(f"round trip {name:34s} relative RMSE {fit.relative_rmse:.4%} over 380-780 nm, "
              f"{inner_rel:.4%} over 390-770 nm")


def drill(n_frames: int) -> None:
    desc = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    rig = TwinRig(desc, scene="colorchecker")
    k = 6
    levels = np.linspace(0, 96, k).astype(np.int32)
    rig.load_sequence(np.repeat(levels[:, None], 1024, axis=1))
    rates = FaultRates(drop_rate=0.02, duplicate_rate=0.02, missed_trigger_rate=0.01, jitter_s=5e-6)
    faults = FaultSchedule.from_rates(rates, seed=11)
    injected = np.array([faults.faults(i)[:3] for i in range(n_frames)])
    injected[0, 2] = False
    driver = open_driver("twin", rig=rig, faults=faults, n_frames=n_frames)
    result = capture_sequences(driver, k, n_slots=8)
    a = result.assembly
    print(f"drill {n_frames} frames, K = {k}: injected drops {injected[:, 0].sum()}, duplicates "
          f"{injected[:, 1].sum()}, missed triggers {injected[:, 2].sum()}; counted drops {a.dropped}, duplicates "
          f"{a.duplicates}, missed triggers {a.missed_triggers}; sequences complete {a.sequences_complete}, "
          f"discarded {a.sequences_discarded}")
    # The same faults, aligned on content alone (pattern 0 is dark): the pattern index is not used at all.
    threshold = 0.5 * (rig.expected_frame(0).mean() + rig.expected_frame(1).mean())
    driver = open_driver("twin", rig=rig, faults=faults, n_frames=n_frames)
    s = capture_sequences(driver, k, n_slots=8, align="sync", sync_max_dn=threshold).assembly
    print(f"drill, align='sync' (dark pattern 0, threshold {threshold:.0f} DN): counted drops {s.dropped}, "
          f"duplicates {s.duplicates}; sequences complete {s.sequences_complete}, discarded "
          f"{s.sequences_discarded}, sync failures {s.sync_failures}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--drill-frames", type=int, default=6000)
    args = ap.parse_args()
    snr(args.seeds)
    round_trip()
    drill(args.drill_frames)


if __name__ == "__main__":
    main()
