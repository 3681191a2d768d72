/* specgpu shared kernel header: pixel loads and conversions, the per-pixel linear map, CIE f(t), Lab and
 * colour differences. Everything works on VW pixels at a time (floatv), in one of two variants chosen by the
 * host per device class (specgpu.runtime.kernel_variant):
 *   VW = 8  "cpu": 8 pixels per work-item (float8), which is how PoCL vectorises; the last work-item of a launch
 *           handles a partial vector with the same code, padding lanes it then does not store.
 *   VW = 1  "gpu": one pixel per work-item (scalar float), so the work-items of a GPU warp read and write
 *           consecutive addresses of every plane (coalesced loads and stores) and float16 is vstore_half.
 *
 * Vector selection is written c ? b : a, which the OpenCL C specification defines as select(a, b, c) and which
 * compiles inline; PoCL calls select() out of line.
 * Multiply-adds are written a * b + c, never fma(): the program is built with -cl-mad-enable, so compilers
 * contract them to FMA instructions inline, while PoCL calls its vector fma() out of line (3.4x slower here).
 *
 * Specialisation macros (set by specgpu.runtime.build_options; defaults make the header parse alone):
 *   VW         pixels per work-item: 8 (default) or 1 (see above)
 *   K          frames per pixel (input planes)
 *   IN_T       input sample type: uchar, ushort or float
 *   IN_LAYOUT  0: planar frames (K, N)    1: interleaved (N, K)
 *   HAS_DARK   0: none  1: one dark frame (N)  2: a dark frame per input frame (K, N)
 *   HAS_GAIN   0/1: per-pixel gain (flat field) (N), applied after the matrix
 *   SAT_LEVEL  inputs >= SAT_LEVEL flag the pixel saturated (mask bit 1); leave undefined for none
 *   IS_FLOAT_IN 1 when IN_T is float: non-finite inputs flag mask bit 2
 *   SQUARE_GAIN, SQUARE_SHIFT  (both or neither) each sample x above the dark becomes
 *              x + SQUARE_GAIN (x - SQUARE_SHIFT)^2: a frame sample's variance with the light's frame-to-frame
 *              fluctuation, which grows with the signal squared (specgpu.estimators.NoiseModel.light_square);
 *              SQUARE_SKIP (optional): the frame whose samples stay as they are (an ambient frame's variance)
 */
#ifndef SPECGPU_COMMON_H
#define SPECGPU_COMMON_H

#ifndef VW
#define VW 8
#endif
#if VW == 8
typedef float8 floatv;
typedef int8 intv;
#define CONVERT_UCHARV convert_uchar8
#elif VW == 1
typedef float floatv;
typedef int intv;
#define CONVERT_UCHARV convert_uchar
#else
#error "VW (pixels per work-item) must be 8 or 1"
#endif

#ifndef K
#define K 1
#endif
#ifndef IN_T
#define IN_T float
#endif
#ifndef IN_LAYOUT
#define IN_LAYOUT 0
#endif
#ifndef HAS_DARK
#define HAS_DARK 0
#endif
#ifndef HAS_GAIN
#define HAS_GAIN 0
#endif
#ifndef IS_FLOAT_IN
#define IS_FLOAT_IN 0
#endif
#ifndef SPLIT_SINCOS
#define SPLIT_SINCOS 0 /* 1: CIEDE2000's hue sine and cosine from sin() and cos(), not sincos() (see delta_e_2000) */
#endif

/* Helpers the compiler must inline: PoCL's clang leaves larger ones as calls, each passing its vectors through
 * the stack. Only where it optimises: unoptimised (Oclgrind builds with -cl-opt-disable) the forced inlining leaves
 * intrinsics the simulator does not know. */
#if defined(__clang__) && defined(__OPTIMIZE__)
#define ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define ALWAYS_INLINE inline
#endif

/* The mask flags come from the host's one enumeration (specgpu.core.mask.Mask, as -D options added by
 * specgpu.engine.runtime to every build); a kernel built without them must not guess. */
#if !defined(MASK_SATURATED) || !defined(MASK_NONFINITE) || !defined(MASK_OUTSIDE)
#error "MASK_SATURATED, MASK_NONFINITE and MASK_OUTSIDE are build options (specgpu.engine.runtime.mask_options)"
#endif

/* Pixels [base, base + count) of this work-item; count < VW only for the last one. */
#define PIXEL_RANGE(n)                                   \
    const ulong base = (ulong)get_global_id(0) * VW;     \
    if (base >= (ulong)(n)) return;                      \
    const uint count = (ulong)(n) - base < VW ? (uint)((ulong)(n) - base) : VW

/* ---------------------------------------------------------------------------------------- loads and stores */

/* Whole-vector loads and stores at element alignment. With VEC_DEREF (set by the host for PoCL, whose vloadn /
 * vstoren are out-of-line calls) they dereference under-aligned vector types, which clang lowers to inline
 * unaligned moves; elsewhere they are the standard vloadn / vstoren, which GPU compilers inline. */
