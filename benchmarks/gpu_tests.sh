#!/usr/bin/env bash
# The GPU test lane: the whole test suite on a CUDA device.
#
#   benchmarks/gpu_tests.sh REPORT [PYTEST ARGS ...]
#
# Runs `pytest --device cuda` over tests/, the test files spread over WORKERS processes
# (default: one per CPU core) when pytest-xdist is installed, so that their CUDA kernel modules
# compile side by side; each file stays in one process, which keeps its module-scoped fixtures
# and compiled kernels together. Writes the GPU's name and pytest's output (failures, skips and
# the closing passed/failed/skipped line) to REPORT. Exits with pytest's status.
set -uo pipefail
report=${1:?usage: gpu_tests.sh REPORT [PYTEST ARGS ...]}
shift
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
workers=${WORKERS:-$(nproc)}
parallel=()
if python3 -c "import xdist" 2>/dev/null; then
  parallel=(-n "$workers" --dist loadfile)
fi
{
  echo "GPU: $(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)"
  echo "packages: $(python3 -c 'import mujoco, mujoco_warp, warp; print("mujoco", mujoco.__version__, "warp-lang", warp.__version__)')"
  echo "command: pytest --device cuda ${parallel[*]} $*"
} > "$report"
python3 -m pytest -q --device cuda "${parallel[@]}" -rfEs -p no:cacheprovider "$@" tests 2>&1 | tee -a "$report"
exit "${PIPESTATUS[0]}"
