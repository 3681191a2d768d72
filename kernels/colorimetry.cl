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

/* Channel c of an (N, 3) image, or of one colour broadcast when single != 0. */
inline floatv load_channel(__global const float *p, int single, ulong base, uint count, uint c)
{
    return single ? (floatv)(p[c]) : load_f_strided(p, base, count, 3, c);
}

__kernel void xyz_to_lab(__global const float *restrict xyz, __global float *restrict lab,
                         const float Xn, const float Yn, const float Zn, const ulong n)
{
    PIXEL_RANGE(n);
    floatv L, a, b;
    lab_from_xyz(load_f_strided(xyz, base, count, 3, 0), load_f_strided(xyz, base, count, 3, 1),
               load_f_strided(xyz, base, count, 3, 2), Xn, Yn, Zn, &L, &a, &b);
    store_f_strided(L, lab, base, count, 3, 0);
    store_f_strided(a, lab, base, count, 3, 1);
    store_f_strided(b, lab, base, count, 3, 2);
}

#ifdef DE_METHOD
__kernel void delta_e(__global const float *restrict lab1, __global const float *restrict lab2,
                      __global float *restrict de, const ulong n)
{
    PIXEL_RANGE(n);
    const floatv d = DELTA_E(load_channel(lab1, LAB1_SINGLE, base, count, 0),
                             load_channel(lab1, LAB1_SINGLE, base, count, 1),
                             load_channel(lab1, LAB1_SINGLE, base, count, 2),
                             load_channel(lab2, LAB2_SINGLE, base, count, 0),
                             load_channel(lab2, LAB2_SINGLE, base, count, 1),
                             load_channel(lab2, LAB2_SINGLE, base, count, 2));
    store_f(d, de, base, count);
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
    store_f_strided(X, xyz_out, base, count, 3, 0);
    store_f_strided(Y, xyz_out, base, count, 3, 1);
    store_f_strided(Z, xyz_out, base, count, 3, 2);
#endif
    floatv L, a, b;
    lab_from_xyz(X, Y, Z, Xn, Yn, Zn, &L, &a, &b);
#if WRITE_LAB
    store_f_strided(L, lab_out, base, count, 3, 0);
    store_f_strided(a, lab_out, base, count, 3, 1);
    store_f_strided(b, lab_out, base, count, 3, 2);
#endif
#if WRITE_DE
    const floatv d = DELTA_E(load_channel(ref_lab, REF_SINGLE, base, count, 0),
                             load_channel(ref_lab, REF_SINGLE, base, count, 1),
                             load_channel(ref_lab, REF_SINGLE, base, count, 2), L, a, b);
    store_f(d, de_out, base, count);
#endif
#if WRITE_MASK
    store_mask(convert_uchar8(flags), mask, base, count);
#endif
}
#endif