#ifndef VEC_DEREF
#define VEC_DEREF 0
#endif
#define VEC8_(T) T##8
#define VEC8(T) VEC8_(T)
#if VEC_DEREF
typedef float8 float8_u __attribute__((aligned(4)));
typedef ushort8 ushort8_u __attribute__((aligned(2)));
typedef uchar8 uchar8_u __attribute__((aligned(1)));
#define VEC8U_(T) T##8_u
#define VEC8U(T) VEC8U_(T)
#define LOAD8(T, p) (*(__global const VEC8U(T) *)(p))
#define STORE8(T, v, p) (*(__global VEC8U(T) *)(p) = (v))
typedef float16 float16_u __attribute__((aligned(4)));
typedef ushort16 ushort16_u __attribute__((aligned(2)));
typedef uchar16 uchar16_u __attribute__((aligned(1)));
#define VEC16U_(T) T##16_u
#define VEC16U(T) VEC16U_(T)
#define LOAD16(T, p) (*(__global const VEC16U(T) *)(p))
#define STORE16(T, v, p) (*(__global VEC16U(T) *)(p) = (v))
#else
#define LOAD8(T, p) vload8(0, (__global const T *)(p))
#define STORE8(T, v, p) vstore8((v), 0, (__global T *)(p))
#define LOAD16(T, p) vload16(0, (__global const T *)(p))
#define STORE16(T, v, p) vstore16((v), 0, (__global T *)(p))
#endif

#if VW == 8
/* VW consecutive float samples p[base..], lanes past count read as 0. */
inline floatv load_f(__global const float *p, ulong base, uint count)
{
    if (count == VW) return LOAD8(float, p + base);
    float t[VW];
    for (uint j = 0; j < VW; ++j) t[j] = j < count ? p[base + j] : 0.0f;
    return vload8(0, t);
}

/* Lane j of pixel base + j, channel c of an interleaved (N, nch) float image. */
inline floatv load_f_strided(__global const float *p, ulong base, uint count, uint nch, uint c)
{
    if (count == VW) {
        __global const float *q = p + base * nch + c;
        return (floatv)(q[0], q[nch], q[2 * nch], q[3 * nch], q[4 * nch], q[5 * nch], q[6 * nch], q[7 * nch]);
    }
    float t[VW];
    for (uint j = 0; j < VW; ++j) t[j] = j < count ? p[(base + j) * nch + c] : 0.0f;
    return vload8(0, t);
}

inline void store_f(floatv v, __global float *p, ulong base, uint count)
{
    if (count == VW) { STORE8(float, v, p + base); return; }
    float t[VW];
    vstore8(v, 0, t);
    for (uint j = 0; j < count; ++j) p[base + j] = t[j];
}

inline void store_f_strided(floatv v, __global float *p, ulong base, uint count, uint nch, uint c)
{
    float t[VW];
    vstore8(v, 0, t);
    for (uint j = 0; j < count; ++j) p[(base + j) * nch + c] = t[j];
}

/* The three channels of VW pixels of an (N, 3) image: three contiguous vector loads de-interleaved in
 * registers (24 scalar loads for the partial last vector). */
inline void load3(__global const float *p, ulong base, uint count, floatv *c0, floatv *c1, floatv *c2)
{
    if (count == VW) {
        __global const float *q = p + base * 3;
        const floatv u = LOAD8(float, q), v = LOAD8(float, q + 8), w = LOAD8(float, q + 16);
        *c0 = (floatv)(u.s0, u.s3, u.s6, v.s1, v.s4, v.s7, w.s2, w.s5);
        *c1 = (floatv)(u.s1, u.s4, u.s7, v.s2, v.s5, w.s0, w.s3, w.s6);
        *c2 = (floatv)(u.s2, u.s5, v.s0, v.s3, v.s6, w.s1, w.s4, w.s7);
        return;
    }
    *c0 = load_f_strided(p, base, count, 3, 0);
    *c1 = load_f_strided(p, base, count, 3, 1);
    *c2 = load_f_strided(p, base, count, 3, 2);
}

/* Inverse of load3. */
inline void store3(floatv c0, floatv c1, floatv c2, __global float *p, ulong base, uint count)
{
    if (count == VW) {
        __global float *q = p + base * 3;
        STORE8(float, ((floatv)(c0.s0, c1.s0, c2.s0, c0.s1, c1.s1, c2.s1, c0.s2, c1.s2)), q);
        STORE8(float, ((floatv)(c2.s2, c0.s3, c1.s3, c2.s3, c0.s4, c1.s4, c2.s4, c0.s5)), q + 8);
        STORE8(float, ((floatv)(c1.s5, c2.s5, c0.s6, c1.s6, c2.s6, c0.s7, c1.s7, c2.s7)), q + 16);
        return;
    }
    store_f_strided(c0, p, base, count, 3, 0);
    store_f_strided(c1, p, base, count, 3, 1);
    store_f_strided(c2, p, base, count, 3, 2);
}


