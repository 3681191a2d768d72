/* specgpu consistency check of a motion-compensated sequence: do the frames' gradient images agree once each is
 * sampled where the motion says that frame saw each pixel?
 *
 * Four passes; each work-item covers 8 consecutive pixels of a row (float8: the width PoCL vectorises these loops to).
 * Rows are stored STRIDE floats apart (the width rounded up to 8; the lanes beyond the width hold copies of the
 * last column's values and are not read back); the aligned images have HALF more columns each side (and up to a
 * whole number of vectors).
 *   consistency_align  each frame's gradient image g_k sampled bilinearly at M_k (x, y, 1), the coordinates
 *                      clamped to the field (scipy.ndimage.map_coordinates, order=1, mode="nearest"), and the
 *                      median of the K samples (the mean of the middle two for even K, as numpy.median):
 *                      aligned (K + 1) planes of height x (STRIDE + 2 HALF), plane K the median r; column
 *                      c holds x = clamp(c - HALF), so that the row sums read WINDOW samples with no clamp
 *   consistency_rows   sums over the WINDOW pixels of the row around x of a_k, a_k^2, a_k r, and of r, r^2:
 *                      rows (3 K + 2) planes
 *   consistency_cols   the same sums over the WINDOW rows around y, clamped (together the WINDOW x WINDOW box of
 *                      scipy.ndimage.uniform_filter, mode="nearest"), running down strips of ROWS rows, and from
 *                      the means the variance of r (vr), per frame its variance va_k and normalised
 *                      cross-correlation with r, (m(a r) - m(a) m(r)) / sqrt(max(va vr, 1e-30)):
 *                      maps (2 K + 2) planes = va_k, ncc_k, vr, m(r)
 *   consistency_worst  worst = min over k of ncc_k where va_k > own_k (a frame with structure of its own), 1
 *                      elsewhere; textured = vr > level
 * Macros: K, WINDOW (odd), STRIDE; TRANSLATE = 1: every map is a translation (rows read as vectors); FLOW = 1: a
 * displacement per pixel and frame instead of the maps (flow (K, 2, H, W): frame k saw pixel (x, y) at
 * (x + flow[k][0][y][x], y + flow[k][1][y][x])), read at the lane's clamped column.
 */

#ifndef K
#define K 1
#endif
#ifndef WINDOW
#define WINDOW 9
#endif
#define HALF (WINDOW / 2)
#ifndef STRIDE
#define STRIDE 8
#endif
#ifndef TRANSLATE
#define TRANSLATE 0
#endif
#ifndef FLOW
#define FLOW 0
#endif
#define PADDED ((STRIDE + 2 * HALF + 7) / 8 * 8) /* a whole number of vectors */
#ifndef ROWS
#define ROWS 16
#endif

/* frame k's gradient image at the lanes' points (sx, sy), bilinear, coordinates clamped to the field */
inline float8 sample8(__global const float *restrict g, float8 sx, float8 sy, uint width, uint height)
{
    const float8 cx = clamp(sx, 0.0f, (float)(width - 1)), cy = clamp(sy, 0.0f, (float)(height - 1));
    /* integer min and clamp with vector bounds: Oclgrind 21.10 evaluates their vector-by-scalar forms wrongly */
    const int8 last_x = (int8)((int)width - 1), last_y = (int8)((int)height - 1);
    const int8 x0 = min(convert_int8_rtz(cx), last_x), y0 = min(convert_int8_rtz(cy), last_y);
    const int8 x1 = min(x0 + 1, last_x), y1 = min(y0 + 1, last_y);
    const float8 fx = cx - convert_float8(x0), fy = cy - convert_float8(y0);
    const int8 a = y0 * (int)width + x0, b = y0 * (int)width + x1, c = y1 * (int)width + x0, d = y1 * (int)width + x1;
    const float8 ga = (float8)(g[a.s0], g[a.s1], g[a.s2], g[a.s3], g[a.s4], g[a.s5], g[a.s6], g[a.s7]);
    const float8 gb = (float8)(g[b.s0], g[b.s1], g[b.s2], g[b.s3], g[b.s4], g[b.s5], g[b.s6], g[b.s7]);
    const float8 gc = (float8)(g[c.s0], g[c.s1], g[c.s2], g[c.s3], g[c.s4], g[c.s5], g[c.s6], g[c.s7]);
    const float8 gd = (float8)(g[d.s0], g[d.s1], g[d.s2], g[d.s3], g[d.s4], g[d.s5], g[d.s6], g[d.s7]);
    const float8 top = ga + fx * (gb - ga), bottom = gc + fx * (gd - gc);
    return top + fy * (bottom - top);
}

