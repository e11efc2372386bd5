"""The heavy kernel modules stay quick to build for CUDA.

Warp unrolls fixed loops of up to 16 iterations, and CUDA inlines every call: a costly routine
called inside such a loop is copied into the module once per iteration. The heightfield
module once held 29 inlined MPRs and never finished building for CUDA (over 20 minutes); the
non-convex one took over 45. Checked on the CUDA source Warp generates (no GPU needed): each
costly routine has one call site in its module (the heightfield's MPR job and cell tests: one in
the queue's modules and one in the contact kernel's, which runs the jobs the queue had no room
for).
"""

import importlib
import pkgutil
import re

import pytest
import warp as wp
from warp._src.context import ModuleBuilder

import mjx_supportfield
from mjx_supportfield.stages import broadphase
from mjx_supportfield.stages import deep_pairs
from mjx_supportfield.stages import heightfield
from mjx_supportfield.stages import multicontact_pass
from mjx_supportfield.stages import narrowphase
from mjx_supportfield.stages import nonconvex
from mjx_supportfield.stages import routing
from mjx_supportfield.types import SUPPORT_EXACT
from mjx_supportfield.types import SUPPORT_FIELD
from mjx_supportfield.types import SUPPORT_REFINED


def _call_sites(kernel, func: str) -> int:
  module = kernel.module
  source = ModuleBuilder(module, module.options, target="cuda").codegen("cuda")
  # a call is the name at the start of a statement or after "= " (a tuple result comes back
  # through output arguments); definitions start with "static". A function a mode factory built
  # is named after the factory too (<factory>__locals__<func>_<n>)
  return len(re.findall(rf"(?:^|= )\s*(?:\w+__locals__)?{func}_\d+\(", source, flags=re.MULTILINE))


@pytest.mark.parametrize(
  "kernel, func, sites",
  [
    (heightfield.stage_kernels(SUPPORT_REFINED).mpr, "mpr_refined", 1),
    (heightfield.stage_kernels(SUPPORT_REFINED).mpr, "_job_mpr", 1),
    (heightfield.stage_kernels(SUPPORT_REFINED).jobs, "_cell_jobs", 2),  # and _queue_beyond's
    (heightfield.stage_kernels(SUPPORT_REFINED).ccd, "job_ccd", 1),
    (heightfield.contacts_kernel(SUPPORT_REFINED), "_job_mpr", 1),
    (heightfield.contacts_kernel(SUPPORT_REFINED), "_cell_jobs", 1),
    (heightfield.contacts_kernel(SUPPORT_REFINED), "job_ccd", 0),
    (nonconvex.nonconvex_narrowphase(SUPPORT_REFINED), "_point", 1),
    (nonconvex.nonconvex_narrowphase(SUPPORT_REFINED), "_segment_min", 1),
  ],
)
def test_call_sites(kernel, func, sites):
  wp.init()
  assert _call_sites(kernel, func) == sites


def _package_kernels() -> list:
  """Every kernel of the package: the module-level ones, and each factory's for one key (the
  support-mode factories' for the default mode)."""
  kernels = []
  for info in pkgutil.walk_packages(mjx_supportfield.__path__, "mjx_supportfield."):
    if not info.name.endswith("__main__"):
      module = importlib.import_module(info.name)
      kernels += [k for k in vars(module).values() if isinstance(k, wp.Kernel)]
  pair_test_key = (0, 1, 1, 1, 1, 0, 0, False, False)
  kernels += [
    broadphase.sweep_kernel(pair_test_key, 0),
    broadphase.listed_pairs_kernel(pair_test_key, True),
    narrowphase.analytic_kernel(routing.ANALYTIC_PAIRS[:1]),
    narrowphase.convex_kernel(False, SUPPORT_REFINED),
    narrowphase.convex_kernel(True, SUPPORT_REFINED),
    narrowphase.sift_mpr_pairs(SUPPORT_REFINED),
    nonconvex.nonconvex_narrowphase(SUPPORT_REFINED),
  ]
  kernels += list(vars(deep_pairs.deep_kernels(SUPPORT_REFINED)).values())
  kernels += list(vars(multicontact_pass.pass_kernels(SUPPORT_REFINED)).values())
  kernels += list(vars(heightfield.stage_kernels(SUPPORT_REFINED)).values())
  kernels.append(heightfield.contacts_kernel(SUPPORT_REFINED))
  return kernels


def test_no_kernel_builds_an_adjoint():
  """The kernels only run forward, and an adjoint would cost build time for nothing (the GJK
  kernel's took NVRTC over 10 minutes). Modules turn it off once with set_module_options; a
  factory's module="unique" kernel takes Warp's global options instead, so it must turn it off
  itself."""
  kernels = _package_kernels()
  assert len(kernels) > 30
  with_adjoint = [k.key for k in kernels if (k.module.options | k.options)["enable_backward"]]
  assert not with_adjoint


def test_support_mode_is_fixed_at_code_generation():
  """Options.support_mode picks the kernels (factories keyed on it), not a kernel input: no kernel
  takes it, each mode's kernels sit in their own modules with their stage's options, and a
  mode's code holds only its own support query (field mode never climbs the hull graph, exact
  mode never reads the field)."""
  kernels = _package_kernels()
  assert not [k.key for k in kernels if "support_mode" in k.adj.arg_types]
  field = heightfield.stage_kernels(SUPPORT_FIELD).mpr
  refined = heightfield.stage_kernels(SUPPORT_REFINED).mpr
  assert field.module is not refined.module
  assert not field.module.options["fuse_fp"] and not field.module.options["enable_backward"]
  wp.init()
  for mode, present, absent in ((SUPPORT_FIELD, "field_lookup", "hill_climb"), (SUPPORT_EXACT, "hull_scan", "field_lookup")):
    assert _call_sites(narrowphase.sift_mpr_pairs(mode), present) > 0
    assert _call_sites(narrowphase.sift_mpr_pairs(mode), absent) == 0
