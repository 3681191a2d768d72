/* specgpu guided filter family (He, Sun and Tang 2010): edge-aware smoothing of a C-channel image p by a
 * one-channel guide g, built from box sums taken as running sums (O(1) per pixel whatever the radius R).
 *
 * Images are (H, W, C) float32, channels last, flattened; the guide (H, W). Windows are clipped to the image and
 * a box mean divides by the count of pixels inside. Per pixel the filter sums, over the window about it, the
 * products x = [p (C), g' p (C), g', g'^2]; from them the guide's mean and variance (once, shared by the C
 * channels) and each channel's linear model a = cov(g', p) / (var g' + eps), b = mean p - a mean g'; then sums the
 * models [a (C), b (C)] over the window again: q = (sum a g' + sum b) / count.
 *
 * g' = g - g[0]: the filter is unchanged by a constant added to its guide, and statistics taken about a value of
 * the image lose less to float32 cancellation than about zero. A sum is a running sum: the value that leaves a
 * window is the one that entered it, read again, so a sum never drifts by recomputation. A non-finite value makes
 * a running sum non-finite for good; while a sum is not finite it is summed again directly over its window (O(R)),
 * so NaN reaches exactly the outputs whose windows hold it ((4R + 1)^2 pixels about it), as with direct sums.
 *
 * Two forms, chosen by the host per kernel variant (build macro STRIPS):
 *
 *   STRIPS = 1 ("cpu"): gf_strips, the whole filter in one launch. Each work-item walks a strip of output rows
 *     across the full width, every loop over the contiguous channels of one pixel (vectorised by the compiler);
 *     its column sums and its last 2R + 1 rows of models stay in its own part of a scratch buffer (a few hundred
 *     KiB, cache resident), so the image is read and the output written once and no full-size intermediate exists.
 *
 *   STRIPS = 0 ("gpu"): three passes over full-size intermediates, one pixel (row) per work-item, so that
 *     neighbouring work-items read neighbouring floats:
 *       gf_columns_in   sums of x down columns                                           -> V (H, W, NV)
 *       gf_rows         sums of V along rows, the models, sums of the models along rows  -> S (H, W, NAB)
 *       gf_columns_out  sums of S down columns, q                                        -> out (H, W, C)
 */

#ifndef C
#define C 1
#endif
#ifndef STRIPS
#define STRIPS 0
#endif
#define NV (2 * C + 2) /* [p, g' p, g', g'^2] */
#define NAB (2 * C)    /* [a, b] */
/* PoCL calls min(), max() and fmax() out of line, and may leave a helper out of line: all written inline here
 * (the helpers' pointers are not restrict: inlined, those make scope declarations Oclgrind does not know). Loops
 * over a pixel's channels are unrolled: PoCL leaves them rolled, their arrays on the stack, otherwise. */
#define INLINE inline __attribute__((always_inline))
#define IMIN(a, b) ((a) < (b) ? (a) : (b))
#define IMAX(a, b) ((a) > (b) ? (a) : (b))
#define FPOS(v) ((v) > 0.0f ? (v) : 0.0f) /* fmax(v, 0); NaN gives 0, as fmax */
#define EACH(c, n) _Pragma("unroll") for (int c = 0; c < (n); ++c)

/* The guide's offset: its first value (0 if that is not finite). */
INLINE float guide_offset(__global const float *g)
{
    const float g0 = g[0];
    return isfinite(g0) ? g0 : 0.0f;
}

/* Whether all N values are finite: the sum of v * 0 is 0 while every value is finite and NaN once one is not,
 * taken in eight independent partial sums that stay in one vector register (an integer test per value made a
 * chain of mask operations, and an unrolled loop of constant length is what keeps the values in registers). */
#define FINITE_OF(name, N, SPACE)                                                                                     \
    INLINE bool name(SPACE const float *v)                                                                             \
    {                                                                                                                  \
        float z[8] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};                                                 \
        EACH(c, N) z[c & 7] += v[c] * 0.0f;                                                                            \
        return ((z[0] + z[1]) + (z[2] + z[3])) + ((z[4] + z[5]) + (z[6] + z[7])) == 0.0f;                              \
    }
