/* specgpu colorimetry kernel family: XYZ -> CIELAB, colour differences, and the fused
 * frames -> XYZ -> Lab -> dE pass.
 *
 * Images are interleaved (N, 3) float32, channels last. Macros (besides those of common.h):
 *   DE_METHOD      76, 94 or 2000 (CIE 1994 is the graphic-arts variant; colour 1 is its reference)
 *   LAB1_SINGLE    1: the first Lab input is one colour (3 floats) broadcast over all pixels
 *   LAB2_SINGLE    1: the same for the second
 *   REF_SINGLE     fused pass: the reference Lab is one colour (1) or a per-pixel image (0)
 *   WRITE_XYZ, WRITE_LAB, WRITE_DE, WRITE_MASK   fused pass: which results to store
 */
#include "common.h"

#ifndef LAB1_SINGLE
#define LAB1_SINGLE 0
#endif
#ifndef LAB2_SINGLE
#define LAB2_SINGLE 0
#endif
#ifndef REF_SINGLE
#define REF_SINGLE 0
#endif

/* The three channels of an (N, 3) image, or of one colour broadcast when single != 0. */
inline void load_colour(__global const float *p, int single, ulong base, uint count, floatv *c0, floatv *c1,
                        floatv *c2)
{
    if (single) {
        *c0 = (floatv)(p[0]);
        *c1 = (floatv)(p[1]);
        *c2 = (floatv)(p[2]);
    } else {
        load3(p, base, count, c0, c1, c2);
    }
}

__kernel void xyz_to_lab(__global const float *restrict xyz, __global float *restrict lab,
                         const float Xn, const float Yn, const float Zn, const ulong n)
{
    PIXEL_RANGE(n);
    floatv X, Y, Z, L, a, b;
    load3(xyz, base, count, &X, &Y, &Z);
    lab_from_xyz(X, Y, Z, Xn, Yn, Zn, &L, &a, &b);
    store3(L, a, b, lab, base, count);
}

#ifdef DE_METHOD
__kernel void delta_e(__global const float *restrict lab1, __global const float *restrict lab2,
                      __global float *restrict de, const ulong n)
{
    PIXEL_RANGE(n);
    floatv L1, a1, b1, L2, a2, b2;
    load_colour(lab1, LAB1_SINGLE, base, count, &L1, &a1, &b1);
    load_colour(lab2, LAB2_SINGLE, base, count, &L2, &a2, &b2);
    store_f(DELTA_E(L1, a1, b1, L2, a2, b2), de, base, count);
}

/* XYZ (N, 3) -> Lab -> dE(reference, pixel) in one pass: the colour of maps already decoded (the filtered or the
 * warped XYZ), the XYZ read once, Lab stored only when asked (WRITE_LAB), dE only with WRITE_DE, no Lab buffer
 * between the two steps. */
__kernel void xyz_to_delta_e(__global const float *restrict xyz,
                             const float Xn, const float Yn, const float Zn,
                             __global const float *restrict ref_lab,
                             __global float *restrict lab_out,
                             __global float *restrict de_out,
                             const ulong n)
{
    PIXEL_RANGE(n);
    floatv X, Y, Z, L, a, b;
    load3(xyz, base, count, &X, &Y, &Z);
    lab_from_xyz(X, Y, Z, Xn, Yn, Zn, &L, &a, &b);
#if WRITE_LAB
    store3(L, a, b, lab_out, base, count);
#endif
#if WRITE_DE
    floatv Lr, ar, br;
    load_colour(ref_lab, REF_SINGLE, base, count, &Lr, &ar, &br);
    store_f(DELTA_E(Lr, ar, br, L, a, b), de_out, base, count);
#endif
}

/* frames -> XYZ = M (o - dark) * gain -> Lab -> dE(reference, pixel), one pass, no intermediate buffers;
 * M is the 3 x K product C . A made on the host. */
