/* specgpu guided filter family (He, Sun and Tang 2010): edge-aware smoothing of a C-channel image p by a
 * one-channel guide g, built from box sums taken as running sums (O(1) per pixel whatever the radius R).
 *
 * Images are (H, W, C) float32, channels last, flattened; the guide (H, W). Windows are clipped to the image and
 * a box mean divides by the count of pixels inside. Three passes, intermediates on the device:
 *
 *   gf_columns_in   sums down columns of x = [p (C), g' p (C), g', g'^2]                 -> V (H, W, NV)
 *   gf_rows         sums along rows of V; the guide's mean and variance once per window, shared by the C
 *                   channels; a = cov(g', p) / (var g' + eps), b = mean p - a mean g'; sums along rows of
 *                   [a (C), b (C)]                                                        -> S (H, W, NAB)
 *   gf_columns_out  sums down columns of S; q = (sum a g' + sum b) / count                -> out (H, W, C)
 *
 * g' = g - g[0]: the filter is unchanged by a constant added to its guide, and statistics taken about a value of
 * the image lose less to float32 cancellation than about zero. Each work-item walks a strip of rows (columns)
 * with its sums in private arrays (C is a build macro): the value that leaves a window is the one that entered
 * it, read again (a and b from the work-item's ring of the last 2R + 1 it made), so a sum never drifts by
 * recomputation. A non-finite value makes a running sum non-finite for good; while a sum is not finite it is
 * summed again directly over its window (O(R)), so NaN reaches exactly the outputs whose windows hold it
 * ((4R + 1)^2 pixels about it), as with direct sums.
 */

#ifndef C
#define C 1
#endif
#define NV (2 * C + 2) /* [p, g' p, g', g'^2] */
#define NAB (2 * C)    /* [a, b] */
/* PoCL calls min(), max() and fmax() out of line, and may leave a helper out of line: all written inline here
 * (the helpers' pointers are not restrict: inlined, those make scope declarations Oclgrind does not know) */
#define INLINE inline __attribute__((always_inline))
#define IMIN(a, b) ((a) < (b) ? (a) : (b))
#define IMAX(a, b) ((a) > (b) ? (a) : (b))
#define FPOS(v) ((v) > 0.0f ? (v) : 0.0f) /* fmax(v, 0); NaN gives 0, as fmax */

#ifndef BX
#define BX 1 /* pixels of a row per work-item in the column passes: a vector loop on CPUs, 1 on GPUs */
#endif

/* The guide's offset: its first value (0 if that is not finite). */
INLINE float guide_offset(__global const float *g)
{
    const float g0 = g[0];
    return isfinite(g0) ? g0 : 0.0f;
}

/* sum += sign * the products of BX pixels of row k from pixel x on (n <= BX of them): [p (C), g' p (C), g', g'^2]
 * each; past the image's edge the last pixel again (its sums are never written out). */
INLINE void add_products(__global const float *p, __global const float *g, const int W,
                         const int x, const int n, const int k, const float g0, const float sign, float *sum)
{
    const size_t q = (size_t)k * W + x;
    for (int i = 0; i < BX; ++i) {
        const int j = IMIN(i, n - 1);
        const float gv = g[q + j] - g0, sg = sign * gv;
        __global const float *pq = p + (q + j) * C;
        float *s = sum + i * NV;
        for (int c = 0; c < C; ++c) {
            s[c] += sign * pq[c];
            s[C + c] += sg * pq[c];
        }
        s[2 * C] += sg;
        s[2 * C + 1] += sg * gv;
    }
}

/* Whether all n sums are finite: no exponent all ones (an integer OR over the lanes, which vectorises; a float
 * reduction would be a chain of dependent adds). */
INLINE bool all_finite(const float *sum, const int n)
{
    int bad = 0;
    for (int c = 0; c < n; ++c)
        bad |= (as_int(sum[c]) & 0x7f800000) == 0x7f800000;
    return !bad;
}

/* Column sums of the products over rows [y - R, y + R] (clipped): each work-item the BX pixels from x = BX i on
 * (contiguous, so its sums are one vector loop); the range is (ceil(W / BX), strips of SY rows). */
