/* specgpu motion-compensated linear kernels: y(x) = A s(x) with s_k(x) the corrected frame k sampled at x + d_k.
 *
 * A moving scene lands on different pixels in different frames of a sequence. Output pixel x is where a scene
 * point is at the sequence's reference time; frame k saw that point at M_k (x, y, 1): a 2 x 3 affine map per frame
 * (a translation d_k is (1, 0, dx_k; 0, 1, dy_k)), in pixels. The sample is the bilinear interpolation, at x + d_k,
 * of the corrected frame c_k(p) = (o_k(p) - dark(p)) * gain(p): dark level and flat field belong to the sensor pixel
 * p, so they are applied before interpolation (for d = 0 this is exactly A (o - dark) * gain of linear.cl).
 *
 * A pixel whose sample point of any frame lies outside the field has no measurement: its outputs are NaN and its
 * mask has bit 4 (MASK_OUTSIDE). The field is the sensor's footprint, [-1/2, W-1/2] x [-1/2, H-1/2] in pixel
 * centres: a point within half a pixel of an edge pixel's centre was seen by that pixel, and takes its value (the
 * interpolation's taps clamped to the field), so a frame displaced by a fraction of a pixel loses no border.
 * Bit 1: a frame pixel used (non-zero weight) is at SAT_LEVEL; bit 2: a non-finite float input.
 *
 * linear_warp: one work-item per output pixel, any motion. Macros (as common.h): K, B, IN_T, HAS_DARK (0 / 1 per
 * pixel / 2 per frame), HAS_GAIN, SAT_LEVEL, IS_FLOAT_IN; FLOW = 1: a displacement per pixel and frame instead
 * (dense motion, flow (K, 2, N): frame k saw pixel i at (x + flow[k][0][i], y + flow[k][1][i])), the affine maps
 * unused; OUT_INTERLEAVED. Arguments: frames (K, H, W), A (B x K, constant), motion (K x 6: the rows of M_k,
 * constant), flow, dark, gain, out (B x N, or N x B), mask (N), width, height.
 * linear_warp_translate (built with GROUPS): every motion a translation, 8 pixels of a row at a time, below; with
 * warp_correct before it when the corrected frames are kept for a later step.
 */
#include "common.h"

#ifndef B
#define B 1
#endif

#ifndef FLOW
#define FLOW 0
#endif

/* OUT_INTERLEAVED = 1: out is (N, B), the outputs of a pixel together (what the host returns as (H, W, B));
 * else planar (B, N) */
#ifndef OUT_INTERLEAVED
#define OUT_INTERLEAVED 0
#endif
#if OUT_INTERLEAVED
#define OUT_AT(b, i) ((ulong)(i) * B + (b))
#else
#define OUT_AT(b, i) ((ulong)(b) * n + (i))
#endif

/* GROUPS (1 to 4): the translation kernel (below), whose B outputs are split into GROUPS consecutive groups of rows
 * of A, group g (G<g>_ROWS rows, G<g>_IL 1 interleaved (N, rows) or 0 planar (rows, N)) written to a buffer of its
 * own, out<g>: the stream's coefficients (N, 5) and XYZ (N, 3) in one pass. Else the per-pixel kernel linear_warp. */
#ifdef GROUPS
#define CORRECTED 1
#else
#define CORRECTED 0
#endif

#if !CORRECTED
inline float corrected(__global const IN_T *restrict plane, __global const float *restrict dark,
                       __global const float *restrict gain, uint k, ulong n, ulong p, float w, int *flags)
{
    const float v = (float)plane[p];
#ifdef SAT_LEVEL
    *flags |= (w > 0.0f && v >= SAT_LEVEL) ? MASK_SATURATED : 0;
#endif
#if IS_FLOAT_IN
    *flags |= (w > 0.0f && !isfinite(v)) ? MASK_NONFINITE : 0;
#endif
    float c = v;
#if HAS_DARK == 1
    c -= dark[p];
#elif HAS_DARK == 2
    c -= dark[(ulong)k * n + p];
#endif
#if HAS_GAIN
    c *= gain[p];
#endif
    return w > 0.0f ? c * w : 0.0f; /* a zero weight never lets a NaN neighbour in */
}

/* Frame k's corrected sample at M_k (x, y, 1), bilinear; flags MASK_OUTSIDE (and returns 0) off the field. */
inline float warp_sample(__global const IN_T *restrict frames, __constant const float *restrict motion,
                         __global const float *restrict flow, __global const float *restrict dark,
                         __global const float *restrict gain, uint k, ulong n, int x, int y, uint width, uint height,
                         int *flags)
{
#if FLOW
    const ulong i = (ulong)y * width + x;
    const float sx = (float)x + flow[2 * k * n + i], sy = (float)y + flow[(2 * k + 1) * n + i];
#else
    __constant const float *m = motion + 6 * k;
    const float sx = m[0] * (float)x + (m[1] * (float)y + m[2]);
    const float sy = m[3] * (float)x + (m[4] * (float)y + m[5]);
#endif
    /* the edge pixels' footprints, plus a tolerance of 1/1024 px that keeps a sample landing on their edge by
     * rounding; no branch, so the work-items of a group stay in step (PoCL vectorises across them) */
    const int inside = sx >= -0.5009765625f && sy >= -0.5009765625f && sx <= (float)width - 0.4990234375f
                       && sy <= (float)height - 0.4990234375f;
    *flags |= inside ? 0 : MASK_OUTSIDE;
    const float cx = clamp(sx, 0.0f, (float)(width - 1)), cy = clamp(sy, 0.0f, (float)(height - 1));
    const int x0 = min((int)cx, (int)width - 1), y0 = min((int)cy, (int)height - 1);
    const int x1 = min(x0 + 1, (int)width - 1), y1 = min(y0 + 1, (int)height - 1);
    const float fx = cx - (float)x0, fy = cy - (float)y0;
    __global const IN_T *plane = frames + (ulong)k * n;
    const ulong r0 = (ulong)y0 * width, r1 = (ulong)y1 * width;
    return corrected(plane, dark, gain, k, n, r0 + x0, (1.0f - fx) * (1.0f - fy), flags)
         + corrected(plane, dark, gain, k, n, r0 + x1, fx * (1.0f - fy), flags)
         + corrected(plane, dark, gain, k, n, r1 + x0, (1.0f - fx) * fy, flags)
         + corrected(plane, dark, gain, k, n, r1 + x1, fx * fy, flags);
}

