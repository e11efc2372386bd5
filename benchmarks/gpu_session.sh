#!/usr/bin/env bash
# One GPU session's measurements, meant to run detached on the GPU machine (setsid) so that the
# compiles and timed runs go on between device calls, which then only poll and fetch results:
#
#   setsid nohup benchmarks/gpu_session.sh RESULTS_DIR [SCENE ...] > RESULTS_DIR/log 2>&1 &
#
# 1. compiles the scenes it will time in parallel processes (Warp's kernel cache);
# 2. times the main scenes (aloha_pot, pile_32_128) with run_suite.py (MAIN=0 skips them);
# 3. times the other scenes (or the SCENEs given), one run_suite.py call each;
# 4. profiles the collision kernels inside 30 steps of the main scenes at 8192 worlds, stock and
#    plugin variants (PROFILE_VARIANTS), and, with BASELINE=DIR (a directory holding another
#    version of the mjx_supportfield package), that version's default too (PROFILE=0 skips it).
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
variants=${PROFILE_VARIANTS:-"default,warm_start=False,mpr_refine=0"}
aloha=$(python3 -c "import mujoco_warp, os; print(os.path.join(os.path.dirname(mujoco_warp.__file__), 'test_data', 'aloha_pot', 'scene.xml'))")

step() { echo "=== $(date +%T) $1"; }

step compile
python3 benchmarks/make_scenes.py
timed=()
[ "${MAIN:-1}" != 0 ] && timed+=(aloha_pot pile_32_128)
for scene in "${others[@]}"; do [ "$scene" != profile ] && timed+=("$scene"); done
if [ -n "${BASELINE:-}" ]; then  # the baseline's own narrow-phase kernels, for the profile
  for scene in benchmarks/scenes/pile_32_128.xml "$aloha"; do
    PYTHONPATH="$BASELINE:${PYTHONPATH:-}" python3 benchmarks/profile_collision.py "$scene" --nworld 64 --steps 1 --no-stock
  done > "$out/compile-baseline.log" 2>&1 &
fi
python3 -c "
import sys; sys.path.insert(0, 'benchmarks')
import run_suite
print(run_suite.compile_all(sys.argv[1:], 8))" "${timed[@]}"
touch "$out/compile.done"

if [ "${MAIN:-1}" != 0 ]; then
  step main-scenes
  python3 benchmarks/run_suite.py --only aloha_pot pile_32_128 --out "$out" --suffix=-main
  touch "$out/main.done"
fi

profile() {
  for scene in benchmarks/scenes/pile_32_128.xml "$aloha"; do
    python3 benchmarks/profile_collision.py "$scene" --nworld 8192 --steps 30 --variants "$variants"
    if [ -n "${BASELINE:-}" ]; then
      echo "== baseline: $BASELINE"
      PYTHONPATH="$BASELINE:${PYTHONPATH:-}" python3 benchmarks/profile_collision.py "$scene" --nworld 8192 --steps 30 --no-stock
    fi
  done > "$out/profile-steps.txt" 2>&1
  touch "$out/profile.done"
}

# "profile" among the SCENEs places the profile there; else it runs last
for scene in "${others[@]}"; do
  step "$scene"
  if [ "$scene" = profile ]; then
    profile
    continue
  fi
  python3 benchmarks/run_suite.py --only "$scene" --out "$out" --suffix="-$scene"
done
touch "$out/others.done"
if [ "${PROFILE:-1}" != 0 ] && [[ " ${others[*]} " != *" profile "* ]]; then
  step profile
  profile
fi
step end
