/* specgpu linear kernel family: y = A (o - dark) * gain for every pixel of full frames.
 *
 * Macros (besides those of common.h):
 *   B           outputs per pixel (rows of A)
 *   OUT_HALF    0: float32 output   1: float16 output (stored with vstore_half, round to nearest even)
 *   OUT_LAYOUT  0: planar (B, N)     1: interleaved (N, B)
 *   WRITE_MASK  0/1: write a uint8 flag per pixel (1 saturated, 2 non-finite input, OR-ed)
 *
 * Arguments: frames (K planes or N x K), A (B x K row-major, constant), dark (N or K x N, or unused),
 * gain (N, or unused), out, mask (N, or unused), n = number of pixels.
 */
#include "common.h"

#ifndef B
#define B 1
#endif
#ifndef OUT_HALF
#define OUT_HALF 0
#endif
#ifndef OUT_LAYOUT
#define OUT_LAYOUT 0
#endif
#ifndef WRITE_MASK
#define WRITE_MASK 0
#endif

#if OUT_HALF
#define OUT_T half
#define STORE store_h
#define STORE_STRIDED store_h_strided
#else
#define OUT_T float
#define STORE store_f
#define STORE_STRIDED store_f_strided
#endif

__kernel void linear_apply(__global const IN_T *restrict frames,
                           __constant const float *restrict A,
                           __global const float *restrict dark,
                           __global const float *restrict gain,
                           __global OUT_T *restrict out,
                           __global uchar *restrict mask,
                           const ulong n)
{
    PIXEL_RANGE(n);
    LOAD_PIXELS();
#if HAS_GAIN
    const floatv g = load_f(gain, base, count);
#endif
    for (uint b = 0; b < B; ++b) {
        floatv y;
        DOT_ROW(y, A, b);
#if HAS_GAIN
        y *= g;
#endif
#if OUT_LAYOUT == 0
        STORE(y, out + (ulong)b * n, base, count);
#else
        STORE_STRIDED(y, out, base, count, B, b);
#endif
    }
#if WRITE_MASK
    store_mask(convert_uchar8(flags), mask, base, count);
#endif
}