/* Output pixel i = (x, y): its K samples and B outputs, and its mask. */
inline void warp_pixel(__global const IN_T *restrict frames, __constant const float *restrict A,
                       __constant const float *restrict motion, __global const float *restrict flow,
                       __global const float *restrict dark, __global const float *restrict gain,
                       __global float *restrict out, __global uchar *restrict mask, uint width, uint height,
                       ulong i)
{
    const ulong n = (ulong)width * height;
    const int x = (int)(i % width), y = (int)(i / width);
    int flags = 0;
#if K <= 128
    /* the K samples in named registers (PoCL keeps a private array in memory), the products unrolled */
#define W_SAMPLE(k) const float s##k = warp_sample(frames, motion, flow, dark, gain, k, n, x, y, width, height, &flags);
#define W_FMA(k) acc = row[k] * s##k + acc;
    REP_(K, W_SAMPLE)
    const int outside = flags & MASK_OUTSIDE;
    for (uint b = 0; b < B; ++b) {
        __constant const float *row = A + b * K;
        float acc = 0.0f;
        REP_(K, W_FMA)
        out[OUT_AT(b, i)] = outside ? NAN : acc; /* planar: consecutive work-items, consecutive addresses */
    }
#else
    float s[K];
    for (uint k = 0; k < K; ++k)
        s[k] = warp_sample(frames, motion, flow, dark, gain, k, n, x, y, width, height, &flags);
    const int outside = flags & MASK_OUTSIDE;
    for (uint b = 0; b < B; ++b) {
        __constant const float *row = A + b * K;
        float acc = 0.0f;
        for (uint k = 0; k < K; ++k) acc = row[k] * s[k] + acc;
        out[OUT_AT(b, i)] = outside ? NAN : acc;
    }
#endif
    mask[i] = (uchar)flags;
}

/* The arguments of the per-pixel kernel */
#define WARP_KERNEL_ARGS __global const IN_T *restrict frames, __constant const float *restrict A, \
    __constant const float *restrict motion, __global const float *restrict flow, \
    __global const float *restrict dark, __global const float *restrict gain, __global float *restrict out, \
    __global uchar *restrict mask, const uint width, const uint height

__kernel void linear_warp(WARP_KERNEL_ARGS)
{
    const ulong i = get_global_id(0);
    if (i >= (ulong)width * height) return;
    warp_pixel(frames, A, motion, flow, dark, gain, out, mask, width, height, i);
}
#endif /* !CORRECTED */

#if CORRECTED && K <= 128 && !FLOW
/* -------------------------------------------------------------------------------------------------- translations
 *
 * Every frame displaced by a translation: all pixels of frame k have the same bilinear weights, and the samples of
 * 8 consecutive output pixels come from 9 consecutive source pixels of two rows, read as vectors. The samples are
 * corrected where they are read (one pass, FROM_CORRECTED = 0): the raw frame's row, the dark and gain maps' same
 * row, (o - dark) * gain with the operations of corrected() above, so the same bits. Or, where a later step reads
 * the corrected frames too (a consistency check), warp_correct writes them first, each plane read as float32 with a
 * uchar plane of its flags (1 saturated, 2 non-finite input), and the kernel samples those (FROM_CORRECTED = 1): the
 * same outputs and mask, bit for bit. tools/benchmarks/warp_cost.py measures both against the static decoder. */

#ifndef STRIP
#define STRIP 8
#endif
#ifndef XSTEPS
#define XSTEPS 1
#endif
#ifndef FROM_CORRECTED
#define FROM_CORRECTED 0
#endif
#ifndef G1_ROWS
#define G1_ROWS 0
#define G1_IL 0
#endif
#ifndef G2_ROWS
#define G2_ROWS 0
#define G2_IL 0
#endif
#ifndef G3_ROWS
#define G3_ROWS 0
#define G3_IL 0
#endif
#define G1_FIRST (G0_ROWS)
#define G2_FIRST (G1_FIRST + G1_ROWS)
#define G3_FIRST (G2_FIRST + G2_ROWS)
#if G3_FIRST + G3_ROWS != B
#error "the output groups' rows (G0_ROWS + G1_ROWS + G2_ROWS + G3_ROWS) must add up to B"
#endif
#define OUT_PARAMS __global float *restrict out0, __global float *restrict out1, __global float *restrict out2, \
    __global float *restrict out3
#define OUT_ARGS out0, out1, out2, out3

/* The helpers of the translation kernel are inlined always (INLINE): PoCL leaves a large helper (the loads of a row,
 * the stores of a group) a function of its own, called with its vectors through memory (measured a third of the
 * pass). Their pointer parameters are not restrict: inlined, a restrict parameter becomes a noalias scope
 * declaration, an intrinsic Oclgrind cannot run (tests/engine/test_oclgrind.py); the kernels' own are. */
#define INLINE __attribute__((always_inline)) inline

