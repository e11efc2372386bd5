"""Compiles the kernel modules of MuJoCo Warp and of the plugin for one device, side by side.

  python benchmarks/preload_kernels.py [--device cuda:0] [--workers N]

The GPU test lane (``gpu_tests.sh``) runs this before pytest. Each pytest worker builds every
kernel module it meets one after another, and sixteen workers that meet the same modules build
them sixteen times at once; here each module is built once, ``--workers`` at a time (Warp's
``force_load`` runs NVRTC in threads), into Warp's kernel cache, from which the workers then load
them. Every module that importing the two packages defines is built, with the plugin's
narrow-phase kernels for both narrow phases; kernels made per model (the broad phase's sweep,
the analytic pairs) are left to the tests, they are small. Modules already in the cache load in
milliseconds, so a second run costs little.
"""

import argparse
import importlib
import os
import pkgutil
import time

import warp as wp
from warp._src.context import user_modules


def import_kernel_modules():
  """Imports every module of mujoco_warp._src and mjx_supportfield (tests excluded)."""
  import mujoco_warp._src as mjw_src

  import mjx_supportfield

  for pkg in (mjw_src, mjx_supportfield):
    for info in pkgutil.iter_modules(pkg.__path__):
      if info.name.endswith("_test") or info.name.startswith("__"):
        continue
      importlib.import_module(f"{pkg.__name__}.{info.name}")
  from mjx_supportfield.stages import deep_pairs
  from mjx_supportfield.stages import heightfield
  from mjx_supportfield.stages import multicontact_pass
  from mjx_supportfield.stages import narrowphase
  from mjx_supportfield.stages import nonconvex
  from mjx_supportfield.options import Options
  from mjx_supportfield.types import SupportMode

  # the support-mode factories' kernels, for the default mode (the others compile on first use)
  mode = SupportMode.of(Options().support_mode)
  for use_gjk in (False, True):
    narrowphase.convex_kernel(use_gjk, mode)
  narrowphase.sift_mpr_pairs(mode)
  deep_pairs.deep_kernels(mode)
  multicontact_pass.pass_kernels(mode)
  heightfield.stage_kernels(mode)
  nonconvex.nonconvex_narrowphase(mode)


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--device", default="cuda:0")
  p.add_argument("--workers", type=int, default=os.cpu_count())
  args = p.parse_args()
  wp.init()
  import_kernel_modules()
  modules = list(user_modules.values())
  t0 = time.perf_counter()
  wp.force_load(device=args.device, modules=modules, max_workers=args.workers)
  print(f"preload_kernels: {len(modules)} modules loaded on {args.device} in {time.perf_counter() - t0:.1f} s "
        f"({args.workers} threads)")


if __name__ == "__main__":
  main()