/* float16 stores round to nearest even and need no cl_khr_fp16: vstore_half where it is native; with VEC_DEREF
 * (PoCL, where vstore_half is an out-of-line call) the half bits are made inline: the F16C instruction where
 * the CPU has it, else branch-free bit arithmetic (NaN stays NaN, beyond the half range is inf, half subnormals
 * are rounded by aligning the mantissa with a float add). Both are bit-exact (tests/test_linear.py). */
#ifndef HALF_SOFT
#define HALF_SOFT 0 /* 1: the bit arithmetic even where F16C exists (its regression test sets this) */
#endif
#if VEC_DEREF && defined(__F16C__) && !HALF_SOFT
/* x86 with F16C: one vcvtps2ph, round to nearest even (immediate 0) */
typedef float f16c_in __attribute__((vector_size(32)));
inline ushort8 half_bits(floatv v)
{
    return as_ushort8(__builtin_ia32_vcvtps2ph256((f16c_in)v, 0));
}
#elif VEC_DEREF
inline ushort8 half_bits(floatv v)
{
    uint8 x = as_uint8(v);
    const uint8 sign = x & (uint8)(0x80000000u);
    x ^= sign;
    const float magic = 0.5f; /* exponent (127 - 15) + (23 - 10) + 1: puts half subnormal bits at the bottom */
    const uint8 subnormal = as_uint8(as_float8(x) + magic) - (uint8)(as_uint(magic));
    const uint8 odd = (x >> 13) & (uint8)(1u);
    const uint8 normal = (x + (uint8)(((uint)(15 - 127) << 23) + 0xfffu) + odd) >> 13;
    uint8 h = x < (uint8)(113u << 23) ? subnormal : normal;
    h = x >= (uint8)((127u + 16u) << 23) ? (uint8)(0x7c00u) : h;
    h = x > (uint8)(255u << 23) ? (uint8)(0x7e00u) : h;
    return as_ushort16(h | (sign >> 16)).even; /* the low halves: a shuffle, where convert_ushort8 packs */
}
#endif
#if VEC_DEREF
#define STORE_HALF8(v, p) STORE8(ushort, half_bits(v), p)
#else
#define STORE_HALF8(v, p) vstore_half8_rte((v), 0, (p))
#endif

inline void store_h(floatv v, __global half *p, ulong base, uint count)
{
    if (count == VW) { STORE_HALF8(v, p + base); return; }
    float t[VW];
    vstore8(v, 0, t);
    for (uint j = 0; j < count; ++j) vstore_half_rte(t[j], 0, p + base + j);
}

inline void store_h_strided(floatv v, __global half *p, ulong base, uint count, uint nch, uint c)
{
    float t[VW];
    vstore8(v, 0, t);
    for (uint j = 0; j < count; ++j) vstore_half_rte(t[j], 0, p + (base + j) * nch + c);
}

inline void store_mask(uchar8 m, __global uchar *p, ulong base, uint count)
{
    if (count == VW) { STORE8(uchar, m, p + base); return; }
    uchar t[VW];
    vstore8(m, 0, t);
    for (uint j = 0; j < count; ++j) p[base + j] = t[j];
}

/* Frame k of the input stack as floats for this work-item's pixels. */
inline floatv load_frame(__global const IN_T *frames, ulong n, uint k, ulong base, uint count)
{
#if IN_LAYOUT == 0
    __global const IN_T *p = frames + (ulong)k * n + base;
    if (count == VW) return convert_float8(LOAD8(IN_T, p));
    float t[VW];
    for (uint j = 0; j < VW; ++j) t[j] = j < count ? (float)p[j] : 0.0f;
    return vload8(0, t);
#else
    __global const IN_T *p = frames + base * K + k;
    if (count == VW)  /* a vector literal, not a private array (see the REP_n note below) */
        return convert_float8((VEC8(IN_T))(p[0], p[K], p[2 * K], p[3 * K], p[4 * K], p[5 * K], p[6 * K], p[7 * K]));
    float t[VW];
    for (uint j = 0; j < VW; ++j) t[j] = j < count ? (float)p[j * K] : 0.0f;
    return vload8(0, t);
#endif
}

#else /* VW == 1: one pixel per work-item; count is 1 for every work-item that gets past PIXEL_RANGE */

inline floatv load_f(__global const float *p, ulong base, uint count) { return p[base]; }

inline floatv load_f_strided(__global const float *p, ulong base, uint count, uint nch, uint c)
{
    return p[base * nch + c];
}

inline void store_f(floatv v, __global float *p, ulong base, uint count) { p[base] = v; }

inline void store_f_strided(floatv v, __global float *p, ulong base, uint count, uint nch, uint c)
{
    p[base * nch + c] = v;
}

