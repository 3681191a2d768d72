/* The per-pixel residual check of a motion-compensated decoding (specgpu.engine.residual): are a pixel's N
 * compensated samples explained by one reflectance?
 *
 * Per pixel: the samples' residual components res = P s (R of them), their covariance
 * C = P diag(var) P^T + mismatch with var_k the noise of sample k at its own level, and chi2 = res^T C^-1 res by a
 * Cholesky factorisation and forward substitution. A pixel whose chi2 exceeds THRESHOLD gets MASK_INCONSISTENT.
 * A NaN sample (outside the field, no response) gives a NaN chi2, which flags nothing, as a negative pivot does.
 *
 * VW pixels per work-item (common.h: 8 as vectors on CPU devices, 1 on GPUs); every loop has a bound known at build
 * time and is unrolled, so the per-pixel arrays are registers, not private memory.
 * Build macros: N (samples per pixel), R (residual components), HAS_GAIN, WRITE_CHI (also write chi2), VW.
 */
#include "common.h"

#ifndef N
#define N 1
#endif
#ifndef R
#define R 1
#endif
#ifndef WRITE_CHI
#define WRITE_CHI 0
#endif

/* samples: N planes of n floats (the warped pass's planar group); gain: n floats (the flat field, a non-positive
 * or non-finite value read as 1); project: R x N; mismatch: R x R; noise: 1 / (e- per DN), read variance DN^2,
 * the light's relative fluctuation squared. */
__kernel void residual_flag(__global const float *samples, __global const float *gain,
                            __constant float *project, __constant float *mismatch,
                            const float inv_e_per_dn, const float read_var, const float light_var,
                            const float threshold, __global uchar *mask, __global float *chi_out,
                            const uint n)
{
    PIXEL_RANGE(n); /* no barrier in this kernel */
    floatv g = (floatv)1.0f;
#if HAS_GAIN
    g = load_f(gain, base, count);
    g = (isfinite(g) & (g > 0.0f)) ? g : (floatv)1.0f;
#endif
    const floatv g2 = g * g;
    floatv s[N], var[N];
    _Pragma("unroll") for (int k = 0; k < N; k++) {
        const floatv v = load_f(samples + (ulong)k * n, base, count);
        floatv raw = v / g;
        raw = raw < 0.0f ? (floatv)0.0f : raw; /* a NaN stays NaN */
        s[k] = v;
        var[k] = (raw * inv_e_per_dn + read_var + light_var * raw * raw) * g2;
    }
    floatv L[R * R], z[R];
    floatv chi = (floatv)0.0f;
    _Pragma("unroll") for (int j = 0; j < R; j++) {
        _Pragma("unroll") for (int a = j; a < R; a++) {
            floatv c = (floatv)mismatch[a * R + j];
            _Pragma("unroll") for (int k = 0; k < N; k++)
                c = (project[a * N + k] * project[j * N + k]) * var[k] + c;
            _Pragma("unroll") for (int m = 0; m < j; m++)
                c -= L[a * R + m] * L[j * R + m];
            if (a == j)
                L[j * R + j] = sqrt(c);
            else
                L[a * R + j] = c / L[j * R + j];
        }
        floatv r = (floatv)0.0f;
        _Pragma("unroll") for (int k = 0; k < N; k++)
            r = project[j * N + k] * s[k] + r;
        _Pragma("unroll") for (int m = 0; m < j; m++)
            r -= L[j * R + m] * z[m];
        z[j] = r / L[j * R + j];
        chi = z[j] * z[j] + chi;
    }
#if WRITE_CHI
    store_f(chi, chi_out, base, count);
#endif
    const intv flag = chi > threshold ? (intv)MASK_INCONSISTENT : (intv)0;
#if VW == 8
    uchar8 m;
    if (count == VW) {
        m = LOAD8(uchar, mask + base);
    } else {
        uchar t[VW];
        for (uint j = 0; j < VW; ++j) t[j] = j < count ? mask[base + j] : 0;
        m = vload8(0, t);
    }
    store_mask(m | CONVERT_UCHARV(flag), mask, base, count);
#else
    mask[base] |= CONVERT_UCHARV(flag);
#endif
}
