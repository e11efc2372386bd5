#!/usr/bin/env bash
# The GPU test lane: the whole test suite on a CUDA device.
#
#   benchmarks/gpu_tests.sh REPORT [PYTEST ARGS ...]
#
# Runs `pytest --device cuda` over tests/, the tests spread over WORKERS processes (default: one
# per CPU core) when pytest-xdist is installed, so that their CUDA kernel modules compile side by
# side. Tests are dealt out one by one and idle workers steal queued ones (a file at a time left
# the long files queued behind each other); a module-scoped fixture then sets up once per worker
# that runs its tests, and Warp's kernel cache (~/.cache/warp) keeps that cheap after the first
# build. First, unless PRELOAD=0, preload_kernels.py builds the kernel modules the workers share,
# once each and side by side, into that cache. Writes the GPU's name and pytest's output (failures, skips and the closing
# passed/failed/skipped line) to REPORT. Exits with pytest's status.
set -uo pipefail
report=${1:?usage: gpu_tests.sh REPORT [PYTEST ARGS ...]}
shift
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
workers=${WORKERS:-$(nproc)}
parallel=()
if python3 -c "import xdist" 2>/dev/null; then
  parallel=(-n "$workers" --dist worksteal)
fi
{
  echo "GPU: $(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)"
  echo "packages: $(python3 -c 'import mujoco, mujoco_warp, warp; print("mujoco", mujoco.__version__, "warp-lang", warp.__version__)')"
  echo "command: pytest --device cuda ${parallel[*]} $*"
} > "$report"
if [ "${PRELOAD:-1}" != 0 ]; then
  python3 benchmarks/preload_kernels.py --device cuda:0 --workers "$workers" 2>&1 | grep -v "^Module " | tee -a "$report"
fi
python3 -m pytest -q --device cuda "${parallel[@]}" -rfEs -p no:cacheprovider "$@" tests 2>&1 | tee -a "$report"
exit "${PIPESTATUS[0]}"
