/* specgpu consistency check of a motion-compensated sequence: do the frames' gradient images agree once each is
 * sampled where the motion says that frame saw each pixel?
 *
 * Per pixel: a_k, frame k's gradient image sampled bilinearly at M_k (x, y, 1), the coordinates clamped to the field
 * (scipy.ndimage.map_coordinates, order=1, mode="nearest"); r, the median of the K samples (the mean of the middle
 * two for even K, as numpy.median); over the WINDOW x WINDOW box around the pixel, rows and columns beyond the
 * field repeating the edge (scipy.ndimage.uniform_filter, mode="nearest"), the means m() of a_k, a_k^2, a_k r, r,
 * r^2, and from them vr = m(r^2) - m(r)^2, va_k = m(a_k^2) - m(a_k)^2 (each at least 0) and the normalised
 * cross-correlation ncc_k = (m(a_k r) - m(a_k) m(r)) / sqrt(max(va_k vr, 1e-30)). The two maps:
 *   worst    = the least ncc_k over the frames with va_k > own median(va_k over the field), 1 where none has;
 *              with FLOOR, also va_k above the frame's noise floor there (floor_k, an image per frame in its own
 *              pixels, sampled where the frame saw the pixel as its gradient image is: bilinear, clamped);
 *   textured = vr > texture mean(vr over the field).
 * Two of these numbers are statistics of the whole field, known only once every pixel's va_k is; writing every
 * va_k, ncc_k and vr for a later pass (2 K + 1 planes) would cost more than the arithmetic. So:
 *   consistency_sample   va_k of a sample of the field (strips of SAMPLE_ROWS rows spread over it) -> sample
 *                        planes
 *   consistency_bracket  per frame, two values of the sample either side of its median, far enough out that the
 *                        field's median lies between them: [lo, hi]; the field's threshold own median(va_k) then
 *                        lies in [own lo, own hi]
 *   consistency_strips   every pixel, each work-item running down a strip of ROWS rows of 8 V columns: a frame
 *                        whose va_k is above own hi counts (its ncc_k enters worst now), one at or below own lo
 *                        does not; the few in between are kept (the pixel, va_k, ncc_k) in the work-item's list;
 *                        per frame the values below lo are counted and those in [lo, hi] kept, so that the exact
 *                        median is a selection among a few percent of the field; vr is written
 *   consistency_median   per frame the exact median (a radix selection among the kept values, the count below lo
 *                        giving their ranks), the threshold own median; and the level texture mean(vr). Where
 *                        the median is not in [lo, hi] (the sample misled) the frame is marked, and the host runs
 *                        the strips again with every value kept
 *   consistency_settle   per work-item of the strips: its undecided frames above their threshold into worst;
 *                        textured
 * Each work-item of the strips covers 8 V consecutive columns (float8 vectors: the width PoCL vectorises to) of
 * ROWS rows. Row sums along the row (over the lanes of a row of NV vectors starting HALF columns left of the first
 * output) are kept in a ring of the last WINDOW rows, and the column sums run down the strip (each row's sums
 * added, the ones of the row WINDOW above taken off): every sample, median and product is made once per row.
 * Maps are stored STRIDE floats a row (the width rounded up to 8 V); the lanes beyond the width hold the values of
 * clamped columns and are neither counted nor read back.
 *
 * Macros: K, WINDOW (odd), V, ROWS, STRIDE, SAMPLE_ROWS; TRANSLATE = 1: every map is a translation, given per frame
 * as the whole and fractional pixels (ix, iy, fx, fy) (rows read as vectors, each source row's horizontal interpolation
 * made once for the two output rows that read it); FLOW = 1: a displacement per pixel and frame instead of the maps
 * (flow (K, 2, H, W): frame k saw pixel (x, y) at (x + flow[k][0][y][x], y + flow[k][1][y][x])), read at the lane's
 * clamped column; else the 2 x 3 affine maps. SCALED = 1: frame k's samples multiplied by scale[k] (the gradient
 * images' 1 / mean, kernels/gradient.cl). SELECT_GROUP: work-items per group of the selections (1: plain counts in
 * local memory; more: local atomics).
 */
#include "common.h"

