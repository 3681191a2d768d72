/* The per-pixel residual check of a motion-compensated decoding (specgpu.engine.residual): are a pixel's N
 * compensated samples explained by one reflectance?
 *
 * Per pixel: the samples' residual components res = P s (R of them), their covariance
 * C = P diag(var) P^T + mismatch with var_k the noise of sample k at its own level, and chi2 = res^T C^-1 res by a
 * Cholesky factorisation and forward substitution. A pixel whose chi2 exceeds THRESHOLD gets MASK_INCONSISTENT.
 * A NaN sample (outside the field, no response) gives a NaN chi2, which flags nothing, as a negative pivot does.
 *
 * Build macros: N (samples per pixel), R (residual components), HAS_GAIN, WRITE_CHI (also write chi2).
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
    const uint i = get_global_id(0);
    if (i >= n)
        return; /* no barrier in this kernel */
    float g = 1.0f;
#if HAS_GAIN
    g = gain[i];
    g = (isfinite(g) && g > 0.0f) ? g : 1.0f;
#endif
    float s[N], var[N];
    for (int k = 0; k < N; k++) {
        const float v = samples[(size_t)k * n + i];
        float raw = v / g;
        raw = raw < 0.0f ? 0.0f : raw; /* a NaN stays NaN */
        s[k] = v;
        var[k] = (raw * inv_e_per_dn + read_var + light_var * raw * raw) * (g * g);
    }
    float L[R * R], z[R];
    float chi = 0.0f;
    for (int j = 0; j < R; j++) {
        for (int a = j; a < R; a++) {
            float c = mismatch[a * R + j];
            for (int k = 0; k < N; k++)
                c = project[a * N + k] * project[j * N + k] * var[k] + c;
            for (int m = 0; m < j; m++)
                c -= L[a * R + m] * L[j * R + m];
            if (a == j)
                L[j * R + j] = sqrt(c);
            else
                L[a * R + j] = c / L[j * R + j];
        }
        float r = 0.0f;
        for (int k = 0; k < N; k++)
            r = project[j * N + k] * s[k] + r;
        for (int m = 0; m < j; m++)
            r -= L[j * R + m] * z[m];
        z[j] = r / L[j * R + j];
        chi = z[j] * z[j] + chi;
    }
#if WRITE_CHI
    chi_out[i] = chi;
#endif
    if (chi > threshold)
        mask[i] |= (uchar)MASK_INCONSISTENT;
}
