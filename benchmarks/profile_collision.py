"""Per-kernel GPU time of the collision stage, plugin and stock (Warp's CUDA activity timing).

  python benchmarks/profile_collision.py SCENE.xml|MODEL.mjb [--nworld 8192] [--settle 200] [--variants V,V,...]
                                        [--steps N]

Without ``--steps``: collision called ``--repeats`` times on one frozen state. That flatters the
plugin's warm start (from the second call on it holds the answer), so with ``--steps N`` the
profile covers N whole ``mjw.step`` calls instead, as ``bench`` times them: each kernel is
counted as collision when a collision call launches it, and the step's other kernels are
reported as the rest (solver, kinematics, ...), with the mean solver iterations.

A variant is ``default`` or Options fields as ``key=value;key=value`` (Python literals), e.g.
``multi_contact=False;mpr_refine=0``. One more key, ``max_registers=N``, rebuilds the MPR, GJK,
tilt, patch and heightfield MPR kernels with at most N registers a thread instead of
launch.grid.HEAVY_REGISTERS (Warp's ``cuda_max_registers``; 255 lifts the cap) for that variant;
``hfield_registers=N`` caps only the heightfield's contact and closed-form kernels; ``ccd_threads=N``
gives the heightfield's GJK/EPA prisms N threads (rows of EPA memory) instead of
hfield_window.CCD_THREADS.
"""

import argparse
import ast
import collections
import contextlib
import functools
from types import SimpleNamespace

import mujoco
import mujoco_warp as mjw
import warp as wp

from mjx_supportfield.driver import install
from mjx_supportfield.options import Options
from mjx_supportfield.stages import heightfield
from mjx_supportfield.stages import multicontact_pass
from mjx_supportfield.stages import narrowphase
from mjx_supportfield.tools.bench import settled_state
from mjx_supportfield.tools.model_file import load_model


def _value(text: str):
  """An Options value from the command line: a Python literal, else the text itself (broadphase=sap)."""
  try:
    return ast.literal_eval(text)
  except (ValueError, SyntaxError):
    return text


def _capped(kernel, cap: int):
  """``kernel`` rebuilt in a module of its own with at most ``cap`` registers a thread."""
  return wp.kernel(kernel.func, module="unique", enable_backward=False, cuda_max_registers=cap)


@contextlib.contextmanager
def _register_cap(cap):
  """Within the block, the narrow phase's heavy kernels are rebuilt with at most ``cap``
  registers a thread (None: unchanged)."""
  if cap is None:
    yield
    return
  saved_convex = narrowphase.convex_kernel
  saved_pass = multicontact_pass.pass_kernels
  saved_stage = heightfield.stage_kernels

  def capped(kernel):
    return _capped(kernel, cap)

  @functools.lru_cache(maxsize=None)
  def capped_pass(mode):
    k = saved_pass(mode)
    return SimpleNamespace(**{**vars(k), "tilt": capped(k.tilt), "tilt_mpr": capped(k.tilt_mpr), "patch": capped(k.patch)})

  @functools.lru_cache(maxsize=None)
  def capped_stage(mode):
    k = saved_stage(mode)
    return SimpleNamespace(**{**vars(k), "mpr": capped(k.mpr)})

  narrowphase.convex_kernel = functools.lru_cache(maxsize=None)(
    lambda use_gjk, mode: capped(saved_convex(use_gjk, mode)))
  multicontact_pass.pass_kernels = capped_pass
  heightfield.stage_kernels = capped_stage
  try:
    yield
  finally:
    narrowphase.convex_kernel = saved_convex
    multicontact_pass.pass_kernels = saved_pass
    heightfield.stage_kernels = saved_stage


@contextlib.contextmanager
def _hfield_register_cap(cap):
  """Within the block, the heightfield's contact and closed-form kernels are rebuilt with at most
  ``cap`` registers a thread (None: unchanged)."""
  if cap is None:
    yield
    return
  saved_contacts = heightfield.contacts_kernel
  saved_closed_form = heightfield.hfield_closed_form

  def capped(kernel):
    return _capped(kernel, cap)

  heightfield.contacts_kernel = functools.lru_cache(maxsize=None)(lambda mode: capped(saved_contacts(mode)))
  heightfield.hfield_closed_form = capped(saved_closed_form)
  try:
    yield
  finally:
    heightfield.contacts_kernel = saved_contacts
    heightfield.hfield_closed_form = saved_closed_form


