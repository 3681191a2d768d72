"""Device resolution order, kernel loading, the program cache and the no-platform error."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from specgpu.engine import runtime
from specgpu.engine.linear_map import apply_linear


def test_order_explicit_beats_array_and_environment(queue, monkeypatch):
    monkeypatch.setenv("SPECGPU_DEVICE", "no-such-device")
    # an explicit device wins over everything, the environment is not even read
    assert runtime.select_device(queue.device) == queue.device
    assert runtime.get_queue(queue) is queue
    # the array's own queue wins over the environment
    arr = cla.zeros(queue, (4,), np.float32)
    assert runtime.get_queue(like=(None, arr)) is queue
    # with neither, the environment is used, and a selector that matches nothing is a clear error
    with pytest.raises(runtime.SpecgpuDeviceError, match="SPECGPU_DEVICE='no-such-device' matches no OpenCL"):
        runtime.select_device()


def test_environment_selector_by_index_and_name(queue, monkeypatch):
    info = next(d for d in runtime.list_devices() if d.device == queue.device)
    monkeypatch.setenv("SPECGPU_DEVICE", info.selector)
    assert runtime.select_device() == queue.device
    monkeypatch.setenv("SPECGPU_DEVICE", info.name.upper()[:6])
    assert runtime.select_device().name == runtime.select_device(info.name[:6]).name


def test_default_prefers_gpu_then_cpu(monkeypatch):
    monkeypatch.delenv("SPECGPU_DEVICE", raising=False)
    devices = runtime.list_devices()
    gpus = [d for d in devices if d.device.type & cl.device_type.GPU]
    chosen = runtime.select_device()
    assert chosen == (gpus[0].device if gpus else next(d.device for d in devices
                                                      if d.device.type & cl.device_type.CPU))


def test_bad_selectors():
    with pytest.raises(runtime.SpecgpuDeviceError, match="device='99:99' matches no OpenCL device"):
        runtime.select_device("99:99")
    with pytest.raises(TypeError, match="selector string"):
        runtime.select_device(3.5)


def test_no_platform_is_a_one_line_error_saying_how_to_get_one(monkeypatch):
    def no_platform():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")

    monkeypatch.setattr(cl, "get_platforms", no_platform)
    with pytest.raises(runtime.SpecgpuDeviceError) as error:
        runtime.list_devices()
    message = str(error.value)
    assert "no OpenCL platform found" in message and "pip install pocl-binary-distribution" in message
    assert "\n" not in message


def test_kernel_sources_found_and_listed():
    assert (runtime.kernel_dir() / "common.h").is_file()
    assert "linear_apply" in runtime.kernel_source("linear.cl")
    with pytest.raises(FileNotFoundError, match="no kernel source 'nope.cl'.*linear.cl"):
        runtime.kernel_source("nope.cl")


def test_a_program_is_built_from_its_text_alone_so_the_compilers_cache_survives_a_new_checkout(queue):
    """The header is inlined into the source and no -I path reaches the build options: the on-disk cache of the
    OpenCL compiler keys a build by text and options, so a path there would recompile every kernel per checkout."""
    text = runtime.kernel_source("warp.cl")
    assert "#include" not in text
    assert text.count('#line 1 "common.h"') == 1
    lines = text.splitlines()
    back = next(i for i, line in enumerate(lines) if line.startswith('#line') and "warp.cl" in line)
    number = int(lines[back].split()[1])
    assert lines[back + 1] == (runtime.kernel_dir() / "warp.cl").read_text().splitlines()[number - 1]
    # the options the device built with, as it reports them: pyopencl's own build call adds its header folder
    # (inside the Python environment) to every build, so the runtime must not go through it
    import pyopencl

    program = runtime.get_program(queue.context, "linear.cl", runtime.build_options(K=3, B=2, IN_T="ushort", FRESH=7))
    used = program.program.get_build_info(queue.device, cl.program_build_info.OPTIONS)
    assert "-DFRESH=7" in used and "-DMASK_SATURATED=1" in used
    assert "-I" not in used.split()
    assert str(runtime.kernel_dir()) not in used and str(pyopencl.__path__[0]) not in used


def test_making_a_kernel_looks_up_no_missing_program_attribute(queue, monkeypatch):
    """``cl.Program`` turns an attribute it lacks into the lookup of a kernel of that name, which an OpenCL
    implementation may report as an error (Oclgrind does): making the runtime's kernels must ask for none."""
    asked = []
    real = cl.Program.__getattr__

    def record(self, attr):
        asked.append(attr)
        return real(self, attr)

    monkeypatch.setattr(cl.Program, "__getattr__", record)
    runtime.get_kernel(queue, "linear.cl", "linear_apply", K=2, B=1, IN_T="ushort", FRESH=11)
    runtime.new_kernel(queue, "linear.cl", "linear_apply", K=2, B=1, IN_T="ushort", FRESH=11)
    assert asked == []


