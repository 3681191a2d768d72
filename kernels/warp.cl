/* specgpu motion-compensated linear kernel: y(x) = A s(x) with s_k(x) the corrected frame k sampled at x + d_k.
 *
 * A moving scene lands on different pixels in different frames of a sequence. Output pixel x is where a scene
 * point is at the sequence's reference time; frame k saw that point at M_k (x, y, 1): a 2 x 3 affine map per frame
 * (a translation d_k is (1, 0, dx_k; 0, 1, dy_k)), in pixels. The sample is the bilinear interpolation, at x + d_k, of the corrected frame
 * c_k(p) = (o_k(p) - dark(p)) * gain(p): dark level and flat field belong to the sensor pixel p, so they are
 * applied before interpolation (for d = 0 this is exactly A (o - dark) * gain of linear.cl).
 *
 * A pixel whose sample point of any frame lies outside the field has no measurement: its outputs are NaN and its
 * mask has bit 4 (MASK_OUTSIDE). The field is the sensor's footprint, [-1/2, W-1/2] x [-1/2, H-1/2] in pixel
 * centres: a point within half a pixel of an edge pixel's centre was seen by that pixel, and takes its value (the
 * interpolation's taps clamped to the field), so a frame displaced by a fraction of a pixel loses no border.
 * Bit 1: a frame pixel used (non-zero weight) is at SAT_LEVEL; bit 2: a non-finite float input. One work-item per
 * output pixel, planar output (B, N) float32.
 *
 * Macros (as common.h): K, B, IN_T, HAS_DARK (0 / 1 per pixel / 2 per frame), HAS_GAIN, SAT_LEVEL, IS_FLOAT_IN;
 * FLOW = 1: a displacement per pixel and frame instead (dense motion, flow (K, 2, N): frame k saw pixel i at
 * (x + flow[k][0][i], y + flow[k][1][i])), the affine maps unused.
 * Arguments: frames (K, H, W), A (B x K, constant), motion (K x 6: the rows of M_k, constant), flow, dark, gain, out (B x N),
 * mask (N), width, height.
 * linear_warp_translate: the same result where every M_k is a translation, 8 pixels of a row per work-item.
 * OUT_INTERLEAVED = 1: out (N x B) instead (the host's (H, W, B) with no transposition after).
 */
#include "common.h"

#ifndef B
#define B 1
#endif
#define MASK_OUTSIDE 4

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

/* The arguments of both kernels (the host sets the same ones for either) */
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

#if K <= 128 && !FLOW
/* Every frame's motion a translation (the affine maps' linear parts the identity): every pixel of frame k has the
 * same bilinear weights, so a work-item takes 8 consecutive pixels of a row and reads each frame's two source rows
 * as vectors of 8 (vload8) and the ninth pixel after them, the weights scalars, the corrections (dark, gain)
 * vectors: what PoCL runs as vector code. A work-item goes down STRIP rows: the lower source row of one output row
 * is the upper one of the next, so each source row is read and corrected once, not twice (and each pixel once, not
 * twice, along the row: the right neighbours are the row shifted by one lane). The arithmetic is linear_warp's,
 * tap by tap (the same products, summed in the same order), with each weight from the fraction of d_k rather than
 * of x + d_k: the same bits where x + d_k is exact in float32, as it is for a d_k of a few binary digits. Where
 * some lane's sample point or neighbour is off the field, or the row ends within the 8, that row's pixels go
 * through linear_warp's code. Work-items over (x / 8, y / STRIP). */
#ifndef STRIP
#define STRIP 8
#endif

/* Frame k's source row at p, corrected: c0 its 8 pixels, c1 the 8 pixels one to the right (the ninth read as a
 * scalar), f0 / f1 their saturated / non-finite flags (applied where the tap's weight is above zero). */
inline void corrected_row(__global const IN_T *restrict plane, __global const float *restrict dark,
                          __global const float *restrict gain, uint k, ulong n, ulong p, float8 *c0, float8 *c1,
                          int8 *f0, int8 *f1)
{
    int8 fv = (int8)(0);
    int f8 = 0;
#if IS_FLOAT_IN
    const float8 v = vload8(0, plane + p);
    const float v8 = plane[p + 8];
    fv |= isfinite(v) ? (int8)(0) : (int8)(MASK_NONFINITE);
    f8 |= isfinite(v8) ? 0 : MASK_NONFINITE;
#else
    const float8 v = convert_float8(vload8(0, plane + p));
    const float v8 = (float)plane[p + 8];
#endif
#ifdef SAT_LEVEL
    fv |= v >= (float8)(SAT_LEVEL) ? (int8)(MASK_SATURATED) : (int8)(0);
    f8 |= v8 >= SAT_LEVEL ? MASK_SATURATED : 0;
#endif
    float8 c = v;
    float c8 = v8;
#if HAS_DARK == 1
    c -= vload8(0, dark + p);
    c8 -= dark[p + 8];
#elif HAS_DARK == 2
    c -= vload8(0, dark + (ulong)k * n + p);
    c8 -= dark[(ulong)k * n + p + 8];
#endif
#if HAS_GAIN
    c *= vload8(0, gain + p);
    c8 *= gain[p + 8];
#endif
    *c0 = c;
    *c1 = (float8)(c.s123, c.s4567, c8);
    *f0 = fv;
    *f1 = (int8)(fv.s123, fv.s4567, f8);
}

