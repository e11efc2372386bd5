#!/usr/bin/env bash
# One GPU session's measurements, meant to run detached on the GPU machine (setsid) so that the
# compiles and timed runs go on between device calls, which then only poll and fetch results:
#
#   setsid nohup benchmarks/gpu_session.sh RESULTS_DIR [SCENE ...] > RESULTS_DIR/log 2>&1 &
#
# 1. compiles every scene of run_suite.py in parallel processes (Warp's kernel cache);
# 2. times the main scenes (aloha_pot, pile_32_128) with run_suite.py;
# 3. profiles the collision kernels inside 30 steps of both at 8192 worlds, stock and plugin
#    variants (PROFILE_VARIANTS);
# 4. times the other scenes (or the SCENEs given), one run_suite.py call each.
# Each step writes its files into RESULTS_DIR as it ends and touches RESULTS_DIR/<step>.done.
set -uo pipefail
out=${1:?results dir}
shift
here=$(cd "$(dirname "$0")" && pwd)
cd "$here/.."
mkdir -p "$out"
export PYTHONUNBUFFERED=1
others=("$@")
[ ${#others[@]} -gt 0 ] || others=(primitives_32 humanoid pile_32_1024 pile_256_128 pile_1024_128 terrain_32)
variants=${PROFILE_VARIANTS:-"default,warm_start=False,max_registers=128"}
aloha=$(python3 -c "import mujoco_warp, os; print(os.path.join(os.path.dirname(mujoco_warp.__file__), 'test_data', 'aloha_pot', 'scene.xml'))")

step() { echo "=== $(date +%T) $1"; }

step compile
python3 -c "
import sys; sys.path.insert(0, 'benchmarks')
import make_scenes, run_suite
make_scenes.main()
print(run_suite.compile_all(list(run_suite.SCENES), 8))"
touch "$out/compile.done"

step main-scenes
python3 benchmarks/run_suite.py --only aloha_pot pile_32_128 --out "$out" --suffix -main
touch "$out/main.done"

step profile
for scene in benchmarks/scenes/pile_32_128.xml "$aloha"; do
  python3 benchmarks/profile_collision.py "$scene" --nworld 8192 --steps 30 --variants "$variants"
done > "$out/profile-steps.txt" 2>&1
touch "$out/profile.done"

for scene in "${others[@]}"; do
  step "$scene"
  python3 benchmarks/run_suite.py --only "$scene" --out "$out" --suffix "-$scene"
done
touch "$out/others.done"
step end
