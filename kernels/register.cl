/* specgpu registration of gradient images on the device (specgpu.engine.registration): each of K frames' gradient
 * image registered to the reference frame's, coarse to fine on a pyramid, by Gauss-Newton steps on the reference's
 * gradients (inverse compositional: frame k is sampled at M_k x, the update composed on the host), with a gain and
 * an offset between the two images solved in closed form from the same sums.
 *   register_halve   one pyramid level from the one below, every plane: [1 3 3 1] / 8 along each axis, output
 *                    pixel i centred on input 2 i + 0.5, edges clamped (every input pixel counts: a NaN reaches
 *                    the coarsest level); a work-item takes 8 columns of a strip of HROWS rows
 *   register_search  the correlation coefficient of the reference and frame k over their overlap at each integer
 *                    shift in [-R, R]^2 of the coarsest level within frame k's reach (-2 beyond it, where the
 *                    overlap is under a quarter of the field or where an image has no variance there)
 *   register_step    per frame, over the reference's pixels whose sample M_k x lies in frame k: the sums of the
 *                    normal equations (J' I, J' 1, J' T, J' J) and of the two images (n, I, T, I^2, I T, T^2),
 *                    each work-group's sums reduced in local memory, one row of NS per group and frame; over
 *                    every stride-th band of BAND rows (1: all; more at full resolution, where the rows are many
 *                    and alike): see ROW_OF_BANDS
 * J is the reference's gradient (central differences, per full-resolution px: times GSCALE) times the warp's
 * Jacobian, for a translation (x, y) or, with AFFINE, the six entries of the affine map in centred coordinates
 * scaled to about [-1, 1] (u = CS x + CU, v = CS y + CV at this level).
 * Macros: AFFINE (0: 2 parameters, 1: 6), GROUP (work-group size of the steps), HROWS (rows of a halving strip),
 * BAND (rows of a band the steps take whole).
 */

#ifndef AFFINE
#define AFFINE 0
#endif
#ifndef GROUP
#define GROUP 64
#endif
#if AFFINE
#define NP 6
#else
#define NP 2
#endif
#define NH (NP * (NP + 1) / 2)
/* The chunks of a level a work-item of the steps takes: with GROUP 1 (a CPU) a run of consecutive ones, else every
 * global-size-th (the work-items of a GPU's group read neighbouring pixels) */
#if GROUP == 1
#define FOR_CHUNKS(c, count)                                                                                   \
    const uint per_item_ = ((uint)(count) + (uint)get_global_size(0) - 1) / (uint)get_global_size(0);         \
    const uint end_ = min((uint)(count), ((uint)get_global_id(0) + 1) * per_item_);                          \
    for (uint c = (uint)get_global_id(0) * per_item_; c < end_; ++c)
#else
#define FOR_CHUNKS(c, count) for (uint c = get_global_id(0); c < (count); c += get_global_size(0))
#endif
#ifndef BAND
#define BAND 32
#endif
/* Row r (0, 1, ...) of the reference's rows a step sums, with stride > 1 every stride-th band of BAND consecutive
 * rows counted from its row 1, whatever the shift: rows taken one in n alias with a scene's structure of a period
 * of n rows (a scene rendered at half the resolution: edges between row pairs), and a set of rows that moved with
 * the shift would change the cost between steps; either made the steps wander px from the truth */
#define ROW_OF_BANDS(r, stride) (1 + ((r) / BAND) * (int)(stride) * BAND + (r) % BAND)
/* the rows r runs over: whole bands up to row h - 2 (the rows past it skipped) */
#define BANDED_ROWS(h, stride) (((((int)(h) - 2 + BAND - 1) / BAND) + (int)(stride) - 1) / (int)(stride) * BAND)

/* the sums of one frame: J' I, J' 1, J' T (NP each), J' J (upper triangle), then n, I, T, I^2, I T, T^2 */
#define NS (3 * NP + NH + 6)

/* 16 values of row p from column x0, columns past last clamped to it (a work-item at the field's right edge; no
 * private array: PoCL would keep it, and the work-item's other values, in memory) */