inline void load3(__global const float *p, ulong base, uint count, floatv *c0, floatv *c1, floatv *c2)
{
    __global const float *q = p + base * 3;
    *c0 = q[0];
    *c1 = q[1];
    *c2 = q[2];
}

inline void store3(floatv c0, floatv c1, floatv c2, __global float *p, ulong base, uint count)
{
    __global float *q = p + base * 3;
    q[0] = c0;
    q[1] = c1;
    q[2] = c2;
}

inline void store_h(floatv v, __global half *p, ulong base, uint count) { vstore_half_rte(v, base, p); }

inline void store_h_strided(floatv v, __global half *p, ulong base, uint count, uint nch, uint c)
{
    vstore_half_rte(v, base * nch + c, p);
}

inline void store_mask(uchar m, __global uchar *p, ulong base, uint count) { p[base] = m; }

inline floatv load_frame(__global const IN_T *frames, ulong n, uint k, ulong base, uint count)
{
#if IN_LAYOUT == 0
    return (float)frames[(ulong)k * n + base];
#else
    return (float)frames[base * K + k];
#endif
}
#endif /* VW */

/* A standard deviation from a variance: sqrt(max(v, 0)), NaN kept NaN (a pixel with no response; fmax alone would
 * return the 0), as NumPy's sqrt(maximum(v, 0)) gives it. */
inline floatv sd_of_variance(floatv v) { return isnan(v) ? v : sqrt(fmax(v, 0.0f)); }

/* ------------------------------------------------------------------------------- the per-pixel linear map */

/* One frame sample of VW pixels: flag saturated / non-finite values, subtract the dark level.
 * The gain is applied by the caller after the matrix (one multiply per output, not per frame). */
inline floatv load_sample(__global const IN_T *frames, __global const float *dark, ulong n, uint k, ulong base,
                          uint count, intv *flags)
{
    floatv v = load_frame(frames, n, k, base, count);
#ifdef SAT_LEVEL
    *flags |= v >= (floatv)(SAT_LEVEL) ? (intv)(MASK_SATURATED) : (intv)(0);
#endif
#if IS_FLOAT_IN
    *flags |= isfinite(v) == (intv)(0) ? (intv)(MASK_NONFINITE) : (intv)(0);
#endif
#if HAS_DARK == 1
    v -= load_f(dark, base, count);
#elif HAS_DARK == 2
    v -= load_f(dark + (ulong)k * n, base, count);
#endif
#ifdef SQUARE_GAIN
#ifdef SQUARE_SKIP
    if (k != SQUARE_SKIP)
#endif
    {
        const floatv s_ = v - SQUARE_SHIFT;
        v += SQUARE_GAIN * (s_ * s_);
    }
#endif
    return v;
}

/* The K samples of a pixel vector are kept in named registers x0 .. x<K-1>, not in a private array:
 * PoCL keeps private arrays in memory, which halves the speed of the matrix product. REP_n(M) expands
 * M(0) M(1) ... M(n-1). Above 128 frames the samples are read again for every output instead of being
 * kept: a private array is allocated by PoCL for every work-item of a group and overflows its stack. */
