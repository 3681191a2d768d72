"""OpenCL runtime: device choice, the one loader of ``kernels/*.cl`` and the program cache.

Device resolution follows one fixed order:

1. an explicit ``device`` argument (a :class:`pyopencl.Device`, a :class:`pyopencl.CommandQueue`,
   a :class:`pyopencl.Context` or a selector string),
2. the queue of an input array that already lives on a device (:class:`pyopencl.array.Array`),
3. the ``SPECGPU_DEVICE`` environment variable (a selector string),
4. the first GPU of any platform,
5. the first CPU of any platform (PoCL from PyPI provides one everywhere).

A selector string is either ``"P:D"`` (platform and device indices as ``specgpu info`` prints them) or a
case-insensitive substring of the platform or device name (``"pocl"``, ``"nvidia"``, ``"A100"``).

Programs are built once per (context, source, options) and their kernels are kept, so no call rebuilds a
program or re-retrieves a kernel.
"""

from __future__ import annotations

import functools
import os
import re
import threading
from dataclasses import dataclass
from importlib import metadata, resources
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.characterize as characterize
import pyopencl.tools  # noqa: F401  (cl.tools.MemoryPool)

from specgpu.core.mask import mask_macros

__all__ = [
    "SpecgpuDeviceError",
    "DeviceInfo",
    "list_devices",
    "select_device",
    "get_queue",
    "get_allocator",
    "kernel_dir",
    "kernel_source",
    "build_options",
    "mask_options",
    "get_kernel",
    "DTYPE_TO_CTYPE",
    "VARIANTS",
    "kernel_variant",
    "is_discrete",
]

ENV_DEVICE = "SPECGPU_DEVICE"
ENV_VARIANT = "SPECGPU_VARIANT"

#: Kernel variants (kernels/common.h, VW): pixels per work-item and what each is for. The runtime picks one per
#: device class; SPECGPU_VARIANT (or a ``variant`` argument) forces one on any device, which is how CI runs the GPU
#: kernels on PoCL.
VARIANTS = {
    "cpu": 8,  # float8 per work-item, register transposes for channels last: what CPU compilers vectorise
    "gpu": 1,  # a work-item per pixel, coalesced planes, a local-memory tile for channels last, vstore_half
}

NO_PLATFORM_HELP = (
    "no OpenCL platform found: install the CPU driver with `pip install pocl-binary-distribution` "
    "(it comes with `pip install specgpu`) or your GPU vendor's OpenCL driver (ICD)"
)

# NumPy dtype -> OpenCL C type, the one table kernels are specialised from (pyopencl.tools.dtype_to_ctype style).
DTYPE_TO_CTYPE = {
    np.dtype(np.uint8): "uchar",
    np.dtype(np.uint16): "ushort",
    np.dtype(np.float32): "float",
    np.dtype(np.float16): "half",
}


def _ask_nv_attributes_only_of_devices_with_them() -> None:
    """pyopencl's kernel invoker (made for every :class:`pyopencl.Kernel`) calls
    :func:`pyopencl.characterize.nv_compute_capability`, which queries CL_DEVICE_COMPUTE_CAPABILITY_MAJOR_NV of
    any device and reads the error a non-NVIDIA device returns as "not NVIDIA". That query belongs to the
    cl_nv_device_attribute_query extension: it is made here only of devices that report the extension, which gives
    the same answer without an invalid API call (a CL_INVALID_VALUE error per kernel object in API checkers such
    as Oclgrind's)."""
    original = characterize.nv_compute_capability
    if getattr(original, "specgpu_guarded", False):
        return

    @functools.wraps(original)
    def nv_compute_capability(dev):
        if "cl_nv_device_attribute_query" not in dev.extensions.split():
            return None
        return original(dev)

    nv_compute_capability.specgpu_guarded = True
    characterize.nv_compute_capability = nv_compute_capability


_ask_nv_attributes_only_of_devices_with_them()


class SpecgpuDeviceError(RuntimeError):
    """No usable OpenCL platform or device, or a selector that matches none."""


@dataclass(frozen=True)
class DeviceInfo:
    """One OpenCL device as ``specgpu info`` lists it."""

    platform_index: int
    device_index: int
    platform: str
    name: str
    type: str
    version: str
    compute_units: int
    global_mem_bytes: int
    device: cl.Device

    @property
    def selector(self) -> str:
        return f"{self.platform_index}:{self.device_index}"


