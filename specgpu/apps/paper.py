"""The figures Tominaga and Horiuchi published (JOSA A 29(9), 1764-1775, 2012), to print beside ours.

X-Rite Mini ColorChecker, 24 patches, spectrometer readings as truth; colour differences dE*ab under D65 unless
named otherwise.
"""

from __future__ import annotations

#: Patch names in chart order (numbers 1-24 of the paper's tables).
PATCHES = (
    "dark skin", "light skin", "blue sky", "foliage", "blue flower", "bluish green", "orange", "purplish blue",
    "moderate red", "purple", "yellow green", "orange yellow", "blue", "green", "red", "yellow", "magenta", "cyan",
    "white", "neutral 8", "neutral 6.5", "neutral 5", "neutral 3.5", "black",
)

#: Table 1: method -> (RMSE average, RMSE maximum, dE*ab average, dE*ab maximum, projections).
TABLE1 = {
    "narrowband": (0.0194, 0.0347, 1.88, 3.90, 31),
    "biased": (0.0195, 0.0309, 3.24, 7.32, 6),
    "symmetric": (0.0153, 0.0244, 2.52, 10.63, 9),
}

#: Table 2, per patch: (RMSE narrowband, RMSE symmetric basis, dE*ab narrowband, dE*ab symmetric basis).
#: (The rows average to the published 0.0194, 1.88 and 2.52, but to 0.0149 for the symmetric RMSE, which the
#: paper prints as 0.0153; its Table 1 repeats 0.0153.)
TABLE2 = (
    (0.0104, 0.0075, 1.45, 2.39), (0.0204, 0.0232, 0.68, 1.41), (0.0254, 0.0134, 2.92, 1.13),
    (0.0127, 0.0107, 2.44, 3.55), (0.0266, 0.0167, 1.37, 1.02), (0.0232, 0.0151, 2.27, 1.73),
    (0.0120, 0.0234, 1.37, 3.93), (0.0249, 0.0244, 2.73, 0.98), (0.0165, 0.0187, 1.91, 3.13),
    (0.0139, 0.0213, 1.29, 3.84), (0.0121, 0.0090, 1.76, 2.16), (0.0191, 0.0213, 2.62, 5.75),
    (0.0153, 0.0106, 2.66, 10.63), (0.0142, 0.0117, 1.43, 3.65), (0.0172, 0.0167, 3.25, 2.14),
    (0.0211, 0.0186, 1.62, 2.14), (0.0321, 0.0188, 3.90, 1.50), (0.0247, 0.0183, 1.33, 2.84),
    (0.0347, 0.0173, 1.78, 0.58), (0.0331, 0.0131, 1.41, 0.56), (0.0258, 0.0131, 1.44, 2.44),
    (0.0171, 0.0071, 1.35, 1.04), (0.0090, 0.0045, 0.58, 1.43), (0.0046, 0.0026, 1.55, 0.50),
)

#: Table 3, per patch: (dE*ab under D65, dE*ab under A) of the tristimulus imager.
TABLE3 = (
    (2.54, 2.16), (1.93, 0.96), (2.58, 2.38), (2.69, 4.06), (2.90, 2.09), (2.48, 3.54), (3.87, 5.15), (2.83, 2.63),
    (2.54, 2.54), (3.58, 2.69), (3.47, 3.13), (2.98, 3.11), (5.08, 2.80), (3.32, 3.95), (1.75, 2.58), (1.48, 3.08),
    (2.17, 3.71), (1.54, 3.52), (0.57, 2.20), (1.76, 2.41), (1.50, 2.09), (1.09, 1.87), (2.20, 2.26), (1.57, 2.82),
)
#: Table 3 summary: illuminant -> (dE*ab average, maximum).
TABLE3_SUMMARY = {"D65": (2.43, 5.08), "A": (2.82, 5.15)}

#: Section 3, the projector: spectral RMSE of the produced illuminants (the paper's units).
PROJECTOR_RMSE = {"A": 0.01, "D65": 2.8}
#: Cumulative variance of the first 5 basis functions of the paper's 507 reflectances.
BASIS_VARIANCE_M5 = 0.9974
#: Reflectance images recovered per second by the paper's system.
PAPER_FPS = 13