#define REP_1(M) M(0)
#define REP_2(M) REP_1(M) M(1)
#define REP_3(M) REP_2(M) M(2)
#define REP_4(M) REP_3(M) M(3)
#define REP_5(M) REP_4(M) M(4)
#define REP_6(M) REP_5(M) M(5)
#define REP_7(M) REP_6(M) M(6)
#define REP_8(M) REP_7(M) M(7)
#define REP_9(M) REP_8(M) M(8)
#define REP_10(M) REP_9(M) M(9)
#define REP_11(M) REP_10(M) M(10)
#define REP_12(M) REP_11(M) M(11)
#define REP_13(M) REP_12(M) M(12)
#define REP_14(M) REP_13(M) M(13)
#define REP_15(M) REP_14(M) M(14)
#define REP_16(M) REP_15(M) M(15)
#define REP_17(M) REP_16(M) M(16)
#define REP_18(M) REP_17(M) M(17)
#define REP_19(M) REP_18(M) M(18)
#define REP_20(M) REP_19(M) M(19)
#define REP_21(M) REP_20(M) M(20)
#define REP_22(M) REP_21(M) M(21)
#define REP_23(M) REP_22(M) M(22)
#define REP_24(M) REP_23(M) M(23)
#define REP_25(M) REP_24(M) M(24)
#define REP_26(M) REP_25(M) M(25)
#define REP_27(M) REP_26(M) M(26)
#define REP_28(M) REP_27(M) M(27)
#define REP_29(M) REP_28(M) M(28)
#define REP_30(M) REP_29(M) M(29)
#define REP_31(M) REP_30(M) M(30)
#define REP_32(M) REP_31(M) M(31)
#define REP_33(M) REP_32(M) M(32)
#define REP_34(M) REP_33(M) M(33)
#define REP_35(M) REP_34(M) M(34)
#define REP_36(M) REP_35(M) M(35)
#define REP_37(M) REP_36(M) M(36)
#define REP_38(M) REP_37(M) M(37)
#define REP_39(M) REP_38(M) M(38)
#define REP_40(M) REP_39(M) M(39)
#define REP_41(M) REP_40(M) M(40)
#define REP_42(M) REP_41(M) M(41)
#define REP_43(M) REP_42(M) M(42)
#define REP_44(M) REP_43(M) M(43)
#define REP_45(M) REP_44(M) M(44)
#define REP_46(M) REP_45(M) M(45)
#define REP_47(M) REP_46(M) M(46)
#define REP_48(M) REP_47(M) M(47)
#define REP_49(M) REP_48(M) M(48)
#define REP_50(M) REP_49(M) M(49)
#define REP_51(M) REP_50(M) M(50)
#define REP_52(M) REP_51(M) M(51)
#define REP_53(M) REP_52(M) M(52)
#define REP_54(M) REP_53(M) M(53)
#define REP_55(M) REP_54(M) M(54)
#define REP_56(M) REP_55(M) M(55)
#define REP_57(M) REP_56(M) M(56)
#define REP_58(M) REP_57(M) M(57)
#define REP_59(M) REP_58(M) M(58)
#define REP_60(M) REP_59(M) M(59)
#define REP_61(M) REP_60(M) M(60)
#define REP_62(M) REP_61(M) M(61)
#define REP_63(M) REP_62(M) M(62)
#define REP_64(M) REP_63(M) M(63)
#define REP_65(M) REP_64(M) M(64)
#define REP_66(M) REP_65(M) M(65)
#define REP_67(M) REP_66(M) M(66)
#define REP_68(M) REP_67(M) M(67)
#define REP_69(M) REP_68(M) M(68)
#define REP_70(M) REP_69(M) M(69)
#define REP_71(M) REP_70(M) M(70)
#define REP_72(M) REP_71(M) M(71)
#define REP_73(M) REP_72(M) M(72)
#define REP_74(M) REP_73(M) M(73)
#define REP_75(M) REP_74(M) M(74)
#define REP_76(M) REP_75(M) M(75)
#define REP_77(M) REP_76(M) M(76)
#define REP_78(M) REP_77(M) M(77)
#define REP_79(M) REP_78(M) M(78)
#define REP_80(M) REP_79(M) M(79)
#define REP_81(M) REP_80(M) M(80)
#define REP_82(M) REP_81(M) M(81)
#define REP_83(M) REP_82(M) M(82)
#define REP_84(M) REP_83(M) M(83)
#define REP_85(M) REP_84(M) M(84)
#define REP_86(M) REP_85(M) M(85)
#define REP_87(M) REP_86(M) M(86)
#define REP_88(M) REP_87(M) M(87)
#define REP_89(M) REP_88(M) M(88)
#define REP_90(M) REP_89(M) M(89)
#define REP_91(M) REP_90(M) M(90)
#define REP_92(M) REP_91(M) M(91)
#define REP_93(M) REP_92(M) M(92)
#define REP_94(M) REP_93(M) M(93)
#define REP_95(M) REP_94(M) M(94)
#define REP_96(M) REP_95(M) M(95)
#define REP_97(M) REP_96(M) M(96)
#define REP_98(M) REP_97(M) M(97)
#define REP_99(M) REP_98(M) M(98)
#define REP_100(M) REP_99(M) M(99)
#define REP_101(M) REP_100(M) M(100)
#define REP_102(M) REP_101(M) M(101)
#define REP_103(M) REP_102(M) M(102)
#define REP_104(M) REP_103(M) M(103)
#define REP_105(M) REP_104(M) M(104)
#define REP_106(M) REP_105(M) M(105)
#define REP_107(M) REP_106(M) M(106)
#define REP_108(M) REP_107(M) M(107)
#define REP_109(M) REP_108(M) M(108)
#define REP_110(M) REP_109(M) M(109)
#define REP_111(M) REP_110(M) M(110)
#define REP_112(M) REP_111(M) M(111)
#define REP_113(M) REP_112(M) M(112)
#define REP_114(M) REP_113(M) M(113)
#define REP_115(M) REP_114(M) M(114)
#define REP_116(M) REP_115(M) M(115)
#define REP_117(M) REP_116(M) M(116)
#define REP_118(M) REP_117(M) M(117)
#define REP_119(M) REP_118(M) M(118)
#define REP_120(M) REP_119(M) M(119)
#define REP_121(M) REP_120(M) M(120)
#define REP_122(M) REP_121(M) M(121)
#define REP_123(M) REP_122(M) M(122)
#define REP_124(M) REP_123(M) M(123)
#define REP_125(M) REP_124(M) M(124)
#define REP_126(M) REP_125(M) M(125)
#define REP_127(M) REP_126(M) M(126)
#define REP_128(M) REP_127(M) M(127)
#define REP__(n, M) REP_##n(M)
#define REP_(n, M) REP__(n, M)