def _platforms() -> list[cl.Platform]:
    try:
        platforms = cl.get_platforms()
    except cl.Error as error:  # PLATFORM_NOT_FOUND_KHR when no ICD is installed
        raise SpecgpuDeviceError(NO_PLATFORM_HELP) from error
    if not platforms:
        raise SpecgpuDeviceError(NO_PLATFORM_HELP)
    return platforms


def list_devices() -> list[DeviceInfo]:
    """Every OpenCL device of every platform, in platform / device order."""
    out = []
    for p_index, platform in enumerate(_platforms()):
        try:
            devices = platform.get_devices()
        except cl.Error:  # a platform with no devices of any type
            continue
        for d_index, device in enumerate(devices):
            out.append(
                DeviceInfo(
                    platform_index=p_index,
                    device_index=d_index,
                    platform=platform.name.strip(),
                    name=device.name.strip(),
                    type=cl.device_type.to_string(device.type),
                    version=device.version.strip(),
                    compute_units=device.max_compute_units,
                    global_mem_bytes=device.global_mem_size,
                    device=device,
                )
            )
    if not out:
        raise SpecgpuDeviceError(NO_PLATFORM_HELP)
    return out


def _match_selector(selector: str, devices: list[DeviceInfo], origin: str) -> cl.Device:
    text = selector.strip()
    if ":" in text and all(part.strip().isdigit() for part in text.split(":", 1)):
        p, d = (int(part) for part in text.split(":", 1))
        for info in devices:
            if (info.platform_index, info.device_index) == (p, d):
                return info.device
    else:
        needle = text.lower()
        for info in devices:
            if needle and (needle in info.name.lower() or needle in info.platform.lower()):
                return info.device
    listing = ", ".join(f"{i.selector} {i.name!r}" for i in devices)
    raise SpecgpuDeviceError(f"{origin}{selector!r} matches no OpenCL device (available: {listing})")


def select_device(device=None, like=None) -> cl.Device:
    """Resolve the device in the fixed order: explicit > the array's own queue > SPECGPU_DEVICE > GPU > CPU.

    Parameters
    ----------
    device : pyopencl.Device, CommandQueue, Context, str or None
        Explicit choice; a string is a selector (``"P:D"`` or a name substring).
    like : sequence of objects or None
        Inputs of the call; the first :class:`pyopencl.array.Array` among them decides the device.
    """
    if device is not None:
        return _device_of(device)
    for obj in like or ():
        queue = getattr(obj, "queue", None)
        if isinstance(queue, cl.CommandQueue):
            return queue.device
    env = os.environ.get(ENV_DEVICE)
    if env:
        return _match_selector(env, list_devices(), f"{ENV_DEVICE}=")
    devices = list_devices()
    for kind in (cl.device_type.GPU, cl.device_type.CPU):
        for info in devices:
            if info.device.type & kind:
                return info.device
    return devices[0].device


def _device_of(device) -> cl.Device:
    if isinstance(device, cl.Device):
        return device
    if isinstance(device, cl.CommandQueue):
        return device.device
    if isinstance(device, cl.Context):
        return device.devices[0]
    if isinstance(device, str):
        return _match_selector(device, list_devices(), "device=")
    raise TypeError("device must be a pyopencl Device, CommandQueue, Context or selector string, "
                    f"not {type(device).__name__}")


_lock = threading.Lock()
_queues: dict[tuple, cl.CommandQueue] = {}
_pools: dict[cl.Context, object] = {}