#ifndef WINDOW
#define WINDOW 9
#endif
#define HALF (WINDOW / 2)
#ifndef V
#define V 4
#endif
#ifndef ROWS
#define ROWS 32
#endif
#ifndef STRIDE
#define STRIDE (8 * V)
#endif
#ifndef SAMPLE_ROWS
#define SAMPLE_ROWS 8
#endif
#ifndef TRANSLATE
#define TRANSLATE 0
#endif
#ifndef FLOW
#define FLOW 0
#endif
#ifndef SCALED
#define SCALED 0
#endif
#ifndef REFRESH
#define REFRESH 16
#endif
#ifndef FLOOR
#define FLOOR 0
#endif
#ifndef SELECT_GROUP
#define SELECT_GROUP 1
#endif
#define NV (V + (2 * HALF + 7) / 8) /* vectors of a row's samples: the outputs' columns and HALF each side */
#define CAP (ROWS * 8 * V)          /* pixels of a strip: the most any of its lists can hold per frame */

/* a float's bits as an unsigned key in the order of the floats (negative ones flipped) */
ALWAYS_INLINE uint8 order_key8(float8 v)
{
    const uint8 b = as_uint8(v);
    return b ^ (as_uint8(as_int8(b) >> 31) | (uint8)(0x80000000u));
}

ALWAYS_INLINE uint order_key(float v)
{
    const uint b = as_uint(v);
    return b ^ ((uint)(as_int(b) >> 31) | 0x80000000u);
}

ALWAYS_INLINE float key_value(uint key)
{
    return as_float((key & 0x80000000u) ? key ^ 0x80000000u : ~key);
}

/* ------------------------------------------------------------------------------------------------- sampling */

/* frame k's gradient image at the lanes' points (sx, sy), bilinear, coordinates clamped to the field */
ALWAYS_INLINE float8 sample8(__global const float *g, float8 sx, float8 sy, uint width, uint height)
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

#if TRANSLATE
/* source row r of frame image g interpolated horizontally at the work-item's NV vectors of columns (first is the
 * column of lane 0 of the first, before clamping), moved by ix whole and fx fractional pixels */
ALWAYS_INLINE void shifted_row(__global const float *g, int r, int first, int ix, float fx, bool inside,
                        uint width, float8 *h)
{
    __global const float *row = g + (ulong)r * width;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 last_x = (int8)((int)width - 1);
    for (int j = 0; j < NV; ++j) {
        float8 p, q;
        if (inside) {  /* no lane's column clamped: two unaligned vector loads */
            p = LOAD8(float, row + first + ix + 8 * j);
            q = LOAD8(float, row + first + ix + 8 * j + 1);
        } else {       /* the output column clamped, then its source columns */
            const int8 c = clamp(first + 8 * j + lane, (int8)(0), last_x) + (int8)(ix);
            const int8 c0 = clamp(c, (int8)(0), last_x), c1 = clamp(c + 1, (int8)(0), last_x);
            p = (float8)(row[c0.s0], row[c0.s1], row[c0.s2], row[c0.s3], row[c0.s4], row[c0.s5], row[c0.s6],
                         row[c0.s7]);
            q = (float8)(row[c1.s0], row[c1.s1], row[c1.s2], row[c1.s3], row[c1.s4], row[c1.s5], row[c1.s6],
                         row[c1.s7]);
        }
        h[j] = p + fx * (q - p);
    }
}
#endif

/* The K frames' samples a[k][j] at row yy (clamped) of the work-item's NV vectors of columns from first. With
 * TRANSLATE, cache[k] holds frame k's last interpolated source row (its index in cached[k]): moving down one row, a
 * frame's upper source row is the previous row's lower one. */