__kernel void gf_columns_in(__global const float *restrict p, __global const float *restrict g,
                            __global float *restrict V, const int H, const int W, const int R, const int SY)
{
    const int x = get_global_id(0) * BX, y0 = get_global_id(1) * SY;
    if (x >= W || y0 >= H)
        return;
    const int n = IMIN(BX, W - x), y1 = IMIN(y0 + SY, H);
    const float g0 = guide_offset(g);
    float sum[BX * NV];
    for (int c = 0; c < BX * NV; ++c)
        sum[c] = 0.0f;
    for (int k = IMAX(y0 - R - 1, 0); k <= IMIN(y0 + R - 1, H - 1); ++k) /* the window of row y0 - 1 */
        add_products(p, g, W, x, n, k, g0, 1.0f, sum);
    for (int y = y0; y < y1; ++y) {
        if (y + R < H)
            add_products(p, g, W, x, n, y + R, g0, 1.0f, sum);
        if (y - R - 1 >= 0)
            add_products(p, g, W, x, n, y - R - 1, g0, -1.0f, sum);
        if (!all_finite(sum, BX * NV)) { /* a non-finite value entered, or left: the window summed afresh */
            for (int c = 0; c < BX * NV; ++c)
                sum[c] = 0.0f;
            for (int k = IMAX(y - R, 0); k <= IMIN(y + R, H - 1); ++k)
                add_products(p, g, W, x, n, k, g0, 1.0f, sum);
        }
        __global float *o = V + ((size_t)y * W + x) * NV;
        for (int c = 0; c < n * NV; ++c)
            o[c] = sum[c];
    }
}

/* gf_rows works on RY rows at once, one vector lane each (RY = 4 on CPUs: its arithmetic in float4; 1 on GPUs). */
#ifndef RY
#define RY 1
#endif
#if RY == 4
typedef float4 floatr;
typedef int4 intr;
#define AS_INTR as_int4
#define ANYR(v) ((v).x | (v).y | (v).z | (v).w)
#define GATHER(rows, i) ((floatr)((rows)[0][i], (rows)[1][i], (rows)[2][i], (rows)[3][i]))
#define SCATTER(rows, i, v, n)                                                                                         \
    do {                                                                                                               \
        (rows)[0][i] = (v).x;                                                                                          \
        if ((n) > 1)                                                                                                   \
            (rows)[1][i] = (v).y;                                                                                      \
        if ((n) > 2)                                                                                                   \
            (rows)[2][i] = (v).z;                                                                                      \
        if ((n) > 3)                                                                                                   \
            (rows)[3][i] = (v).w;                                                                                      \
    } while (0)
#elif RY == 1
typedef float floatr;
typedef int intr;
#define AS_INTR as_int
#define ANYR(v) (v)
#define GATHER(rows, i) ((rows)[0][i])
#define SCATTER(rows, i, v, n) ((rows)[0][i] = (v))
#else
#error "RY must be 1 or 4"
#endif

/* Whether all n sums of RY rows are finite (see all_finite). */
INLINE bool all_finite_r(const floatr *sum, const int n)
{
    intr bad = 0;
    for (int c = 0; c < n; ++c)
        bad |= (AS_INTR(sum[c]) & 0x7f800000) == 0x7f800000;
    return !ANYR(bad);
}

/* The window's linear models [a (C), b (C)] from its sums of the products over n pixels (per row lane). */
INLINE void coefficients(const floatr *sum, const floatr n, const float eps, floatr *ab)
{
    const floatr rn = 1.0f / n;
    const floatr mg = sum[2 * C] * rn;
    const floatr vg0 = sum[2 * C + 1] * rn - mg * mg;
    const floatr vg = vg0 > (floatr)0.0f ? vg0 : (floatr)0.0f; /* fmax(vg0, 0), NaN giving 0 as fmax */
    const floatr inv = 1.0f / (vg + eps); /* the guide's statistics, once for every channel */
    for (int c = 0; c < C; ++c) {
        const floatr mp = sum[c] * rn;
        const floatr a = (sum[C + c] * rn - mg * mp) * inv;
        ab[c] = a;
        ab[C + c] = mp - a * mg;
    }
}