__kernel void frames_to_delta_e(__global const IN_T *restrict frames,
                                __constant const float *restrict M,
                                __global const float *restrict dark,
                                __global const float *restrict gain,
                                const float Xn, const float Yn, const float Zn,
                                __global const float *restrict ref_lab,
                                __global float *restrict xyz_out,
                                __global float *restrict lab_out,
                                __global float *restrict de_out,
                                __global uchar *restrict mask,
                                const ulong n)
{
    PIXEL_RANGE(n);
    LOAD_PIXELS();
    floatv X, Y, Z;
    DOT_ROW(X, M, 0);
    DOT_ROW(Y, M, 1);
    DOT_ROW(Z, M, 2);
#if HAS_GAIN
    const floatv g = load_f(gain, base, count);
    X *= g; Y *= g; Z *= g;
#endif
#if WRITE_XYZ
    store3(X, Y, Z, xyz_out, base, count);
#endif
    floatv L, a, b;
    lab_from_xyz(X, Y, Z, Xn, Yn, Zn, &L, &a, &b);
#if WRITE_LAB
    store3(L, a, b, lab_out, base, count);
#endif
#if WRITE_DE
    floatv Lr, ar, br;
    load_colour(ref_lab, REF_SINGLE, base, count, &Lr, &ar, &br);
    store_f(DELTA_E(Lr, ar, br, L, a, b), de_out, base, count);
#endif
#if WRITE_MASK
    store_mask(CONVERT_UCHARV(flags), mask, base, count);
#endif
}
#endif

/* d f / d t of cie_f: (1/3) t^(-2/3) above (24/116)^3, 841/108 below. */
inline floatv cie_f_prime(floatv t)
{
    const floatv r = cbrt(fmax(t, (floatv)(216.0f / 24389.0f)));
    return t > (floatv)(216.0f / 24389.0f) ? (1.0f / 3.0f) / (r * r) : (floatv)(841.0f / 108.0f);
}

/* First-order CIEDE2000 standard deviation of each pixel's XYZ (N, 3) given its covariance: the noise part per
 * pixel (N, 6: XX XY XZ YY YZ ZZ) plus the constant part c (6 floats, the same order). The Lab covariance is
 * J C J^T with J the analytic XYZ -> Lab Jacobian; dE2000 to first order is its trace weighted by the local
 * metric along L*, a*, b* (dE2000 of a 0.5 step along each, over 0.5, squared), as estimators.delta_E_sigma. */
__kernel void delta_e_sigma(__global const float *restrict xyz,
                            __global const float *restrict cov,
                            __constant const float *restrict c,
                            const float Xn, const float Yn, const float Zn,
                            __global float *restrict out,
                            const ulong n)
{
    PIXEL_RANGE(n);
    floatv X, Y, Z, L, a, b;
    load3(xyz, base, count, &X, &Y, &Z);
    const floatv cxx = load_f_strided(cov, base, count, 6, 0) + c[0];
    const floatv cxy = load_f_strided(cov, base, count, 6, 1) + c[1];
    const floatv cyy = load_f_strided(cov, base, count, 6, 3) + c[3];
    const floatv cyz = load_f_strided(cov, base, count, 6, 4) + c[4];
    const floatv czz = load_f_strided(cov, base, count, 6, 5) + c[5];
    const floatv dx = cie_f_prime(X / Xn) / Xn, dy = cie_f_prime(Y / Yn) / Yn, dz = cie_f_prime(Z / Zn) / Zn;
    const floatv var_L = 116.0f * 116.0f * dy * dy * cyy;
    const floatv var_a = 500.0f * 500.0f * (dx * dx * cxx - 2.0f * dx * dy * cxy + dy * dy * cyy);
    const floatv var_b = 200.0f * 200.0f * (dy * dy * cyy - 2.0f * dy * dz * cyz + dz * dz * czz);
    lab_from_xyz(X, Y, Z, Xn, Yn, Zn, &L, &a, &b);
    const floatv gL = delta_e_2000(L, a, b, L + 0.5f, a, b) * 2.0f;
    const floatv ga = delta_e_2000(L, a, b, L, a + 0.5f, b) * 2.0f;
    const floatv gb = delta_e_2000(L, a, b, L, a, b + 0.5f) * 2.0f;
    store_f(sd_of_variance(gL * gL * var_L + ga * ga * var_a + gb * gb * var_b), out, base, count);
}
