/* specgpu gradient images: the spectrum-independent image a frame is registered and checked on
 * (specgpu.pipeline.moving.gradient_image), on the device.
 *
 * f = (o - dark) * gain of a raw frame o (a NaN gain reads 0: a pixel with no response), its Sobel gradient
 * magnitude sqrt(gy^2 + gx^2) with the border mirrored by one pixel (the edge repeated: scipy.ndimage.sobel's
 * "reflect"), over the frame's mean of f:
 *   gradient_sobel  the magnitude of each frame (unscaled, K planes of H x W), each work-item 8 columns of a strip
 *                   of GROWS rows (each corrected row read once for the three output rows that use it), and its
 *                   compensated sum of f (Kahan, per lane, then over the lanes): (sum, carry) per work-item
 *   gradient_scale  per frame the mean from those sums (compensated again: the float64 mean to float32 rounding),
 *                   scale = 1 / mean where the mean is positive, else 1
 *   gradient_apply  the magnitudes multiplied by their frame's scale, in place (the consistency check instead
 *                   multiplies its samples: kernels/consistency.cl, SCALED)
 * The arithmetic is gradient_image's, in its order: (2 c + l) + r along each axis, differences, squares summed.
 * Macros (kernels/common.h): IN_T, HAS_DARK (0, 1: one (H, W) dark frame, 2: one per frame), HAS_GAIN; GROWS.
 */
#include "common.h"

#ifndef GROWS
#define GROWS 32
#endif

/* columns x0 - 1 .. x0 + 8 of row r of a plane p: the 8 from x0 (centre) and the columns either side (edges),
 * columns outside the field clamped to it (when not inside) */
#define ROW_OF(T, p, r, centre, edges)                                                                          \
    do {                                                                                                       \
        __global const T *row_ = (p) + (ulong)(r) * width;                                                     \
        if (inside) {                                                                                          \
            centre = convert_float8(LOAD8(T, row_ + x0));                                                     \
            edges = (float2)(row_[x0 - 1], row_[x0 + 8]);                                                     \
        } else {                                                                                               \
            const int8 at_ = clamp((int8)(x0) + lane, (int8)(0), (int8)((int)width - 1));                        \
            centre = (float8)(row_[at_.s0], row_[at_.s1], row_[at_.s2], row_[at_.s3], row_[at_.s4], row_[at_.s5],     \
                              row_[at_.s6], row_[at_.s7]);                                                       \
            edges = (float2)(row_[max(x0 - 1, 0)], row_[min(x0 + 8, (int)width - 1)]);                         \
        }                                                                                                      \
    } while (0)

/* a row of 8 corrected values c and the columns either side e as the 8 columns left of, at and right of x0 */
ALWAYS_INLINE void shifted3(float8 c, float2 e, float8 *left, float8 *centre, float8 *right)
{
    *left = (float8)(e.s0, c.s0, c.s1, c.s2, c.s3, c.s4, c.s5, c.s6);
    *centre = c;
    *right = (float8)(c.s1, c.s2, c.s3, c.s4, c.s5, c.s6, c.s7, e.s1);
}

/* The dark frame and the flat field (a NaN gain as 0) at row r around x0, for frame k (the dark frame of frame k
 * with HAS_DARK 2); 0 and 1 where absent. */
#define CALIBRATION(k, r)                                                                                      \
    do {                                                                                                       \
        if (HAS_DARK) ROW_OF(float, dark + (HAS_DARK == 2 ? (ulong)(k) * n : 0), r, d, de);                    \
        if (HAS_GAIN) {                                                                                        \
            ROW_OF(float, gain, r, g, ge);                                                                     \
            g = isnan(g) ? (float8)(0.0f) : g;                                                                 \
            ge = isnan(ge) ? (float2)(0.0f) : ge;                                                              \
        }                                                                                                      \
    } while (0)

/* frame k's row r corrected, as left, centre and right (d, de, g, ge: its calibration, CALIBRATION) */
#define CORRECTED(k, r, left, centre, right)                                                                   \
    do {                                                                                                       \
        float8 c_;                                                                                             \
        float2 e_;                                                                                             \
        ROW_OF(IN_T, frames + (ulong)(k) * n, r, c_, e_);                                                      \
        if (HAS_DARK) {                                                                                        \
            c_ = c_ - d;                                                                                       \
            e_ = e_ - de;                                                                                      \
        }                                                                                                      \
        if (HAS_GAIN) {                                                                                        \
            c_ = c_ * g;                                                                                       \
            e_ = e_ * ge;                                                                                      \
        }                                                                                                      \
        shifted3(c_, e_, &(left), &(centre), &(right));                                                        \
    } while (0)

/* Each work-item: 8 columns of a strip of GROWS rows of every frame, the dark frame and flat field read once a row
 * for all K (one per frame with HAS_DARK 2); per frame the corrected rows above and at y held (left, centre,
 * right) while row y + 1 is read. */
