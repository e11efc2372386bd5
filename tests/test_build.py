"""The heavy kernel modules stay quick to build for CUDA.

Warp unrolls fixed loops of up to 16 iterations, and CUDA inlines every call: a costly routine
called inside such a loop is copied into the module once per iteration. The heightfield
module once held 29 inlined MPRs and never finished building for CUDA (over 20 minutes); the
non-convex one took over 45. Checked on the CUDA source Warp generates (no GPU needed): each
costly routine has one call site in its module, or one in each kernel that needs it (the
heightfield's MPR job and cell tests: in the queue's kernels and in the contact kernel, which
runs the jobs the queue had no room for).
"""

import re

import pytest
import warp as wp
from warp._src.context import ModuleBuilder

from mjx_supportfield import heightfield
from mjx_supportfield import nonconvex


def _call_sites(kernel, func: str) -> int:
  module = kernel.module
  source = ModuleBuilder(module, module.options, target="cuda").codegen("cuda")
  # a call is the name at the start of a statement or after "= " (a tuple result comes back
  # through output arguments); definitions start with "static"
  return len(re.findall(rf"(?:^|= )\s*{func}_\d+\(", source, flags=re.MULTILINE))


@pytest.mark.parametrize(
  "kernel, func, sites",
  [
    (heightfield.hfield_mpr, "mpr_refined", 1),
    (heightfield.hfield_mpr, "_job_mpr", 2),
    (heightfield.hfield_jobs, "_cell_jobs", 2),
    (nonconvex.nonconvex_narrowphase, "_point", 1),
    (nonconvex.nonconvex_narrowphase, "_segment_min", 1),
  ],
)
def test_call_sites(kernel, func, sites):
  wp.init()
  assert _call_sites(kernel, func) == sites