/* A tap's term as corrected() makes it: zero where its weight is, never a NaN or saturated neighbour let in */
inline float8 tap8(float8 c, int8 f, float w, int8 *flags)
{
    if (w <= 0.0f) return (float8)(0.0f);
    *flags |= f;
    return c * w;
}

__kernel void linear_warp_translate(WARP_KERNEL_ARGS)
{
    const int x0 = 8 * get_global_id(0), top = STRIP * get_global_id(1);
    if (x0 >= (int)width || top >= (int)height) return;
    const ulong n = (ulong)width * height;
    const int rows = min(STRIP, (int)height - top);
    int columns = x0 + 8 <= (int)width; /* the 8 pixels and each frame's 9 source columns within the field */
    for (uint k = 0; k < K; ++k) {
        const int ix = x0 + (int)floor(motion[6 * k + 2]);
        columns &= ix >= 0 && ix + 8 <= (int)width - 1;
    }
    /* each frame's source rows so far (the upper row of the next output row), valid while `held` */
    float8 up0[K], up1[K];
    int8 upf0[K], upf1[K];
    int held = 0;
    for (int r = 0; r < rows; ++r) {
        const int y = top + r;
        const ulong i = (ulong)y * width + x0;
        int interior = columns;
        for (uint k = 0; k < K; ++k) {
            const int iy = y + (int)floor(motion[6 * k + 5]);
            interior &= iy >= 0 && iy + 1 <= (int)height - 1;
        }
        if (!interior) {
            for (int j = 0; j < 8 && x0 + j < (int)width; ++j)
                warp_pixel(frames, A, motion, flow, dark, gain, out, mask, width, height, i + j);
            held = 0;
            continue;
        }
        int8 flags = (int8)(0);
#define T_SAMPLE(k) float8 t##k;                                                                                   \
        {                                                                                                          \
            const float dx = motion[6 * k + 2], dy = motion[6 * k + 5];                                            \
            const float fdx = floor(dx), fdy = floor(dy);                                                          \
            const float fx = dx - fdx, fy = dy - fdy;                                                              \
            const ulong p = (ulong)(y + (int)fdy) * width + (ulong)(x0 + (int)fdx);                                \
            __global const IN_T *plane = frames + (ulong)k * n;                                                    \
            if (!held) corrected_row(plane, dark, gain, k, n, p, &up0[k], &up1[k], &upf0[k], &upf1[k]);            \
            float8 d0, d1;                                                                                         \
            int8 df0, df1;                                                                                         \
            corrected_row(plane, dark, gain, k, n, p + width, &d0, &d1, &df0, &df1);                               \
            t##k = tap8(up0[k], upf0[k], (1.0f - fx) * (1.0f - fy), &flags)                                        \
                 + tap8(up1[k], upf1[k], fx * (1.0f - fy), &flags)                                                 \
                 + tap8(d0, df0, (1.0f - fx) * fy, &flags)                                                         \
                 + tap8(d1, df1, fx * fy, &flags);                                                                 \
            up0[k] = d0; up1[k] = d1; upf0[k] = df0; upf1[k] = df1;                                                \
        }
#define T_FMA(k) acc = row[k] * t##k + acc;
        REP_(K, T_SAMPLE)
        held = 1;
        for (uint b = 0; b < B; ++b) {
            __constant const float *row = A + b * K;
            float8 acc = (float8)(0.0f);
            REP_(K, T_FMA)
#if OUT_INTERLEAVED  /* the 8 pixels' B outputs are 8 B consecutive floats */
            __global float *o = out + i * B + b;
            o[0] = acc.s0; o[B] = acc.s1; o[2 * B] = acc.s2; o[3 * B] = acc.s3;
            o[4 * B] = acc.s4; o[5 * B] = acc.s5; o[6 * B] = acc.s6; o[7 * B] = acc.s7;
#else
            vstore8(acc, 0, out + (ulong)b * n + i);
#endif
        }
        vstore8(convert_uchar8(flags), 0, mask + i);
    }
}
#endif