def test_programs_built_once_and_kernels_kept(queue):
    frames = np.ones((2, 3, 5), np.uint16)
    apply_linear(frames, np.ones((1, 2)), device=queue)
    size = runtime.program_cache_size()
    k1 = runtime.get_kernel(queue, "linear.cl", "linear_apply", K=2, B=1, IN_T="ushort")
    for _ in range(3):
        apply_linear(frames, np.ones((1, 2)), device=queue)
    k2 = runtime.get_kernel(queue, "linear.cl", "linear_apply", B=1, IN_T="ushort", K=2)  # option order irrelevant
    assert k1 is k2
    assert runtime.program_cache_size() == size + 1  # only the get_kernel variant above was new


def test_build_failure_names_the_source_and_options(queue):
    with pytest.raises(runtime.SpecgpuDeviceError, match=r"building colorimetry.cl with -DDE_METHOD=77"):
        runtime.get_kernel(queue, "colorimetry.cl", "delta_e", DE_METHOD=77)


def test_build_options_are_sorted_and_typed():
    assert runtime.build_options(B=2, A=True, C=None, D="ushort") == ("-DA=1", "-DB=2", "-DD=ushort")


def test_describe_names_the_chosen_device(queue):
    text = runtime.describe(queue.device)
    assert "chosen: " + queue.device.name.strip() in text
    assert "pyopencl" in text and "kernels:" in text


def test_a_context_given_is_the_context_used(queue):
    other = cl.Context([queue.device])
    q = runtime.get_queue(other)
    assert q.context == other and q.device == queue.device
    assert runtime.get_queue(other) is q  # and kept
    assert runtime.get_queue(queue.device).context != other  # our own context per device is unaffected
    frames = cla.to_device(q, np.ones((2, 3, 4), np.uint16))
    np.testing.assert_array_equal(apply_linear(frames, np.ones((1, 2))).get(), 2.0)


def test_kernel_variant_by_device_type_and_overrides(queue, monkeypatch):
    monkeypatch.delenv("SPECGPU_VARIANT", raising=False)
    device = queue.device
    expected = "gpu" if device.type & cl.device_type.GPU else "cpu"
    assert runtime.kernel_variant(device) == expected
    monkeypatch.setenv("SPECGPU_VARIANT", "GPU ")
    assert runtime.kernel_variant(device) == "gpu"
    assert runtime.kernel_variant(device, "cpu") == "cpu"  # an argument beats the environment
    assert "kernel variant: gpu (SPECGPU_VARIANT='GPU ';" in runtime.describe(device)
    monkeypatch.setenv("SPECGPU_VARIANT", "fast")
    with pytest.raises(runtime.SpecgpuDeviceError, match=r"^SPECGPU_VARIANT='fast' is no kernel variant \(choose "
                                                         r"from cpu, gpu\)$"):
        runtime.kernel_variant(device)
    with pytest.raises(runtime.SpecgpuDeviceError, match=r"^variant='x' is no kernel variant"):
        runtime.kernel_variant(device, "x")


def test_describe_lists_each_device_variant_and_memory_kind(queue, monkeypatch):
    monkeypatch.delenv("SPECGPU_VARIANT", raising=False)
    text = runtime.describe(queue.device)
    cpu = bool(queue.device.type & cl.device_type.CPU)
    assert f"kernels {'cpu' if cpu else 'gpu'}" in text
    assert ("host memory: zero-copy" if cpu else "") in text
    assert "kernel variant:" in text and "override with SPECGPU_VARIANT=cpu|gpu" in text
    assert runtime.is_discrete(queue.device) is (not cpu and not queue.device.host_unified_memory)
