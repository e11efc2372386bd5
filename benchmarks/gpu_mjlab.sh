#!/usr/bin/env bash
# mjlab's tasks on the GPU machine, unattended (setsid), after benchmarks/mjlab_wheels.sh's
# wheels are installed: compiles each task's kernels side by side at 64 envs (stock and plugin;
# the plugin's heightfield module takes minutes from an empty cache), then times each task at
# 1024 and 4096 envs, one at a time. Writes OUT/mjlab-<task>.json and OUT/log; OUT/done at the end.
#
#   setsid nohup benchmarks/gpu_mjlab.sh OUT > OUT.log 2>&1 &
set -uo pipefail
out=${1:?results dir}
mkdir -p "$out"
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
tasks=${TASKS:-"Mjlab-Velocity-Rough-Unitree-Go1 Mjlab-Velocity-Rough-Unitree-G1 Mjlab-Lift-Cube-Yam Mjlab-Multi-Cube-Seg-Yam"}
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > "$out/gpu.txt"
echo "=== $(date +%T) compile" >> "$out/log"
for t in $tasks; do
  python3 benchmarks/mjlab_tasks.py --tasks "$t" --num-envs 64 --steps 5 --warmup 1 > "$out/compile-$t.log" 2>&1 &
done
wait
for t in $tasks; do
  echo "=== $(date +%T) $t" >> "$out/log"
  python3 benchmarks/mjlab_tasks.py --tasks "$t" --num-envs ${NUM_ENVS:-1024 4096} --steps ${STEPS:-100} \
    --json "$out/mjlab-$t.json" > "$out/mjlab-$t.log" 2>&1
done
echo "=== $(date +%T) done" >> "$out/log"
touch "$out/done"
