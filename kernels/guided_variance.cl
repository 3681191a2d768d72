/* specgpu guided-filter variance family: the variance of a guided filter's output (kernels/guided.cl's filter,
 * windows clipped to the image) when its input carries independent per-pixel noise and its guide carries noise of
 * its own.
 *
 * With the guide g fixed the filter is linear, q_i = sum_j W_ij p_j, with
 *     W_ij = 1/m_i sum_{windows k holding i and j} 1/n_k (1 + alpha_k (g_i - mu_k) (g_j - mu_k)),
 * mu_k, alpha_k = 1 / (var_k g + eps) and n_k the window's mean, regularised inverse variance and pixel count, m_i
 * the count of windows holding i. Independent noise of variance v_j leaves sum_j W_ij^2 v_j (all (4R + 1)^2
 * neighbours). The guide's own noise passes where the output follows the guide: q_i = abar_i g_i + bbar_i with
 * bbar_i the box means of p - a g, so it adds abar_d abar_e var g_i (1 - 2 b_ii + sum_j b_ij^2) to cov(q_d, q_e),
 * abar the mean over the windows holding i of each slope image's a_k = cov_k(g, s) alpha_k and b the weights of the
 * box means (W of a flat guide). Per channel c:
 *
 *     out = sum_j W_ij^2 own'_j + sum_t w_t abar_{d_t} abar_{e_t} gvar_i (1 - 2 b_ii + sum_j b_ij^2)
 *           + total_i - own'_i + offset_c
 *
 * (its square root with SQRT; NaN where that is NaN) with the terms (d_t, e_t, w_t) of channel c listed in
 * terms[starts[c] .. starts[c + 1]). own' = own where own and total are finite and the pixel's mask holds none of
 * SKIPPED_BITS, else 0. Two passes:
 *
 *   gv_stats   per window centre: 1 / n, mu, alpha, and a of each of the D slope images, and the pixel's
 *              own' of each channel                                                   -> stats (3 + D + C planes)
 *   gv_apply   per eight pixels of a row: W_i. from its windows' prefix and suffix sums (O(R^2) per pixel),
 *              abar, then the C channels                                                    -> out (H, W, C)
 */

#ifndef R
#define R 2
#endif
#ifndef C
#define C 1
#endif
#ifndef D
#define D 1
#endif
#ifndef SQRT
#define SQRT 0
#endif
#ifndef SKIPPED_BITS
#define SKIPPED_BITS 0
#endif
#define NK (2 * R + 1)
#define NW (4 * R + 1)
#define NS (3 + D)
#define INLINE inline __attribute__((always_inline))

INLINE float own_part(__global const float *own, __global const float *total, __global const uchar *mask,
                      const size_t e, const size_t p)
{
    const float o = own[e];
#if SKIPPED_BITS
    const bool ok = isfinite(o) && isfinite(total[e]) && ((mask[p] & (uchar)(SKIPPED_BITS)) == 0);
#else
    const bool ok = isfinite(o) && isfinite(total[e]); /* no mask: the argument is never read */
#endif
    return ok ? o : 0.0f;
}