#if K <= 128
#define X_LOAD_ONE(k) const floatv x##k = load_sample(frames, dark, n, k, base, count, &flags);
#define X_FMA_ONE(k) acc_ = m_[k] * x##k + acc_;
/* Declares intv flags and the samples of this work-item's pixels. */
#define LOAD_PIXELS() intv flags = (intv)(0); REP_(K, X_LOAD_ONE)
/* acc = sum_k M[row, k] x_k  (M row-major, K columns) */
#define DOT_ROW(acc, M, row)                                      \
    do {                                                          \
        __constant const float *m_ = (M) + (uint)(row) * K;       \
        floatv acc_ = (floatv)(0.0f);                             \
        REP_(K, X_FMA_ONE)                                        \
        acc = acc_;                                               \
    } while (0)
#else
/* flags from one pass over the samples (dead code when no mask is written) */
#define LOAD_PIXELS()                                                                          \
    intv flags = (intv)(0);                                                                    \
    for (uint k = 0; k < K; ++k) (void)load_sample(frames, dark, n, k, base, count, &flags)
#define DOT_ROW(acc, M, row)                                                                   \
    do {                                                                                       \
        __constant const float *m_ = (M) + (uint)(row) * K;                                    \
        floatv acc_ = (floatv)(0.0f);                                                          \
        intv unused_ = (intv)(0);                                                              \
        for (uint k = 0; k < K; ++k)                                                           \
            acc_ = m_[k] * load_sample(frames, dark, n, k, base, count, &unused_) + acc_;      \
        acc = acc_;                                                                            \
    } while (0)
#endif

/* 8 x 8 transpose of floatv registers: rj lane i = ai lane j. Turns 8 outputs of 8 pixels (one register per
 * output) into 8 pixel rows of 8 outputs, so interleaved (N, B) results are written as contiguous rows.
 * Written with swizzle constructors, which compilers lower to single vector shuffles (shuffle2 with a mask
 * variable is a generic library loop on PoCL). Every component is a single lane: multi-lane components
 * ((p).s01, (p).lo) compile to widening shuffles with undefined lanes, which crash Oclgrind's uninitialised-value
 * check (tests/test_oclgrind.py); both forms optimise to the same shuffle. */
#define UNPACK_LO(p, q) (floatv)((p).s0, (q).s0, (p).s1, (q).s1, (p).s4, (q).s4, (p).s5, (q).s5)
#define UNPACK_HI(p, q) (floatv)((p).s2, (q).s2, (p).s3, (q).s3, (p).s6, (q).s6, (p).s7, (q).s7)
#define PAIRS_LO(p, q) (floatv)((p).s0, (p).s1, (q).s0, (q).s1, (p).s4, (p).s5, (q).s4, (q).s5)
#define PAIRS_HI(p, q) (floatv)((p).s2, (p).s3, (q).s2, (q).s3, (p).s6, (p).s7, (q).s6, (q).s7)
#define HALVES_LO(p, q) (floatv)((p).s0, (p).s1, (p).s2, (p).s3, (q).s0, (q).s1, (q).s2, (q).s3)
#define HALVES_HI(p, q) (floatv)((p).s4, (p).s5, (p).s6, (p).s7, (q).s4, (q).s5, (q).s6, (q).s7)
#define TRANSPOSE8(a0, a1, a2, a3, a4, a5, a6, a7, r0, r1, r2, r3, r4, r5, r6, r7)                        \
    do {                                                                                               \
        const floatv t0 = UNPACK_LO(a0, a1), t1 = UNPACK_HI(a0, a1);                                   \
        const floatv t2 = UNPACK_LO(a2, a3), t3 = UNPACK_HI(a2, a3);                                   \
        const floatv t4 = UNPACK_LO(a4, a5), t5 = UNPACK_HI(a4, a5);                                   \
        const floatv t6 = UNPACK_LO(a6, a7), t7 = UNPACK_HI(a6, a7);                                   \
        const floatv u0 = PAIRS_LO(t0, t2), u1 = PAIRS_HI(t0, t2);                                     \
        const floatv u2 = PAIRS_LO(t1, t3), u3 = PAIRS_HI(t1, t3);                                     \
        const floatv u4 = PAIRS_LO(t4, t6), u5 = PAIRS_HI(t4, t6);                                     \
        const floatv u6 = PAIRS_LO(t5, t7), u7 = PAIRS_HI(t5, t7);                                     \
        r0 = HALVES_LO(u0, u4); r4 = HALVES_HI(u0, u4);                                                \
        r1 = HALVES_LO(u1, u5); r5 = HALVES_HI(u1, u5);                                                \
        r2 = HALVES_LO(u2, u6); r6 = HALVES_HI(u2, u6);                                                \
        r3 = HALVES_LO(u3, u7); r7 = HALVES_HI(u3, u7);                                                \
    } while (0)