ALWAYS_INLINE void sample_row(__global const float *grads, __global const float *scale,
                       __constant const float *motion, __global const float *flow, int yy,
                       int first, uint width, uint height, float8 a[K][NV], float8 cache[K][NV], int cached[K])
{
    const ulong n = (ulong)width * height;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 last_x = (int8)((int)width - 1);
    for (int k = 0; k < K; ++k) {
        __constant const float *m = motion + 6 * k;
        __global const float *g = grads + (ulong)k * n;
#if TRANSLATE
        const int ix = (int)m[0], iy = (int)m[1];
        const float fx = m[2], fy = m[3];
        const int r0 = clamp(yy + iy, 0, (int)height - 1), r1 = clamp(yy + iy + 1, 0, (int)height - 1);
        const bool inside = first >= 0 && first + 8 * NV <= (int)width && first + ix >= 0
                            && first + ix + 8 * NV + 1 <= (int)width;
        float8 h0[NV];
        if (r0 == cached[k]) {
            for (int j = 0; j < NV; ++j) h0[j] = cache[k][j];
        } else {
            shifted_row(g, r0, first, ix, fx, inside, width, h0);
        }
        if (r1 != r0) {
            shifted_row(g, r1, first, ix, fx, inside, width, cache[k]);
        } else {
            for (int j = 0; j < NV; ++j) cache[k][j] = h0[j];
        }
        cached[k] = r1;
        for (int j = 0; j < NV; ++j) a[k][j] = h0[j] + fy * (cache[k][j] - h0[j]);
#else
        for (int j = 0; j < NV; ++j) {
            const int8 xi = clamp(first + 8 * j + lane, (int8)(0), last_x);
            const float8 x = convert_float8(xi), y = (float8)((float)yy);
#if FLOW
            const int8 i = (int8)(yy * (int)width) + xi;
            __global const float *fxp = flow + (ulong)(2 * k) * n, *fyp = fxp + n;
            const float8 dx = (float8)(fxp[i.s0], fxp[i.s1], fxp[i.s2], fxp[i.s3], fxp[i.s4], fxp[i.s5], fxp[i.s6],
                                       fxp[i.s7]);
            const float8 dy = (float8)(fyp[i.s0], fyp[i.s1], fyp[i.s2], fyp[i.s3], fyp[i.s4], fyp[i.s5], fyp[i.s6],
                                       fyp[i.s7]);
            a[k][j] = sample8(g, x + dx, y + dy, width, height);
#else
            a[k][j] = sample8(g, m[0] * x + (m[1] * y + m[2]), m[3] * x + (m[4] * y + m[5]), width, height);
#endif
        }
#endif
#if SCALED
        const float s = scale[k];
        for (int j = 0; j < NV; ++j) a[k][j] *= s;
#endif
    }
}

#if FLOOR
/* frame k's noise floor image f at the output pixels (x, y) of the lanes (columns clamped), sampled where the motion
 * says the frame saw them, as sample_row samples its gradient image */
ALWAYS_INLINE float8 floor_at(__global const float *f, __constant const float *m, __global const float *flow, int k,
                              int x, int y, uint width, uint height)
{
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int8 xi = min(x + lane, (int8)((int)width - 1));
#if TRANSLATE
    return sample8(f, convert_float8(xi + (int8)((int)m[0])) + (float8)(m[2]),
                   (float8)((float)(y + (int)m[1]) + m[3]), width, height);
#elif FLOW
    const ulong n = (ulong)width * height;
    const int8 i = (int8)(y * (int)width) + xi;
    __global const float *fxp = flow + (ulong)(2 * k) * n, *fyp = fxp + n;
    const float8 dx = (float8)(fxp[i.s0], fxp[i.s1], fxp[i.s2], fxp[i.s3], fxp[i.s4], fxp[i.s5], fxp[i.s6], fxp[i.s7]);
    const float8 dy = (float8)(fyp[i.s0], fyp[i.s1], fyp[i.s2], fyp[i.s3], fyp[i.s4], fyp[i.s5], fyp[i.s6], fyp[i.s7]);
    return sample8(f, convert_float8(xi) + dx, (float8)((float)y) + dy, width, height);
#else
    const float8 xf = convert_float8(xi), yf = (float8)((float)y);
    return sample8(f, m[0] * xf + (m[1] * yf + m[2]), m[3] * xf + (m[4] * yf + m[5]), width, height);
#endif
}
#endif

/* the median of each lane's K samples: an odd-even transposition sort of a copy, the comparisons that cannot
 * reach the middle dropped by the compiler (a ? b : c compiles inline; PoCL's min and max are calls) */
ALWAYS_INLINE float8 median8(float8 a[K][NV], int j)
{
    float8 t[K];
    for (int k = 0; k < K; ++k) t[k] = a[k][j];
    for (int pass = 0; pass < K; ++pass)
        for (int i = pass & 1; i + 1 < K; i += 2) {
            const int8 swap = t[i + 1] < t[i];
            const float8 lo = swap ? t[i + 1] : t[i], hi = swap ? t[i] : t[i + 1];
            t[i] = lo;
            t[i + 1] = hi;
        }
    return (K % 2) ? t[K / 2] : 0.5f * (t[K / 2 - 1] + t[K / 2]);
}

#if WINDOW == 9
/* sum of the 9 values from each lane on, of the 16 in a (0-7) and b (8-15), by pairwise sums and swizzles of
 * single lanes (straight-line vector code; Oclgrind's uninitialised-value check cannot take multi-lane parts) */