__kernel void consistency_align(__global const float *restrict grads, __constant const float *restrict motion,
                                __global const float *restrict flow, __global float *restrict aligned,
                                const uint width, const uint height)
{
    const int c0 = 8 * get_global_id(0), y = get_global_id(1);
    if (c0 >= PADDED || y >= (int)height) return;
    const ulong n = (ulong)width * height, plane = (ulong)PADDED * height, o = (ulong)y * PADDED + c0;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 last_x = (int8)((int)width - 1);
    const float8 x = convert_float8(clamp(c0 - HALF + lane, (int8)(0), last_x));
    const int first = c0 - HALF;  /* x of lane 0 before clamping */
    float8 s[K];
    for (uint k = 0; k < K; ++k) {
        __constant const float *m = motion + 6 * k;
        __global const float *g = grads + (ulong)k * n;
#if FLOW
        {
            const int8 xi = clamp(first + lane, (int8)(0), last_x);
            const int8 i = (int8)(y * (int)width) + xi;
            __global const float *fx = flow + (ulong)(2 * k) * n, *fy = fx + n;
            const float8 dx = (float8)(fx[i.s0], fx[i.s1], fx[i.s2], fx[i.s3], fx[i.s4], fx[i.s5], fx[i.s6], fx[i.s7]);
            const float8 dy = (float8)(fy[i.s0], fy[i.s1], fy[i.s2], fy[i.s3], fy[i.s4], fy[i.s5], fy[i.s6], fy[i.s7]);
            s[k] = sample8(g, x + dx, (float8)((float)y) + dy, width, height);
        }
#elif TRANSLATE
        /* every lane the same fraction; whole rows read as vectors where no lane's samples are clamped */
        const float sx0 = (float)first + m[2], sy = (float)y + m[5];
        const int ix = (int)floor(sx0), iy = (int)floor(sy);
        if (first >= 0 && first + 7 <= (int)width - 1 && ix >= 0 && ix + 8 <= (int)width - 1 && iy >= 0
            && iy + 1 <= (int)height - 1) {
            const float fx = sx0 - (float)ix, fy = sy - (float)iy;
            __global const float *r0 = g + (ulong)iy * width + ix, *r1 = r0 + width;
            const float8 a = vload8(0, r0), b = vload8(0, r0 + 1), c = vload8(0, r1), d = vload8(0, r1 + 1);
            const float8 top = a + fx * (b - a), bottom = c + fx * (d - c);
            s[k] = top + fy * (bottom - top);
        } else {
            s[k] = sample8(g, x + m[2], (float8)((float)y + m[5]), width, height);
        }
#else
        const float8 yf = (float8)((float)y);
        s[k] = sample8(g, m[0] * x + (m[1] * yf + m[2]), m[3] * x + (m[4] * yf + m[5]), width, height);
#endif
        vstore8(s[k], 0, aligned + (ulong)k * plane + o);
    }
    /* the median by ranks (ties broken by index): no data-dependent branch */
    float8 lo = (float8)(0.0f), hi = (float8)(0.0f);
    for (uint a = 0; a < K; ++a) {
        int8 rank = (int8)(0);
        for (uint b = 0; b < K; ++b)
            rank -= (b < a) ? (s[b] <= s[a]) : (s[b] < s[a]);  /* a true lane of a vector comparison is -1 */
        lo = (rank == (int8)((K - 1) / 2)) ? s[a] : lo;
        hi = (rank == (int8)(K / 2)) ? s[a] : hi;
    }
    vstore8((K % 2) ? lo : 0.5f * (lo + hi), 0, aligned + (ulong)K * plane + o);
}