__kernel void gradient_sobel(__global const IN_T *restrict frames, __global const float *restrict dark,
                             __global const float *restrict gain, __global float *restrict out,
                             __global float2 *restrict sums, const uint width, const uint height)
{
    const int x0 = 8 * get_global_id(0), y0 = GROWS * get_global_id(1);
    const ulong part = get_global_id(1) * get_global_size(0) + get_global_id(0);
    const ulong parts = get_global_size(0) * get_global_size(1);
    if (x0 >= (int)width || y0 >= (int)height) {  /* a work-item of the padded range */
        for (int k = 0; k < K; ++k) sums[k * parts + part] = (float2)(0.0f);
        return;
    }
    const int y1 = min(y0 + GROWS, (int)height), last = (int)height - 1;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 valid = x0 + lane < (int8)((int)width);
    const bool inside = x0 >= 1 && x0 + 9 <= (int)width;  /* columns x0 - 1 .. x0 + 8 all in the field */
    const ulong n = (ulong)width * height;
    float8 d = (float8)(0.0f), g = (float8)(1.0f);
    float2 de = (float2)(0.0f), ge = (float2)(1.0f);
    float8 held[K][6];  /* per frame the corrected rows above and at y: left, centre, right */
    float8 sum[K], carry[K];
    for (int k = 0; k < K; ++k) {
        sum[k] = carry[k] = (float8)(0.0f);
        CALIBRATION(k, max(y0 - 1, 0));
        CORRECTED(k, max(y0 - 1, 0), held[k][0], held[k][1], held[k][2]);
        CALIBRATION(k, y0);
        CORRECTED(k, y0, held[k][3], held[k][4], held[k][5]);
    }
    for (int y = y0; y < y1; ++y) {
        const int r = min(y + 1, last);
        if (HAS_DARK != 2) CALIBRATION(0, r);
        for (int k = 0; k < K; ++k) {
            if (HAS_DARK == 2) CALIBRATION(k, r);
            float8 dl, dc, dr;
            CORRECTED(k, r, dl, dc, dr);
            const float8 ul = held[k][0], uc = held[k][1], ur = held[k][2];
            const float8 cl = held[k][3], cc = held[k][4], cr = held[k][5];
            /* (2 c + l) + r along each axis, as gradient_image */
            const float8 gy = ((2.0f * dc + dl) + dr) - ((2.0f * uc + ul) + ur);
            const float8 gx = ((2.0f * cr + ur) + dr) - ((2.0f * cl + ul) + dl);
            const float8 m = sqrt(gy * gy + gx * gx);
            __global float *o = out + (ulong)k * n + (ulong)y * width + x0;
            if (x0 + 8 <= (int)width) {
                STORE8(float, m, o);
            } else {
                const float t[8] = {m.s0, m.s1, m.s2, m.s3, m.s4, m.s5, m.s6, m.s7};
                for (int j = 0; j < (int)width - x0; ++j) o[j] = t[j];
            }
            /* Kahan: the carry holds what the sum lost */
            const float8 x = (valid ? cc : (float8)(0.0f)) - carry[k], s = sum[k] + x;
            carry[k] = (s - sum[k]) - x;
            sum[k] = s;
            held[k][0] = cl;
            held[k][1] = cc;
            held[k][2] = cr;
            held[k][3] = dl;
            held[k][4] = dc;
            held[k][5] = dr;
        }
    }
    for (int k = 0; k < K; ++k) {
        float total = 0.0f, lost = 0.0f;
        const float8 sk = sum[k], ck = -carry[k];
        const float lanes[16] = {sk.s0, sk.s1, sk.s2, sk.s3, sk.s4, sk.s5, sk.s6, sk.s7,
                                 ck.s0, ck.s1, ck.s2, ck.s3, ck.s4, ck.s5, ck.s6, ck.s7};
        for (int j = 0; j < 16; ++j) {  /* Neumaier */
            const float t = total + lanes[j];
            lost += fabs(total) >= fabs(lanes[j]) ? (total - t) + lanes[j] : (lanes[j] - t) + total;
            total = t;
        }
        sums[k * parts + part] = (float2)(total, lost);
    }
}

/* frame gid(0)'s scale from the parts parts (sum, carry) of its sum: 1 / mean, or 1 where the mean is not positive */
__kernel void gradient_scale(__global const float2 *restrict sums, const uint parts, __global float *restrict scale,
                             const uint width, const uint height)
{
    const uint k = get_global_id(0);
    float total = 0.0f, lost = 0.0f;
    for (uint i = 0; i < parts; ++i) {
        const float2 p = sums[(ulong)k * parts + i];
        for (int j = 0; j < 2; ++j) {
            const float x = j ? p.y : p.x, t = total + x;
            lost += fabs(total) >= fabs(x) ? (total - t) + x : (x - t) + total;
            total = t;
        }
    }
    const float mean = (total + lost) / (float)((ulong)width * height);
    scale[k] = mean > 0.0f ? 1.0f / mean : 1.0f;
}

/* the magnitudes of frame gid(1) times its scale, 8 at a time */
__kernel void gradient_apply(__global float *restrict images, __global const float *restrict scale,
                             const uint width, const uint height)
{
    const ulong n = (ulong)width * height, i = 8 * (ulong)get_global_id(0);
    if (i >= n) return;
    const uint k = get_global_id(1);
    __global float *p = images + (ulong)k * n + i;
    const float s = scale[k];
    if (i + 8 <= n) {
        STORE8(float, LOAD8(float, p) * s, p);
    } else {
        for (uint j = 0; j < n - i; ++j) p[j] *= s;
    }
}
