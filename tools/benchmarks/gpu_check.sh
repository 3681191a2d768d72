#!/usr/bin/env bash
# The GPU measurement set in one command: the figures of the README's GPU table, each beside its target.
#
# On a machine with a package index, once (downloads the wheels a GPU machine without one installs; .whl/ is
# git-ignored):
#     tools/benchmarks/gpu_check.sh fetch
# Then, on the GPU machine, with .whl/ copied beside the source tree (three parts of under 10 minutes each):
#     bash tools/benchmarks/gpu_check.sh info bench  # selftest; bench 640x480 .. 4096x4096 incl. NumPy in / out
#     bash tools/benchmarks/gpu_check.sh stream      # bench --stream 2048x2048 and 640x480 (fused, 61-band f16
#                                                    # cube, motion, denoise)
#     bash tools/benchmarks/gpu_check.sh tests       # the whole suite (in parallel where pytest-xdist is installed)
#     bash tools/benchmarks/gpu_check.sh motion      # the motion stream against the static one, each motion step's
#                                                    # cost, and the kernel and motion tests on the GPU (~6 minutes)
# or `bash tools/benchmarks/gpu_check.sh all` where no time limit applies. Everything lands under $OUT (default
# ./gpu_out): info.txt, bench.json / bench.txt, stream_*.json / .txt, tests.txt, and summary.txt (the GPU targets,
# each with its figure; `python tools/benchmarks/gpu_summary.py DIR` redoes it over the files of several calls put
# together).
set -u -o pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-$PWD/gpu_out}
mkdir -p "$OUT"
PARTS=("$@")
[ ${#PARTS[@]} -eq 0 ] && PARTS=(all)
[ "${PARTS[0]}" = all ] && PARTS=(info bench stream tests)

if [ "${PARTS[0]}" = fetch ]; then
    # every requirement of pyproject.toml (dependencies and the test extra) with its own dependencies, as CPython 3.12
    # manylinux wheels; PoCL is left out (the GPU is the device there) and pytest-xdist added (the suite in parallel).
    # The GPU machine's image already has the large scientific stack: those wheels are dropped so the set stays
    # within what one device call can carry, and the install below skips anything that machine already has.
    grep -qx '/.whl/' .gitignore 2>/dev/null || grep -qx '/.whl/' "$(git rev-parse --git-common-dir)/info/exclude" \
        2>/dev/null || echo /.whl/ >> "$(git rev-parse --git-common-dir)/info/exclude"
    mapfile -t REQS < <(python3 -c 'import tomllib
p = tomllib.load(open("pyproject.toml", "rb"))["project"]
for r in p["dependencies"] + p["optional-dependencies"]["test"]:
    if not r.startswith("pocl-binary-distribution"):
        print(r.split(";")[0].strip())')
    rm -rf .whl
    python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform any -d .whl "${REQS[@]}" pytest-xdist || exit 1
    for big in numpy scipy scikit_image matplotlib pillow fonttools networkx kiwisolver contourpy imageio \
               tifffile pygments pytest-[0-9] hypothesis click tqdm; do
        rm -f .whl/"$big"-*.whl
    done
    ls .whl; du -sh .whl
    exit 0
fi

# ---- on the GPU machine: wheels, the NVIDIA ICD, specgpu from the source tree
if [ -d .whl ]; then
    # only the distributions this machine lacks: its own numpy / scipy builds stay in charge
    mapfile -t MISSING < <(python3 -c 'import sys, importlib.metadata as md
from pathlib import Path
for w in sorted(Path(".whl").glob("*.whl")):
    name = w.name.split("-")[0]
    try:
        md.version(name)
    except md.PackageNotFoundError:
        print(w)')
    if [ ${#MISSING[@]} -gt 0 ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "${MISSING[@]}" || exit 1
    fi
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
S() { python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' "$@"; }

for part in "${PARTS[@]}"; do
    case $part in
    info)
        { S info --device "$DEV"; nvidia-smi 2>/dev/null | head -15; } 2>&1 | tee "$OUT/info.txt"
        S selftest -v --device "$DEV" 2>&1 | tee -a "$OUT/info.txt" ;;
    bench)  # kernels on device data and the NumPy-in / NumPy-out API call, 4096 x 4096 included
        timeout 540 python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --device "$DEV" --sizes 640x480,2048x2048,4096x4096 --json "$OUT/bench.json" 2>&1 \
            | tee "$OUT/bench.txt" ;;
    stream)  # raw frames/s: coefficients + XYZ + dE2000 at 2048 x 2048 and 640 x 480, the 61-band f16 cube
        timeout 330 python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 2048x2048 --stream-cases fused --stream-seconds 8 \
            --json "$OUT/stream_2048.json" 2>&1 | tee "$OUT/stream_2048.txt"
        timeout 230 python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 640x480 --stream-cases fused,cube --stream-seconds 8 \
            --json "$OUT/stream_640.json" 2>&1 | tee "$OUT/stream_640.txt"
        # what motion compensation (--motion global) and the edge-aware denoiser cost there
        timeout 200 python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 640x480 --stream-cases motion,linear,denoise \
            --stream-seconds 5 --json "$OUT/stream_640_extra.json" 2>&1 | tee "$OUT/stream_640_extra.txt" ;;
    motion)  # --motion global / flow against the static stream, each step's cost, the kernel and motion tests
        timeout 150 python3 -c 'import sys; from specgpu.apps.cli import main; sys.argv[0] = "specgpu"; main()' \
            bench --stream --device "$DEV" --stream-size 640x480 --stream-cases motion --stream-seconds 5 \
            --stream-rounds 3 --json "$OUT/stream_640_motion.json" 2>&1 | tee "$OUT/stream_640_motion.txt"
        SPECGPU_DEVICE=$DEV timeout 90 python3 tools/benchmarks/motion_cost.py --repeats 9 --outputs 8 2>&1 \
            | tee "$OUT/motion_cost.txt"
        XDIST=(); python3 -c 'import xdist' 2>/dev/null && XDIST=(-n 8)
        SPECGPU_DEVICE=$DEV timeout 200 python3 -m pytest -q -p no:cacheprovider -p no:randomly "${XDIST[@]}" \
            tests/engine tests/motion tests/pipeline/test_moving_decode.py \
            tests/pipeline/test_moving_layers.py 2>&1 | tail -30 \
            | tee "$OUT/tests_motion.txt" ;;
    tests)  # the whole suite on the GPU (both kernel variants are forced inside the kernel tests)
        XDIST=(); python3 -c 'import xdist' 2>/dev/null && XDIST=(-n 8)   # 16 cores there: the suite in parallel
        SPECGPU_DEVICE=$DEV timeout 560 python3 -m pytest -q -p no:cacheprovider -p no:randomly "${XDIST[@]}" \
            2>&1 | tail -40 | tee "$OUT/tests.txt" ;;
    *) echo "unknown part $part (fetch, all, info, bench, stream, motion, tests)" >&2; exit 2 ;;
    esac
done

PYTHONPATH=. python3 tools/benchmarks/gpu_summary.py "$OUT" 2>&1 | tee "$OUT/summary.txt"
