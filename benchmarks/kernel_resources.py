"""Registers, stack per thread and build time of the plugin's kernels for a GPU, without a GPU.

  python benchmarks/kernel_resources.py [--arch 90] [--ptxas PATH] [--out FILE] [--max-registers N]
                                        [--only WORD,WORD]

Warp writes each kernel module's PTX for the given architecture (``wp.compile_aot_module``);
``ptxas -v`` then reports what the GPU would run. A kernel at the 255-register cap spills to
its stack: a large stack means slow local-memory traffic for every thread, whatever branch it
takes (MPR and GJK in one kernel cost MPR 10 KB a thread). Warp 1.19 emits PTX 9.4, which
needs ptxas from CUDA 13.4 or later, e.g. the ``nvidia-cuda-nvcc`` wheel
(``nvidia/cu13/bin/ptxas`` inside it).

The build time is NVRTC's (CUDA source to PTX) plus ptxas's (PTX to machine code) for the
kernel's whole module, roughly what a user's first run waits for on the GPU; kernels of a
module built earlier in the run show "shared".
"""

import argparse
import os
import re
import subprocess
import tempfile
import time

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.options import Options
from mjx_supportfield.stages import broadphase
from mjx_supportfield.stages import deep_pairs
from mjx_supportfield.stages import heightfield
from mjx_supportfield.stages import multicontact_pass
from mjx_supportfield.stages import narrowphase
from mjx_supportfield.stages import nonconvex
from mjx_supportfield.stages import routing
from mjx_supportfield.types import SupportMode

# broad-phase kernels are built per model; this key is a model without per-world sizes or sleep
_KEY = (0, 1, 1, 1, 1, 1, 1, False, False)
# the analytic kernel is built per model's pair types: those of a scene of primitives (no meshes)
_PRIMITIVE_PAIRS = tuple(t for t in routing.ANALYTIC_PAIRS if GeomType.MESH not in t)

# the support-mode factories' kernels are reported for the default mode
_MODE = SupportMode.of(Options().support_mode)

ENTRY = re.compile(r"Compiling entry function '([^']+)'")
USAGE = re.compile(r"Used (\d+) registers(?:.*?(\d+) bytes cumulative stack size)?")


def kernels() -> dict:
  """The kernels to report: name -> Warp kernel."""
  return {
    "listed pairs (nxn)": broadphase.listed_pairs_kernel(_KEY, True),
    "compact pairs (SAP)": broadphase.compact_pairs,
    "sift MPR pairs": narrowphase.sift_mpr_pairs(_MODE),
    "analytic (primitives)": narrowphase.analytic_kernel(_PRIMITIVE_PAIRS),
    "convex (MPR)": narrowphase.convex_kernel(False, _MODE),
    "convex (GJK/EPA)": narrowphase.convex_kernel(True, _MODE),
    "deep pairs (faces, lanes)": deep_pairs.deep_kernels(_MODE).faces,
    "deep pairs (walk round, lanes)": deep_pairs.deep_kernels(_MODE).round,
    "deep pairs (edges, lanes)": deep_pairs.deep_kernels(_MODE).edges,
    "deep pairs (finish)": deep_pairs.deep_kernels(_MODE).finish,
    "tilt (closed form)": multicontact_pass.pass_kernels(_MODE).tilt,
    "tilt (MPR)": multicontact_pass.pass_kernels(_MODE).tilt_mpr,
    "patch (multi-contact)": multicontact_pass.pass_kernels(_MODE).patch,
    "manifold (face clipping)": multicontact_pass.pass_kernels(_MODE).manifold,
    "heightfield jobs": heightfield.stage_kernels(_MODE).jobs,
    "heightfield MPR": heightfield.stage_kernels(_MODE).mpr,
    "heightfield GJK/EPA": heightfield.stage_kernels(_MODE).ccd,
    "heightfield contacts": heightfield.contacts_kernel(_MODE),
    "heightfield closed form": heightfield.hfield_closed_form,
    "non-convex (SDF)": nonconvex.nonconvex_narrowphase(_MODE),
  }


def resources(kernel, arch: int, ptxas: str, workdir: str) -> tuple[int, int, float | None]:
  """(registers, stack bytes) of one kernel's forward entry, from ptxas, and the seconds its
  module took to build (None when an earlier kernel of this run built it)."""
  start = time.perf_counter()
  built_before = set(os.listdir(workdir))
  paths = wp.compile_aot_module(kernel.module, arch=arch, use_ptx=True, module_dir=workdir)
  fresh = any(os.path.basename(path) not in built_before for path in paths)
  name = kernel.get_mangled_name()  # known once the module is built
  for path in paths:
    ptx = os.path.join(workdir, "kernel.ptx")
    with open(path, "rb") as src, open(ptx, "wb") as dst:
      dst.write(src.read().replace(b"\0", b""))  # the PTX file ends with a NUL ptxas refuses
    out = subprocess.run([ptxas, "-v", f"-arch=sm_{arch}", ptx, "-o", os.devnull], capture_output=True, text=True)
    if out.returncode != 0:
      raise RuntimeError(f"ptxas failed on {path}: {out.stderr.strip()[-500:]}")
    seconds = time.perf_counter() - start if fresh else None
    entry = None
    for line in (out.stdout + out.stderr).splitlines():
      if m := ENTRY.search(line):
        entry = m.group(1)
      elif (m := USAGE.search(line)) and entry and entry.startswith(name) and entry.endswith("forward"):
        return int(m.group(1)), int(m.group(2) or 0), seconds  # no stack line: a kernel without calls
  raise RuntimeError(f"ptxas reported nothing for {name}")


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--arch", type=int, default=90, help="SM architecture (90: H100 / H200)")
  p.add_argument("--ptxas", default="ptxas", help="ptxas of CUDA 13.4 or later")
  p.add_argument("--out", help="also write the table to this file")
  p.add_argument("--max-registers", type=int, help="rebuild each kernel with this register cap (cuda_max_registers)")
  p.add_argument("--only", help="report only the kernels whose label contains one of these comma-separated words")
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  wp.init()
  cap = f", at most {args.max_registers} registers" if args.max_registers else ""
  lines = [f"sm_{args.arch}, warp {wp.__version__}{cap}",
           f"{'kernel':24s} {'registers':>9s} {'stack B':>8s} {'build s':>8s}"]
  print("\n".join(lines), flush=True)
  with tempfile.TemporaryDirectory() as workdir:
    for label, kernel in kernels().items():
      if args.only and not any(word in label for word in args.only.split(",")):
        continue
      if args.max_registers:
        kernel = wp.kernel(kernel.func, module="unique", enable_backward=False, cuda_max_registers=args.max_registers)
      regs, stack, seconds = resources(kernel, args.arch, args.ptxas, workdir)
      built = "shared" if seconds is None else f"{seconds:.1f}"
      lines.append(f"{label:24s} {regs:9d} {stack:8d} {built:>8s}")
      print(lines[-1], flush=True)
  text = "\n".join(lines)
  if args.out:
    with open(args.out, "w") as f:
      f.write(text + "\n")


if __name__ == "__main__":
  main()
