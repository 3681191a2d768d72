"""
Design a plan within a time budget
==================================

A plan is the illuminant sequence the light shows and the decoder from its frames to the outputs. Here four
methods are planned within the same 60 ms per sequence on the paper's rig (its exact calibration, the twin's
ground truth, so no measurement is needed), and the illuminants of two of them are drawn.
"""

import matplotlib.pyplot as plt
import numpy as np

from specgpu.calibration import oracle_calibration
from specgpu.pipeline.recovery import default_basis
from specgpu.planning import budget_plan
from specgpu.rig import load_rig

rig = load_rig()  # the paper's bench: every key of the rig TOML at its default
bundle = oracle_calibration(rig)
budget_s = 0.060
wavelengths = np.arange(400.0, 701.0, 10.0)

# %%
# Each method within 60 ms: the exposure is capped so that every frame, with the light's switch time, fits.
plans = {
    "hadamard-7": budget_plan("hadamard", bundle, budget_s, bands=7),
    "symmetric-9": budget_plan("symmetric", bundle, budget_s, default_basis(), m=5, output_wavelengths=wavelengths),
    "biased-6": budget_plan("biased", bundle, budget_s, default_basis(), m=5, output_wavelengths=wavelengths),
    "tristimulus-D65": budget_plan("tristimulus", bundle, budget_s, illuminant="D65"),
}
for name, plan in plans.items():
    print(f"{name:>16}: {plan.K} frames x {plan.exposure_s * 1e3:5.2f} ms exposure, "
          f"{plan.sequence_s * 1e3:5.1f} ms a sequence ({1 / plan.sequence_s:5.1f} sequences/s), "
          f"{plan.A.shape[0]} outputs ({plan.output})")

# %%
# The light's spectrum in each frame (the target the DMD pattern reproduces), for two of the plans.
fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), sharey=True)
for ax, name in zip(axes, ("symmetric-9", "tristimulus-D65")):
    plan = plans[name]
    for k, spectrum in enumerate(plan.target_spectra):
        ax.plot(plan.light_wavelengths, spectrum / spectrum.max(), lw=1, label=f"frame {k + 1}")
    ax.set_title(name)
    ax.set_xlabel("wavelength (nm)")
axes[0].set_ylabel("relative power")
axes[1].legend(fontsize=7)
fig.tight_layout()
plt.show()
