"""
A scene that moves
==================

A sequence takes K frame periods, and a scene that moves meanwhile lands on different pixels in different
frames: the per-pixel decoder then mixes the spectra of neighbouring surfaces. Here the twin's natural scene
translates 2 px per frame to the right and 1 px down; the same sequence is recovered as decoded and
motion-compensated (``--motion global``), and both are compared with the truth the capture recorded. The
commands are run in-process, exactly as on the command line.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import specgpu
from specgpu.apps.cli import main
from specgpu.calibration import oracle_calibration


def specgpu_command(*args):
    """``specgpu ARGS`` in this process (an error raises instead of exiting)."""
    main.main([str(a) for a in args], standalone_mode=False)


work = Path(tempfile.mkdtemp())
(work / "rig.toml").write_text(
    "[camera]\nroi_width = 320\nroi_height = 240\nframe_rate_hz = 200.0\nexposure_s = 0.0049\n"
    "[scene]\nsource = \"natural\"\n"
    "[motion]\nvelocity_px_per_frame = [2.0, 1.0]\n")

# %%
# The rig's exact calibration (the twin's ground truth; ``specgpu calibrate`` measures one on a real rig), the
# biased basis method (6 frames) and one sequence of the moving scene.
specgpu.save_calibration(work / "calib.npz", oracle_calibration(specgpu.load_rig(work / "rig.toml")))
specgpu_command("plan", "biased", "--calib", work / "calib.npz", "--out", work / "plan.npz")
specgpu_command("capture", "--rig", work / "rig.toml", "--plan", work / "plan.npz", "--calib", work / "calib.npz",
                "--out", work / "seq", "--sequences", "1")

# %%
# Recover the sequence twice: as decoded, and with each frame's displacement estimated and compensated in the
# decoding pass. Pixels that no motion explains (the borders the scene left) are NaN and flagged.
specgpu_command("recover", work / "seq", "--out", work / "moving.npz")
specgpu_command("recover", work / "seq", "--sequence", "0", "--motion", "global", "--out", work / "compensated.npz")

truth, wavelengths, _ = specgpu.read_cube(work / "seq" / "motion_truth" / "sequence_0000.npz")
errors = {}
for name in ("moving", "compensated"):
    cube, cube_wavelengths, _ = specgpu.read_cube(work / f"{name}.npz")
    truth_at = np.stack([np.interp(cube_wavelengths, wavelengths, px) for px in truth.reshape(-1, len(wavelengths))])
    errors[name] = np.sqrt(np.mean((cube - truth_at.reshape(cube.shape)) ** 2, axis=-1))
    print(f"{name:>12}: per-pixel RMSE {np.nanmean(errors[name]):.4f} against the truth, "
          f"{np.isnan(errors[name]).mean() * 100:.1f} % of the pixels flagged")

# %%
# The error maps on one scale: the decoded sequence errs along every edge the motion crossed.
fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
for ax, (name, error) in zip(axes, errors.items()):
    image = ax.imshow(error, vmin=0, vmax=0.15, cmap="magma")
    ax.set_title(name)
    ax.set_axis_off()
fig.colorbar(image, ax=axes, label="per-pixel RMSE (reflectance)", shrink=0.8)
plt.show()