ALWAYS_INLINE float8 box9(float8 a, float8 b)
{
    const float8 s2l = a + (float8)(a.s1, a.s2, a.s3, a.s4, a.s5, a.s6, a.s7, b.s0);  /* in[j] + in[j + 1] */
    const float8 s2u = b + (float8)(b.s1, b.s2, b.s3, b.s4, b.s5, b.s6, b.s7, b.s7);  /* j = 8..14 */
    const float8 s4l = s2l + (float8)(s2l.s2, s2l.s3, s2l.s4, s2l.s5, s2l.s6, s2l.s7, s2u.s0, s2u.s1);
    const float8 s4u = s2u + (float8)(s2u.s2, s2u.s3, s2u.s4, s2u.s5, s2u.s6, s2u.s7, s2u.s6, s2u.s7);
    return s4l + (float8)(s4l.s4, s4l.s5, s4l.s6, s4l.s7, s4u.s0, s4u.s1, s4u.s2, s4u.s3) + b; /* in[j .. j + 8] */
}
#endif

/* the sums over the WINDOW columns around each lane of output vector j, of a row held in q[0..NV) */
ALWAYS_INLINE float8 row_box(float8 q[NV], int j)
{
#if WINDOW == 9
    return box9(q[j], q[j + 1]);
#else
    float f[8 * NV];
    for (int i = 0; i < NV; ++i) vstore8(q[i], i, f);
    float8 s = vload8(0, f + 8 * j);
    for (int t = 1; t < WINDOW; ++t) s += vload8(0, f + 8 * j + t);
    return s;
#endif
}

/* one row's sums of a quantity into slot of its ring (the last WINDOW rows' sums), the column sums c moved on:
 * started at the strip's first row (step 0), added while the window fills (1), the row WINDOW above taken off
 * after (2), or summed again from the ring (3: every REFRESH rows, so that a strip's running sums carry the rounding
 * of at most REFRESH steps) */
ALWAYS_INLINE void advance(float8 q[NV], float8 ring[WINDOW][V], int slot, float8 c[V], int step)
{
    for (int j = 0; j < V; ++j) {
        const float8 s = row_box(q, j);
        if (step == 3) {
            ring[slot][j] = s;
            float8 t = ring[0][j];
            for (int i = 1; i < WINDOW; ++i) t += ring[i][j];
            c[j] = t;
        } else {
            c[j] = step == 0 ? s : step == 1 ? c[j] + s : c[j] + s - ring[slot][j];
            ring[slot][j] = s;
        }
    }
}

/* advance's step at virtual row v (y0 - HALF is the first) of a strip from row y0 */
ALWAYS_INLINE int strip_step(int v, int y0)
{
    return v == y0 - HALF ? 0 : v <= y0 + HALF ? 1 : (v - y0 - HALF) % REFRESH == 0 ? 3 : 2;
}

/* Appending the lanes of v where m is true (a comparison's result) to a list at its count c, returning the new
 * count. Every lane is written from c on, the count moving past the true ones: the list needs room for 8 past its
 * count, which a work-item's lists have (its pixels so far are fewer by 8 at least). With AVX-512 (PoCL on such a
 * CPU) the true lanes are packed in a register (vcompressps) and stored as one vector; else one lane at a time. */
#if VEC_DEREF && defined(__AVX512VL__)
typedef float packed_in __attribute__((vector_size(32)));
ALWAYS_INLINE uint lane_bits(int8 m)
{
    return (uint)__builtin_ia32_movmskps256((packed_in)as_float8(m));
}

ALWAYS_INLINE uint append8(__global float *list, uint c, float8 v, uint bits)
{
    STORE8(float, as_float8(__builtin_ia32_compresssf256_mask((packed_in)v, (packed_in)v, (uchar)bits)), list + c);
    return c + (uint)__builtin_popcount(bits);
}
#else
ALWAYS_INLINE uint lane_bits(int8 m)
{
    return (uint)((m.s0 & 1) | (m.s1 & 2) | (m.s2 & 4) | (m.s3 & 8) | (m.s4 & 16) | (m.s5 & 32) | (m.s6 & 64)
                  | (m.s7 & 128));
}

ALWAYS_INLINE uint append8(__global float *list, uint c, float8 v, uint bits)
{
    const float lanes[8] = {v.s0, v.s1, v.s2, v.s3, v.s4, v.s5, v.s6, v.s7};
    for (int l = 0; l < 8; ++l) {
        list[c] = lanes[l];
        c += (bits >> l) & 1u;
    }
    return c;
}
#endif

/* whether any lane of a comparison's result is true (PoCL's any() is a call) */
ALWAYS_INLINE bool any8(int8 m)
{
    const int4 t = m.lo | m.hi;
    const int2 u = t.lo | t.hi;
    return (u.x | u.y) != 0;
}

ALWAYS_INLINE float8 positive(float8 v)
{
    return v > (float8)(0.0f) ? v : (float8)(0.0f);
}

/* ---------------------------------------------------------------------------------------------- the sample */