def get_queue(device=None, like=None) -> cl.CommandQueue:
    """The command queue for the resolved device: the caller's own queue when one is given or implied.

    One context and one in-order queue are kept per device, so programs built for it are reused.

    Parameters
    ----------
    device : pyopencl.Device, CommandQueue, Context, str or None
        Explicit choice (a queue is returned as it is); a string is a selector, ``"P:D"`` or a case-insensitive
        substring of the platform or device name. None resolves in the fixed order of :func:`select_device`.
    like : sequence of objects or None
        Inputs of the call; the queue of the first :class:`pyopencl.array.Array` among them is returned.

    Returns
    -------
    pyopencl.CommandQueue
        An in-order queue with profiling enabled; the same object for every call that resolves to the device.

    Raises
    ------
    SpecgpuDeviceError
        No OpenCL platform, or a selector that matches no device.

    Examples
    --------
    >>> import pyopencl as cl
    >>> from specgpu.engine import get_queue
    >>> queue = get_queue()
    >>> isinstance(queue, cl.CommandQueue), get_queue() is queue, get_queue(queue) is queue
    (True, True, True)
    """
    if isinstance(device, cl.CommandQueue):
        return device
    if device is None:
        for obj in like or ():
            queue = getattr(obj, "queue", None)
            if isinstance(queue, cl.CommandQueue):
                return queue
    dev = select_device(device, like)
    # keyed by the context the caller gave, else by the device (one context of ours per device); the key holds
    # the objects themselves, so an address freed and reused can never reach a stale queue
    key = (device, dev) if isinstance(device, cl.Context) else (None, dev)
    with _lock:
        queue = _queues.get(key)
        if queue is None:
            context = device if isinstance(device, cl.Context) else cl.Context([dev])
            queue = cl.CommandQueue(context, dev, properties=cl.command_queue_properties.PROFILING_ENABLE)
            _queues[key] = queue
        return queue


def get_allocator(queue: cl.CommandQueue):
    """A memory pool for the queue's context: device outputs reuse freed buffers instead of mapping fresh
    memory (on CPU devices a fresh buffer costs a page fault per 4 KiB on first write)."""
    key = queue.context
    with _lock:
        pool = _pools.get(key)
        if pool is None:
            pool = cl.tools.MemoryPool(cl.tools.ImmediateAllocator(queue))
            _pools[key] = pool
        return pool


def override(value: str | None, argument: str, env: str, valid: tuple[str, ...], what: str) -> str | None:
    """A per-call choice (``argument=value``) else the environment variable ``env``, lower-cased and checked
    against ``valid``; None when neither is set (the caller's device-based default applies)."""
    choice, origin = (value, f"{argument}=") if value is not None else (os.environ.get(env), f"{env}=")
    if not choice:
        return None
    key = choice.strip().lower()
    if key not in valid:
        raise SpecgpuDeviceError(f"{origin}{choice!r} is no {what} (choose from {', '.join(valid)})")
    return key


def kernel_variant(device: cl.Device, variant: str | None = None) -> str:
    """The kernel variant for ``device``: ``variant`` when given, else SPECGPU_VARIANT, else "gpu" on GPU devices
    and "cpu" on every other (CPU, accelerator)."""
    chosen = override(variant, "variant", ENV_VARIANT, VARIANTS, "kernel variant")
    return chosen or ("gpu" if device.type & cl.device_type.GPU else "cpu")


def is_discrete(device: cl.Device) -> bool:
    """Whether the device has memory of its own (a discrete GPU): host arrays then cross a bus and go through
    pinned staging (:mod:`specgpu.engine.transfer`); CPU devices and integrated GPUs share the host's memory."""
    if device.type & cl.device_type.CPU:
        return False
    try:
        return not device.host_unified_memory
    except (cl.Error, AttributeError):  # OpenCL 2.0+ drivers may drop the query
        return bool(device.type & cl.device_type.GPU)


# ---------------------------------------------------------------------------------------------- kernel sources


@functools.cache
def kernel_dir() -> Path:
    """The folder holding the OpenCL sources.

    An installed wheel carries them inside the package (``specgpu/_kernels``); a source checkout (or an
    editable install) has them at the top level, next to the package.
    """
    packaged = resources.files("specgpu") / "_kernels"
    if packaged.is_dir():
        return Path(str(packaged))
    source_tree = Path(__file__).resolve().parents[2] / "kernels"
    if source_tree.is_dir():
        return source_tree
    raise FileNotFoundError(
        f"OpenCL kernel sources not found in {packaged} nor {source_tree}: the specgpu installation is incomplete"
    )


_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+)"[ \t]*$', re.MULTILINE)