FINITE_OF(finite_v, NV, )
FINITE_OF(finite_ab, NAB, )
FINITE_OF(finite_ab_global, NAB, __global)

/* s += sign * the products x of row k at pixel x (s private). */
INLINE void add_products(__global const float *p, __global const float *g, const int W, const int k, const int x,
                         const float g0, const float sign, float *s)
{
    const size_t q = (size_t)k * W + x;
    const float gv = g[q] - g0, sg = sign * gv;
    __global const float *pq = p + q * C;
    float pv[C];
    EACH(c, C) pv[c] = pq[c];
    EACH(c, C)
    {
        s[c] += sign * pv[c];
        s[C + c] += sg * pv[c];
    }
    s[2 * C] += sg;
    s[2 * C + 1] += sg * gv;
}

/* The window's linear models [a (C), b (C)] from its sums of the products over n pixels. */
INLINE void coefficients(const float *sum, const float n, const float eps, float *ab)
{
    const float rn = 1.0f / n;
    const float mg = sum[2 * C] * rn;
    const float vg = FPOS(sum[2 * C + 1] * rn - mg * mg);
    const float inv = 1.0f / (vg + eps); /* the guide's statistics, once for every channel */
    EACH(c, C)
    {
        const float mp = sum[c] * rn;
        const float a = (sum[C + c] * rn - mg * mp) * inv;
        ab[c] = a;
        ab[C + c] = mp - a * mg;
    }
}

/* The count of a window's pixels along one axis: [i - R, i + R] clipped to [0, n). */
INLINE float span(const int i, const int R, const int n)
{
    return (float)(IMIN(i + R, n - 1) - IMAX(i - R, 0) + 1);
}

#if STRIPS

/* The column sums of pixel x moved down to lead row yl (the products of row yl + R in, those of row yl - R - 1
 * out; summed again over rows [yl - R, yl + R] when not finite): s in the scratch buffer, t a private copy. */
INLINE void column_down(__global const float *p, __global const float *g, const int H, const int W, const int R,
                        const int yl, const int x, const float g0, __global float *s, float *t)
{
    EACH(c, NV) t[c] = s[c];
    if (yl + R < H)
        add_products(p, g, W, yl + R, x, g0, 1.0f, t);
    if (yl - R - 1 >= 0)
        add_products(p, g, W, yl - R - 1, x, g0, -1.0f, t);
    if (!finite_v(t)) {
        EACH(c, NV) t[c] = 0.0f;
        for (int k = IMAX(yl - R, 0); k <= IMIN(yl + R, H - 1); ++k)
            add_products(p, g, W, k, x, g0, 1.0f, t);
    }
    EACH(c, NV) s[c] = t[c];
}

/* Output rows [y0, y0 + SY) of work-item y0 / SY; the range is (ceil(H / SY)). The lead row yl runs R rows ahead
 * of the output row y = yl - R. Per lead row, over the work-item's scratch (colV (W, NV), colAB (W, NAB), a ring
 * of L = min(2R + 1, H) rows of models (W, NAB) each):
 *   1. colV[x]: the sums of the products down column x over rows [yl - R, yl + R]
 *   2. along the row, running sums of colV over [x - R, x + R]: the window's models, stored in the ring and added
 *      to colAB[x], the sums of the models down column x over rows [y - R, y + R] (the row of models leaving the
 *      window, 2R + 1 rows up, subtracted first)
 *   3. along output row y, running sums of colAB over [x - R, x + R]: q.
 * Rows of models outside the image count as zeros (they are never stored). */