/* va_k of every pixel of strips of SAMPLE_ROWS rows step apart (strip gid(1) step + offset), into the sample planes
 * (K, sample_rows, STRIDE), a strip's rows from gid(1) SAMPLE_ROWS */
__kernel void consistency_sample(__global const float *restrict grads, __global const float *restrict scale,
                                 __constant const float *restrict motion, __global const float *restrict flow,
                                 __global float *restrict sample, const uint step, const uint offset,
                                 const uint sample_rows, const uint width, const uint height)
{
    const int x0 = 8 * V * get_global_id(0), strip = get_global_id(1) * step + offset;
    const int y0 = SAMPLE_ROWS * strip;
    if (x0 >= STRIDE || y0 >= (int)height) return;
    const int y1 = min(y0 + SAMPLE_ROWS, (int)height);
    const int first = x0 - HALF;
    const ulong plane = (ulong)STRIDE * sample_rows;
    const float inv = 1.0f / (float)(WINDOW * WINDOW);
    float8 ring[2 * K][WINDOW][V];
    float8 col[2 * K][V];
    float8 a[K][NV];
    float8 cache[K][NV];
    int cached[K];
    for (int k = 0; k < K; ++k) cached[k] = -1;
    for (int v = y0 - HALF; v < y1 + HALF; ++v) {
        sample_row(grads, scale, motion, flow, clamp(v, 0, (int)height - 1), first, width, height, a, cache, cached);
        const int slot = (v - (y0 - HALF)) % WINDOW;
        const int step = strip_step(v, y0);
        for (int k = 0; k < K; ++k) {
            float8 q[NV];
            advance(a[k], ring[2 * k], slot, col[2 * k], step);
            for (int j = 0; j < NV; ++j) q[j] = a[k][j] * a[k][j];
            advance(q, ring[2 * k + 1], slot, col[2 * k + 1], step);
        }
        if (v < y0 + HALF) continue;
        const int y = v - HALF;
        for (int j = 0; j < V; ++j) {
            const ulong o = (ulong)(get_global_id(1) * SAMPLE_ROWS + (y - y0)) * STRIDE + x0 + 8 * j;
            for (int k = 0; k < K; ++k) {
                const float8 ma = col[2 * k][j] * inv;
                STORE8(float, positive(col[2 * k + 1][j] * inv - ma * ma), sample + (ulong)k * plane + o);
            }
        }
    }
}

/* ------------------------------------------------------------------------------------------ the selections */

#define BINS 2048 /* radix digits of 11, 11 and 10 bits */

/* The values of ranks r0 <= r1 (counted from 0) among a work-group's values, as order keys, into state[0] and
 * state[1] (local: state[0..4] hold the two prefixes, the ranks left within them and the mask of the digits found):
 * three radix passes (digits of 11, 11 and 10 bits), each counting the digit of the values whose higher digits are
 * those found so far (one count for both ranks while they share them); after fewer than three passes the keys found
 * have their lower digits 0. The values are lists l in [0, lists) of
 * LENGTH(l) values AT(l, e), each work-item taking the lists from its local id on in steps of the group's size;
 * hist (2 BINS) is local scratch. The state lives in local memory, written by the first work-item between
 * barriers: nothing private is carried across them (PoCL lost private arrays kept over barriers in loops). */