@functools.cache
def kernel_source(name: str) -> str:
    """The text of ``kernels/<name>`` (for example ``"linear.cl"``), its ``#include "..."`` lines replaced by the
    text they name (once each).

    The program is built from this text alone, with no ``-I`` path among its options: the OpenCL compiler's
    on-disk cache (PoCL's, a driver's) keys a build by its text and options, so a path there would make every new
    checkout or virtual environment compile every kernel again.
    """
    path = kernel_dir() / name
    if not path.is_file():
        available = sorted(p.name for p in kernel_dir().glob("*.cl"))
        raise FileNotFoundError(f"no kernel source {name!r} in {kernel_dir()} (available: {available})")
    included: set[str] = set()

    def inline(match: re.Match) -> str:
        header = match.group(1)
        if header in included:
            return ""
        included.add(header)
        header_path = kernel_dir() / header
        if not header_path.is_file():
            raise FileNotFoundError(f"{name} includes {header!r}, which is not in {kernel_dir()}")
        text = _INCLUDE.sub(inline, header_path.read_text(encoding="utf-8"))
        return f'#line 1 "{header}"\n{text}\n#line {match.string.count(chr(10), 0, match.end()) + 2} "{name}"'

    return _INCLUDE.sub(inline, path.read_text(encoding="utf-8"))


def build_options(**macros) -> tuple[str, ...]:
    """``-D`` options from keyword macros; booleans become 0/1, None drops the macro. Sorted: stable cache keys."""
    options = []
    for key in sorted(macros):
        value = macros[key]
        if value is None:
            continue
        if isinstance(value, bool):
            value = int(value)
        options.append(f"-D{key}={value}")
    return tuple(options)


def mask_options() -> tuple[str, ...]:
    """The mask flags as ``-D`` options (``-DMASK_SATURATED=1`` ...), from :class:`specgpu.core.mask.Mask`: every
    program is built with them, and a kernel source defines none of its own (``common.h`` stops a build without
    them)."""
    return build_options(**mask_macros())


def _device_options(device: cl.Device) -> list[str]:
    """Options a device family needs. PoCL's clang honours under-aligned vector types, which replace its
    out-of-line vloadn / vstoren calls by inline unaligned moves (kernels/common.h, VEC_DEREF).

    Oclgrind, the conformance-checking OpenCL simulator (tests/engine/test_oclgrind.py), interprets the LLVM IR its
    clang makes, and two of its defects are avoided here. Optimised, a vector ``c ? 1 : 0`` (the mask flags) becomes a
    zero extension of a vector of booleans, which Oclgrind 21.10 evaluates to 255 instead of 1 per true lane;
    unoptimised IR keeps the select, which it evaluates right (tests/data/oclgrind_defects.cl has the reduced
    kernel). Its uninitialised-read check stops at the private out-pointer of sincos(), so CIEDE2000 calls sin()
    and cos() there (SPLIT_SINCOS)."""
    platform = device.platform.name.lower()
    if "portable computing language" in platform:
        return ["-DVEC_DEREF=1"]
    if "oclgrind" in platform:
        return ["-cl-opt-disable", "-DSPLIT_SINCOS=1"]
    return []


class _Program:
    """A built program and the kernels retrieved from it (kept: retrieving one per call is slow)."""

    def __init__(self, program):
        self.program = program  # pyopencl's low-level program (``_cl._Program``): what ``cl.Kernel`` takes
        self.kernels: dict[str, cl.Kernel] = {}
        self.lock = threading.Lock()

    def kernel(self, name: str) -> cl.Kernel:
        with self.lock:
            kernel = self.kernels.get(name)
            if kernel is None:
                kernel = cl.Kernel(self.program, name)
                self.kernels[name] = kernel
            return kernel


_programs: dict[tuple, _Program] = {}


def _build(context: cl.Context, source: str, options: list[str]):
    """Build ``source`` with exactly ``options``.

    ``cl.Program.build`` adds ``-I <pyopencl's header folder>`` to every build. That folder lies inside the Python
    environment, and an on-disk compiler cache keys a build by its options (PoCL's does), so each new virtual
    environment or clone would compile every kernel again: a fresh checkout's test suite took 2.5 times the CPU of
    a warm one. No kernel here includes a pyopencl header, so the program is built by pyopencl's low-level
    ``_Program`` with the options as given, and that object is returned (``cl.Kernel`` takes it as it is;
    wrapped in ``cl.Program``, every kernel made from it would first look up a ``_source`` attribute the wrapper
    lacks, which pyopencl turns into a lookup of a kernel of that name: a runtime error under Oclgrind). The
    public call is kept for a pyopencl that lacks the low-level class.
    """
    low_level = getattr(getattr(cl, "_cl", None), "_Program", None)
    if low_level is None:  # pragma: no cover - a future pyopencl without the low-level class
        return cl.Program(context, source).build(options=options)
    program = low_level(context, source)
    program.build(" ".join(options).encode(), None)
    return program