/* Output b of pixel i (of n) into its group's buffer (the last pixels of a row, fewer than 8) */
inline void put_output(OUT_PARAMS, uint b, ulong i, ulong n, float v)
{
    if (b < G1_FIRST)
        out0[G0_IL ? i * G0_ROWS + b : (ulong)b * n + i] = v;
    else if (b < G2_FIRST)
        out1[G1_IL ? i * G1_ROWS + (b - G1_FIRST) : (ulong)(b - G1_FIRST) * n + i] = v;
    else if (b < G3_FIRST)
        out2[G2_IL ? i * G2_ROWS + (b - G2_FIRST) : (ulong)(b - G2_FIRST) * n + i] = v;
    else
        out3[G3_IL ? i * G3_ROWS + (b - G3_FIRST) : (ulong)(b - G3_FIRST) * n + i] = v;
}

/* The corrected frames for FROM_CORRECTED. Arguments: frames (the input frames, planes of n), frame_of (K,
 * constant: the input frame of plane k, the `read` selection), dark (n, or one per input frame), gain (n), corr
 * (K x n float32), cflags (K x n uchar), n. 8 consecutive pixels per work-item, the last one partial. */
__kernel void warp_correct(__global const IN_T *restrict frames, __constant const uint *restrict frame_of,
                           __global const float *restrict dark, __global const float *restrict gain,
                           __global float *restrict corr, __global uchar *restrict cflags, const ulong n)
{
    const ulong base = (ulong)get_global_id(0) * 8;
    if (base >= n) return;
    if (n - base < 8) { /* the last work-item, partial: the same operations, pixel by pixel */
        for (uint k = 0; k < K; ++k) {
            const ulong src = (ulong)frame_of[k] * n;
            for (ulong p = base; p < n; ++p) {
                const float v = (float)frames[src + p];
                float c = v;
#if HAS_DARK == 1
                c -= dark[p];
#elif HAS_DARK == 2
                c -= dark[src + p];
#endif
#if HAS_GAIN
                c *= gain[p];
#endif
                corr[(ulong)k * n + p] = c;
                int f = 0;
#ifdef SAT_LEVEL
                f |= v >= SAT_LEVEL ? MASK_SATURATED : 0;
#endif
#if IS_FLOAT_IN
                f |= isfinite(v) ? 0 : MASK_NONFINITE;
#endif
                cflags[(ulong)k * n + p] = (uchar)f;
            }
        }
        return;
    }
#if HAS_DARK == 1
    const float8 d = LOAD8(float, dark + base);
#endif
#if HAS_GAIN
    const float8 g = LOAD8(float, gain + base);
#endif
    for (uint k = 0; k < K; ++k) {
        const ulong src = (ulong)frame_of[k] * n + base;
        const float8 v = convert_float8(LOAD8(IN_T, frames + src));
        float8 c = v;
#if HAS_DARK == 1
        c -= d;
#elif HAS_DARK == 2
        c -= LOAD8(float, dark + src);
#endif
#if HAS_GAIN
        c *= g;
#endif
        STORE8(float, c, corr + (ulong)k * n + base);
        int8 f = (int8)(0);
#ifdef SAT_LEVEL
        f |= v >= (float8)(SAT_LEVEL) ? (int8)(MASK_SATURATED) : (int8)(0);
#endif
#if IS_FLOAT_IN
        f |= isfinite(v) ? (int8)(0) : (int8)(MASK_NONFINITE);
#endif
        STORE8(uchar, convert_uchar8(f), cflags + (ulong)k * n + base);
    }
}

/* Interleaved stores of 8 pixels' R outputs (a_b: output b of the 8 pixels), R = 2 .. 7: the 8 R consecutive floats
 * at o as R vector stores, built from single lanes (see TRANSPOSE8 in common.h) */