@contextlib.contextmanager
def _ccd_threads(n):
  """Within the block, the heightfield's GJK/EPA prisms get ``n`` threads, each with a row of EPA
  memory (None: hfield_window.CCD_THREADS)."""
  saved = heightfield.CCD_THREADS
  heightfield.CCD_THREADS = saved if n is None else n
  try:
    yield
  finally:
    heightfield.CCD_THREADS = saved


def main():
  p = argparse.ArgumentParser()
  p.add_argument("model")
  p.add_argument("--nworld", type=int, default=8192)
  p.add_argument("--settle", type=int, default=200)
  p.add_argument("--keyframe", type=int, default=None, help="settle from this keyframe instead of qpos0")
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--variants", default="default", help="plugin variants (see above), comma-separated")
  p.add_argument("--steps", type=int, default=0, help="profile N evolving steps instead of one frozen state")
  p.add_argument("--top", type=int, default=12, help="kernels listed per table")
  p.add_argument("--no-stock", action="store_true", help="profile only the plugin variants")
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  mjm = load_model(args.model)  # MJCF, or a compiled model (.mjb) such as one saved from mjlab
  mjd = settled_state(mjm, args.settle, args.keyframe)
  ncon = int(1.5 * mjd.ncon) + 16
  for impl in ([] if args.no_stock else ["stock"]) + args.variants.split(","):
    fields = dict(kv.split("=", 1) for kv in impl.split(";") if kv not in ("default", "stock"))
    cap = fields.pop("max_registers", None)
    hfield_cap = fields.pop("hfield_registers", None)
    ccd_threads = fields.pop("ccd_threads", None)
    with (_register_cap(None if cap is None else int(cap)),
          _hfield_register_cap(None if hfield_cap is None else int(hfield_cap)),
          _ccd_threads(None if ccd_threads is None else int(ccd_threads))):
      _profile_variant(args, mjm, mjd, ncon, impl, fields)


def _profile_variant(args, mjm, mjd, ncon: int, impl: str, fields: dict):
  """Profiles one implementation: stock, or the plugin with the given Options fields."""
  m = mjw.put_model(mjm)
  if impl != "stock":
    install(mjm, m, Options(**{k: _value(v) for k, v in fields.items()}))
  d = mjw.put_data(mjm, mjd, nworld=args.nworld, nconmax=ncon, njmax=6 * ncon + mjd.nefc)
  if args.steps:
    mjw.forward(m, d)
  # (a frozen state keeps MuJoCo C's kinematics from put_data: only the collision kernels compile)
  mjw.collision(m, d)
  wp.synchronize()
  collision_ms = _profile(lambda: mjw.collision(m, d), args.repeats)
  if not args.steps:
    _report(f"{impl}: collision on one frozen state", collision_ms, args.nworld, args.top)
    return
  niter = []

  def step():
    mjw.step(m, d)
    niter.append(float(d.solver_niter.numpy().mean()))  # the sync costs no GPU time

  step_ms = _profile(step, args.steps)
  in_collision = {k: v for k, v in step_ms.items() if k in collision_ms}
  rest = {k: v for k, v in step_ms.items() if k not in collision_ms}
  iters = sum(niter) / len(niter)
  _report(f"{impl}: collision inside {args.steps} steps", in_collision, args.nworld, args.top)
  _report(f"{impl}: rest of the step (mean solver iterations {iters:.2f})", rest, args.nworld, args.top)


def _profile(fn, repeats: int) -> dict:
  """Mean GPU milliseconds per call of ``fn``, by kernel (or memset/memcpy) name."""
  wp.timing_begin(cuda_filter=wp.TIMING_ALL)
  for _ in range(repeats):
    fn()
  wp.synchronize()
  per = collections.defaultdict(float)
  for r in wp.timing_end():
    per[r.name] += r.elapsed / repeats
  return per


def _report(title: str, per: dict, nworld: int, top: int):
  print(f"== {title}: {sum(per.values()):.3f} ms of GPU activity per call, nworld {nworld}")
  for name, ms in sorted(per.items(), key=lambda x: -x[1])[:top]:
    print(f"  {ms:8.3f} ms  {name[:90]}")

if __name__ == "__main__":
  main()