__kernel void gv_stats(__global const float *g, __global const float *slopes, __global const float *own,
                       __global const float *total, __global const uchar *mask, __global float *stats, const int H,
                       const int W, const float eps)
{
    const size_t p = get_global_id(0);
    if (p >= (size_t)H * W)
        return;
    const int x = (int)(p % W), y = (int)(p / W);
    const float gc = g[p]; /* sums about the centre's value: less float32 cancellation */
    float n = 0.0f, sg = 0.0f, sgg = 0.0f;
    float ss[D], ssg[D];
    for (int d = 0; d < D; ++d)
        ss[d] = ssg[d] = 0.0f;
    for (int dy = -R; dy <= R; ++dy) {
        const int jy = y + dy;
        if (jy < 0 || jy >= H)
            continue;
        for (int dx = -R; dx <= R; ++dx) {
            const int jx = x + dx;
            if (jx < 0 || jx >= W)
                continue;
            const size_t j = (size_t)jy * W + jx;
            const float gv = g[j] - gc;
            n += 1.0f;
            sg += gv;
            sgg = gv * gv + sgg;
            for (int d = 0; d < D; ++d) {
                const float s = slopes[j * D + d];
                ss[d] += s;
                ssg[d] = s * gv + ssg[d];
            }
        }
    }
    const float inv = 1.0f / n, mean = sg * inv, var = sgg * inv - mean * mean;
    const float alpha = 1.0f / ((var > 0.0f ? var : 0.0f) + eps);
    const size_t plane = (size_t)H * W; /* one plane per quantity: the apply pass reads VX pixels' at once */
    stats[p] = inv;
    stats[plane + p] = gc + mean;
    stats[2 * plane + p] = alpha;
    for (int d = 0; d < D; ++d)
        stats[(3 + d) * plane + p] = (ssg[d] * inv - ss[d] * inv * mean) * alpha;
    /* the pixel's own' of each channel, in planes: what the weights take of it, read once and tested once */
    for (int c = 0; c < C; ++c)
        stats[(NS + c) * plane + p] = own_part(own, total, mask, p * C + c, p);
}

/* Pixel i's weights W_ij through its windows' sums. With u_k = mu_k - g_i and dg_j = g_j - g_i,
 *     m_i W_ij = sum_k q0_k + q2_k - dg_j q1_k,   q0 = 1/n, q1 = q0 alpha u, q2 = q1 u,
 * the sums over the windows k holding both i and j: those of i's (2R + 1)^2 whose centres lie within R of j, a
 * rectangle of them (a window outside the image counts as zeros). Every such rectangle starts at the first row
 * (column) of i's windows or ends at the last: a prefix or a suffix. So the window quantities summed along each row
 * into prefixes and suffixes (X: (2R + 1) x (4R + 1) each), then those down each column, give all (4R + 1)^2
 * rectangles' sums in O(R^2), by additions only. u and dg are taken about g_i, as the direct sums are (no
 * cancellation of the guide's level).
 *
 * Written once for a type T of VX pixels along a row, through the macros below: a float8 of eight neighbouring
 * pixels inside the image by 2R or more (every window whole: no bound checked; PoCL vectorises no loop across
 * work-items that holds loops, so the lanes are explicit), and a float for one pixel anywhere (the borders). */
