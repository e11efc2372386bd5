"""Builds Warp's CUDA kernel cache for benchmark scenes on a machine without a GPU.

  python benchmarks/warm_cache.py CACHE_DIR [SCENE ...] [--arch 90] [--ptx]
  python benchmarks/warm_cache.py CACHE_DIR --all-modules [--jobs N]

Each SCENE (a run_suite.py scene name or an MJCF path; default terrain_32) runs once on the
CPU at 2 worlds, both implementations, as ``run_suite.py --compile-only`` runs it, so that Warp
holds the kernel modules the GPU run will load (their names carry a hash of their code). Each
loaded module is then compiled for the GPU (``wp.compile_aot_module``) into CACHE_DIR, in the
kernel cache's layout; modules already there are skipped.

On the GPU machine, Warp 1.19 reads the cache from ``$WARP_CACHE_PATH/<warp version>``: put
CACHE_DIR's contents there. It loads CUBIN for the GPU's architecture when the driver is older
than Warp's NVRTC (the H200 machine: driver 13.0, NVRTC 13.4), else PTX for sm_75 (``--ptx
--arch 75``). The .cu sources are not read at load time; leave them out of what you carry.
Modules that Warp builds differently for the GPU than for the CPU are still compiled there.

``--all-modules`` runs no scene: it compiles every module that preload_kernels.py builds on the
GPU (all of MuJoCo Warp's and the plugin's, with both narrow-phase kernels), ``--jobs`` at a time,
so that the GPU test lane's preload finds them all in the carried cache.
"""

import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import warp as wp
from warp._src.context import user_modules

from mjx_supportfield.options import Options
from mjx_supportfield.tools import bench

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import run_suite  # noqa: E402


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("cache_dir")
  p.add_argument("scenes", nargs="*", default=["terrain_32"])
  p.add_argument("--arch", type=int, default=90, help="SM architecture (90: H100 / H200)")
  p.add_argument("--ptx", action="store_true", help="PTX instead of CUBIN")
  p.add_argument("--all-modules", action="store_true", help="every module preload_kernels.py builds, no scene")
  p.add_argument("--jobs", type=int, default=os.cpu_count(), help="modules compiled at a time (--all-modules)")
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  wp.init()
  if args.all_modules:
    _compile_all(args)
    return
  for scene in args.scenes:
    path = run_suite.SCENES[scene][0] if scene in run_suite.SCENES else scene
    start = time.perf_counter()
    bench.bench_scene(path, [2], 1, 200, None, Options())
    print(f"{scene}: ran on the CPU in {time.perf_counter() - start:.0f} s", flush=True)
  modules = [m for m in list(user_modules.values()) if m.execs]
  wp.config.kernel_cache_dir = os.path.abspath(args.cache_dir)
  start = time.perf_counter()
  for module in modules:
    wp.compile_aot_module(module, arch=args.arch, use_ptx=args.ptx)
  print(f"{len(modules)} modules in {args.cache_dir} ({time.perf_counter() - start:.0f} s)", flush=True)


def _compile_all(args):
  import preload_kernels

  preload_kernels.import_kernel_modules()
  modules = [m for m in user_modules.values() if m.kernels]  # modules of functions only have nothing to build
  wp.config.kernel_cache_dir = os.path.abspath(args.cache_dir)
  start = time.perf_counter()
  with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:  # NVRTC runs outside the GIL
    list(pool.map(lambda m: wp.compile_aot_module(m, arch=args.arch, use_ptx=args.ptx), modules))
  print(f"{len(modules)} modules in {args.cache_dir} ({time.perf_counter() - start:.0f} s)", flush=True)


if __name__ == "__main__":
  main()
