#!/usr/bin/env bash
# The GPU measurement set in one command: the figures the README's "On a GPU" table waits for.
#
# On the project machine, once (downloads the wheels the GPU machine cannot fetch; .whl/ is git-ignored locally):
#     tools/gpu_check.sh fetch
# Then, on the GPU machine (the device tool: carry [".whl"]; each call is limited to 10 minutes, so three calls):
#     bash tools/gpu_check.sh info bench   # selftest; bench 640x480 .. 4096x4096 incl. NumPy in / NumPy out
#     bash tools/gpu_check.sh stream       # bench --stream 2048x2048 and 640x480 (fused, 61-band f16 cube)
#     bash tools/gpu_check.sh tests        # the whole suite
# or `bash tools/gpu_check.sh all` where no time limit applies. Everything lands under $OUT (default ./gpu_out):
# info.txt, bench.json / bench.txt, stream_*.json / .txt, tests.txt, and summary.txt (the GPU targets, each
# with its figure; `python tools/gpu_summary.py DIR` redoes it over the files of several calls put together).
set -u -o pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-$PWD/gpu_out}
mkdir -p "$OUT"
PARTS=("$@")
[ ${#PARTS[@]} -eq 0 ] && PARTS=(all)
[ "${PARTS[0]}" = all ] && PARTS=(info bench stream tests)

if [ "${PARTS[0]}" = fetch ]; then
    grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> "$(git rev-parse --git-common-dir)/info/exclude"
    for p in pyopencl pytools platformdirs siphash24 colour-science OpenImageIO pyusb typing_extensions; do
        python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
            --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
            --platform manylinux2014_x86_64 --platform any -d .whl "$p" || exit 1
    done
    ls -la .whl
    exit 0
fi

# ---- on the GPU machine: wheels, the NVIDIA ICD, specgpu from the source tree
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1
if [ ! -s /etc/OpenCL/vendors/nvidia.icd ]; then
    lib=$(find / -xdev -name 'libnvidia-opencl.so*' 2>/dev/null | head -1)
    if [ -n "$lib" ]; then mkdir -p /etc/OpenCL/vendors && echo "$lib" > /etc/OpenCL/vendors/nvidia.icd; fi
fi
DEV=${SPECGPU_GPU:-nvidia}
S() { python3 -c 'import sys; from specgpu.cli import main; sys.argv[0] = "specgpu"; main()' "$@"; }

for part in "${PARTS[@]}"; do
    case $part in
    info)
        { S info --device "$DEV"; nvidia-smi 2>/dev/null | head -15; } 2>&1 | tee "$OUT/info.txt"
        S selftest -v --device "$DEV" 2>&1 | tee -a "$OUT/info.txt" ;;
    bench)  # kernels on device data and the NumPy-in / NumPy-out API call, 4096 x 4096 included
        timeout 540 python3 -c 'import sys; from specgpu.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --device "$DEV" --sizes 640x480,2048x2048,4096x4096 --json "$OUT/bench.json" 2>&1 \
            | tee "$OUT/bench.txt" ;;
    stream)  # raw frames/s: coefficients + XYZ + dE2000 at 2048 x 2048 and 640 x 480, the 61-band f16 cube
        timeout 330 python3 -c 'import sys; from specgpu.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 2048x2048 --stream-cases fused --stream-seconds 8 \
            --json "$OUT/stream_2048.json" 2>&1 | tee "$OUT/stream_2048.txt"
        timeout 230 python3 -c 'import sys; from specgpu.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 640x480 --stream-cases fused,cube --stream-seconds 8 \
            --json "$OUT/stream_640.json" 2>&1 | tee "$OUT/stream_640.txt" ;;
    tests)  # the whole suite on the GPU (both kernel variants are forced inside the kernel tests)
        SPECGPU_DEVICE=$DEV timeout 560 python3 -m pytest -q -p no:cacheprovider -p no:randomly \
            2>&1 | tail -40 | tee "$OUT/tests.txt" ;;
    *) echo "unknown part $part (fetch, all, info, bench, stream, tests)" >&2; exit 2 ;;
    esac
done

python3 tools/gpu_summary.py "$OUT" 2>&1 | tee "$OUT/summary.txt"