#define VX 8
#define APPLY_BODY(T, LOAD, INSIDE)                                                                             \
    const T gi = LOAD(g, p);                                                                                           \
    T X0[NK][NW], X1[NK][NW], X2[NK][NW];                                                                              \
    T abar[D];                                                                                                         \
    for (int d = 0; d < D; ++d)                                                                                        \
        abar[d] = (T)0.0f;                                                                                             \
    float m = 0.0f;                                                                                                    \
    for (int a = 0; a < NK; ++a) {                                                                                     \
        const int ky = y + a - R;                                                                                      \
        T q0[NK], q1[NK], q2[NK];                                                                                      \
        for (int b = 0; b < NK; ++b) {                                                                                 \
            const int kx = x + b - R;                                                                                  \
            q0[b] = q1[b] = q2[b] = (T)0.0f;                                                                           \
            if (!(INSIDE) && (ky < 0 || ky >= H || kx < 0 || kx >= W))                                                 \
                continue;                                                                                              \
            const size_t k = (size_t)ky * W + kx;                                                                      \
            const T inv = LOAD(stats, k), u = LOAD(stats + plane, k) - gi;                                             \
            q0[b] = inv;                                                                                               \
            q1[b] = inv * LOAD(stats + 2 * plane, k) * u;                                                              \
            q2[b] = q1[b] * u;                                                                                         \
            m += 1.0f;                                                                                                 \
            for (int d = 0; d < D; ++d)                                                                                \
                abar[d] += LOAD(stats + (3 + d) * plane, k);                                                           \
        }                                                                                                              \
        T s0 = (T)0.0f, s1 = (T)0.0f, s2 = (T)0.0f;                                                                    \
        for (int b = 0; b < NK; ++b) { /* prefixes: windows [0, b] of the row, offset ox = b - 2R */                   \
            s0 += q0[b];                                                                                               \
            s1 += q1[b];                                                                                               \
            s2 += q2[b];                                                                                               \
            X0[a][b] = s0;                                                                                             \
            X1[a][b] = s1;                                                                                             \
            X2[a][b] = s2;                                                                                             \
        }                                                                                                              \
        s0 = s1 = s2 = (T)0.0f;                                                                                        \
        for (int b = NK - 1; b >= 1; --b) { /* suffixes: windows [b, 2R], offset ox = b */                             \
            s0 += q0[b];                                                                                               \
            s1 += q1[b];                                                                                               \
            s2 += q2[b];                                                                                               \
            X0[a][b + 2 * R] = s0;                                                                                     \
            X1[a][b + 2 * R] = s1;                                                                                     \
            X2[a][b + 2 * R] = s2;                                                                                     \
        }                                                                                                              \
    }                                                                                                                  \
    const float scale = 1.0f / m;                                                                                      \
    T acc[C];                                                                                                          \
    for (int c = 0; c < C; ++c)                                                                                        \
        acc[c] = (T)0.0f;                                                                                              \
    T bb = (T)0.0f, bii = (T)0.0f;                                                                                     \
    for (int col = 0; col < NW; ++col) {                                                                               \
        const int jx = x + col - 2 * R;                                                                                \
        const bool xin = (INSIDE) || (jx >= 0 && jx < W);                                                              \
        T s0 = (T)0.0f, s1 = (T)0.0f, s2 = (T)0.0f;                                                                    \
        /* rows of windows [0, a] (offset oy = a - 2R, a = 0 .. 2R), then [a, 2R] (oy = a, a = 2R .. 1) */             \
        for (int t = 0; t < 2 * NK - 1; ++t) {                                                                         \
            const int a = t < NK ? t : NW - t;                                                                         \
            if (t == NK)                                                                                               \
                s0 = s1 = s2 = (T)0.0f;                                                                                \
            s0 += X0[a][col];                                                                                          \
            s1 += X1[a][col];                                                                                          \
            s2 += X2[a][col];                                                                                          \
            const int oy = t < NK ? a - 2 * R : a;                                                                     \
            const int jy = y + oy;                                                                                     \
            if (!xin || (!(INSIDE) && (jy < 0 || jy >= H)))                                                            \
                continue;                                                                                              \
            bb = s0 * s0 + bb;                                                                                         \
            if (oy == 0 && col == 2 * R)                                                                               \
                bii = s0;                                                                                              \
            const size_t j = (size_t)jy * W + jx;                                                                      \
            const T wt = ((s0 + s2) - (LOAD(g, j) - gi) * s1) * scale;                                                 \
            const T w2 = wt * wt;                                                                                      \
            for (int c = 0; c < C; ++c)                                                                                \
                acc[c] = LOAD(stats + (NS + c) * plane, j) * w2 + acc[c];                                              \
        }                                                                                                              \
    }                                                                                                                  \
    /* the guide's noise at i less its box means' (b_ij = sum q0 / m: the weights of a flat guide):                    \
     * 1 - 2 b_ii + sum_j b_ij^2 */                                                                                    \
    const T gv = LOAD(gvar, p) * scale * scale * (1.0f - 2.0f * bii * scale + bb * scale * scale);                    \
    for (int c = 0; c < C; ++c) {                                                                                      \
        T pass = (T)0.0f;                                                                                              \
        for (int t = starts[c]; t < starts[c + 1]; ++t)                                                                \
            pass = terms[3 * t + 2] * abar[(int)terms[3 * t]] * abar[(int)terms[3 * t + 1]] + pass;                   \
        STORE(out, p, c, acc[c] + pass * gv, OWN_PART(p, c));                                                          \
    }