inline float16 load16_clamped(__global const float *p, const int x0, const int last)
{
    if (x0 + 15 <= last) return vload16(0, p + x0);
    return (float16)(p[min(x0, last)], p[min(x0 + 1, last)], p[min(x0 + 2, last)], p[min(x0 + 3, last)],
                     p[min(x0 + 4, last)], p[min(x0 + 5, last)], p[min(x0 + 6, last)], p[min(x0 + 7, last)],
                     p[min(x0 + 8, last)], p[min(x0 + 9, last)], p[min(x0 + 10, last)], p[min(x0 + 11, last)],
                     p[min(x0 + 12, last)], p[min(x0 + 13, last)], p[min(x0 + 14, last)], p[min(x0 + 15, last)]);
}

#ifndef HROWS
#define HROWS 16
#endif

/* input row r of plane p: 16 columns from c0 and the one either side (left, right: clamped) */
#define HALVE_ROW(r, centre, edges)                                                                            \
    do {                                                                                                       \
        __global const float *row_ = p + (ulong)clamp((r), 0, (int)h - 1) * w;                                  \
        centre = load16_clamped(row_, 2 * x, last);                                                            \
        edges = (float2)(row_[left], row_[right]);                                                             \
    } while (0)

/* gid(0): 8 output columns from 8 gid(0), gid(1): a strip of HROWS output rows, gid(2): the plane. Output row y
 * is input rows 2 y - 1 .. 2 y + 2 summed [1 3 3 1] (16 columns and the one either side), then pairs of columns
 * [1 3 3 1]; the two rows it shares with the next output row are kept, so each input row is read once. */
__kernel void register_halve(__global const float *restrict src, __global float *restrict dst, const uint w,
                             const uint h, const uint w2, const uint h2)
{
    const int x = 8 * get_global_id(0), y0 = HROWS * get_global_id(1);
    const ulong k = get_global_id(2);
    if (x >= (int)w2 || y0 >= (int)h2) return; /* no barrier in this kernel */
    __global const float *p = src + k * w * h;
    const int last = (int)w - 1, left = max(2 * x - 1, 0), right = min(2 * x + 16, last);
    float16 c0, c1, c2, c3;
    float2 e0, e1, e2, e3;
    HALVE_ROW(2 * y0 - 1, c0, e0);
    HALVE_ROW(2 * y0, c1, e1);
    const int y1 = min(y0 + HROWS, (int)h2);
    for (int y = y0; y < y1; ++y) {
        HALVE_ROW(2 * y + 1, c2, e2);
        HALVE_ROW(2 * y + 2, c3, e3);
        const float16 c = 0.125f * (c0 + c3) + 0.375f * (c1 + c2);
        const float2 e = 0.125f * (e0 + e3) + 0.375f * (e1 + e2);
        /* single lanes, never .even / .odd: Oclgrind's uninitialised-value check fails on multi-lane components */
        const float8 even = (float8)(c.s0, c.s2, c.s4, c.s6, c.s8, c.sa, c.sc, c.se);
        const float8 odd = (float8)(c.s1, c.s3, c.s5, c.s7, c.s9, c.sb, c.sd, c.sf);
        const float8 before = (float8)(e.s0, c.s1, c.s3, c.s5, c.s7, c.s9, c.sb, c.sd);
        const float8 after = (float8)(c.s2, c.s4, c.s6, c.s8, c.sa, c.sc, c.se, e.s1);
        const float8 out = 0.375f * (even + odd) + 0.125f * (before + after);
        __global float *o = dst + k * w2 * h2 + (ulong)y * w2 + x;
        if (x + 8 <= (int)w2) {
            vstore8(out, 0, o);
        } else {
            const int left_over = (int)w2 - x;
            o[0] = out.s0;
            if (left_over > 1) o[1] = out.s1;
            if (left_over > 2) o[2] = out.s2;
            if (left_over > 3) o[3] = out.s3;
            if (left_over > 4) o[4] = out.s4;
            if (left_over > 5) o[5] = out.s5;
            if (left_over > 6) o[6] = out.s6;
        }
        c0 = c2;
        e0 = e2;
        c1 = c3;
        e1 = e3;
    }
}