/* The lead window moved on to column xl (sums of V over [xl - R, xl + R], clipped), and its models. */
INLINE void lead_models(__global const float **rows, const int W, const int R, const int xl, const floatr ny,
                        const float eps, floatr *sum, floatr *ab)
{
    if (xl + R < W) {
        const size_t in = (size_t)(xl + R) * NV;
        for (int c = 0; c < NV; ++c)
            sum[c] += GATHER(rows, in + c);
    }
    if (xl - R - 1 >= 0) {
        const size_t out = (size_t)(xl - R - 1) * NV;
        for (int c = 0; c < NV; ++c)
            sum[c] -= GATHER(rows, out + c);
    }
    if (!all_finite_r(sum, NV)) { /* a non-finite value entered, or left: the window summed afresh */
        for (int c = 0; c < NV; ++c)
            sum[c] = 0.0f;
        for (int k = IMAX(xl - R, 0); k <= IMIN(xl + R, W - 1); ++k)
            for (int c = 0; c < NV; ++c)
                sum[c] += GATHER(rows, (size_t)k * NV + c);
    }
    const float nx = (float)(IMIN(xl + R, W - 1) - IMAX(xl - R, 0) + 1);
    coefficients(sum, nx * ny, eps, ab);
}

/* Row sums over columns [x - R, x + R] (clipped) of the models a, b of the windows centred there, RY rows per
 * work-item; the range is (ceil(H / RY), NSX strips of SX columns); each work-item keeps the models it made in its
 * own ring of L = min(2R + 1, W) slots. */
__kernel void gf_rows(__global const float *restrict V, __global floatr *restrict ring_all, __global float *restrict S,
                      const int H, const int W, const int R, const int SX, const int NSX, const int L,
                      const float eps)
{
    const int y = get_global_id(0) * RY, strip = get_global_id(1), x0 = strip * SX;
    if (y >= H || x0 >= W)
        return;
    const int x1 = IMIN(x0 + SX, W), n = IMIN(RY, H - y);
    __global const float *rows[RY]; /* past the image's last row, that row again (its sums never written out) */
    __global float *outs[RY];
    float nys[RY];
    for (int i = 0; i < RY; ++i) {
        const int yi = IMIN(y + i, H - 1);
        rows[i] = V + (size_t)yi * W * NV;
        outs[i] = S + (size_t)yi * W * NAB;
        nys[i] = (float)(IMIN(yi + R, H - 1) - IMAX(yi - R, 0) + 1);
    }
#if RY == 4
    const floatr ny = (floatr)(nys[0], nys[1], nys[2], nys[3]);
#else
    const floatr ny = nys[0];
#endif
    __global floatr *ring = ring_all + ((size_t)get_global_id(0) * NSX + strip) * (size_t)L * NAB;
    floatr sum[NV], acc[NAB], ab[NAB];
    for (int c = 0; c < NV; ++c)
        sum[c] = 0.0f;
    for (int c = 0; c < NAB; ++c)
        acc[c] = 0.0f;
    /* the lead window of column xs - 1, then the models of [xs, x0 + R - 1] (the window of x0 - 1, clipped) */
    const int xs = IMAX(x0 - R - 1, 0);
    for (int k = IMAX(xs - R - 1, 0); k <= IMIN(xs + R - 1, W - 1); ++k)
        for (int c = 0; c < NV; ++c)
            sum[c] += GATHER(rows, (size_t)k * NV + c);
    int slot_in = 0; /* the ring slot of the next model made, (xl - xs) % L */
    for (int xl = xs; xl <= IMIN(x0 + R - 1, W - 1); ++xl) {
        lead_models(rows, W, R, xl, ny, eps, sum, ab);
        __global floatr *slot = ring + (size_t)slot_in * NAB;
        for (int c = 0; c < NAB; ++c) {
            slot[c] = ab[c];
            acc[c] += ab[c];
        }
        slot_in = slot_in + 1 == L ? 0 : slot_in + 1;
    }
    int slot_out = 0; /* the ring slot of the model leaving next: the first made, xs, leaves first */
    for (int xo = x0; xo < x1; ++xo) {
        if (xo - R - 1 >= 0) { /* the model leaving, read before its slot is reused */
            __global const floatr *old = ring + (size_t)slot_out * NAB;
            for (int c = 0; c < NAB; ++c)
                acc[c] -= old[c];
            slot_out = slot_out + 1 == L ? 0 : slot_out + 1;
        }
        if (xo + R < W) { /* the model entering */
            lead_models(rows, W, R, xo + R, ny, eps, sum, ab);
            __global floatr *slot = ring + (size_t)slot_in * NAB;
            for (int c = 0; c < NAB; ++c) {
                slot[c] = ab[c];
                acc[c] += ab[c];
            }
            slot_in = slot_in + 1 == L ? 0 : slot_in + 1;
        }
        if (!all_finite_r(acc, NAB)) { /* the models of the window, summed afresh from the ring */
            for (int c = 0; c < NAB; ++c)
                acc[c] = 0.0f;
            for (int k = IMAX(xo - R, 0); k <= IMIN(xo + R, W - 1); ++k)
                for (int c = 0; c < NAB; ++c)
                    acc[c] += ring[(size_t)((k - xs) % L) * NAB + c];
        }
        const size_t o = (size_t)xo * NAB;
        for (int c = 0; c < NAB; ++c)
            SCATTER(outs, o + c, acc[c], n);
    }
}