#if WINDOW == 9
/* sum of the 9 values from each lane on, of the 16 in a (0-7) and b (8-15), by pairwise sums and swizzles:
 * straight-line vector code (9 loads in a loop ran five times slower on PoCL) */
inline float8 box9(float8 a, float8 b)
{
    const float8 s2l = a + (float8)(a.s123, a.s4567, b.s0);                  /* in[j] + in[j + 1], j = 0..7 */
    const float8 s2u = b + (float8)(b.s123, b.s4567, b.s7);                  /* j = 8..14 */
    const float8 s4l = s2l + (float8)(s2l.s23, s2l.s4567, s2u.s01);          /* in[j .. j + 3], j = 0..7 */
    const float8 s4u = s2u + (float8)(s2u.s23, s2u.s4567, s2u.s67);          /* j = 8..12 */
    return s4l + (float8)(s4l.s4567, s4u.s0123) + b;                          /* in[j .. j + 8] */
}
#endif

__kernel void consistency_rows(__global const float *restrict aligned, __global float *restrict rows,
                               const uint width, const uint height)
{
    const int x0 = 8 * get_global_id(0), y = get_global_id(1);
    if (x0 >= STRIDE || y >= (int)height) return;
    const ulong plane = (ulong)STRIDE * height, o = (ulong)y * STRIDE + x0;
    const ulong aplane = (ulong)PADDED * height;
    __global const float *ref = aligned + (ulong)K * aplane + (ulong)y * PADDED + x0;  /* column x0 - HALF */
#if WINDOW == 9
    const float8 ra = vload8(0, ref), rb = vload8(1, ref);
    vstore8(box9(ra, rb), 0, rows + (ulong)(3 * K) * plane + o);
    vstore8(box9(ra * ra, rb * rb), 0, rows + (ulong)(3 * K + 1) * plane + o);
    for (uint k = 0; k < K; ++k) {
        __global const float *a = aligned + (ulong)k * aplane + (ulong)y * PADDED + x0;
        const float8 aa = vload8(0, a), ab = vload8(1, a);
        vstore8(box9(aa, ab), 0, rows + (ulong)(3 * k) * plane + o);
        vstore8(box9(aa * aa, ab * ab), 0, rows + (ulong)(3 * k + 1) * plane + o);
        vstore8(box9(aa * ra, ab * rb), 0, rows + (ulong)(3 * k + 2) * plane + o);
    }
#else
    float8 sr = (float8)(0.0f), srr = (float8)(0.0f);
    for (int t = 0; t < WINDOW; ++t) {
        const float8 r = vload8(0, ref + t);
        sr += r;
        srr = r * r + srr;
    }
    vstore8(sr, 0, rows + (ulong)(3 * K) * plane + o);
    vstore8(srr, 0, rows + (ulong)(3 * K + 1) * plane + o);
    for (uint k = 0; k < K; ++k) {
        __global const float *a = aligned + (ulong)k * aplane + (ulong)y * PADDED + x0;
        float8 sa = (float8)(0.0f), saa = (float8)(0.0f), sar = (float8)(0.0f);
        for (int t = 0; t < WINDOW; ++t) {
            const float8 v = vload8(0, a + t);
            sa += v;
            saa = v * v + saa;
            sar = v * vload8(0, ref + t) + sar;
        }
        vstore8(sa, 0, rows + (ulong)(3 * k) * plane + o);
        vstore8(saa, 0, rows + (ulong)(3 * k + 1) * plane + o);
        vstore8(sar, 0, rows + (ulong)(3 * k + 2) * plane + o);
    }
#endif
}

/* sum of a rows plane over the WINDOW rows around y (clamped), at 8 columns from x0 */
inline float8 column_sum(__global const float *restrict p, int y, uint height)
{
    float8 s = (float8)(0.0f);
    for (int t = -HALF; t <= HALF; ++t)
        s += vload8(0, p + (ulong)clamp(y + t, 0, (int)height - 1) * STRIDE);
    return s;
}