INLINE void store_il2(__global float *o, float8 a0, float8 a1)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a0.s1, a1.s1, a0.s2, a1.s2, a0.s3, a1.s3)), o + 0);
    STORE8(float, ((float8)(a0.s4, a1.s4, a0.s5, a1.s5, a0.s6, a1.s6, a0.s7, a1.s7)), o + 8);
}
INLINE void store_il3(__global float *o, float8 a0, float8 a1, float8 a2)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a2.s0, a0.s1, a1.s1, a2.s1, a0.s2, a1.s2)), o + 0);
    STORE8(float, ((float8)(a2.s2, a0.s3, a1.s3, a2.s3, a0.s4, a1.s4, a2.s4, a0.s5)), o + 8);
    STORE8(float, ((float8)(a1.s5, a2.s5, a0.s6, a1.s6, a2.s6, a0.s7, a1.s7, a2.s7)), o + 16);
}
INLINE void store_il4(__global float *o, float8 a0, float8 a1, float8 a2, float8 a3)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a2.s0, a3.s0, a0.s1, a1.s1, a2.s1, a3.s1)), o + 0);
    STORE8(float, ((float8)(a0.s2, a1.s2, a2.s2, a3.s2, a0.s3, a1.s3, a2.s3, a3.s3)), o + 8);
    STORE8(float, ((float8)(a0.s4, a1.s4, a2.s4, a3.s4, a0.s5, a1.s5, a2.s5, a3.s5)), o + 16);
    STORE8(float, ((float8)(a0.s6, a1.s6, a2.s6, a3.s6, a0.s7, a1.s7, a2.s7, a3.s7)), o + 24);
}
INLINE void store_il5(__global float *o, float8 a0, float8 a1, float8 a2, float8 a3, float8 a4)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a2.s0, a3.s0, a4.s0, a0.s1, a1.s1, a2.s1)), o + 0);
    STORE8(float, ((float8)(a3.s1, a4.s1, a0.s2, a1.s2, a2.s2, a3.s2, a4.s2, a0.s3)), o + 8);
    STORE8(float, ((float8)(a1.s3, a2.s3, a3.s3, a4.s3, a0.s4, a1.s4, a2.s4, a3.s4)), o + 16);
    STORE8(float, ((float8)(a4.s4, a0.s5, a1.s5, a2.s5, a3.s5, a4.s5, a0.s6, a1.s6)), o + 24);
    STORE8(float, ((float8)(a2.s6, a3.s6, a4.s6, a0.s7, a1.s7, a2.s7, a3.s7, a4.s7)), o + 32);
}
INLINE void store_il6(__global float *o, float8 a0, float8 a1, float8 a2, float8 a3, float8 a4, float8 a5)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a2.s0, a3.s0, a4.s0, a5.s0, a0.s1, a1.s1)), o + 0);
    STORE8(float, ((float8)(a2.s1, a3.s1, a4.s1, a5.s1, a0.s2, a1.s2, a2.s2, a3.s2)), o + 8);
    STORE8(float, ((float8)(a4.s2, a5.s2, a0.s3, a1.s3, a2.s3, a3.s3, a4.s3, a5.s3)), o + 16);
    STORE8(float, ((float8)(a0.s4, a1.s4, a2.s4, a3.s4, a4.s4, a5.s4, a0.s5, a1.s5)), o + 24);
    STORE8(float, ((float8)(a2.s5, a3.s5, a4.s5, a5.s5, a0.s6, a1.s6, a2.s6, a3.s6)), o + 32);
    STORE8(float, ((float8)(a4.s6, a5.s6, a0.s7, a1.s7, a2.s7, a3.s7, a4.s7, a5.s7)), o + 40);
}
INLINE void store_il7(__global float *o, float8 a0, float8 a1, float8 a2, float8 a3, float8 a4, float8 a5,
                      float8 a6)
{
    STORE8(float, ((float8)(a0.s0, a1.s0, a2.s0, a3.s0, a4.s0, a5.s0, a6.s0, a0.s1)), o + 0);
    STORE8(float, ((float8)(a1.s1, a2.s1, a3.s1, a4.s1, a5.s1, a6.s1, a0.s2, a1.s2)), o + 8);
    STORE8(float, ((float8)(a2.s2, a3.s2, a4.s2, a5.s2, a6.s2, a0.s3, a1.s3, a2.s3)), o + 16);
    STORE8(float, ((float8)(a3.s3, a4.s3, a5.s3, a6.s3, a0.s4, a1.s4, a2.s4, a3.s4)), o + 24);
    STORE8(float, ((float8)(a4.s4, a5.s4, a6.s4, a0.s5, a1.s5, a2.s5, a3.s5, a4.s5)), o + 32);
    STORE8(float, ((float8)(a5.s5, a6.s5, a0.s6, a1.s6, a2.s6, a3.s6, a4.s6, a5.s6)), o + 40);
    STORE8(float, ((float8)(a6.s6, a0.s7, a1.s7, a2.s7, a3.s7, a4.s7, a5.s7, a6.s7)), o + 48);
}

/* sum_k A[b][k] t_k over the 8 pixels, in warp_pixel's order */
#define T_FMA(k) acc_ = row_[k] * t##k + acc_;
#define DOT8(acc, b)                                                                                               \
    do {                                                                                                           \
        __constant const float *row_ = A + (uint)(b) * K;                                                          \
        float8 acc_ = (float8)(0.0f);                                                                              \
        REP_(K, T_FMA)                                                                                             \
        acc = acc_;                                                                                                \
    } while (0)
/* the K samples of the 8 pixels as arguments (named registers, not a private array: see REP_n in common.h) */
#define T_PARAM(k) , const float8 t##k
#define T_ARG(k) , t##k

/* Outputs [first, first + rows) of the 8 pixels from i into o, planar (rows, n) or interleaved (n, rows) */
INLINE void write_group(__global float *o, __constant const float *A, const uint first, const uint rows,
                        const int interleaved, const ulong n, const ulong i REP_(K, T_PARAM))
{
    if (!interleaved) {
        for (uint b = 0; b < rows; ++b) {
            float8 acc;
            DOT8(acc, first + b);
            STORE8(float, acc, o + (ulong)b * n + i);
        }
        return;
    }
    if (rows >= 8) {
        /* blocks of 8 outputs transposed in registers into 8 pixel rows, as linear.cl writes them; a last block of
         * fewer is shifted back to end at `rows`, and writes its first outputs again with the same values */
        for (uint next = 0; next < rows; next += 8) {
            const uint b0 = next + 8 <= rows ? next : rows - 8;
            float8 a0, a1, a2, a3, a4, a5, a6, a7, r0, r1, r2, r3, r4, r5, r6, r7;
            DOT8(a0, first + b0); DOT8(a1, first + b0 + 1); DOT8(a2, first + b0 + 2); DOT8(a3, first + b0 + 3);
            DOT8(a4, first + b0 + 4); DOT8(a5, first + b0 + 5); DOT8(a6, first + b0 + 6); DOT8(a7, first + b0 + 7);
            TRANSPOSE8(a0, a1, a2, a3, a4, a5, a6, a7, r0, r1, r2, r3, r4, r5, r6, r7);
            __global float *q = o + i * rows + b0;
            STORE8(float, r0, q); STORE8(float, r1, q + rows); STORE8(float, r2, q + 2 * rows);
            STORE8(float, r3, q + 3 * rows); STORE8(float, r4, q + 4 * rows); STORE8(float, r5, q + 5 * rows);
            STORE8(float, r6, q + 6 * rows); STORE8(float, r7, q + 7 * rows);
        }
        return;
    }
    float8 a0, a1, a2, a3, a4, a5, a6;
    DOT8(a0, first);
    if (rows > 1) DOT8(a1, first + 1);
    if (rows > 2) DOT8(a2, first + 2);
    if (rows > 3) DOT8(a3, first + 3);
    if (rows > 4) DOT8(a4, first + 4);
    if (rows > 5) DOT8(a5, first + 5);
    if (rows > 6) DOT8(a6, first + 6);
    __global float *q = o + i * rows;
    switch (rows) {
    case 1: STORE8(float, a0, q); break;
    case 2: store_il2(q, a0, a1); break;
    case 3: store_il3(q, a0, a1, a2); break;
    case 4: store_il4(q, a0, a1, a2, a3); break;
    case 5: store_il5(q, a0, a1, a2, a3, a4); break;
    case 6: store_il6(q, a0, a1, a2, a3, a4, a5); break;
    default: store_il7(q, a0, a1, a2, a3, a4, a5, a6); break;
    }
}