#define SELECT_TWO(lists, LENGTH, AT, r0, r1, hist, state, passes)                                              \
    do {                                                                                                       \
        const uint lid_ = get_local_id(0), group_ = get_local_size(0);                                         \
        if (lid_ == 0) {                                                                                       \
            (state)[0] = (state)[1] = (state)[4] = 0u;                                                         \
            (state)[2] = (r0);                                                                                 \
            (state)[3] = (r1);                                                                                 \
        }                                                                                                      \
        for (int pass_ = 0; pass_ < (passes); ++pass_) {                                                       \
            const uint shift_ = pass_ == 0 ? 21u : pass_ == 1 ? 10u : 0u;                                      \
            const uint digits_ = pass_ == 2 ? 1024u : 2048u;                                                   \
            for (uint b_ = lid_; b_ < 2 * BINS; b_ += group_) (hist)[b_] = 0u;                                 \
            barrier(CLK_LOCAL_MEM_FENCE);                                                                      \
            {                                                                                                  \
                const uint p0_ = (state)[0], p1_ = (state)[1], mask_ = (state)[4];                             \
                const bool same_ = p0_ == p1_;                                                                 \
                for (uint l_ = lid_; l_ < (lists); l_ += group_) {                                             \
                    const uint length_ = (LENGTH(l_));                                                         \
                    for (uint e_ = 0; e_ < length_; ++e_) {                                                    \
                        const uint key_ = order_key(AT(l_, e_));                                               \
                        const uint digit_ = (key_ >> shift_) & (digits_ - 1u);                                 \
                        if ((key_ & mask_) == p0_) COUNT_UP((hist) + digit_);                                  \
                        if (!same_ && (key_ & mask_) == p1_) COUNT_UP((hist) + BINS + digit_);                 \
                    }                                                                                          \
                }                                                                                              \
            }                                                                                                  \
            barrier(CLK_LOCAL_MEM_FENCE);                                                                      \
            if (lid_ == 0) {                                                                                   \
                const bool same_ = (state)[0] == (state)[1];                                                   \
                for (int t_ = 0; t_ < 2; ++t_) {                                                               \
                    __local const uint *h_ = (hist) + (t_ == 1 && !same_ ? BINS : 0);                          \
                    uint below_ = 0u, d_ = 0u;                                                                 \
                    while (d_ + 1u < digits_ && below_ + h_[d_] <= (state)[2 + t_]) below_ += h_[d_++];        \
                    (state)[t_] |= d_ << shift_;                                                               \
                    (state)[2 + t_] -= below_;                                                                 \
                }                                                                                              \
                (state)[4] |= (digits_ - 1u) << shift_;                                                        \
            }                                                                                                  \
            barrier(CLK_LOCAL_MEM_FENCE);                                                                      \
        }                                                                                                      \
    } while (0)

#if SELECT_GROUP > 1
#define COUNT_UP(p) atomic_inc(p)
#else
#define COUNT_UP(p) (*(p) += 1u)
#endif

#define SAMPLE_LENGTH(l) ((width + 3) / 4)
#define SAMPLE_AT(l, e) s[(ulong)(l) * STRIDE + 4 * (e)]

/* per frame (one work-group each): the values of ranks middle -+ spread of every fourth column of the sample (its
 * error is its strips', not its count's), to 21 bits (two radix passes; lo's lower bits 0, hi's 1: the bracket only
 * widens), as the bracket of the field's median: bracket[k] = (lo key, hi key, own lo, own hi), the last two as
 * float bits */
__kernel void consistency_bracket(__global const float *restrict sample, const uint sample_rows, const uint spread,
                                  const float own, __global uint4 *restrict bracket, const uint width)
{
    __local uint hist[2 * BINS];
    __local uint state[5];
    __global const float *s = sample + (ulong)get_group_id(0) * STRIDE * sample_rows;
    const uint count = sample_rows * ((width + 3) / 4);
    SELECT_TWO(sample_rows, SAMPLE_LENGTH, SAMPLE_AT, count / 2 > spread ? count / 2 - spread : 0u,
               min(count / 2 + spread, count - 1u), hist, state, 2);
    if (get_local_id(0) == 0) {
        const uint lo = state[0], hi = state[1] | 0x3ffu;
        bracket[get_group_id(0)] = (uint4)(lo, hi, as_uint(own * key_value(lo)), as_uint(own * key_value(hi)));
    }
}

/* ------------------------------------------------------------------------------------------------ the strips */

/* Every pixel of the strip gid(1) of ROWS rows and 8 V columns from 8 V gid(0) (see the file's head). Lists per
 * frame k and work-item w (of nw) at (k nw + w) CAP: kept values (of va in [lo, hi]) and undecided frames (the
 * pixel's offset in the maps, va_k, ncc_k); below[k nw + w] counts the values under lo. */