/* gid(0): the shift (dy + R) (2 R + 1) + dx + R; gid(1): the frame, the reference skipped */
__kernel void register_search(__global const float *restrict level, const uint w, const uint h, const uint ref,
                              const int R, const float speed, __global float *restrict score)
{
    const int side = 2 * R + 1, s = get_global_id(0);
    if (s >= side * side) return; /* no barrier in this kernel */
    const uint j = get_global_id(1), k = j + (j >= ref);
    const int dx = s % side - R, dy = s / side - R;
    /* frame k's reach: speed (px of this level per frame) times the frames from the reference, and a pixel */
    const float reach = speed * (float)abs((int)k - (int)ref) + 1.0f;
    if ((float)abs(dx) > ceil(reach) || (float)abs(dy) > ceil(reach)) {
        score[(ulong)j * side * side + s] = -2.0f;
        return;
    }
    const ulong n = (ulong)w * h;
    __global const float *T = level + (ulong)ref * n, *I = level + (ulong)k * n;
    const int x0 = max(0, -dx), x1 = min((int)w, (int)w - dx), y0 = max(0, -dy), y1 = min((int)h, (int)h - dy);
    float st = 0.0f, si = 0.0f, stt = 0.0f, sii = 0.0f, sti = 0.0f;
    for (int y = y0; y < y1; ++y) {
        __global const float *tr = T + (ulong)y * w, *ir = I + (ulong)(y + dy) * w + dx;
        for (int x = x0; x < x1; ++x) {
            const float t = tr[x], i = ir[x];
            st += t;
            si += i;
            stt = t * t + stt;
            sii = i * i + sii;
            sti = t * i + sti;
        }
    }
    const float count = (float)(max(x1 - x0, 0) * max(y1 - y0, 0));
    float r = -2.0f;
    if (4.0f * count >= (float)n) {
        const float vt = stt - st * st / count, vi = sii - si * si / count, c = sti - st * si / count;
        if (vt > 0.0f && vi > 0.0f) r = c / sqrt(vt * vi);
    }
    score[(ulong)j * side * side + s] = r;
}

/* The sums of one frame, in the host's order: J' I, J' 1, J' T (NP each), J' J (upper triangle, by rows), then n,
 * I, T, I^2, I T, T^2; each a named register (PoCL keeps a private array in memory). */
#define SUMS_TRANSLATION(X) \
    X(0, tx * i) X(1, ty * i) X(2, tx) X(3, ty) X(4, tx * t) X(5, ty * t) X(6, tx * tx) X(7, tx * ty) \
    X(8, ty * ty) X(9, 1.0f) X(10, i) X(11, t) X(12, i * i) X(13, i * t) X(14, t * t)
#define SUMS_AFFINE(X) \
    X(0, j0 * i) X(1, j1 * i) X(2, j2 * i) X(3, j3 * i) X(4, j4 * i) X(5, j5 * i) X(6, j0) X(7, j1) X(8, j2) \
    X(9, j3) X(10, j4) X(11, j5) X(12, j0 * t) X(13, j1 * t) X(14, j2 * t) X(15, j3 * t) X(16, j4 * t) \
    X(17, j5 * t) X(18, j0 * j0) X(19, j0 * j1) X(20, j0 * j2) X(21, j0 * j3) X(22, j0 * j4) X(23, j0 * j5) \
    X(24, j1 * j1) X(25, j1 * j2) X(26, j1 * j3) X(27, j1 * j4) X(28, j1 * j5) X(29, j2 * j2) X(30, j2 * j3) \
    X(31, j2 * j4) X(32, j2 * j5) X(33, j3 * j3) X(34, j3 * j4) X(35, j3 * j5) X(36, j4 * j4) X(37, j4 * j5) \
    X(38, j5 * j5) X(39, 1.0f) X(40, i) X(41, t) X(42, i * i) X(43, i * t) X(44, t * t)