/* Every group's outputs of 8 full pixels from i */
#define T_WRITE_GROUPS(i)                                                                                          \
    do {                                                                                                           \
        write_group(out0, A, 0, G0_ROWS, G0_IL, n, (i) REP_(K, T_ARG));                                            \
        if (GROUPS > 1) write_group(out1, A, G1_FIRST, G1_ROWS, G1_IL, n, (i) REP_(K, T_ARG));                     \
        if (GROUPS > 2) write_group(out2, A, G2_FIRST, G2_ROWS, G2_IL, n, (i) REP_(K, T_ARG));                     \
        if (GROUPS > 3) write_group(out3, A, G3_FIRST, G3_ROWS, G3_IL, n, (i) REP_(K, T_ARG));                     \
    } while (0)

/* A source row of corrected plane c (its pixels from ix): c0 the 8 from ix, c1 the 8 from ix + 1 (the ninth read
 * alone); f0, f1 their flags from the flag plane f, 8 bytes as one ulong (lane j in byte j on a little-endian
 * device). */
INLINE void load_row(__global const float *c, __global const uchar *f, int ix, float8 *c0, float8 *c1, ulong *f0,
                     ulong *f1)
{
    const float8 v = LOAD8(float, c + ix);
    const float v8 = c[ix + 8];
    *c0 = v;
    *c1 = (float8)(v.s1, v.s2, v.s3, v.s4, v.s5, v.s6, v.s7, v8);
    const ulong u = as_ulong(LOAD8(uchar, f + ix)), u8 = f[ix + 8];
    *f0 = u;
#ifdef __ENDIAN_LITTLE__
    *f1 = (u >> 8) | (u8 << 56);
#else
    *f1 = (u << 8) | u8;
#endif
}

/* The 9 columns from ix of a row, each clamped to the row as warp_sample clamps its taps: j, and j8 the ninth */
INLINE void clamped_columns(int ix, uint width, int8 *j, int *j8)
{
    const int last = (int)width - 1;
    int8 c = (int8)(ix) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    *j = c < (int8)(0) ? (int8)(0) : (c > (int8)(last) ? (int8)(last) : c); /* PoCL calls min and max out of line */
    *j8 = ix + 8 < 0 ? 0 : (ix + 8 > last ? last : ix + 8);
}

/* load_row where some of the 9 columns from ix are off the row (a work-item at the field's left or right edge, or
 * at the row's end): each column clamped to the row, as warp_sample clamps its taps. A lane whose sample point is
 * within the edge pixel's half then reads that pixel for both its taps (the weights' sum, where warp_sample has
 * weight 1: the same value to float32 rounding, the same flags). */
INLINE void load_row_clamped(__global const float *c, __global const uchar *f, int ix, uint width, float8 *c0,
                             float8 *c1, ulong *f0, ulong *f1)
{
    int8 j;
    int j8;
    clamped_columns(ix, width, &j, &j8);
    const float8 v = (float8)(c[j.s0], c[j.s1], c[j.s2], c[j.s3], c[j.s4], c[j.s5], c[j.s6], c[j.s7]);
    const float v8 = c[j8];
    *c0 = v;
    *c1 = (float8)(v.s1, v.s2, v.s3, v.s4, v.s5, v.s6, v.s7, v8);
    const uchar8 u = (uchar8)(f[j.s0], f[j.s1], f[j.s2], f[j.s3], f[j.s4], f[j.s5], f[j.s6], f[j.s7]);
    *f0 = as_ulong(u);
    *f1 = as_ulong((uchar8)(u.s1, u.s2, u.s3, u.s4, u.s5, u.s6, u.s7, f[j8]));
}

/* load_row for the one-pass build: the 9 columns from ix of row o of a raw frame corrected as warp_correct corrects
 * them, (o - dark) * gain (d, g: the dark and gain maps' same row), contiguous or clamped to the row as load_row and
 * load_row_clamped read them. No flags: `watch` gathers what tells whether a sample may raise one (the largest
 * sample; a NaN where one is not finite or, float frames, saturated), checked once per step, where the kernel then
 * reads the step's flags from the raw frames (raw_flags). */