__kernel void consistency_strips(__global const float *restrict grads, __global const float *restrict scale,
                                 __constant const float *restrict motion, __global const float *restrict flow,
                                 __global const float *restrict floors, __global const uint4 *restrict bracket,
                                 __global float *restrict worst,
                                 __global float *restrict vr_map, __global float *restrict vr_sums,
                                 __global uint *restrict below, __global uint *restrict kept_count,
                                 __global float *restrict kept, __global uint *restrict open_count,
                                 __global uint *restrict open_at, __global float *restrict open_va,
                                 __global float *restrict open_ncc, const uint width, const uint height)
{
    const int x0 = 8 * V * get_global_id(0), y0 = ROWS * get_global_id(1);
    const uint nw = get_global_size(0) * get_global_size(1);
    const uint w = get_global_id(1) * get_global_size(0) + get_global_id(0);
    if (x0 >= STRIDE || y0 >= (int)height) {  /* a work-item of the padded range: empty lists */
        vstore8((float8)(0.0f), w, vr_sums);
        for (int k = 0; k < K; ++k) below[k * nw + w] = kept_count[k * nw + w] = open_count[k * nw + w] = 0u;
        return;
    }
    const int y1 = min(y0 + ROWS, (int)height);
    const int first = x0 - HALF;
    const float inv = 1.0f / (float)(WINDOW * WINDOW);
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    float8 ring[3 * K + 2][WINDOW][V];
    float8 col[3 * K + 2][V];
    float8 a[K][NV];
    float8 cache[K][NV];
    int cached[K];
    uint n_kept[K], n_open[K];
    int8 n_below[K];  /* per lane, less the count (a true lane is -1) */
    for (int k = 0; k < K; ++k) {
        cached[k] = -1;
        n_kept[k] = n_open[k] = 0u;
        n_below[k] = (int8)(0);
    }
    float8 vr_sum = (float8)(0.0f);
    for (int v = y0 - HALF; v < y1 + HALF; ++v) {
        sample_row(grads, scale, motion, flow, clamp(v, 0, (int)height - 1), first, width, height, a, cache, cached);
        float8 r[NV], q[NV];
        for (int j = 0; j < NV; ++j) r[j] = median8(a, j);
        const int slot = (v - (y0 - HALF)) % WINDOW;
        const int step = strip_step(v, y0);
        advance(r, ring[3 * K], slot, col[3 * K], step);
        for (int j = 0; j < NV; ++j) q[j] = r[j] * r[j];
        advance(q, ring[3 * K + 1], slot, col[3 * K + 1], step);
        for (int k = 0; k < K; ++k) {
            advance(a[k], ring[3 * k], slot, col[3 * k], step);
            for (int j = 0; j < NV; ++j) q[j] = a[k][j] * a[k][j];
            advance(q, ring[3 * k + 1], slot, col[3 * k + 1], step);
            for (int j = 0; j < NV; ++j) q[j] = a[k][j] * r[j];
            advance(q, ring[3 * k + 2], slot, col[3 * k + 2], step);
        }
        if (v < y0 + HALF) continue;
        const int y = v - HALF;
        for (int j = 0; j < V; ++j) {
            const int xj = x0 + 8 * j;
            const ulong o = (ulong)y * STRIDE + xj;
            const int8 valid = xj + lane < (int8)((int)width);
            const float8 mr = col[3 * K][j] * inv;
            const float8 vr = positive(col[3 * K + 1][j] * inv - mr * mr);
            STORE8(float, vr, vr_map + o);
            vr_sum += valid ? vr : (float8)(0.0f);
            float8 least = (float8)(1.0f);
            for (int k = 0; k < K; ++k) {
                const uint4 br = bracket[k];
                const float8 ma = col[3 * k][j] * inv;
                const float8 va = positive(col[3 * k + 1][j] * inv - ma * ma);
                const uint8 key = order_key8(va);
                const int8 under = valid & (key < (uint8)(br.x));
                const int8 inside = valid & (key >= (uint8)(br.x)) & (key <= (uint8)(br.y));
                n_below[k] += under;
                const ulong list = ((ulong)k * nw + w) * CAP;
                if (any8(inside)) n_kept[k] = append8(kept + list, n_kept[k], va, lane_bits(inside));
                /* the frame may count where va_k is above own lo: its correlation then */
#if FLOOR
                int8 may = va > (float8)(as_float(br.z));
                if (!any8(may)) continue;
                /* nor where it is no more than the frame's noise gives there: a bright flat area's shot noise */
                may &= va > floor_at(floors + (ulong)k * width * height, motion + 6 * k, flow, k, xj, y, width,
                                     height);
#else
                const int8 may = va > (float8)(as_float(br.z));
#endif
                if (!any8(may)) continue;
                const float8 vv = va * vr;
                const float8 ncc = (col[3 * k + 2][j] * inv - ma * mr)
                                   / sqrt(vv > (float8)(1e-30f) ? vv : (float8)(1e-30f));
                const int8 sure = may & (va > (float8)(as_float(br.w)));
                least = (sure & (ncc < least)) ? ncc : least;
                const int8 open = valid & may & ~sure;
                if (any8(open)) {
                    const uint bits = lane_bits(open), c = n_open[k];
                    append8((__global float *)(open_at + list), c, as_float8((uint8)((uint)o) + as_uint8(lane)), bits);
                    append8(open_va + list, c, va, bits);
                    n_open[k] = append8(open_ncc + list, c, ncc, bits);
                }
            }
            STORE8(float, least, worst + o);
        }
    }
    vstore8(vr_sum, w, vr_sums);
    for (int k = 0; k < K; ++k) {
        const int8 b = n_below[k];
        below[k * nw + w] = -(b.s0 + b.s1 + b.s2 + b.s3 + b.s4 + b.s5 + b.s6 + b.s7);
        kept_count[k * nw + w] = n_kept[k];
        open_count[k * nw + w] = n_open[k];
    }
}

