/* specgpu linear kernel family: y = A (o - dark) * gain for every pixel of full frames.
 *
 * Macros (besides those of common.h):
 *   B           outputs per pixel (rows of A)
 *   OUT_HALF    0: float32 output   1: float16 output (stored with vstore_half, round to nearest even)
 *   OUT_LAYOUT  0: planar (B, N)     1: interleaved (N, B)
 *   WRITE_MASK  0/1: write a uint8 flag per pixel (1 saturated, 2 non-finite input, OR-ed)
 *   GROUP       work-group size of the launch (the "gpu" variant's channels-last tile, VW = 1)
 *   TILE        "gpu" variant, channels last: 1 = a work-item per pixel, its B outputs staged in local memory and
 *               the group's GROUP x B outputs written back as one contiguous coalesced run (the default where
 *               the tile fits); 0 = a work-item per output element (n x B work-items)
 *   OUT_SQRT    0/1: write sqrt(max(y_b + c_b, 0)) instead of y_b, with the B offsets c_b stored after the B x K
 *               matrix in A (a standard deviation from a variance that is linear in the frames plus a constant)
 *   SQUARE_GAIN, SQUARE_SHIFT  optional: samples squared before the matrix (common.h), for the variance of a frame
 *               whose light fluctuates
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

#ifndef OUT_SQRT
#define OUT_SQRT 0
#endif
#if OUT_SQRT
#define POST(y, b) y = sd_of_variance(y + A[B * K + (b)])
#else
#define POST(y, b)
#endif

#if OUT_HALF
#define OUT_T half
#define STORE store_h
#define STORE_STRIDED store_h_strided
#define STORE_ROW(v, p) STORE_HALF8(v, p)
#else
#define OUT_T float
#define STORE store_f
#define STORE_STRIDED store_f_strided
#define STORE_ROW(v, p) STORE8(float, v, p)
#endif

#ifndef GROUP
#define GROUP 64
#endif
#ifndef TILE
#define TILE 1
#endif

#if VW == 1 && OUT_LAYOUT == 1
#if TILE
/* "gpu" variant, channels last: each work-item computes its pixel's B outputs into a local tile (row stride B,
 * so an odd B has no bank conflicts), then the group writes the tile, GROUP x B consecutive outputs, with
 * consecutive work-items on consecutive addresses. */
__kernel __attribute__((reqd_work_group_size(GROUP, 1, 1)))
void linear_apply(__global const IN_T *restrict frames,
                  __constant const float *restrict A,
                  __global const float *restrict dark,
                  __global const float *restrict gain,
                  __global OUT_T *restrict out,
                  __global uchar *restrict mask,
                  const ulong n)
{
    __local float tile[GROUP * B];
    const uint lid = get_local_id(0);
    const ulong base = get_global_id(0);
    const ulong first = base - lid;
    /* no return before the barrier, not even a whole group's past the end: PoCL 3.0's work-group loops
     * (POCL_WORK_GROUP_METHOD=loopvec, its default on CPUs) crash on a kernel that returns before a barrier */
    if (base < n) {
        const uint count = 1;
        LOAD_PIXELS();
#if HAS_GAIN
        const floatv g = gain[base];
#endif
        for (uint b = 0; b < B; ++b) {
            floatv y;
            DOT_ROW(y, A, b);
#if HAS_GAIN
            y *= g;
#endif
            POST(y, b);
            tile[lid * B + b] = y;
        }
#if WRITE_MASK
        mask[base] = CONVERT_UCHARV(flags);
#endif
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const uint pixels = first >= n ? 0 : (n - first < GROUP ? (uint)(n - first) : GROUP);
    const uint total = pixels * B;
    __global OUT_T *dst = out + (pixels ? first * B : 0); /* a group past the end writes nothing */
    for (uint j = lid; j < total; j += GROUP) {
#if OUT_HALF
        vstore_half_rte(tile[j], j, dst);
#else
        dst[j] = tile[j];
#endif
    }
}
#else
/* "gpu" variant, channels last, no tile: a work-item per output element (pixel i, output b); consecutive
 * work-items write consecutive addresses, the K samples of a pixel are read by its B work-items (cached). */
__kernel void linear_apply(__global const IN_T *restrict frames,
                           __constant const float *restrict A,
                           __global const float *restrict dark,
                           __global const float *restrict gain,
                           __global OUT_T *restrict out,
                           __global uchar *restrict mask,
                           const ulong n)
{
    const ulong e = get_global_id(0);
    if (e >= n * B) return;
    const ulong base = e / B;
    const uint b = (uint)(e - base * B), count = 1;
    LOAD_PIXELS();
    floatv y;
    DOT_ROW(y, A, b);
#if HAS_GAIN
    y *= gain[base];
#endif
    POST(y, b);
#if OUT_HALF
    vstore_half_rte(y, e, out);
#else
    out[e] = y;
#endif
#if WRITE_MASK
    if (b == 0) mask[base] = CONVERT_UCHARV(flags);
#endif
}
#endif
#else /* planar (both variants) and the "cpu" variant's channels last */

/* Pixel row j (8 consecutive outputs from b0) of an interleaved block, when pixel j exists. */
#define STORE_PIXEL_ROW(j, r) if ((j) < count) STORE_ROW(r, out + (base + (j)) * B + b0)

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
#if OUT_LAYOUT == 0
    for (uint b = 0; b < B; ++b) {
        floatv y;
        DOT_ROW(y, A, b);
#if HAS_GAIN
        y *= g;
#endif
        POST(y, b);
        STORE(y, out + (ulong)b * n, base, count);
    }
#else
    /* interleaved: blocks of 8 outputs are transposed in registers and written as 8 contiguous pixel rows
     * (one stream per work-item instead of 8 strided scalar stores per output). When B is not a multiple of 8
     * the last block is shifted back to end at B: the few outputs it shares with the block before are computed
     * again and written again, with the same values, by the same work-item. */
#if B >= 8
    for (uint next = 0; next < B; next += 8) {
        const uint b0 = next + 8 <= B ? next : B - 8;
        floatv a0, a1, a2, a3, a4, a5, a6, a7, r0, r1, r2, r3, r4, r5, r6, r7;
        DOT_ROW(a0, A, b0 + 0); DOT_ROW(a1, A, b0 + 1); DOT_ROW(a2, A, b0 + 2); DOT_ROW(a3, A, b0 + 3);
        DOT_ROW(a4, A, b0 + 4); DOT_ROW(a5, A, b0 + 5); DOT_ROW(a6, A, b0 + 6); DOT_ROW(a7, A, b0 + 7);
#if HAS_GAIN
        a0 *= g; a1 *= g; a2 *= g; a3 *= g; a4 *= g; a5 *= g; a6 *= g; a7 *= g;
#endif
        POST(a0, b0 + 0); POST(a1, b0 + 1); POST(a2, b0 + 2); POST(a3, b0 + 3);
        POST(a4, b0 + 4); POST(a5, b0 + 5); POST(a6, b0 + 6); POST(a7, b0 + 7);
        TRANSPOSE8(a0, a1, a2, a3, a4, a5, a6, a7, r0, r1, r2, r3, r4, r5, r6, r7);
        STORE_PIXEL_ROW(0, r0); STORE_PIXEL_ROW(1, r1); STORE_PIXEL_ROW(2, r2); STORE_PIXEL_ROW(3, r3);
        STORE_PIXEL_ROW(4, r4); STORE_PIXEL_ROW(5, r5); STORE_PIXEL_ROW(6, r6); STORE_PIXEL_ROW(7, r7);
    }
#else
    for (uint b0 = 0; b0 < B; ++b0) {
        floatv y;
        DOT_ROW(y, A, b0);
#if HAS_GAIN
        y *= g;
#endif
        POST(y, b0);
        STORE_STRIDED(y, out, base, count, B, b0);
    }
#endif
#endif
#if WRITE_MASK
    store_mask(CONVERT_UCHARV(flags), mask, base, count);
#endif
}
#endif /* VW == 1 && OUT_LAYOUT == 1 */