INLINE void load_row_raw(__global const IN_T *o, __global const float *d, __global const float *g, int ix,
                         int contiguous, uint width, float8 *c0, float8 *c1, float8 *watch, float *watch8)
{
    float8 v;
    float v8;
    float8 c;
    if (contiguous) {
        v = convert_float8(LOAD8(IN_T, o + ix));
        v8 = (float)o[ix + 8];
        c = v;
#if HAS_DARK
        c -= LOAD8(float, d + ix);
#endif
#if HAS_GAIN
        c *= LOAD8(float, g + ix);
#endif
        ix += 8;
    } else {
        int8 j;
        int j8;
        clamped_columns(ix, width, &j, &j8);
        v = convert_float8((VEC8(IN_T))(o[j.s0], o[j.s1], o[j.s2], o[j.s3], o[j.s4], o[j.s5], o[j.s6], o[j.s7]));
        v8 = (float)o[j8];
        c = v;
#if HAS_DARK
        c -= (float8)(d[j.s0], d[j.s1], d[j.s2], d[j.s3], d[j.s4], d[j.s5], d[j.s6], d[j.s7]);
#endif
#if HAS_GAIN
        c *= (float8)(g[j.s0], g[j.s1], g[j.s2], g[j.s3], g[j.s4], g[j.s5], g[j.s6], g[j.s7]);
#endif
        ix = j8;
    }
    float c8 = v8;
#if HAS_DARK
    c8 -= d[ix];
#endif
#if HAS_GAIN
    c8 *= g[ix];
#endif
    *c0 = c;
    *c1 = (float8)(c.s1, c.s2, c.s3, c.s4, c.s5, c.s6, c.s7, c8);
#if IS_FLOAT_IN
    /* a NaN in the lanes where some sample is NaN or infinite (v * 0), else 0; the largest sample for saturation */
    *watch = *watch + v * 0.0f;
    *watch8 = *watch8 + v8 * 0.0f;
#endif
#if defined(SAT_LEVEL) && !IS_FLOAT_IN
    *watch = v > *watch ? v : *watch;
    *watch8 = v8 > *watch8 ? v8 : *watch8;
#elif defined(SAT_LEVEL)
    *watch = (v >= (float8)(SAT_LEVEL)) ? (float8)(NAN) : *watch;
    *watch8 = v8 >= SAT_LEVEL ? NAN : *watch8;
#endif
}

/* The flags of the 9 columns from ix of row o of a raw frame (clamped as load_row_raw reads them), as load_row
 * gives the corrected planes' */
INLINE void raw_flags(__global const IN_T *o, int ix, int contiguous, uint width, ulong *f0, ulong *f1)
{
    int8 j;
    int j8;
    clamped_columns(ix, width, &j, &j8);
    const float8 v = contiguous ? convert_float8(LOAD8(IN_T, o + ix))
        : convert_float8((VEC8(IN_T))(o[j.s0], o[j.s1], o[j.s2], o[j.s3], o[j.s4], o[j.s5], o[j.s6], o[j.s7]));
    const float v8 = (float)o[j8];
    int8 f = (int8)(0);
    int f8 = 0;
#ifdef SAT_LEVEL
    f |= v >= (float8)(SAT_LEVEL) ? (int8)(MASK_SATURATED) : (int8)(0);
    f8 |= v8 >= SAT_LEVEL ? MASK_SATURATED : 0;
#endif
#if IS_FLOAT_IN
    f |= isfinite(v) ? (int8)(0) : (int8)(MASK_NONFINITE);
    f8 |= isfinite(v8) ? 0 : MASK_NONFINITE;
#endif
    const uchar8 u = convert_uchar8(f);
    *f0 = as_ulong(u);
    *f1 = as_ulong((uchar8)(u.s1, u.s2, u.s3, u.s4, u.s5, u.s6, u.s7, (uchar)f8));
}

/* A bilinear tap: zero where its weight is (no NaN or saturated neighbour let in), as corrected() */
INLINE float8 row_tap(float8 c, float w)
{
    return w > 0.0f ? c * w : (float8)(0.0f);
}

/* floor(x) of x clamped to +-2^24 (beyond, every sample is off the field, and the integer part must exist), inline:
 * PoCL calls floor and clamp out of line */
INLINE float floor_bounded(float x)
{
    x = x < -16777216.0f ? -16777216.0f : (x > 16777216.0f ? 16777216.0f : x);
    const float t = (float)(int)x;
    return t > x ? t - 1.0f : t;
}

/* Frame k's translation: its whole-pixel part (dix: the source column offset, iy: the source row offset) and the
 * four bilinear weights from its fraction (as the per-pixel kernel's for a d_k whose x + d_k is exact in float32),
 * and the masks that let a tap's flags in where its weight is above zero. mode: 1 every weight above zero (the taps
 * summed without selects, the products contracted into FMAs), 2 a whole pixel (weight 1 on the upper left tap:
 * the sample is that pixel, as for the reference frame), 0 any other (zero-weight taps by selects, their flags
 * masked). */