/* ------------------------------------------------------------------------------------------- colorimetry */

/* CIE 1976 intermediate lightness function f(t): cube root above (24/116)^3, linear below (and for t < 0). */
inline floatv cie_f(floatv t)
{
    const floatv linear = t * (841.0f / 108.0f) + (16.0f / 116.0f);
    return t > (floatv)(216.0f / 24389.0f) ? cbrt(t) : linear;
}

/* XYZ -> CIELAB for the reference white (Xn, Yn, Zn); L in [0, 100] for 0 <= Y <= Yn. */
inline void lab_from_xyz(floatv X, floatv Y, floatv Z, float Xn, float Yn, float Zn,
                       floatv *L, floatv *a, floatv *b)
{
    const floatv fx = cie_f(X / Xn);
    const floatv fy = cie_f(Y / Yn);
    const floatv fz = cie_f(Z / Zn);
    *L = 116.0f * fy - 16.0f;
    *a = 500.0f * (fx - fy);
    *b = 200.0f * (fy - fz);
}

#define DEG2RAD 0.017453292519943295f
#define RAD2DEG 57.29577951308232f

/* Chroma sqrt(a^2 + b^2): no overflow guard is needed for any float32 Lab value of a real colour, and hypot()
 * costs several times more on CPU devices. */
inline floatv chroma(floatv a, floatv b)
{
    return sqrt(a * a + b * b);
}

/* CIE 1976: Euclidean distance in CIELAB. */
inline floatv delta_e_76(floatv L1, floatv a1, floatv b1, floatv L2, floatv a2, floatv b2)
{
    const floatv dL = L1 - L2, da = a1 - a2, db = b1 - b2;
    return sqrt(dL * dL + da * da + db * db);
}

/* CIE 1994, graphic arts (kL = 1, K1 = 0.045, K2 = 0.015); colour 1 is the reference (its chroma weights). */
inline floatv delta_e_94(floatv L1, floatv a1, floatv b1, floatv L2, floatv a2, floatv b2)
{
    const floatv C1 = chroma(a1, b1), C2 = chroma(a2, b2);
    const floatv sC = 1.0f + 0.045f * C1, sH = 1.0f + 0.015f * C1;
    const floatv dL = L1 - L2, dC = C1 - C2, da = a1 - a2, db = b1 - b2;
    const floatv radical = da * da + db * db - dC * dC;
    const floatv dH2 = radical > (floatv)(0.0f) ? radical : (floatv)(0.0f);
    const floatv tC = dC / sC;
    return sqrt(dL * dL + tC * tC + dH2 / (sH * sH));
}

/* atan2(y, x) in radians for CIEDE2000's hue angles, inline: atan on [0, 1] of min / max as t P(t^2), P of degree 8
 * (a minimax fit, within 1.2e-7 rad of atan in float32: the rounding of the result), then the octant. PoCL's vector
 * atan2 is an out-of-line call; this is about a sixth of the CIEDE2000 kernel's time less there. As atan2: 0 at
 * (0, 0), pi for y = +-0 and x < 0 (the hue 180 degrees either way). A NaN in y gives a finite angle here, but
 * every colour difference reading it is NaN through the chroma. */
ALWAYS_INLINE floatv atan2_hue(floatv y, floatv x)
{
    const floatv zero = (floatv)(0.0f);
    const floatv ax = fabs(x), ay = fabs(y);
    const intv steep = ay > ax;
    const floatv hi = steep ? ay : ax, lo = steep ? ax : ay;
    const floatv t = hi > zero ? lo / hi : zero;
    const floatv s = t * t;
    floatv p = s * 0.0024567205214554907f - 0.014401342314893694f;
    p = p * s + 0.03978119926151421f;
    p = p * s - 0.07234855399114098f;
    p = p * s + 0.10498945195530149f;
    p = p * s - 0.1416122898044801f;
    p = p * s + 0.19985906741341566f;
    p = p * s - 0.3333259702712914f;
    p = p * s + 0.999999886383039f;
    floatv r = p * t;
    r = steep ? 1.5707963267948966f - r : r;
    r = x < zero ? 3.141592653589793f - r : r;
    return y < zero ? -r : r;
}

/* CIEDE2000 (Sharma, Wu and Dalal 2005), kL = kC = kH = 1, branch-free over the lanes.
 * Hue angles are in degrees where the formula compares them (its +-180 / +-360 rules). The four cosines of T
 * come from one sincos and multiple-angle identities (same accuracy, a quarter of the cost); with SPLIT_SINCOS
 * from a sin and a cos (the same values on PoCL, measured up to 13 % slower there), for Oclgrind, whose
 * uninitialised-read check cannot follow sincos's private out-pointer (specgpu.runtime sets it for that device).
 * A vector form of the hue terms (cross and dot products of a'b') was measured: no faster on PoCL and
 * ill-conditioned for nearly opposite hues, so the angles stay. */
