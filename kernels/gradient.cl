/* specgpu gradient images: the spectrum-independent image a frame is registered and checked on
 * (specgpu.pipeline.moving.gradient_image), on the device.
 *
 * f = (o - dark) * gain of a raw frame o (a NaN gain reads 0: a pixel with no response), its Sobel gradient
 * magnitude sqrt(gy^2 + gx^2) with the border mirrored by one pixel (the edge repeated: scipy.ndimage.sobel's
 * "reflect"), over the frame's mean of f:
 *   gradient_sobel  the magnitude of each frame (unscaled, K planes of H x W); a work-item takes 16 columns of a
 *                   strip of GROWS rows (each corrected row read once for the three output rows that use it), and its
 *                   compensated sum of f (Kahan, per lane, then over the lanes): (sum, carry) per work-item
 *   gradient_scale  per frame the mean from those sums (compensated again: the float64 mean to float32 rounding),
 *                   scale = 1 / mean where the mean is positive, else 1
 *   gradient_apply  the magnitudes multiplied by their frame's scale, in place (the consistency check instead
 *                   multiplies its samples: kernels/consistency.cl, SCALED)
 * The arithmetic is gradient_image's, in its order: (2 c + l) + r along each axis, differences, squares summed.
 * 16 columns a work-item (float16): on PoCL with AVX-512 a quarter faster than 8.
 * Macros (kernels/common.h): IN_T, HAS_DARK (0, 1: one (H, W) dark frame, 2: one per frame), HAS_GAIN; GROWS.
 */
#include "common.h"

#ifndef GROWS
#define GROWS 32
#endif

/* columns x0 - 1 .. x0 + 16 of row r of a plane p: the 16 from x0 (centre) and the columns either side (edges),
 * columns outside the field clamped to it (when not inside) */
#define ROW_OF(T, p, r, centre, edges)                                                                          \
    do {                                                                                                       \
        __global const T *row_ = (p) + (ulong)(r) * width;                                                     \
        if (inside) {                                                                                          \
            centre = convert_float16(LOAD16(T, row_ + x0));                                                     \
            edges = (float2)(row_[x0 - 1], row_[x0 + 16]);                                                     \
        } else {                                                                                               \
            const int16 at_ = clamp((int16)(x0) + lane, (int16)(0), (int16)((int)width - 1));                        \
            centre = (float16)(row_[at_.s0], row_[at_.s1], row_[at_.s2], row_[at_.s3], row_[at_.s4], row_[at_.s5],   \
                               row_[at_.s6], row_[at_.s7], row_[at_.s8], row_[at_.s9], row_[at_.sa], row_[at_.sb],   \
                               row_[at_.sc], row_[at_.sd], row_[at_.se], row_[at_.sf]);                             \
            edges = (float2)(row_[max(x0 - 1, 0)], row_[min(x0 + 16, (int)width - 1)]);                         \
        }                                                                                                      \
    } while (0)

/* a row of 16 corrected values c and the columns either side e as the 16 columns left of, at and right of x0 */
ALWAYS_INLINE void shifted3(float16 c, float2 e, float16 *left, float16 *centre, float16 *right)
{
    *left = (float16)(e.s0, c.s0, c.s1, c.s2, c.s3, c.s4, c.s5, c.s6, c.s7, c.s8, c.s9, c.sa, c.sb, c.sc, c.sd,
                      c.se);
    *centre = c;
    *right = (float16)(c.s1, c.s2, c.s3, c.s4, c.s5, c.s6, c.s7, c.s8, c.s9, c.sa, c.sb, c.sc, c.sd, c.se, c.sf,
                       e.s1);
}

/* The dark frame and the flat field (a NaN gain as 0) at row r around x0, for frame k (the dark frame of frame k
 * with HAS_DARK 2); 0 and 1 where absent. */
#define CALIBRATION(k, r)                                                                                      \
    do {                                                                                                       \
        if (HAS_DARK) ROW_OF(float, dark + (HAS_DARK == 2 ? (ulong)(k) * n : 0), r, d, de);                    \
        if (HAS_GAIN) {                                                                                        \
            ROW_OF(float, gain, r, g, ge);                                                                     \
            g = isnan(g) ? (float16)(0.0f) : g;                                                                 \
            ge = isnan(ge) ? (float2)(0.0f) : ge;                                                              \
        }                                                                                                      \
    } while (0)

/* frame k's row r corrected, as left, centre and right (d, de, g, ge: its calibration, CALIBRATION) */
#define CORRECTED(k, r, left, centre, right)                                                                   \
    do {                                                                                                       \
        float16 c_;                                                                                             \
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

/* Each work-item: 16 columns of a strip of GROWS rows of every frame, the dark frame and flat field read once a row
 * for all K (one per frame with HAS_DARK 2); per frame the corrected rows above and at y held (left, centre,
 * right) while row y + 1 is read. */
__kernel void gradient_sobel(__global const IN_T *restrict frames, __global const float *restrict dark,
                             __global const float *restrict gain, __global float *restrict out,
                             __global float2 *restrict sums, const uint width, const uint height)
{
    const int x0 = 16 * get_global_id(0), y0 = GROWS * get_global_id(1);
    const ulong part = get_global_id(1) * get_global_size(0) + get_global_id(0);
    const ulong parts = get_global_size(0) * get_global_size(1);
    if (x0 >= (int)width || y0 >= (int)height) {  /* a work-item of the padded range */
        for (int k = 0; k < K; ++k) sums[k * parts + part] = (float2)(0.0f);
        return;
    }
    const int y1 = min(y0 + GROWS, (int)height), last = (int)height - 1;
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const int16 valid = x0 + lane < (int16)((int)width);
    const bool inside = x0 >= 1 && x0 + 17 <= (int)width;  /* columns x0 - 1 .. x0 + 16 all in the field */
    const ulong n = (ulong)width * height;
    float16 d = (float16)(0.0f), g = (float16)(1.0f);
    float2 de = (float2)(0.0f), ge = (float2)(1.0f);
    float16 held[K][6];  /* per frame the corrected rows above and at y: left, centre, right */
    float16 sum[K], carry[K];
    for (int k = 0; k < K; ++k) {
        sum[k] = carry[k] = (float16)(0.0f);
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
            float16 dl, dc, dr;
            CORRECTED(k, r, dl, dc, dr);
            const float16 ul = held[k][0], uc = held[k][1], ur = held[k][2];
            const float16 cl = held[k][3], cc = held[k][4], cr = held[k][5];
            /* (2 c + l) + r along each axis, as gradient_image */
            const float16 gy = ((2.0f * dc + dl) + dr) - ((2.0f * uc + ul) + ur);
            const float16 gx = ((2.0f * cr + ur) + dr) - ((2.0f * cl + ul) + dl);
            const float16 m = sqrt(gy * gy + gx * gx);
            __global float *o = out + (ulong)k * n + (ulong)y * width + x0;
            if (x0 + 16 <= (int)width) {
                STORE16(float, m, o);
            } else {
                float t[16];
                vstore16(m, 0, t);
                for (int j = 0; j < (int)width - x0; ++j) o[j] = t[j];
            }
            /* Kahan: the carry holds what the sum lost */
            const float16 x = (valid ? cc : (float16)(0.0f)) - carry[k], s = sum[k] + x;
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
        const float16 sk = sum[k], ck = -carry[k];
        float lanes[32];
        vstore16(sk, 0, lanes);
        vstore16(ck, 1, lanes);
        for (int j = 0; j < 32; ++j) {  /* Neumaier */
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