/* the window moved down one row to y: the row entering added, the one leaving taken off (clamped rows, so the
 * window holds the same multiset of rows as column_sum's) */
inline float8 column_step(float8 s, __global const float *restrict p, int y, uint height)
{
    return s + vload8(0, p + (ulong)clamp(y + HALF, 0, (int)height - 1) * STRIDE)
             - vload8(0, p + (ulong)clamp(y - 1 - HALF, 0, (int)height - 1) * STRIDE);
}

/* each work-item a strip of ROWS rows of 8 columns, the column sums running down it */
__kernel void consistency_cols(__global const float *restrict rows, __global float *restrict maps,
                               const uint width, const uint height)
{
    const int x0 = 8 * get_global_id(0), y0 = ROWS * get_global_id(1);
    if (x0 >= STRIDE || y0 >= (int)height) return;
    const int y1 = min(y0 + ROWS, (int)height);
    const ulong plane = (ulong)STRIDE * height;
    const float inv = 1.0f / (float)(WINDOW * WINDOW);
    __global const float *pr = rows + (ulong)(3 * K) * plane + x0, *prr = pr + plane;
    __global float *out_vr = maps + (ulong)(2 * K) * plane + x0, *out_mr = out_vr + plane;
    float8 sr = column_sum(pr, y0, height), srr = column_sum(prr, y0, height);
    for (int y = y0; y < y1; ++y) {
        if (y > y0) {
            sr = column_step(sr, pr, y, height);
            srr = column_step(srr, prr, y, height);
        }
        const float8 mr = sr * inv;
        vstore8(max(srr * inv - mr * mr, 0.0f), 0, out_vr + (ulong)y * STRIDE);
        vstore8(mr, 0, out_mr + (ulong)y * STRIDE);
    }
    for (uint k = 0; k < K; ++k) {
        __global const float *pa = rows + (ulong)(3 * k) * plane + x0, *paa = pa + plane, *par = paa + plane;
        __global float *out_va = maps + (ulong)k * plane + x0, *out_ncc = maps + (ulong)(K + k) * plane + x0;
        float8 sa = column_sum(pa, y0, height), saa = column_sum(paa, y0, height);
        float8 sar = column_sum(par, y0, height);
        for (int y = y0; y < y1; ++y) {
            if (y > y0) {
                sa = column_step(sa, pa, y, height);
                saa = column_step(saa, paa, y, height);
                sar = column_step(sar, par, y, height);
            }
            const ulong o = (ulong)y * STRIDE;
            const float8 mr = vload8(0, out_mr + o), vr = vload8(0, out_vr + o);
            const float8 ma = sa * inv;
            const float8 va = max(saa * inv - ma * ma, 0.0f);
            vstore8(va, 0, out_va + o);
            vstore8((sar * inv - ma * mr) / sqrt(max(va * vr, 1e-30f)), 0, out_ncc + o);
        }
    }
}

__kernel void consistency_worst(__global const float *restrict maps, __constant const float *restrict own,
                                const float level, __global float *restrict worst,
                                __global uchar *restrict textured, const uint width, const uint height)
{
    const int x0 = 8 * get_global_id(0), y = get_global_id(1);
    if (x0 >= STRIDE || y >= (int)height) return;
    const ulong plane = (ulong)STRIDE * height, o = (ulong)y * STRIDE + x0;
    float8 w = (float8)(1.0f);
    for (uint k = 0; k < K; ++k) {
        const float8 ncc = vload8(0, maps + (ulong)(K + k) * plane + o);
        w = min(w, (vload8(0, maps + (ulong)k * plane + o) > (float8)(own[k])) ? ncc : (float8)(1.0f));
    }
    vstore8(w, 0, worst + o);
    vstore8(convert_uchar8(-(vload8(0, maps + (ulong)(2 * K) * plane + o) > (float8)(level))), 0, textured + o);
}

