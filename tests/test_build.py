"""The heavy kernel modules stay quick to build for CUDA.

Warp unrolls fixed loops of up to 16 iterations, and CUDA inlines every call: a costly routine
called inside such a loop is copied into the module once per iteration. The heightfield
module once held 29 inlined MPRs and never finished building for CUDA (over 20 minutes); the
non-convex one took over 45. Checked on the CUDA source Warp generates (no GPU needed): each
costly routine has one call site in its module.
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
  return len(re.findall(rf"= {func}_\d+\(", source))


@pytest.mark.parametrize(
  "kernel, func",
  [
    (heightfield.hfield_narrowphase, "mpr_refined"),
    (nonconvex.nonconvex_narrowphase, "_point"),
    (nonconvex.nonconvex_narrowphase, "_segment_min"),
  ],
)
def test_one_call_site(kernel, func):
  wp.init()
  assert _call_sites(kernel, func) == 1