__kernel void gf_strips(__global const float *restrict p, __global const float *restrict g,
                        __global float *restrict out, __global float *restrict scratch, const int H, const int W,
                        const int R, const int SY, const int L, const float eps)
{
    const int strip = get_global_id(0), y0 = strip * SY;
    if (y0 >= H)
        return;
    const int y1 = IMIN(y0 + SY, H);
    __global float *restrict colV = scratch + (size_t)strip * W * (NV + NAB + (size_t)L * NAB);
    __global float *restrict colAB = colV + (size_t)W * NV;
    __global float *restrict ring = colAB + (size_t)W * NAB;
    const float g0 = guide_offset(g);
    const int ys = IMAX(y0 - R, 0); /* the first lead row: rows of models above it are in no window of the strip */
    /* colV: the column sums of the window of lead row ys - 1; colAB: no models yet */
    for (int x = 0; x < W; ++x) {
        float t[NV];
        EACH(c, NV) t[c] = 0.0f;
        for (int k = IMAX(ys - R - 1, 0); k <= IMIN(ys + R - 1, H - 1); ++k)
            add_products(p, g, W, k, x, g0, 1.0f, t);
        __global float *s = colV + (size_t)x * NV, *a = colAB + (size_t)x * NAB;
        EACH(c, NV) s[c] = t[c];
        EACH(c, NAB) a[c] = 0.0f;
    }
    for (int yl = ys; yl < y1 + R; ++yl) {
        const int leaving = yl - 2 * R - 1;
        if (leaving >= ys) {
            __global const float *old = ring + (size_t)((leaving - ys) % L) * W * NAB;
            for (int i = 0; i < W * NAB; ++i)
                colAB[i] -= old[i];
        }
        if (yl < H) {
            /* 1. the column sums moved down to lead row yl */
            for (int x = 0; x < W; ++x) {
                float t[NV];
                column_down(p, g, H, W, R, yl, x, g0, colV + (size_t)x * NV, t);
            }
            /* 2. the windows along the row, their models into the ring and colAB */
            const float ny = span(yl, R, H);
            __global float *slot = ring + (size_t)((yl - ys) % L) * W * NAB;
            float sum[NV];
            EACH(c, NV) sum[c] = 0.0f;
            for (int k = 0; k <= IMIN(R - 1, W - 1); ++k)
                EACH(c, NV) sum[c] += colV[(size_t)k * NV + c];
            for (int x = 0; x < W; ++x) {
                if (x + R < W)
                    EACH(c, NV) sum[c] += colV[(size_t)(x + R) * NV + c];
                if (x - R - 1 >= 0)
                    EACH(c, NV) sum[c] -= colV[(size_t)(x - R - 1) * NV + c];
                if (!finite_v(sum)) {
                    EACH(c, NV) sum[c] = 0.0f;
                    for (int k = IMAX(x - R, 0); k <= IMIN(x + R, W - 1); ++k)
                        EACH(c, NV) sum[c] += colV[(size_t)k * NV + c];
                }
                float ab[NAB], m[NAB];
                coefficients(sum, ny * span(x, R, W), eps, ab);
                __global float *o = slot + (size_t)x * NAB, *col = colAB + (size_t)x * NAB;
                EACH(c, NAB) m[c] = col[c] + ab[c];
                EACH(c, NAB) o[c] = ab[c];
                EACH(c, NAB) col[c] = m[c];
            }
        }
        /* a column of colAB not finite: summed again from the ring's rows of its window, [yl - 2R, yl] */
        for (int x = 0; x < W; ++x) {
            __global float *col = colAB + (size_t)x * NAB;
            if (finite_ab_global(col))
                continue;
            EACH(c, NAB) col[c] = 0.0f;
            for (int k = IMAX(yl - 2 * R, ys); k <= IMIN(yl, H - 1); ++k)
                EACH(c, NAB) col[c] += ring[((size_t)((k - ys) % L) * W + x) * NAB + c];
        }
        /* 3. output row y: the models' sums along the row */
        const int y = yl - R;
        if (y < y0)
            continue;
        const float ny = span(y, R, H);
        float acc[NAB];
        EACH(c, NAB) acc[c] = 0.0f;
        for (int k = 0; k <= IMIN(R - 1, W - 1); ++k)
            EACH(c, NAB) acc[c] += colAB[(size_t)k * NAB + c];
        for (int x = 0; x < W; ++x) {
            if (x + R < W)
                EACH(c, NAB) acc[c] += colAB[(size_t)(x + R) * NAB + c];
            if (x - R - 1 >= 0)
                EACH(c, NAB) acc[c] -= colAB[(size_t)(x - R - 1) * NAB + c];
            if (!finite_ab(acc)) {
                EACH(c, NAB) acc[c] = 0.0f;
                for (int k = IMAX(x - R, 0); k <= IMIN(x + R, W - 1); ++k)
                    EACH(c, NAB) acc[c] += colAB[(size_t)k * NAB + c];
            }
            const float rn = 1.0f / (ny * span(x, R, W));
            const size_t q = (size_t)y * W + x;
            const float gv = g[q] - g0;
            __global float *o = out + q * C;
            EACH(c, C) o[c] = (acc[c] * gv + acc[C + c]) * rn;
        }
    }
}

