/* The variance of a motion-compensated decoding's outputs, made where the warped pass samples the frames
 * (specgpu.engine.warped_variance; the NumPy reference is specgpu.pipeline.moving_decode.warped_sample_variances).
 *
 * Frame k's sample of a pixel is the bilinear interpolation s = sum_i w_i c_i of the four corrected sensor pixels
 * c_i = (o_i - dark_i) * gain_i around the point the frame saw it at. Per frame and pixel:
 *   own      sum_i w_i^2 v_i, v_i = gain_i^2 (x_i / (e- per DN) + read variance), x_i = o_i - dark_i
 *   total    own + (light_rms * sum_i w_i gain_i (x_i - room_i))^2 with WITH_LIGHT (room_i: the ambient frame's
 *            x_i; the ambient frame itself gets no light term), else own
 *   filtered (sum_i w_i v_i) rho(fx) rho(fy), rho(f) = 1 - 2 f (1 - f) corr: the own part as a guided filter, which
 *            averages neighbouring samples that share sensor pixels, takes it
 * and what is written is not the K frames' variances but NCH channels of them, out[c] = sum_k weights[c][k] V_k
 * (the outputs' variances through the decoder's squared rows), for each kind asked for: no K-plane map is made.
 * A pixel any frame saw outside the field (beyond half a pixel of the edge) is NaN in every channel; the taps are
 * clamped to the field as the warped pass clamps them.
 *
 * A work-item takes VW consecutive pixels of a row (common.h: 8 as vectors on CPU devices, one on GPUs). A frame
 * displaced by a translation whose taps of those pixels all lie inside the field reads them as two vectors per row
 * of taps (the weights are the same for every pixel); any other frame (an affine map, the field's edges) goes pixel
 * by pixel.
 *
 * Build macros: IN_T (uchar, ushort, float), KR (frames read), NCH (channels), HAS_GAIN, WITH_LIGHT, AMBIENT (the
 * ambient frame's plane in the frames buffer, or -1), WANT_OWN, WANT_FILTERED, VW.
 */
#include "common.h"

#ifndef KR
#define KR 1
#endif
#ifndef NCH
#define NCH 1
#endif
#ifndef WITH_LIGHT
#define WITH_LIGHT 0
#endif
#ifndef AMBIENT
#define AMBIENT (-1)
#endif
#ifndef WANT_OWN
#define WANT_OWN 0
#endif
#ifndef WANT_FILTERED
#define WANT_FILTERED 0
#endif

#if VW == 8
#define VLOAD(p, i) vload8(0, (p) + (i))
#define TO_F(v) convert_float8(v)
#else
#define VLOAD(p, i) ((p)[i])
#define TO_F(v) ((float)(v))
#endif

#if HAS_GAIN
#define GAIN2(i) VLOAD(gain2, i)
#define GAIN2_1(i) gain2[i]
#else
#define GAIN2(i) ((floatv)1.0f)
#define GAIN2_1(i) 1.0f
#endif
#if WITH_LIGHT && AMBIENT >= 0
#define ROOM(i) (TO_F(VLOAD(room_plane, i)) - VLOAD(dark, i))
#define ROOM_1(i) ((float)room_plane[i] - dark[i])
#else
#define ROOM(i) ((floatv)0.0f)
#define ROOM_1(i) 0.0f
#endif

/* One tap: its sensor pixel's variance v and the sums it adds to (own: w^2 v, interp: w v, signal: w g (x - room)). */
#define TAP(i, w, LOAD, G2, RM, T)                                    \
    {                                                                 \
        const T xi = TO_##LOAD(plane, i) - LOAD_DARK_##LOAD(i);       \
        const T g2 = G2(i);                                           \
        const T v = g2 * (xi * inv_e_per_dn + read_var);              \
        own += (w) * (w) * v;                                         \
        interp += (w) * v;                                            \
        LIGHT_TAP((w) * sqrt(g2) * (xi - RM(i)))                      \
    }