#if VW == 8 && OUT_HALF && OUT_LAYOUT == 0 && K <= 128
/* Planar float16 with 16 pixels per work-item: the two 8-pixel halves of each output plane are converted together
 * and written as one 32-byte store, which halves the store instructions per plane and lets the 61 plane streams
 * keep pace with the arithmetic (measured 30 % faster than 8 pixels per work-item, and faster than float32).
 * The host launches n / 16 work-items of this entry for planar float16 outputs. */
#define Y_LOAD_ONE(k)                                                                          \
    const floatv x##k = load_sample(frames, dark, n, k, base, count, &flags);                 \
    const floatv y##k = load_sample(frames, dark, n, k, base2, count2, &flags2);
#define Y_FMA_ONE(k) acc0 = m_[k] * x##k + acc0; acc1 = m_[k] * y##k + acc1;

__kernel void linear_apply_h16(__global const IN_T *restrict frames,
                               __constant const float *restrict A,
                               __global const float *restrict dark,
                               __global const float *restrict gain,
                               __global half *restrict out,
                               __global uchar *restrict mask,
                               const ulong n)
{
    const ulong base = (ulong)get_global_id(0) * 16;
    if (base >= n) return;
    const ulong base2 = base + VW;
    const uint count = n - base < VW ? (uint)(n - base) : VW;
    const uint count2 = base2 >= n ? 0 : (n - base2 < VW ? (uint)(n - base2) : VW);
    intv flags = (intv)(0), flags2 = (intv)(0);
    REP_(K, Y_LOAD_ONE)
#if HAS_GAIN
    const floatv g = load_f(gain, base, count), g2 = count2 ? load_f(gain, base2, count2) : (floatv)(0.0f);
#endif
    for (uint b = 0; b < B; ++b) {
        __constant const float *m_ = A + b * K;
        floatv acc0 = (floatv)(0.0f), acc1 = (floatv)(0.0f);
        REP_(K, Y_FMA_ONE)
#if HAS_GAIN
        acc0 *= g;
        acc1 *= g2;
#endif
        POST(acc0, b);
        POST(acc1, b);
        __global half *plane = out + (ulong)b * n;
#if VEC_DEREF
        if (count2 == VW) {
            typedef ushort16 ushort16_u __attribute__((aligned(2)));
            *(__global ushort16_u *)(plane + base) = (ushort16)(half_bits(acc0), half_bits(acc1));
            continue;
        }
#endif
        store_h(acc0, plane, base, count);
        if (count2) store_h(acc1, plane, base2, count2);
    }
#if WRITE_MASK
    store_mask(CONVERT_UCHARV(flags), mask, base, count);
    if (count2) store_mask(convert_uchar8(flags2), mask, base2, count2);
#endif
}
#endif