/* ------------------------------------------------------------------------------------------- the thresholds */

/* per frame k < K (a work-group each): the exact median of va_k over the field, a selection among the kept values
 * (the work-items' lists) whose ranks the count below the bracket gives;
 * thresholds[k] = own median and status[k] = 0, or status[k] = 1 where the median is outside the bracket (the
 * sample misled). Work-group K: the level texture mean(vr) into thresholds[K]. */
__kernel void consistency_median(__global const uint *restrict below, __global const uint *restrict kept_count,
                                 __global const float *restrict kept, __global const float *restrict vr_sums,
                                 const uint nw, const float own, const float texture,
                                 __global float *restrict thresholds, __global uint *restrict status,
                                 const uint width, const uint height)
{
    __local uint hist[2 * BINS];
    __local uint state[5];
    const uint k = get_group_id(0);
    const ulong n = (ulong)width * height;
    const bool level = k == K;
    ulong total_below = 0;
    uint m = 0;
    for (uint i = 0; i < (level ? 0 : nw); ++i) {
        total_below += below[k * nw + i];
        m += kept_count[k * nw + i];
    }
    const long first = (long)((n - 1) / 2) - (long)total_below, second = (long)(n / 2) - (long)total_below;
    const bool missed = !level && (first < 0 || second >= (long)m);
    __global const float *lists = kept + (ulong)k * nw * CAP;
    __global const uint *lengths = kept_count + k * nw;
#define KEPT_LENGTH(l) lengths[l]
#define KEPT_AT(l, e) lists[(ulong)(l) * CAP + (e)]
    /* every group through the selection's barriers (the level's and a missed frame's with nothing to select) */
    SELECT_TWO(level || missed ? 0u : nw, KEPT_LENGTH, KEPT_AT, missed ? 0u : (uint)first, missed ? 0u : (uint)second,
               hist, state, 3);
    if (get_local_id(0) != 0) return;
    if (level) {
        /* compensated sum of the work-items' sums (each of at most ROWS 8 V values) */
        float sum = 0.0f, carry = 0.0f;
        for (uint i = 0; i < 8 * nw; ++i) {
            const float x = vr_sums[i], t = sum + x;
            carry += fabs(sum) >= fabs(x) ? (sum - t) + x : (x - t) + sum;
            sum = t;
        }
        thresholds[K] = texture * ((sum + carry) / (float)n);
    } else if (missed) {
        status[k] = 1u;
        thresholds[k] = NAN;
    } else {
        const float lo = key_value(state[0]), hi = key_value(state[1]);
        status[k] = 0u;
        thresholds[k] = own * (n % 2 ? lo : 0.5f * (lo + hi));
    }
}

/* ----------------------------------------------------------------------------------------------- the result */

/* per work-item of the strips (gid(0) of nw): textured over its pixels, and its undecided frames whose va_k is above
 * the frame's threshold into worst */
__kernel void consistency_settle(__global const uint *restrict open_count, __global const uint *restrict open_at,
                                 __global const float *restrict open_va, __global const float *restrict open_ncc,
                                 __global const float *restrict thresholds, __global const float *restrict vr_map,
                                 __global float *restrict worst, __global uchar *restrict textured, const uint nw,
                                 const uint columns, const uint height)
{
    const uint w = get_global_id(0);
    if (w >= nw) return;
    const int x0 = 8 * V * (w % columns), y0 = ROWS * (w / columns);
    const int y1 = x0 < STRIDE ? min(y0 + ROWS, (int)height) : y0;  /* none of a padded work-item's */
    const float8 level = (float8)(thresholds[K]);
    for (int y = y0; y < y1; ++y)
        for (int j = 0; j < V; ++j) {
            const ulong o = (ulong)y * STRIDE + x0 + 8 * j;
            vstore8(convert_uchar8(-(LOAD8(float, vr_map + o) > level)), 0, textured + o);
        }
    for (int k = 0; k < K; ++k) {
        const float t = thresholds[k];
        const ulong base = ((ulong)k * nw + w) * CAP;
        const uint c = open_count[k * nw + w];
        for (uint e = 0; e < c; ++e)
            if (open_va[base + e] > t) {
                const uint at = open_at[base + e];
                worst[at] = min(worst[at], open_ncc[base + e]);
            }
    }
}