#define TO_V(p, i) TO_F(VLOAD(p, i))
#define TO_S(p, i) ((float)(p)[i])
#define LOAD_DARK_V(i) VLOAD(dark, i)
#define LOAD_DARK_S(i) dark[i]
#if WITH_LIGHT
#define LIGHT_TAP(term) signal += (term);
#else
#define LIGHT_TAP(term)
#endif

/* frames: the frames buffer's planes of n samples; frame_of: the plane of each frame read; maps: KR x 6, the
 * affine map (x, y, 1) -> the point frame k saw the pixel at; weights: NCH x KR; dark, gain2: n floats (gain2 the
 * squared flat field); outputs: NCH planes of n floats each. Noise: 1 / (e- per DN), read variance DN^2,
 * light_rms; corr: the filter's interpolation correlation. */
__kernel void warped_variances(__global const IN_T *restrict frames, __constant const uint *restrict frame_of,
                               __constant const float *restrict maps, __constant const float *restrict weights,
                               __global const float *restrict dark, __global const float *restrict gain2,
                               const float inv_e_per_dn, const float read_var, const float light_rms,
                               const float corr, __global float *restrict total, __global float *restrict own_out,
                               __global float *restrict filtered_out, const uint width, const uint height)
{
    const uint px0 = get_global_id(0) * VW, py = get_global_id(1);
    if (px0 >= width || py >= height)
        return;
    const uint n = width * height;
    const float y = (float)py;
#if WITH_LIGHT && AMBIENT >= 0
    __global const IN_T *room_plane = frames + (ulong)AMBIENT * n;
#endif
    floatv acc_t[NCH], acc_o[NCH], acc_f[NCH];
    for (int c = 0; c < NCH; ++c) {
        acc_t[c] = (floatv)0.0f;
        acc_o[c] = (floatv)0.0f;
        acc_f[c] = (floatv)0.0f;
    }
    floatv outside = (floatv)0.0f;
    for (int k = 0; k < KR; ++k) {
        __constant const float *m = maps + 6 * k;
        __global const IN_T *plane = frames + (ulong)frame_of[k] * n;
        floatv own = (floatv)0.0f, interp = (floatv)0.0f, signal = (floatv)0.0f, rho;
        const bool translation = m[0] == 1.0f && m[1] == 0.0f && m[3] == 0.0f && m[4] == 1.0f;
        const float sx0 = (float)px0 + m[2], sy0 = y + m[5];
        const float fx0 = floor(sx0), fy0 = floor(sy0);
        if (translation && fx0 >= 0.0f && fx0 + VW <= (float)(width - 1) && fy0 >= 0.0f
            && fy0 + 1.0f <= (float)(height - 1)) {
            /* every tap inside the field: two vectors per row of taps, one set of weights */
            const float fx = sx0 - fx0, fy = sy0 - fy0;
            const float w00 = (1.0f - fx) * (1.0f - fy), w01 = fx * (1.0f - fy), w10 = (1.0f - fx) * fy,
                        w11 = fx * fy;
            const uint i00 = (uint)fy0 * width + (uint)fx0;
            TAP(i00, w00, V, GAIN2, ROOM, floatv)
            TAP(i00 + 1, w01, V, GAIN2, ROOM, floatv)
            TAP(i00 + width, w10, V, GAIN2, ROOM, floatv)
            TAP(i00 + width + 1, w11, V, GAIN2, ROOM, floatv)
            rho = (floatv)((1.0f - 2.0f * fx * (1.0f - fx) * corr) * (1.0f - 2.0f * fy * (1.0f - fy) * corr));
        } else {
            /* pixel by pixel: each its own point, taps clamped to the field */
            float o_[VW], i_[VW], s_[VW], r_[VW], out_[VW];
            for (int l = 0; l < VW; ++l) {
                const float x = (float)min(px0 + l, width - 1);
                float sx = m[0] * x + m[1] * y + m[2];
                float sy = m[3] * x + m[4] * y + m[5];
                out_[l] = ((sx < -0.501f) | (sy < -0.501f) | (sx > (float)width - 0.499f)
                           | (sy > (float)height - 0.499f)) ? 1.0f : 0.0f;
                sx = clamp(sx, 0.0f, (float)(width - 1));
                sy = clamp(sy, 0.0f, (float)(height - 1));
                const float flx = floor(sx), fly = floor(sy);
                const uint x0 = (uint)flx, y0 = (uint)fly;
                const uint dx = x0 + 1 < width ? 1u : 0u, dy = y0 + 1 < height ? width : 0u;
                const float fx = sx - flx, fy = sy - fly;
                const uint i00 = y0 * width + x0;
                const float w00 = (1.0f - fx) * (1.0f - fy), w01 = fx * (1.0f - fy), w10 = (1.0f - fx) * fy,
                            w11 = fx * fy;
                float own = 0.0f, interp = 0.0f, signal = 0.0f;
                TAP(i00, w00, S, GAIN2_1, ROOM_1, float)
                TAP(i00 + dx, w01, S, GAIN2_1, ROOM_1, float)
                TAP(i00 + dy, w10, S, GAIN2_1, ROOM_1, float)
                TAP(i00 + dy + dx, w11, S, GAIN2_1, ROOM_1, float)
                o_[l] = own;
                i_[l] = interp;
                s_[l] = signal;
                r_[l] = (1.0f - 2.0f * fx * (1.0f - fx) * corr) * (1.0f - 2.0f * fy * (1.0f - fy) * corr);
            }
#if VW == 8
            own = vload8(0, o_);
            interp = vload8(0, i_);
            signal = vload8(0, s_);
            rho = vload8(0, r_);
            outside += vload8(0, out_);
#else
            own = o_[0];
            interp = i_[0];
            signal = s_[0];
            rho = r_[0];
            outside += out_[0];
#endif
        }
        floatv tot = own;
#if WITH_LIGHT
        if ((int)frame_of[k] != AMBIENT) {
            const floatv l = light_rms * signal;
            tot += l * l;
        }
#endif
        const floatv smoothed = interp * rho;
        for (int c = 0; c < NCH; ++c) {
            const float wc = weights[c * KR + k];
            acc_t[c] += wc * tot;
            acc_o[c] += wc * own;
            acc_f[c] += wc * smoothed;
        }
    }
    const uint p = py * width + px0;
    const floatv nan_ = (floatv)NAN;
    for (int c = 0; c < NCH; ++c) {
        const floatv t = outside > 0.0f ? nan_ : acc_t[c];
        const floatv o = outside > 0.0f ? nan_ : acc_o[c];
        const floatv f = outside > 0.0f ? nan_ : acc_f[c];
#if VW == 8
        if (px0 + 8 <= width) {
            vstore8(t, 0, total + (ulong)c * n + p);
#if WANT_OWN
            vstore8(o, 0, own_out + (ulong)c * n + p);
#endif
#if WANT_FILTERED
            vstore8(f, 0, filtered_out + (ulong)c * n + p);
#endif
        } else {
            float t_[8], o_[8], f_[8];
            vstore8(t, 0, t_);
            vstore8(o, 0, o_);
            vstore8(f, 0, f_);
            for (uint l = 0; l < width - px0; ++l) {
                total[(ulong)c * n + p + l] = t_[l];
#if WANT_OWN
                own_out[(ulong)c * n + p + l] = o_[l];
#endif
#if WANT_FILTERED
                filtered_out[(ulong)c * n + p + l] = f_[l];
#endif
            }
        }
#else
        total[(ulong)c * n + p] = t;
#if WANT_OWN
        own_out[(ulong)c * n + p] = o;
#endif
#if WANT_FILTERED
        filtered_out[(ulong)c * n + p] = f;
#endif
#endif
    }
}
