"""Write the golden regression set (tests/data/golden.npz) that `specgpu selftest` reproduces on any device.

Inputs are small, seeded and of odd sizes (19 x 13 = 247 pixels, not a multiple of the 8-pixel vector width);
expected outputs are computed in float64 by the NumPy / colour-science references of tests/reference.py, and
the CIEDE2000 case uses Sharma, Wu and Dalal's published pairs. Run from the repository root:

    PYTHONPATH=. python tools/maintenance/make_golden.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import reference as ref  # noqa: E402

H, W = 19, 13
SEED = 20120901  # JOSA A 29(9), 2012


def main(out: Path = ROOT / "tests" / "data" / "golden.npz") -> None:
    rng = np.random.default_rng(SEED)
    cases = []
    arrays = {}

    def add(name, tolerances, **data):
        cases.append({"name": name, "tolerances": tolerances})
        for key, value in data.items():
            arrays[f"{name}/{key}"] = np.asarray(value)

    # ---- linear: y = A (o - dark) * gain
    frames = rng.integers(0, 1024, (9, H, W), dtype=np.uint16)
    A = rng.normal(0, 1e-3, (61, 9))
    dark = rng.uniform(20, 40, (H, W)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (H, W)).astype(np.float32)
    add("linear_u16_planar_f32_dark_gain", {"y": ["range", 1e-5]}, frames=frames, A=A, dark=dark, gain=gain,
        expected_y=ref.linear_ref(frames, A, dark, gain, "planar"))

    frames = rng.integers(0, 256, (3, H, W), dtype=np.uint8)
    A = rng.uniform(-1, 1, (31, 3)) / 255
    add("linear_u8_interleaved_f16", {"y": ["range", 1e-3]}, frames=frames, A=A,
        expected_y=ref.linear_ref(frames, A))

    frames = rng.uniform(0, 1.05, (6, H, W)).astype(np.float32)
    frames[2, 3, 4] = np.nan
    frames[5, 10, 0] = np.inf
    dark = rng.uniform(0, 0.02, (6, H, W)).astype(np.float32)
    A = rng.normal(0, 1, (5, 6))
    add("linear_f32_perframe_dark_mask_nan", {"y": ["range", 1e-5], "mask": ["abs", 0]}, frames=frames, A=A,
        dark=dark, saturation=np.float64(1.0), expected_y=ref.linear_ref(frames, A, dark),
        expected_mask=ref.mask_ref(frames, 1.0))

    frames = rng.integers(0, 4096, (61, 9, 7), dtype=np.uint16)
    A = rng.normal(0, 1, (31, 61)) / 4095
    add("linear_u16_k61_b31_f16_planar", {"y": ["range", 1e-3]}, frames=frames, A=A,
        expected_y=ref.linear_ref(frames, A, layout="planar"))

    # ---- XYZ -> Lab
    for name, illuminant in (("xyz_to_lab_d65", "D65"), ("xyz_to_lab_a", "A")):
        XYZ = rng.uniform(0, 1.1, (H, W, 3)).astype(np.float32)
        XYZ[0, 0] = 0.0  # black
        XYZ[0, 1] = [0.001, 0.002, 0.0015]  # below the linear-segment threshold of f(t)
        add(name, {"Lab": ["abs", 1e-4]}, XYZ=XYZ, expected_Lab=ref.XYZ_to_Lab_ref(XYZ, illuminant))

    # ---- colour differences (pairs near CIEDE2000's hue discontinuity are re-drawn: see reference.py)
    for name, method in (("delta_e_cie1976", "CIE 1976"), ("delta_e_cie1994", "CIE 1994"),
                         ("delta_e_cie2000", "CIE 2000")):
        Lab_1 = ref.random_Lab(rng, (H, W)).astype(np.float32)
        Lab_2 = ref.random_Lab(rng, (H, W)).astype(np.float32)
        near = ref.near_hue_discontinuity(Lab_1, Lab_2)
        Lab_2[near] = Lab_1[near] + 1.0
        # CIEDE2000: the documented 1e-3 absolute; CIE 1976 / 1994 are sums of squares whose float32 error
        # grows with the difference itself, so their bound is relative to the range
        tol = ["abs", 1e-3] if method == "CIE 2000" else ["range", 2e-6]
        add(name, {"dE": tol}, Lab_1=Lab_1, Lab_2=Lab_2,
            expected_dE=ref.delta_E_ref(Lab_1, Lab_2, method))
    Lab_1 = np.array([52.0, 41.5, -18.25], dtype=np.float32)
    Lab_2 = ref.random_Lab(rng, (H, W)).astype(np.float32)
    add("delta_e_cie2000_single_reference", {"dE": ["abs", 1e-3]}, Lab_1=Lab_1, Lab_2=Lab_2,
        expected_dE=ref.delta_E_ref(Lab_1, Lab_2, "CIE 2000"))
    L1, L2, dE00 = ref.sharma_pairs(ROOT / "tests" / "data" / "ciede2000_sharma2005.csv")
    # published to 4 decimals: 5e-5 of rounding plus float32
    add("delta_e_cie2000_sharma2005", {"dE": ["abs", 1e-4]}, Lab_1=L1.astype(np.float32),
        Lab_2=L2.astype(np.float32), expected_dE=dE00)

    # ---- reflectance -> XYZ
    wl = np.arange(400, 701, 10, dtype=np.float64)
    R = rng.uniform(0, 1, (H, W, wl.size)).astype(np.float32)
    add("reflectance_to_xyz_d65_2deg", {"XYZ": ["abs", 1e-5]}, R=R, wavelengths=wl,
        expected_XYZ=ref.reflectance_to_XYZ_ref(R, wl, "D65"))
    wl = np.arange(380, 781, 5, dtype=np.float64)
    R = rng.uniform(0, 1, (H, W, wl.size)).astype(np.float32)
    add("reflectance_to_xyz_a_10deg", {"XYZ": ["abs", 1e-5]}, R=R, wavelengths=wl,
        expected_XYZ=ref.reflectance_to_XYZ_ref(R, wl, "A", "CIE 1964 10 Degree Standard Observer"))

    # ---- fused frames -> XYZ -> Lab -> dE: a 5-output decoder composed with outputs -> XYZ
    for name, method in (("fused_frames_to_de2000", "CIE 2000"), ("fused_frames_to_de94", "CIE 1994")):
        frames = rng.integers(0, 1024, (9, H, W), dtype=np.uint16)
        frames[:, 7, 7] = 1023  # a saturated pixel
        A = rng.uniform(0, 1, (5, 9)) / (9 * 1023)
        C = rng.uniform(0.2, 1, (3, 5))
        C /= C.sum(axis=1, keepdims=True)
        dark = rng.uniform(0, 8, (H, W)).astype(np.float32)
        gain = rng.uniform(0.95, 1.05, (H, W)).astype(np.float32)
        XYZ = ref.linear_ref(frames, C @ A, dark, gain)
        Lab = ref.XYZ_to_Lab_ref(XYZ)
        reference = ref.random_Lab(rng, (H, W)).astype(np.float32)
        near = ref.near_hue_discontinuity(reference, Lab)
        reference[near] = (Lab[near] + 1.0).astype(np.float32)
        add(name, {"XYZ": ["abs", 1e-5], "Lab": ["abs", 5e-4], "dE": ["abs", 1e-3], "mask": ["abs", 0]},
            frames=frames, A=A, C=C, dark=dark, gain=gain, reference=reference, saturation=np.float64(1023),
            expected_XYZ=XYZ, expected_Lab=Lab, expected_dE=ref.delta_E_ref(reference, Lab, method),
            expected_mask=ref.mask_ref(frames, 1023))

    # ---- guided filter (recover --denoise): a step edge in the guide, noisy channels, windows clipped at borders
    guide = rng.uniform(0.2, 0.4, (H, W)).astype(np.float32)
    guide[:, W // 2:] += 0.5
    image = (guide[..., None] * rng.uniform(0.2, 1.0, 5) + rng.normal(0, 0.02, (H, W, 5))).astype(np.float32)
    for radius, eps in ((2, 1e-4), (4, 1e-2)):
        add(f"guided_r{radius}_eps{eps:g}", {"q": ["abs", 2e-5]}, image=image, guide=guide,
            expected_q=ref.guided_filter_numpy(image, guide, radius, eps))

    # ---- reflectance -> XYZ -> Lab with the white of the grid: the first row a perfect white, (100, 0, 0)
    for name, wl, illuminant, cmfs, integration in (
            ("reflectance_white_to_lab_d65_10nm", np.arange(400, 701, 10, dtype=np.float64), "D65",
             "CIE 1931 2 Degree Standard Observer", "rectangle"),
            ("reflectance_white_to_lab_a_astm_20nm", np.arange(400, 701, 20, dtype=np.float64), "A",
             "CIE 1964 10 Degree Standard Observer", "ASTM E308")):
        R = rng.uniform(0, 1, (H, W, wl.size)).astype(np.float32)
        R[0] = 1.0
        XYZ = ref.reflectance_to_XYZ_ref(R, wl, illuminant, cmfs, integration)
        Lab = ref.XYZ_to_Lab_ref(XYZ, illuminant, cmfs, wl, integration)
        assert np.abs(Lab[0] - [100.0, 0.0, 0.0]).max() < 1e-9
        add(name, {"XYZ": ["abs", 1e-5], "Lab": ["abs", 2e-4]}, R=R, wavelengths=wl, expected_XYZ=XYZ,
            expected_Lab=Lab)

    manifest = {"format": "specgpu-golden", "version": 1, "seed": SEED, "cases": cases}
    np.savez_compressed(out, _manifest=np.array(json.dumps(manifest)), **arrays)
    print(f"wrote {out}: {len(cases)} cases, {out.stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