/* acc += sign * the sums of a and b of BX pixels of row k from pixel x on (n <= BX of them; past the image's
 * edge, values of its last pixel, never written out). */
INLINE void add_models(__global const float *S, const int W, const int x, const int n, const int k,
                       const float sign, float *acc)
{
    __global const float *s = S + ((size_t)k * W + x) * NAB;
    if (n == BX)
        for (int c = 0; c < BX * NAB; ++c)
            acc[c] += sign * s[c];
    else
        for (int c = 0; c < BX * NAB; ++c)
            acc[c] += sign * s[IMIN(c, n * NAB - 1)];
}

/* q = (sum a * g' + sum b) / count, the sums of S down columns over rows [y - R, y + R] (clipped); each work-item
 * the BX pixels from x = BX i on; the range is (ceil(W / BX), strips of SY rows). */
__kernel void gf_columns_out(__global const float *restrict S, __global const float *restrict g,
                             __global float *restrict out, const int H, const int W, const int R, const int SY)
{
    const int x = get_global_id(0) * BX, y0 = get_global_id(1) * SY;
    if (x >= W || y0 >= H)
        return;
    const int n = IMIN(BX, W - x), y1 = IMIN(y0 + SY, H);
    const float g0 = guide_offset(g);
    float acc[BX * NAB];
    for (int c = 0; c < BX * NAB; ++c)
        acc[c] = 0.0f;
    for (int k = IMAX(y0 - R - 1, 0); k <= IMIN(y0 + R - 1, H - 1); ++k)
        add_models(S, W, x, n, k, 1.0f, acc);
    for (int y = y0; y < y1; ++y) {
        if (y + R < H)
            add_models(S, W, x, n, y + R, 1.0f, acc);
        if (y - R - 1 >= 0)
            add_models(S, W, x, n, y - R - 1, -1.0f, acc);
        if (!all_finite(acc, BX * NAB)) {
            for (int c = 0; c < BX * NAB; ++c)
                acc[c] = 0.0f;
            for (int k = IMAX(y - R, 0); k <= IMIN(y + R, H - 1); ++k)
                add_models(S, W, x, n, k, 1.0f, acc);
        }
        const float ny = (float)(IMIN(y + R, H - 1) - IMAX(y - R, 0) + 1);
        const size_t q = (size_t)y * W + x;
        for (int i = 0; i < n; ++i) {
            const float rn = 1.0f / (ny * (float)(IMIN(x + i + R, W - 1) - IMAX(x + i - R, 0) + 1));
            const float gv = g[q + i] - g0;
            __global float *o = out + (q + i) * C;
            for (int c = 0; c < C; ++c)
                o[c] = (acc[i * NAB + c] * gv + acc[i * NAB + C + c]) * rn;
        }
    }
}
