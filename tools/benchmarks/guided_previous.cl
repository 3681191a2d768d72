/* The guided filter before the running sums (a copy kept for tools/benchmarks/guided_speed.py, which times it
 * beside the package's filter; the package never builds it): a multi-channel image smoothed by a one-channel guide,
 * built from box means.
 *
 * Images are (H, W, C) float32, channels last, flattened; one work-item per element, its channel the fastest
 * dimension of the range (no index division; neighbouring work-items read neighbouring floats). A box mean covers the
 * (2R + 1) taps along one axis that lie inside the image and divides by their count, so two passes (x, then y)
 * give the mean over the window clipped to the image.
 */

/* Box mean along x of an (H, W, C) image; the range is (C, W, H). */
__kernel void box_h(__global const float *restrict src, __global float *restrict dst, const int H, const int W,
                    const int C, const int R)
{
    const int c = get_global_id(0), x = get_global_id(1), y = get_global_id(2);
    if (c >= C || x >= W || y >= H)
        return;
    const int x0 = max(x - R, 0), x1 = min(x + R, W - 1);
    __global const float *row = src + (size_t)y * W * C + c;
    float s = 0.0f;
    for (int k = x0; k <= x1; ++k)
        s += row[(size_t)k * C];
    dst[((size_t)y * W + x) * C + c] = s / (float)(x1 - x0 + 1);
}

/* Box mean along y of an (H, W, C) image; the range is (C, W, H). */
__kernel void box_v(__global const float *restrict src, __global float *restrict dst, const int H, const int W,
                    const int C, const int R)
{
    const int c = get_global_id(0), x = get_global_id(1), y = get_global_id(2);
    if (c >= C || x >= W || y >= H)
        return;
    const size_t rowlen = (size_t)W * C;
    const int y0 = max(y - R, 0), y1 = min(y + R, H - 1);
    __global const float *col = src + (size_t)x * C + c;
    float s = 0.0f;
    for (int k = y0; k <= y1; ++k)
        s += col[(size_t)k * rowlen];
    dst[(size_t)y * rowlen + (size_t)x * C + c] = s / (float)(y1 - y0 + 1);
}

/* The products the filter averages: x = [p (B), g p (B), g, g^2] per pixel, from the image p (N, B) and the
 * guide g (N); the range is (B, N). */
__kernel void gf_products(__global const float *restrict p, __global const float *restrict g,
                          __global float *restrict x, const int B, const ulong n)
{
    const int b = get_global_id(0);
    const size_t q = get_global_id(1);
    if (b >= B || q >= n)
        return;
    const float gi = g[q];
    const float v = p[q * B + b];
    __global float *o = x + q * (size_t)(2 * B + 2);
    o[b] = v;
    o[B + b] = gi * v;
    if (b == 0) {
        o[2 * B] = gi;
        o[2 * B + 1] = gi * gi;
    }
}

/* Per-window linear model p = a g + b from the box means m of the products: a = cov(g, p) / (var g + eps),
 * b = mean p - a mean g; ab = [a (B), b (B)] per pixel; the range is (B, N). */
__kernel void gf_coeffs(__global const float *restrict m, __global float *restrict ab, const int B, const float eps,
                        const ulong n)
{
    const int b = get_global_id(0);
    const size_t q = get_global_id(1);
    if (b >= B || q >= n)
        return;
    __global const float *o = m + q * (size_t)(2 * B + 2);
    const float mg = o[2 * B];
    const float vg = fmax(o[2 * B + 1] - mg * mg, 0.0f);
    const float a = (o[B + b] - mg * o[b]) / (vg + eps);
    ab[q * (size_t)(2 * B) + b] = a;
    ab[q * (size_t)(2 * B) + B + b] = o[b] - a * mg;
}

/* The filtered image q = mean a * g + mean b from the box means of the coefficients (N, 2B); the range is
 * (B, N). */
__kernel void gf_apply(__global const float *restrict mab, __global const float *restrict g,
                       __global float *restrict out, const int B, const ulong n)
{
    const int b = get_global_id(0);
    const size_t q = get_global_id(1);
    if (b >= B || q >= n)
        return;
    out[q * B + b] = mab[q * (size_t)(2 * B) + b] * g[q] + mab[q * (size_t)(2 * B) + B + b];
}
