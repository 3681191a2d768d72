/* The noise floors of a sequence's frames on the device (specgpu.engine.noise_floor; the NumPy reference is
 * specgpu.motion.consistency.noise_floors): per frame and pixel, coef_k (max(m_k, 0) / g + read_box), m_k the mean
 * over a (2 R + 1)^2 box (edges replicated, as scipy.ndimage's "nearest") of the frame above its dark level times
 * the squared flat field, read_box the same box mean of the read noise times the squared flat field (made once).
 *
 * Two separable passes: floor_cols sums each pixel's column window (a running sum), floor_rows those sums along
 * its row's window and writes the floor. On CPU devices a work-item takes 8 columns (vectors, common.h's VW) down
 * a strip of CSTRIP rows, then a span of RSPAN pixels of a row (few work-items: PoCL's cost per work-item is
 * more than a pixel's); on GPUs one pixel each, neighbours along x (coalesced loads). A running sum starts afresh
 * every strip, so float32 rounding does not build up along thousands of rows. The row pass sums each window
 * whole: on CPU devices 8 pixels at a time (2 R + 1 vector loads) where their windows lie inside the row.
 *
 * Build macros: IN_T (uchar, ushort, float), HAS_DARK, HAS_GAIN, R (the window's half width), VW, CSTRIP, RSPAN.
 */
/* common.h: VW, and the defaults of IN_T, HAS_DARK and HAS_GAIN */
#include "common.h"

#ifndef R
#define R 4
#endif
#ifndef CSTRIP
#define CSTRIP 1
#endif
#ifndef RSPAN
#define RSPAN 1
#endif

/* x (o - dark) times the squared flat field of sample i of a frame's plane */
inline float floor_value(__global const IN_T *restrict plane, __global const float *restrict dark,
                         __global const float *restrict flat2, uint i)
{
    float x = (float)plane[i];
#if HAS_DARK
    x -= dark[i];
#endif
#if HAS_GAIN
    x *= flat2[i];
#endif
    return x;
}

#if VW == 8
/* the same of the 8 samples from i on */
inline float8 floor_values8(__global const IN_T *restrict plane, __global const float *restrict dark,
                            __global const float *restrict flat2, uint i)
{
    float8 x = convert_float8(vload8(0, plane + i));
#if HAS_DARK
    x -= vload8(0, dark + i);
#endif
#if HAS_GAIN
    x *= vload8(0, flat2 + i);
#endif
    return x;
}
#endif

/* frames: the frames buffer's planes of n samples; frame_of: the plane of each frame made (get_global_id(2));
 * sums: its planes of n floats, each pixel's sum over its column's window. A work-item takes VW pixels of a row
 * down CSTRIP rows, a running sum of whole rows (each row of the frame read once per strip, 2 R more). */
__kernel void floor_cols(__global const IN_T *restrict frames, __constant const uint *restrict frame_of,
                         __global const float *restrict dark, __global const float *restrict flat2,
                         __global float *restrict sums, const uint width, const uint height)
{
    const uint x0 = get_global_id(0) * VW, y0 = get_global_id(1) * CSTRIP, k = get_global_id(2);
    if (x0 >= width || y0 >= height)
        return;
    const uint n = width * height, y1 = min(y0 + CSTRIP, height);
    const int last = (int)height - 1;
    __global const IN_T *plane = frames + (ulong)frame_of[k] * n;
    __global float *out = sums + (ulong)k * n;
#if VW == 8
    if (x0 + 8 <= width) {
        float8 s = (float8)0.0f;
        for (int j = -R; j <= R; ++j)
            s += floor_values8(plane, dark, flat2, (uint)clamp((int)y0 + j, 0, last) * width + x0);
        for (uint y = y0; y < y1; ++y) {
            vstore8(s, 0, out + y * width + x0);
            s += floor_values8(plane, dark, flat2, (uint)min((int)y + R + 1, last) * width + x0)
                 - floor_values8(plane, dark, flat2, (uint)max((int)y - R, 0) * width + x0);
        }
        return;
    }
#endif
    for (uint x = x0; x < min(x0 + VW, width); ++x) {
        float s = 0.0f;
        for (int j = -R; j <= R; ++j)
            s += floor_value(plane, dark, flat2, (uint)clamp((int)y0 + j, 0, last) * width + x);
        for (uint y = y0; y < y1; ++y) {
            out[y * width + x] = s;
            s += floor_value(plane, dark, flat2, (uint)min((int)y + R + 1, last) * width + x)
                 - floor_value(plane, dark, flat2, (uint)max((int)y - R, 0) * width + x);
        }
    }
}

/* sums: floor_cols' planes; coef: per frame made; read_box: n floats (or unread without HAS_GAIN: read_var);
 * floors: planes of n floats. A work-item takes RSPAN pixels of a row. */
__kernel void floor_rows(__global const float *restrict sums, __constant const float *restrict coef,
                         __global const float *restrict read_box, const float read_var, const float inv_e_per_dn,
                         __global float *restrict floors, const uint width, const uint height)
{
    const uint x0 = get_global_id(0) * RSPAN, y = get_global_id(1), k = get_global_id(2);
    if (x0 >= width || y >= height)
        return;
    const uint n = width * height, row = y * width, x1 = min(x0 + RSPAN, width);
    const int last = (int)width - 1;
    __global const float *col = sums + (ulong)k * n + row;
    __global float *out = floors + (ulong)k * n + row;
    const float area = 1.0f / (float)((2 * R + 1) * (2 * R + 1)), c = coef[k];
    /* the pixels whose windows lie inside the row: [inner0, inner1) */
    const uint inner0 = max(x0, (uint)R), inner1 = (uint)max((int)min(x1, width - R), (int)inner0);
    for (uint x = x0; x < x1; ++x) {
#if VW == 8
        if (x == inner0) { /* vectors of 8 pixels: 2 R + 1 loads of 8 sums each */
            for (; x + 8 <= inner1; x += 8) {
                float8 v = (float8)0.0f;
                for (int j = -R; j <= R; ++j)
                    v += vload8(0, col + x + j);
#if HAS_GAIN
                const float8 rb = vload8(0, read_box + row + x);
#else
                const float8 rb = (float8)read_var;
#endif
                vstore8(c * (max(v * area, 0.0f) * inv_e_per_dn + rb), 0, out + x);
            }
            if (x >= x1)
                break;
        }
#endif
        float s = 0.0f;
        for (int j = -R; j <= R; ++j)
            s += col[clamp((int)x + j, 0, last)];
#if HAS_GAIN
        const float rb = read_box[row + x];
#else
        const float rb = read_var;
#endif
        out[x] = c * (max(s * area, 0.0f) * inv_e_per_dn + rb);
    }
}