#define T_SETUP(k)                                                                                                 \
    const float dx##k = motion[6 * k + 2], dy##k = motion[6 * k + 5];                                              \
    const float fdx##k = floor_bounded(dx##k), fdy##k = floor_bounded(dy##k);                                      \
    const float fx##k = dx##k - fdx##k, fy##k = dy##k - fdy##k;                                                    \
    const int dix##k = (int)fdx##k, iy##k = (int)fdy##k;                                                           \
    const float w00_##k = (1.0f - fx##k) * (1.0f - fy##k), w10_##k = fx##k * (1.0f - fy##k);                       \
    const float w01_##k = (1.0f - fx##k) * fy##k, w11_##k = fx##k * fy##k;                                         \
    const ulong m00_##k = w00_##k > 0.0f ? ~0UL : 0UL, m10_##k = w10_##k > 0.0f ? ~0UL : 0UL;                      \
    const ulong m01_##k = w01_##k > 0.0f ? ~0UL : 0UL, m11_##k = w11_##k > 0.0f ? ~0UL : 0UL;                      \
    const int mode##k = (m00_##k & m10_##k & m01_##k & m11_##k) ? 1                                                \
                        : (w00_##k == 1.0f && !(m10_##k | m01_##k | m11_##k)) ? 2 : 0;                             \
    float8 h##k;                                                                                                   \
    ulong hf##k;
/* Frame k at the 8 pixels from xb: the source column of the first (ix), whether the 9 source columns are all on the
 * row, and the lanes whose sample point is off the field in x (warp_sample's test, on the same float32 coordinate
 * x + dx) */
#define T_STEP(k)                                                                                                  \
    const int ix##k = xb + dix##k;                                                                                 \
    const int cols##k = ix##k >= 0 && ix##k + 8 <= (int)width - 1;                                                 \
    {                                                                                                              \
        const float8 sx = xs + dx##k;                                                                              \
        off_x |= sx >= (float8)(-0.5009765625f) && sx <= (float8)((float)width - 0.4990234375f) ? (int8)(0)        \
                                                                                                : (int8)(-1);      \
    }
/* Frame k's source row `row` (clamped to the field) as c0_, c1_, f0_, f1_ */
#define ROW_CLAMPED(row) ((row) < 0 ? 0 : ((row) > (int)height - 1 ? (int)height - 1 : (row)))
#if FROM_CORRECTED
#define T_LOAD(k, row)                                                                                             \
    float8 c0_, c1_;                                                                                               \
    ulong f0_, f1_;                                                                                                \
    {                                                                                                              \
        const int r_ = (row);                                                                                      \
        const ulong p_ = (ulong)k * n + (ulong)ROW_CLAMPED(r_) * width;                                            \
        if (cols##k)                                                                                               \
            load_row(src + p_, cflags + p_, ix##k, &c0_, &c1_, &f0_, &f1_);                                        \
        else                                                                                                       \
            load_row_clamped(src + p_, cflags + p_, ix##k, width, &c0_, &c1_, &f0_, &f1_);                         \
    }
#else
#if HAS_DARK == 2
#define DARK_PLANE(k) (dark + (ulong)frame_of[k] * n)
#else
#define DARK_PLANE(k) dark
#endif
#define T_LOAD(k, row)                                                                                             \
    float8 c0_, c1_;                                                                                               \
    const ulong f0_ = 0, f1_ = 0; /* the flags: after the step's rows, where watch finds any */                    \
    {                                                                                                              \
        const int r_ = (row);                                                                                      \
        const ulong p_ = (ulong)ROW_CLAMPED(r_) * width;                                                           \
        __global const IN_T *o_ = src + (ulong)frame_of[k] * n + p_;                                               \
        load_row_raw(o_, DARK_PLANE(k) + p_, gain + p_, ix##k, cols##k, width, &c0_, &c1_, &watch, &watch8);       \
    }
/* Frame k's flags for output row y, each tap's where its weight is above zero, OR-ed into flags */
#define T_RAW_FLAGS(k)                                                                                             \
    {                                                                                                              \
        __global const IN_T *o_ = src + (ulong)frame_of[k] * n;                                                    \
        const int u_ = y + iy##k, l_ = y + iy##k + 1;                                                              \
        ulong u0_, u1_, l0_, l1_;                                                                                  \
        raw_flags(o_ + (ulong)ROW_CLAMPED(u_) * width, ix##k, cols##k, width, &u0_, &u1_);                         \
        raw_flags(o_ + (ulong)ROW_CLAMPED(l_) * width, ix##k, cols##k, width, &l0_, &l1_);                         \
        flags |= (u0_ & m00_##k) | (u1_ & m10_##k) | (l0_ & m01_##k) | (l1_ & m11_##k);                            \
    }
#endif
/* The upper taps of the first output row's upper source row */
#define T_INIT(k)                                                                                                  \
    {                                                                                                              \
        T_LOAD(k, top + iy##k)                                                                                     \
        h##k = row_tap(c0_, w00_##k) + row_tap(c1_, w10_##k);                                                      \
        hf##k = (f0_ & m00_##k) | (f1_ & m10_##k);                                                                 \
    }
/* Output row y's sample of frame k: the upper source row's two taps (held from the row above, whose lower source
 * row it was) plus the lower row's two, summed in linear_warp_translate's order; then the lower row's upper taps
 * held for the next output row. Rows are clamped to the field as warp_sample clamps them (the held row is then the
 * same one again). on_y: whether every frame's sample point is within the field in y (warp_sample's test). */
#define T_ROW(k)                                                                                                   \
    float8 t##k;                                                                                                   \
    {                                                                                                              \
        T_LOAD(k, y + iy##k + 1)                                                                                   \
        if (mode##k == 1) {                                                                                        \
            t##k = h##k + c0_ * w01_##k + c1_ * w11_##k;                                                           \
            flags |= hf##k | f0_ | f1_;                                                                            \
            h##k = c0_ * w00_##k + c1_ * w10_##k;                                                                  \
            hf##k = f0_ | f1_;                                                                                     \
        } else if (mode##k == 2) {                                                                                 \
            t##k = h##k;                                                                                           \
            flags |= hf##k;                                                                                        \
            h##k = c0_;                                                                                            \
            hf##k = f0_;                                                                                           \
        } else {                                                                                                   \
            t##k = h##k + row_tap(c0_, w01_##k) + row_tap(c1_, w11_##k);                                           \
            flags |= hf##k | (f0_ & m01_##k) | (f1_ & m11_##k);                                                    \
            h##k = row_tap(c0_, w00_##k) + row_tap(c1_, w10_##k);                                                  \
            hf##k = (f0_ & m00_##k) | (f1_ & m10_##k);                                                             \
        }                                                                                                          \
        const float sy_ = (float)y + dy##k;                                                                        \
        on_y &= sy_ >= -0.5009765625f && sy_ <= (float)height - 0.4990234375f;                                     \
    }

/* Output row top + r at the step's 8 pixels: i its first pixel, t0 .. t<K-1> its samples (t0 NaN where a sample
 * point is off the field: an output with one is NaN, and t0 is in every output), flags its mask */
#define T_OUTPUT_ROW(r)                                                                                            \
    const int y = top + (r);                                                                                       \
    const ulong i = (ulong)y * width + xb;                                                                         \
    ulong flags = 0;                                                                                               \
    int on_y = 1;                                                                                                  \
    REP_(K, T_ROW)                                                                                                 \
    t0 = (off_x | (int8)(on_y ? 0 : -1)) ? (float8)(NAN) : t0;                                                     \
    flags |= on_y ? outside_x : 0x0404040404040404UL

/* The warp of translations. A work-item takes STRIP rows of 8 XSTEPS pixels and goes along them 8 pixels at a
 * time, down the STRIP rows at each step (unrolled): each frame's source row read once (8 pixels as a vector and
 * the ninth), the row below's upper taps held for the next output row, every load of the unrolled rows going 32
 * bytes a step. FROM_CORRECTED = 1: from the corrected planes and their flags (src, cflags: warp_correct's, the
 * second pass); 0: from the raw frames, dark and gain, corrected as they are read (one pass), the flags found
 * where a step's samples may raise some. A sample point off the field makes the pixel's outputs NaN
 * and its mask bit 4, as warp_pixel. Arguments: src (the corrected planes, K x n float32, or the input frames),
 * frame_of, dark, gain (as warp_correct's, unused from the corrected planes), cflags (K x n, unused from the
 * frames), A (B x K), motion (K x 6, translations), out0 .. out3 (the groups'), mask (n), width, height. The
 * work-items over (x / (8 XSTEPS), y / STRIP). */
#if FROM_CORRECTED
#define SRC_T float
#else
#define SRC_T IN_T
#endif
__kernel void linear_warp_translate(__global const SRC_T *restrict src, __constant const uint *restrict frame_of,
                                    __global const float *restrict dark, __global const float *restrict gain,
                                    __global const uchar *restrict cflags, __constant const float *restrict A,
                                    __constant const float *restrict motion, OUT_PARAMS,
                                    __global uchar *restrict mask, const uint width, const uint height)
{
    const int x0 = 8 * XSTEPS * get_global_id(0), top = STRIP * get_global_id(1);
    if (x0 >= (int)width || top >= (int)height) return;
    const ulong n = (ulong)width * height;
    const int rows = (int)height - top < STRIP ? (int)height - top : STRIP;
    REP_(K, T_SETUP)
    for (int s = 0; s < XSTEPS; ++s) {
        const int xb = x0 + 8 * s;
        if (xb >= (int)width) break;
        const uint count = width - (uint)xb < 8u ? width - (uint)xb : 8u; /* the pixels of the 8 within the row */
        const float8 xs = convert_float8((int8)(xb) + (int8)(0, 1, 2, 3, 4, 5, 6, 7));
        int8 off_x = (int8)(0); /* lanes whose sample point of some frame is off the field in x */
        REP_(K, T_STEP)
        const ulong outside_x = as_ulong(convert_uchar8(off_x & (int8)(MASK_OUTSIDE)));
#if !FROM_CORRECTED
        float8 watch = (float8)(0.0f);
        float watch8 = 0.0f;
#endif
        REP_(K, T_INIT)
        /* the rows unrolled, so that each row's loads are instructions of their own, each going 32 bytes a step:
         * streams the CPU's prefetchers follow. The rows of a last strip past the field are computed (from rows
         * clamped to the field) and not stored. */
#pragma unroll
        for (int r = 0; r < STRIP; ++r) {
            T_OUTPUT_ROW(r);
            if (r >= rows) continue;
            if (count == 8) {
                T_WRITE_GROUPS(i);
                STORE8(uchar, as_uchar8(flags), mask + i);
                continue;
            }
            /* the row's last pixels, fewer than 8: lane by lane */
            for (uint b = 0; b < B; ++b) {
                float8 acc;
                DOT8(acc, b);
                float v[8];
                vstore8(acc, 0, v);
                for (uint j = 0; j < count; ++j) put_output(OUT_ARGS, b, i + j, n, v[j]);
            }
            uchar m[8];
            vstore8(as_uchar8(flags), 0, m);
            for (uint j = 0; j < count; ++j) mask[i + j] = m[j];
        }
#if !FROM_CORRECTED
        /* where some sample the step read is saturated or not finite (rare), each row's flags from the raw frames,
         * tap by tap as from the flag planes, OR-ed into its mask */
#if IS_FLOAT_IN
        const int8 suspect = watch != watch; /* NaN: a non-finite or saturated sample */
        int flagged = watch8 != watch8;
#elif defined(SAT_LEVEL)
        const int8 suspect = watch >= (float8)(SAT_LEVEL);
        int flagged = watch8 >= SAT_LEVEL;
#else
        const int8 suspect = (int8)(0);
        int flagged = 0;
#endif
        flagged |= suspect.s0 | suspect.s1 | suspect.s2 | suspect.s3 | suspect.s4 | suspect.s5 | suspect.s6
                   | suspect.s7;
        if (flagged) {
            for (int r = 0; r < rows; ++r) {
                const int y = top + r;
                const ulong i = (ulong)y * width + xb;
                ulong flags = 0;
                REP_(K, T_RAW_FLAGS)
                uchar m[8];
                vstore8(as_uchar8(flags), 0, m);
                for (uint j = 0; j < count; ++j) mask[i + j] |= m[j];
            }
        }
#endif
    }
}
#endif