inline floatv delta_e_2000(floatv L1, floatv a1, floatv b1, floatv L2, floatv a2, floatv b2)
{
    const float p25_7 = 6103515625.0f; /* 25^7 */
    const floatv zero = (floatv)(0.0f);
    const floatv Cbar = 0.5f * (chroma(a1, b1) + chroma(a2, b2));
    const floatv Cbar2 = Cbar * Cbar, Cbar7 = Cbar2 * Cbar2 * Cbar2 * Cbar;
    const floatv G = 0.5f * (1.0f - sqrt(Cbar7 / (Cbar7 + p25_7)));
    const floatv a1p = (1.0f + G) * a1, a2p = (1.0f + G) * a2;
    const floatv C1p = chroma(a1p, b1), C2p = chroma(a2p, b2);

    /* atan2(0, 0) is 0, the formula's hue of an achromatic colour */
    floatv h1p = atan2_hue(b1, a1p) * RAD2DEG;
    floatv h2p = atan2_hue(b2, a2p) * RAD2DEG;
    h1p = h1p < zero ? h1p + 360.0f : h1p;
    h2p = h2p < zero ? h2p + 360.0f : h2p;

    const floatv Cprod = C1p * C2p;
    const intv chromatic = Cprod != zero;
    const floatv dL = L2 - L1;
    const floatv dC = C2p - C1p;
    floatv dh = h2p - h1p;
    dh = dh > (floatv)(180.0f) ? dh - 360.0f : dh;
    dh = dh < (floatv)(-180.0f) ? dh + 360.0f : dh;
    dh = chromatic ? dh : zero;
    const floatv dH = 2.0f * sqrt(Cprod) * sin(dh * (0.5f * DEG2RAD));

    const floatv Lbar = 0.5f * (L1 + L2);
    const floatv Cbarp = 0.5f * (C1p + C2p);
    const floatv hsum = h1p + h2p;
    floatv hbar = fabs(h1p - h2p) <= (floatv)(180.0f) ? hsum
                  : hsum < (floatv)(360.0f) ? hsum + 360.0f : hsum - 360.0f;
    hbar = chromatic ? 0.5f * hbar : hsum;

    /* T = 1 - 0.17 cos(h - 30) + 0.24 cos(2h) + 0.32 cos(3h + 6) - 0.20 cos(4h - 63), h in degrees */
#if SPLIT_SINCOS
    const floatv s1 = sin(hbar * DEG2RAD), c1 = cos(hbar * DEG2RAD);
#else
    floatv c1;
    const floatv s1 = sincos(hbar * DEG2RAD, &c1);
#endif
    const floatv c2 = 2.0f * c1 * c1 - 1.0f, s2 = 2.0f * s1 * c1;
    const floatv c3 = c1 * (4.0f * c1 * c1 - 3.0f), s3 = s1 * (3.0f - 4.0f * s1 * s1);
    const floatv c4 = 2.0f * c2 * c2 - 1.0f, s4 = 2.0f * s2 * c2;
    const float cos30 = 0.8660254037844387f, sin30 = 0.5f;
    const float cos6 = 0.9945218953682733f, sin6 = 0.10452846326765347f;
    const float cos63 = 0.45399049973954675f, sin63 = 0.8910065241883679f;
    const floatv T = 1.0f - 0.17f * (c1 * cos30 + s1 * sin30) + 0.24f * c2 + 0.32f * (c3 * cos6 - s3 * sin6)
                     - 0.20f * (c4 * cos63 + s4 * sin63);
    const floatv q = (hbar - 275.0f) * (1.0f / 25.0f);
    const floatv dtheta = 30.0f * exp(-q * q);
    const floatv Cbarp2 = Cbarp * Cbarp, Cbarp7 = Cbarp2 * Cbarp2 * Cbarp2 * Cbarp;
    const floatv RC = 2.0f * sqrt(Cbarp7 / (Cbarp7 + p25_7));
    const floatv Lm = (Lbar - 50.0f) * (Lbar - 50.0f);
    const floatv SL = 1.0f + 0.015f * Lm / sqrt(20.0f + Lm);
    const floatv SC = 1.0f + 0.045f * Cbarp;
    const floatv SH = 1.0f + 0.015f * Cbarp * T;
    const floatv RT = -sin(2.0f * dtheta * DEG2RAD) * RC;

    const floatv tL = dL / SL, tC = dC / SC, tH = dH / SH;
    return sqrt(tL * tL + tC * tC + tH * tH + RT * tC * tH);
}

#ifdef DE_METHOD
#if DE_METHOD == 76
#define DELTA_E delta_e_76
#elif DE_METHOD == 94
#define DELTA_E delta_e_94
#elif DE_METHOD == 2000
#define DELTA_E delta_e_2000
#else
#error "DE_METHOD must be 76, 94 or 2000"
#endif
#endif

#endif /* SPECGPU_COMMON_H */