#else /* the three passes */

/* Column sums of the products over rows [y - R, y + R] (clipped), pixel x of each row of a strip of SY rows; the
 * range is (W, strips). */
__kernel void gf_columns_in(__global const float *restrict p, __global const float *restrict g,
                            __global float *restrict V, const int H, const int W, const int R, const int SY)
{
    const int x = get_global_id(0), y0 = get_global_id(1) * SY;
    if (x >= W || y0 >= H)
        return;
    const int y1 = IMIN(y0 + SY, H);
    const float g0 = guide_offset(g);
    float sum[NV];
    EACH(c, NV) sum[c] = 0.0f;
    for (int k = IMAX(y0 - R - 1, 0); k <= IMIN(y0 + R - 1, H - 1); ++k) /* the window of row y0 - 1 */
        add_products(p, g, W, k, x, g0, 1.0f, sum);
    for (int y = y0; y < y1; ++y) {
        if (y + R < H)
            add_products(p, g, W, y + R, x, g0, 1.0f, sum);
        if (y - R - 1 >= 0)
            add_products(p, g, W, y - R - 1, x, g0, -1.0f, sum);
        if (!finite_v(sum)) { /* a non-finite value entered, or left: the window summed afresh */
            EACH(c, NV) sum[c] = 0.0f;
            for (int k = IMAX(y - R, 0); k <= IMIN(y + R, H - 1); ++k)
                add_products(p, g, W, k, x, g0, 1.0f, sum);
        }
        __global float *o = V + ((size_t)y * W + x) * NV;
        EACH(c, NV) o[c] = sum[c];
    }
}

/* The lead window moved on to column xl (sums of V over [xl - R, xl + R], clipped), and its models. */
INLINE void lead_models(__global const float *row, const int W, const int R, const int xl, const float ny,
                        const float eps, float *sum, float *ab)
{
    if (xl + R < W)
        EACH(c, NV) sum[c] += row[(size_t)(xl + R) * NV + c];
    if (xl - R - 1 >= 0)
        EACH(c, NV) sum[c] -= row[(size_t)(xl - R - 1) * NV + c];
    if (!finite_v(sum)) { /* a non-finite value entered, or left: the window summed afresh */
        EACH(c, NV) sum[c] = 0.0f;
        for (int k = IMAX(xl - R, 0); k <= IMIN(xl + R, W - 1); ++k)
            EACH(c, NV) sum[c] += row[(size_t)k * NV + c];
    }
    coefficients(sum, ny * span(xl, R, W), eps, ab);
}

/* Row sums over columns [x - R, x + R] (clipped) of the models a, b of the windows centred there, one row and a
 * strip of SX columns per work-item; the range is (H, NSX strips); each work-item keeps the models it made in its
 * own ring of L = min(2R + 1, W) slots. */