#if AFFINE
#define SUMS SUMS_AFFINE
#else
#define SUMS SUMS_TRANSLATION
#endif
#define SUM_DECLARE(n, e) float s##n = 0.0f;
#define SUM_ADD(n, e) s##n += (e);
#define SUM_PUT(n, e) part[(n) * GROUP + lid] = s##n;

/* Pixels of a row a work-item takes at a time */
#define CHUNK 32

/* gid(0) strides over chunks of CHUNK pixels of the reference's rows, one in from its edge; gid(1) is the frame (the
 * reference skipped); maps: per frame the 2 x 3 map M_k of this level's pixels, frame px = M_k (x, y, 1); out: NS
 * sums per group and frame */
__kernel void register_step(__global const float *restrict level, const uint w, const uint h, const uint ref,
                            __global const float *restrict maps, const float CS, const float CU, const float CV,
                            const float GSCALE, const uint stride, __global float *restrict out)
{
    const uint j = get_global_id(1), k = j + (j >= ref), lid = get_local_id(0);
    const ulong n = (ulong)w * h;
    __global const float *T = level + (ulong)ref * n, *I = level + (ulong)k * n;
    __global const float *m = maps + 6 * j;
    const float m0 = m[0], m1 = m[1], m2 = m[2], m3 = m[3], m4 = m[4], m5 = m[5];
    const float right = (float)w - 1.0f, bottom = (float)h - 1.0f;
    const uint per_row = (w - 2 + CHUNK - 1) / CHUNK, chunks = per_row * BANDED_ROWS(h, stride);
    SUMS(SUM_DECLARE)
    FOR_CHUNKS(c, chunks) {
        const int y = ROW_OF_BANDS((int)(c / per_row), stride), x0 = 1 + (c % per_row) * CHUNK;
        const int x1 = min(x0 + CHUNK, (int)w - 1);
        if (y > (int)h - 2) continue;
        const float bx = m1 * y + m2, by = m4 * y + m5;
#if AFFINE
        const float v = CS * y + CV;
#endif
        __global const float *row = T + (ulong)y * w;
        for (int x = x0; x < x1; ++x) {
            const float xs = m0 * x + bx, ys = m3 * x + by;
            if (!(xs >= 0.0f && ys >= 0.0f && xs <= right && ys <= bottom)) continue; /* NaN maps too */
            const int ix = min((int)xs, (int)w - 2), iy = min((int)ys, (int)h - 2);
            const float fx = xs - (float)ix, fy = ys - (float)iy;
            __global const float *q = I + (ulong)iy * w + ix;
            const float top = (q[1] - q[0]) * fx + q[0], low = (q[w + 1] - q[w]) * fx + q[w];
            const float i = (low - top) * fy + top;
            const float t = row[x];
            const float tx = 0.5f * GSCALE * (row[x + 1] - row[x - 1]);
            const float ty = 0.5f * GSCALE * (row[x + w] - row[x - (int)w]);
#if AFFINE
            const float u = CS * x + CU;
            const float j0 = tx * u, j1 = tx * v, j2 = tx, j3 = ty * u, j4 = ty * v, j5 = ty;
#endif
            SUMS(SUM_ADD)
        }
    }
    __local float part[NS * GROUP];
    SUMS(SUM_PUT)
    barrier(CLK_LOCAL_MEM_FENCE);
    const ulong at = ((ulong)j * get_num_groups(0) + get_group_id(0)) * NS;
    for (uint s = lid; s < NS; s += GROUP) {
        float total = 0.0f;
        for (int e = 0; e < GROUP; ++e) total += part[s * GROUP + e];
        out[at + s] = total;
    }
}

/* register_step for a translation per frame, 16 pixels at a time (float16: on PoCL with AVX-512 a third faster
 * than 8): the bilinear weights are the same at every pixel, and the pixels whose sample lies in frame k a
 * rectangle (a column dropped at an integer shift) */