/* out = acc + pass + (total - own') + offset (its square root with SQRT; NaN where that is NaN) */
INLINE void store1(__global float *out, __global const float *own, __global const float *total,
                   __global const uchar *mask, __constant float *offset, const size_t p, const int c, const float v)
{
    const size_t e = p * C + c;
    const float r = v + (total[e] - own_part(own, total, mask, e, p)) + offset[c];
#if SQRT
    out[e] = isnan(r) ? r : sqrt(r > 0.0f ? r : 0.0f);
#else
    out[e] = r;
#endif
}

#define LOAD1(base, i) ((base)[i])
#define STORE(out, p, c, v, unused) store1(out, own, total, mask, offset, p, c, v)

/* One pixel, anywhere in the image. */
INLINE void apply_one(__global const float *g, __global const float *stats, __global const float *own,
                      __global const float *total, __global const uchar *mask, __constant float *terms,
                      __constant int *starts, __global const float *gvar, __constant float *offset,
                      __global float *out, const int H, const int W, const int x, const int y)
{
    const size_t p = (size_t)y * W + x, plane = (size_t)H * W;
    APPLY_BODY(float, LOAD1, 0)
}

#undef STORE
#define LOAD8(base, i) vload8(0, (base) + (i))
#define STORE(out, p, c, v, unused)                                                                                    \
    {                                                                                                                  \
        const float8 lanes = (v);                                                                                      \
        store1(out, own, total, mask, offset, (p) + 0, c, lanes.s0);                                                   \
        store1(out, own, total, mask, offset, (p) + 1, c, lanes.s1);                                                   \
        store1(out, own, total, mask, offset, (p) + 2, c, lanes.s2);                                                   \
        store1(out, own, total, mask, offset, (p) + 3, c, lanes.s3);                                                   \
        store1(out, own, total, mask, offset, (p) + 4, c, lanes.s4);                                                   \
        store1(out, own, total, mask, offset, (p) + 5, c, lanes.s5);                                                   \
        store1(out, own, total, mask, offset, (p) + 6, c, lanes.s6);                                                   \
        store1(out, own, total, mask, offset, (p) + 7, c, lanes.s7);                                                   \
    }

/* Eight pixels x .. x + 7 of row y, all inside the image by 2R or more. */
INLINE void apply_eight(__global const float *g, __global const float *stats, __global const float *own,
                        __global const float *total, __global const uchar *mask, __constant float *terms,
                        __constant int *starts, __global const float *gvar, __constant float *offset,
                        __global float *out, const int H, const int W, const int x, const int y)
{
    const size_t p = (size_t)y * W + x, plane = (size_t)H * W;
    APPLY_BODY(float8, LOAD8, 1)
}

/* Work-item: VX pixels of one row, (ceil(W / VX) per row, row by row). */
__kernel void gv_apply(__global const float *g, __global const float *stats, __global const float *own,
                       __global const float *total, __global const uchar *mask, __constant float *terms,
                       __constant int *starts, __global const float *gvar, __constant float *offset,
                       __global float *out, const int H, const int W)
{
    const int tiles = (W + VX - 1) / VX;
    const size_t id = get_global_id(0);
    if (id >= (size_t)H * tiles)
        return;
    const int y = (int)(id / tiles), x0 = (int)(id % tiles) * VX;
    if (y >= 2 * R && y < H - 2 * R && x0 >= 2 * R && x0 + VX <= W - 2 * R) {
        apply_eight(g, stats, own, total, mask, terms, starts, gvar, offset, out, H, W, x0, y);
        return;
    }
    for (int x = x0; x < x0 + VX && x < W; ++x)
        apply_one(g, stats, own, total, mask, terms, starts, gvar, offset, out, H, W, x, y);
}