__kernel void gf_rows(__global const float *restrict V, __global float *restrict ring_all, __global float *restrict S,
                      const int H, const int W, const int R, const int SX, const int NSX, const int L,
                      const float eps)
{
    const int y = get_global_id(0), strip = get_global_id(1), x0 = strip * SX;
    if (y >= H || x0 >= W)
        return;
    const int x1 = IMIN(x0 + SX, W);
    __global const float *row = V + (size_t)y * W * NV;
    __global float *outs = S + (size_t)y * W * NAB;
    const float ny = span(y, R, H);
    __global float *ring = ring_all + ((size_t)y * NSX + strip) * (size_t)L * NAB;
    float sum[NV], acc[NAB], ab[NAB];
    EACH(c, NV) sum[c] = 0.0f;
    EACH(c, NAB) acc[c] = 0.0f;
    /* the lead window of column xs - 1, then the models of [xs, x0 + R - 1] (the window of x0 - 1, clipped) */
    const int xs = IMAX(x0 - R - 1, 0);
    for (int k = IMAX(xs - R - 1, 0); k <= IMIN(xs + R - 1, W - 1); ++k)
        EACH(c, NV) sum[c] += row[(size_t)k * NV + c];
    int slot_in = 0; /* the ring slot of the next model made, (xl - xs) % L */
    for (int xl = xs; xl <= IMIN(x0 + R - 1, W - 1); ++xl) {
        lead_models(row, W, R, xl, ny, eps, sum, ab);
        __global float *slot = ring + (size_t)slot_in * NAB;
        EACH(c, NAB)
        {
            slot[c] = ab[c];
            acc[c] += ab[c];
        }
        slot_in = slot_in + 1 == L ? 0 : slot_in + 1;
    }
    int slot_out = 0; /* the ring slot of the model leaving next: the first made, xs, leaves first */
    for (int xo = x0; xo < x1; ++xo) {
        if (xo - R - 1 >= 0) { /* the model leaving, read before its slot is reused */
            __global const float *old = ring + (size_t)slot_out * NAB;
            EACH(c, NAB) acc[c] -= old[c];
            slot_out = slot_out + 1 == L ? 0 : slot_out + 1;
        }
        if (xo + R < W) { /* the model entering */
            lead_models(row, W, R, xo + R, ny, eps, sum, ab);
            __global float *slot = ring + (size_t)slot_in * NAB;
            EACH(c, NAB)
            {
                slot[c] = ab[c];
                acc[c] += ab[c];
            }
            slot_in = slot_in + 1 == L ? 0 : slot_in + 1;
        }
        if (!finite_ab(acc)) { /* the models of the window, summed afresh from the ring */
            EACH(c, NAB) acc[c] = 0.0f;
            for (int k = IMAX(xo - R, 0); k <= IMIN(xo + R, W - 1); ++k)
                EACH(c, NAB) acc[c] += ring[(size_t)((k - xs) % L) * NAB + c];
        }
        __global float *o = outs + (size_t)xo * NAB;
        EACH(c, NAB) o[c] = acc[c];
    }
}

/* q = (sum a * g' + sum b) / count, the sums of S down columns over rows [y - R, y + R] (clipped), pixel x of each
 * row of a strip of SY rows; the range is (W, strips). */
__kernel void gf_columns_out(__global const float *restrict S, __global const float *restrict g,
                             __global float *restrict out, const int H, const int W, const int R, const int SY)
{
    const int x = get_global_id(0), y0 = get_global_id(1) * SY;
    if (x >= W || y0 >= H)
        return;
    const int y1 = IMIN(y0 + SY, H);
    const float g0 = guide_offset(g);
    const float nx = span(x, R, W);
    float acc[NAB];
    EACH(c, NAB) acc[c] = 0.0f;
    for (int k = IMAX(y0 - R - 1, 0); k <= IMIN(y0 + R - 1, H - 1); ++k)
        EACH(c, NAB) acc[c] += S[((size_t)k * W + x) * NAB + c];
    for (int y = y0; y < y1; ++y) {
        if (y + R < H)
            EACH(c, NAB) acc[c] += S[((size_t)(y + R) * W + x) * NAB + c];
        if (y - R - 1 >= 0)
            EACH(c, NAB) acc[c] -= S[((size_t)(y - R - 1) * W + x) * NAB + c];
        if (!finite_ab(acc)) {
            EACH(c, NAB) acc[c] = 0.0f;
            for (int k = IMAX(y - R, 0); k <= IMIN(y + R, H - 1); ++k)
                EACH(c, NAB) acc[c] += S[((size_t)k * W + x) * NAB + c];
        }
        const float rn = 1.0f / (span(y, R, H) * nx);
        const size_t q = (size_t)y * W + x;
        const float gv = g[q] - g0;
        __global float *o = out + q * C;
        EACH(c, C) o[c] = (acc[c] * gv + acc[C + c]) * rn;
    }
}

#endif
