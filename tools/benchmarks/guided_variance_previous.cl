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
 * SKIPPED_BITS, else 0. Two passes, one work-item per pixel:
 *
 *   gv_stats   per window centre: 1 / n, mu, alpha, and a of each of the D slope images   -> stats (H, W, 3 + D)
 *   gv_apply   per pixel: W_i. in a private array of (4R + 1)^2, abar, then the C channels  -> out (H, W, C)
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

__kernel void gv_stats(__global const float *g, __global const float *slopes, __global float *stats, const int H,
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
    __global float *st = stats + p * NS;
    st[0] = inv;
    st[1] = gc + mean;
    st[2] = alpha;
    for (int d = 0; d < D; ++d)
        st[3 + d] = (ssg[d] * inv - ss[d] * inv * mean) * alpha;
}

__kernel void gv_apply(__global const float *g, __global const float *stats, __global const float *own,
                       __global const float *total, __global const uchar *mask, __constant float *terms,
                       __constant int *starts, __global const float *gvar, __constant float *offset,
                       __global float *out, const int H, const int W)
{
    const size_t p = get_global_id(0);
    if (p >= (size_t)H * W)
        return;
    const int x = (int)(p % W), y = (int)(p / W);
    const float gi = g[p];
    float w[NW * NW], b[NW * NW];
    float abar[D];
    for (int o = 0; o < NW * NW; ++o)
        w[o] = b[o] = 0.0f;
    for (int d = 0; d < D; ++d)
        abar[d] = 0.0f;
    float m = 0.0f;
    for (int dy = -R; dy <= R; ++dy) {
        const int ky = y + dy;
        if (ky < 0 || ky >= H)
            continue;
        for (int dx = -R; dx <= R; ++dx) {
            const int kx = x + dx;
            if (kx < 0 || kx >= W)
                continue;
            __global const float *st = stats + ((size_t)ky * W + kx) * NS;
            const float inv = st[0], mu = st[1], c = st[2] * (gi - mu) * inv;
            m += 1.0f;
            for (int d = 0; d < D; ++d)
                abar[d] += st[3 + d];
            for (int ey = -R; ey <= R; ++ey) {
                const int jy = ky + ey;
                if (jy < 0 || jy >= H)
                    continue;
                for (int ex = -R; ex <= R; ++ex) {
                    const int jx = kx + ex;
                    if (jx < 0 || jx >= W)
                        continue;
                    const int o = (dy + ey + 2 * R) * NW + (dx + ex + 2 * R);
                    w[o] = c * (g[(size_t)jy * W + jx] - mu) + inv + w[o];
                    b[o] += inv;
                }
            }
        }
    }
    /* the guide's noise at i less its box means' (b: the weights of a flat guide): 1 - 2 b_ii + sum_j b_ij^2 */
    const float scale = 1.0f / m;
    float bb = 0.0f;
    for (int o = 0; o < NW * NW; ++o)
        bb = b[o] * b[o] + bb;
    const float gv = gvar[p] * scale * scale * (1.0f - 2.0f * b[2 * R * NW + 2 * R] * scale + bb * scale * scale);
    /* each neighbour's weight squared once, its C channels read together (contiguous) */
    float acc[C];
    for (int c = 0; c < C; ++c)
        acc[c] = 0.0f;
    for (int oy = -2 * R; oy <= 2 * R; ++oy) {
        const int jy = y + oy;
        if (jy < 0 || jy >= H)
            continue;
        for (int ox = -2 * R; ox <= 2 * R; ++ox) {
            const int jx = x + ox;
            if (jx < 0 || jx >= W)
                continue;
            const float wt = w[(oy + 2 * R) * NW + (ox + 2 * R)] * scale, w2 = wt * wt;
            const size_t j = (size_t)jy * W + jx;
#if SKIPPED_BITS
            if ((mask[j] & (uchar)(SKIPPED_BITS)) != 0)
                continue;
#endif
            __global const float *oj = own + j * C, *tj = total + j * C;
            for (int c = 0; c < C; ++c) {
                const float o = oj[c];
                acc[c] = (isfinite(o) && isfinite(tj[c]) ? o : 0.0f) * w2 + acc[c];
            }
        }
    }
    for (int c = 0; c < C; ++c) {
        float pass = 0.0f;
        for (int t = starts[c]; t < starts[c + 1]; ++t)
            pass = terms[3 * t + 2] * abar[(int)terms[3 * t]] * abar[(int)terms[3 * t + 1]] + pass;
        const size_t e = p * C + c;
        const float v = acc[c] + pass * gv + (total[e] - own_part(own, total, mask, e, p)) + offset[c];
#if SQRT
        out[e] = isnan(v) ? v : sqrt(v > 0.0f ? v : 0.0f);
#else
        out[e] = v;
#endif
    }
}