#define SHIFT_SUMS(X) \
    X(0, tx * i) X(1, ty * i) X(2, tx) X(3, ty) X(4, tx * t) X(5, ty * t) X(6, tx * tx) X(7, tx * ty) \
    X(8, ty * ty) X(9, one) X(10, i) X(11, t) X(12, i * i) X(13, i * t) X(14, t * t)
#define SHIFT_DECLARE(n, e) float16 s##n = (float16)(0.0f);
#define SHIFT_ADD(n, e) s##n += (e);
#define SHIFT_PUT(n, e) part[(n) * GROUP + lid] = s##n.s0 + s##n.s1 + s##n.s2 + s##n.s3 + s##n.s4 + s##n.s5 \
    + s##n.s6 + s##n.s7 + s##n.s8 + s##n.s9 + s##n.sa + s##n.sb + s##n.sc + s##n.sd + s##n.se + s##n.sf;

__kernel void register_shift(__global const float *restrict level, const uint w, const uint h, const uint ref,
                             __global const float *restrict maps, const float GSCALE, const uint stride,
                             __global float *restrict out)
{
    const uint j = get_global_id(1), k = j + (j >= ref), lid = get_local_id(0);
    const ulong n = (ulong)w * h;
    __global const float *T = level + (ulong)ref * n, *I = level + (ulong)k * n;
    const float dx = maps[6 * j + 2], dy = maps[6 * j + 5];
    const float fdx = floor(dx), fdy = floor(dy);
    /* NaN or far off the field: no pixel (the ranges below come out empty) */
    const int ix = (isfinite(fdx) && fabs(fdx) < (float)w) ? (int)fdx : (int)w;
    const int iy = (isfinite(fdy) && fabs(fdy) < (float)h) ? (int)fdy : (int)h;
    const float fx = dx - floor(dx), fy = dy - floor(dy);
    const int xlo = max(1, -ix), xhi = min((int)w - 2, (int)w - 2 - ix);
    const int ylo = max(1, -iy), yhi = min((int)h - 2, (int)h - 2 - iy);
    const int per_row = max(0, (xhi - xlo + 16) / 16), rows = yhi >= ylo ? BANDED_ROWS(h, stride) : 0;
    const uint chunks = (uint)(per_row * rows);
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    SHIFT_SUMS(SHIFT_DECLARE)
    FOR_CHUNKS(c, chunks) {
        const int y = ROW_OF_BANDS((int)c / per_row, stride), x = xlo + 16 * ((int)c % per_row);
        if (y < ylo || y > yhi) continue; /* the rows of the reference whose samples lie in frame k */
        const int16 inside = x + lane <= (int16)(xhi);
        const float16 one = inside ? (float16)(1.0f) : (float16)(0.0f);
        __global const float *row = T + (ulong)y * w;
        __global const float *q = I + (ulong)(y + iy) * w;
        const float16 a = load16_clamped(q, x + ix, xhi + ix), b = load16_clamped(q, x + ix + 1, xhi + ix + 1);
        const float16 d = load16_clamped(q + w, x + ix, xhi + ix), e = load16_clamped(q + w, x + ix + 1, xhi + ix + 1);
        const float16 top = (b - a) * fx + a, low = (e - d) * fx + d;
        const float16 i = ((low - top) * fy + top) * one;
        const float16 t = load16_clamped(row, x, xhi) * one;
        const float16 tx = 0.5f * GSCALE * (load16_clamped(row, x + 1, xhi + 1) - load16_clamped(row, x - 1, xhi - 1))
                          * one;
        const float16 ty = 0.5f * GSCALE * (load16_clamped(row + w, x, xhi) - load16_clamped(row - w, x, xhi)) * one;
        SHIFT_SUMS(SHIFT_ADD)
    }
    __local float part[15 * GROUP];
    SHIFT_SUMS(SHIFT_PUT)
    barrier(CLK_LOCAL_MEM_FENCE);
    const ulong at = ((ulong)j * get_num_groups(0) + get_group_id(0)) * 15;
    for (uint s = lid; s < 15; s += GROUP) {
        float total = 0.0f;
        for (int e = 0; e < GROUP; ++e) total += part[s * GROUP + e];
        out[at + s] = total;
    }
}
