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