def get_program(context: cl.Context, source_name: str, options: tuple[str, ...]) -> _Program:
    """Build (once) the program for ``kernels/<source_name>`` with ``options`` in ``context``."""
    source = kernel_source(source_name)
    key = (context, source, options)  # the Context itself: a reused address never hits a stale program
    with _lock:
        entry = _programs.get(key)
    if entry is not None:
        return entry
    # -cl-denorms-are-zero: CIEDE2000's chroma and hue-rotation terms underflow into float32 denormals for
    # near-neutral colours, which x86 handles in microcode (the fused pass ran at half speed on such data); values
    # below 1.2e-38 carry no meaning here
    full_options = [*options, *mask_options(), *_device_options(context.devices[0]), "-cl-mad-enable",
                    "-cl-denorms-are-zero"]
    try:
        program = _build(context, source, full_options)
    except cl.RuntimeError as error:
        first = str(error).strip().splitlines()
        raise SpecgpuDeviceError(
            f"building {source_name} with {' '.join(options)} failed on {context.devices[0].name.strip()}: "
            + " | ".join(line for line in first if "error" in line.lower())[:2000]
        ) from error
    entry = _Program(program)
    with _lock:
        entry = _programs.setdefault(key, entry)
    return entry


def get_kernel(queue: cl.CommandQueue, source_name: str, kernel_name: str, **macros) -> cl.Kernel:
    """The kernel ``kernel_name`` of ``kernels/<source_name>`` specialised by ``macros``, built once and kept."""
    return get_program(queue.context, source_name, build_options(**macros)).kernel(kernel_name)


def new_kernel(queue: cl.CommandQueue, source_name: str, kernel_name: str, **macros) -> cl.Kernel:
    """A kernel object of its own (arguments set on it stay set) from the cached program: for a launch repeated
    with most arguments unchanged (the stream), where setting every argument per call costs more than the call."""
    return cl.Kernel(get_program(queue.context, source_name, build_options(**macros)).program, kernel_name)


def program_cache_size() -> int:
    """Number of distinct programs built so far (for tests and diagnostics)."""
    return len(_programs)


def describe(device=None) -> str:
    """The text of ``specgpu info``: platforms, devices with their selectors, the chosen device and versions."""
    lines = []
    devices = list_devices()
    chosen = select_device(device)
    if device is not None:
        reason = f"--device {device!r}"
    elif os.environ.get(ENV_DEVICE):
        reason = f"{ENV_DEVICE}={os.environ[ENV_DEVICE]!r}"
    else:
        reason = "default order: first GPU, else first CPU"
    platforms = {}
    for info in devices:
        platforms.setdefault(info.platform_index, []).append(info)
    for p_index, infos in platforms.items():
        platform = infos[0].device.platform
        lines.append(f"platform {p_index}: {platform.name.strip()} ({platform.version.strip()})")
        for info in infos:
            mark = "*" if info.device.int_ptr == chosen.int_ptr else " "
            lines.append(
                f" {mark} {info.selector}  {info.name}  [{info.type}, {info.compute_units} compute units, "
                f"{info.global_mem_bytes / 2**30:.1f} GiB, {info.version}, kernels {kernel_variant(info.device)}, "
                f"{'discrete: pinned staging' if is_discrete(info.device) else 'host memory: zero-copy'}]"
            )
    lines.append(f"chosen: {chosen.name.strip()} ({reason}); override with --device or {ENV_DEVICE}=P:D|name")
    variant_reason = f"{ENV_VARIANT}={os.environ[ENV_VARIANT]!r}" if os.environ.get(ENV_VARIANT) else "by device type"
    lines.append(f"kernel variant: {kernel_variant(chosen)} ({variant_reason}; "
                 + ", ".join(f"{k}: {v} pixel{'s' if v > 1 else ''} per work-item" for k, v in VARIANTS.items())
                 + f"); override with {ENV_VARIANT}=cpu|gpu")
    versions = []
    for package in ("specgpu", "pyopencl", "pocl-binary-distribution", "numpy", "colour-science", "OpenImageIO"):
        try:
            versions.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{package} (not installed)")
    lines.append("versions: " + ", ".join(versions))
    lines.append(f"kernels: {kernel_dir()}")
    return "\n".join(lines)
