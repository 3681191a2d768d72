/* Reduced kernels of four Oclgrind 21.10 defects that specgpu's kernels met (tests/engine/test_oclgrind.py runs them).
 *
 * vector_bool: the mask flags of kernels/common.h (load_sample) in their smallest form. OpenCL C defines a vector
 * c ? b : a as select(a, b, c), which takes b's lane where the most significant bit of c's lane is set, so
 * x >= level ? (int8)(1) : (int8)(0) is 1 in every lane where x >= level, as the explicit select() is. Clang's
 * optimiser rewrites the former into a zero extension of the comparison's vector of booleans
 * (zext <8 x i1> to <8 x i32>), which LLVM defines as 1 per true lane; Oclgrind keeps a true vector-compare lane
 * as -1 in one byte (its fcmp / icmp store -1 for vectors) and zero-extends that byte, giving 255. PoCL, and
 * Oclgrind on the unoptimised program (-cl-opt-disable), give 1 in both rows.
 *
 * pairs_multi_lane / pairs_single_lane: the same vector built from two-lane components ((p).s01) and from
 * single lanes. The first compiles to shuffles that widen a 2-lane vector to 8 lanes with undefined lanes, on
 * which Oclgrind's uninitialised-value check (OCLGRIND_UNINITIALIZED=1) crashes the process (a segmentation
 * fault in its plugin); the second is the same shuffle without them. kernels/common.h uses single lanes.
 *
 * min_vector_scalar: OpenCL C's integer min(gentype, sgentype), a vector against a scalar, as kernels/consistency.cl
 * clamped its sample indices to the field. Oclgrind returns zeros or garbage for it, optimised or not, where the
 * same min with the scalar made a vector first is right (and PoCL is right for both); kernels/consistency.cl uses
 * vector bounds.
 *
 * copy_floats: a plain copy, run on a buffer written from the host in one write from offset 0, then on one written
 * in two halves (the second at an offset, as engine.consistency uploads a list of images): Oclgrind's
 * uninitialised-value check reports the second half's values as uninitialised, though they are right. */

__kernel void vector_bool(__global const float *x, __global int *out, const float level)
{
    const float8 v = vload8(0, x);
    vstore8(v >= (float8)(level) ? (int8)(1) : (int8)(0), 0, out);
    vstore8(select((int8)(0), (int8)(1), v >= (float8)(level)), 1, out);
}

__kernel void pairs_multi_lane(__global const float *v, __global float *out)
{
    const float8 p = vload8(0, v), q = vload8(1, v);
    vstore8((float8)(p.s01, q.s01, p.s45, q.s45), 0, out);
}

__kernel void pairs_single_lane(__global const float *v, __global float *out)
{
    const float8 p = vload8(0, v), q = vload8(1, v);
    vstore8((float8)(p.s0, p.s1, q.s0, q.s1, p.s4, p.s5, q.s4, q.s5), 0, out);
}

__kernel void min_vector_scalar(__global const int *x, __global int *out, const int last)
{
    const int8 v = vload8(0, x);
    vstore8(min(v, last), 0, out);
    vstore8(min(v, (int8)(last)), 1, out);
}

__kernel void copy_floats(__global const float *in, __global float *out)
{
    out[get_global_id(0)] = in[get_global_id(0)];
}
