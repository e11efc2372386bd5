"""mjlab's tasks stepped stock and with the plugin, through mjlab's own graph-captured step.

  python benchmarks/mjlab_tasks.py [--tasks Mjlab-Velocity-Rough-Unitree-Go1 ...] [--num-envs 1024 4096]
                                   [--steps 200] [--profile 10] [--device cuda:0] [--json OUT]

Needs mjlab 1.6.0 over our pins (docs/mjlab.md). For each task, env count and implementation
("stock", then "plugin": ``install(env.sim.mj_model, env.sim.wp_model)``, one collision
uncaptured, ``env.sim.create_graph()``), the environment steps ``--steps`` times with uniform
random actions in [-1, 1], terminated and timed-out worlds reset by mjlab itself (a masked
``reset_data`` in its reset graph). Reports env-steps per second (after ``--warmup`` steps),
contacts per world, worlds with NaN in qpos or qvel, worlds with a body below the ground
(``bodies_below_ground``: more than 0.2 m under the lowest point of any heightfield, box or plane
of the static world), MuJoCo Warp's overflow flags (``overflow_flags``; ``buffer_overflow``
names those of buffers that drop contacts or constraints), as JSON with the GPU's name.
With ``--profile N``, N more env steps are timed by Warp's CUDA activity timing: GPU milliseconds
per env step in all, the ``--top`` activities (a CUDA graph's launch is one, "graph": mjlab's
captured physics shows as its graphs), and the wall time of those steps, to tell GPU work from
host work.

mjlab imports wandb, torchrunx, onnxscript and imageio_ffmpeg at module level for what its tasks
never call; ``stub_optional_imports`` stands in for those that are not installed.
"""

import argparse
import importlib.abc
import importlib.machinery
import importlib.util
import json
import sys
import time
import types

import numpy as np

# packages mjlab imports at module level for what its tasks never call (its loggers, launcher,
# exporter and video writer); the viewer and rsl_rl's imports (viser, mjviser, tensorboard) must
# be installed
OPTIONAL = ("wandb", "torchrunx", "onnxscript", "imageio_ffmpeg")
TASKS = ("Mjlab-Velocity-Rough-Unitree-Go1", "Mjlab-Velocity-Rough-Unitree-G1", "Mjlab-Lift-Cube-Yam",
         "Mjlab-Multi-Cube-Seg-Yam")
BELOW = 0.2  # m under the lowest static surface: a body there went through the ground
# MuJoCo Warp's overflow flags of buffers that drop contacts or constraints (the others flag a
# solver's or CCD's iteration limit)
BUFFER_OVERFLOWS = ("NEFC", "NJMAX_NNZ", "BROADPHASE", "NARROWPHASE", "HFIELD", "NVMAX")


class _StubType(type):
  """A stand-in class: its attributes, and its instances' attributes, are stand-in classes."""

  def __getattr__(cls, name):
    if name.startswith("__"):
      raise AttributeError(name)
    return _stub_class(name)


def _stub_class(name: str) -> type:
  return _StubType(name, (), {"__init__": lambda self, *a, **k: None, "__call__": lambda self, *a, **k: None,
                              "__getattr__": lambda self, attr: _stub_class(attr)})


class _Anything(types.ModuleType):
  """A stand-in module: every attribute is a stand-in class."""

  def __getattr__(self, name):
    if name.startswith("__"):
      raise AttributeError(name)
    return _stub_class(name)


class _StubFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
  """Finds a stand-in for ``OPTIONAL`` packages (and their submodules) that are not installed."""

  def __init__(self, names):
    self.names = set(names)

  def find_spec(self, fullname, path, target=None):
    if fullname.split(".")[0] in self.names:
      return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
    return None

  def create_module(self, spec):
    module = _Anything(spec.name)
    module.__path__ = []
    return module

  def exec_module(self, module):
    pass


def stub_optional_imports() -> list[str]:
  """Stands in for the optional packages that are not installed; returns their names."""
  missing = [n for n in OPTIONAL if importlib.util.find_spec(n) is None]
  if missing:
    sys.meta_path.append(_StubFinder(missing))
  return missing


def make_env(task: str, num_envs: int, device: str, plugin: bool):
  """mjlab's environment of ``task``; with ``plugin``, the plugin installed under it and mjlab's
  graphs captured again (after one collision outside a graph, which builds the plugin's state
  and compiles its kernels)."""
  import mjlab.tasks  # noqa: F401  (registers the tasks)
  import mjx_supportfield as sf
  from mjlab.envs import ManagerBasedRlEnv
  from mjlab.tasks.registry import load_env_cfg

  cfg = load_env_cfg(task)
  cfg.scene.num_envs = num_envs
  env = ManagerBasedRlEnv(cfg, device=device)
  if plugin:
    sf.install(env.sim.mj_model, env.sim.wp_model)
    sf.collision(env.sim.wp_model, env.sim.wp_data)
    env.sim.create_graph()
  return env


def ground_level(mjm) -> float:
  """The lowest point of the static world's heightfields, boxes and planes."""
  import mujoco

  low = np.inf
  mjd = mujoco.MjData(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  for g in range(mjm.ngeom):
    if mjm.body_weldid[mjm.geom_bodyid[g]] != 0 or not (mjm.geom_contype[g] or mjm.geom_conaffinity[g]):
      continue
    z = mjd.geom_xpos[g][2]
    t = mjm.geom_type[g]
    if t == mujoco.mjtGeom.mjGEOM_HFIELD:
      low = min(low, z - mjm.hfield_size[mjm.geom_dataid[g]][3])
    elif t == mujoco.mjtGeom.mjGEOM_BOX:
      low = min(low, z - np.abs(mjd.geom_xmat[g].reshape(3, 3)[2]) @ mjm.geom_size[g])
    elif t == mujoco.mjtGeom.mjGEOM_PLANE:
      low = min(low, z)
  return float(low) if np.isfinite(low) else 0.0


def random_actions(env):
  """Uniform random actions in [-1, 1] for every env."""
  import torch

  return torch.rand(env.action_space.shape, device=env.device) * 2.0 - 1.0


def run(env, steps: int, warmup: int) -> dict:
  """Steps ``env`` with random actions; speed and the health of its worlds."""
  import warp as wp

  d = env.sim.wp_data
  floor = ground_level(env.sim.mj_model) - BELOW
  env.reset()
  ncon, below, nonfinite, overflow = [], np.zeros(env.num_envs, bool), np.zeros(env.num_envs, bool), 0
  t0 = None
  for i in range(warmup + steps):
    if i == warmup:
      wp.synchronize()
      t0 = time.perf_counter()
    env.step(random_actions(env))
    if i >= warmup and (i - warmup) % 20 == 19:  # a host read now and then, outside the timed ratio's bulk
      ncon.append(int(d.nacon.numpy()[0]) / env.num_envs)
      xpos = d.xpos.numpy()[:, 1:, 2]
      below |= (xpos < floor).any(axis=1)
      nonfinite |= ~(np.isfinite(d.qpos.numpy()).all(axis=1) & np.isfinite(d.qvel.numpy()).all(axis=1))
      overflow |= int(np.bitwise_or.reduce(d.overflow.numpy()))
  wp.synchronize()
  seconds = time.perf_counter() - t0
  from mujoco_warp._src.types import OverflowType

  buffers = sum(int(OverflowType[name]) for name in BUFFER_OVERFLOWS)
  return {"env_steps_per_s": env.num_envs * steps / seconds, "ms_per_step": 1e3 * seconds / steps,
          "contacts_per_world": float(np.mean(ncon)) if ncon else None, "nonfinite_worlds": int(nonfinite.sum()),
          "bodies_below_ground": int(below.sum()), "overflow_flags": overflow,
          "buffer_overflow": [e.name for e in OverflowType if overflow & buffers & int(e)], "steps": steps}


def profile(env, steps: int, top: int) -> dict:
  """GPU milliseconds per env step of ``steps`` more random-action steps, by kernel name."""
  import collections

  import warp as wp

  wp.timing_begin(cuda_filter=wp.TIMING_ALL)
  t0 = time.perf_counter()
  for _ in range(steps):
    env.step(random_actions(env))
  wp.synchronize()
  wall = time.perf_counter() - t0
  per = collections.defaultdict(float)
  for r in wp.timing_end():
    per[r.name] += r.elapsed / steps
  ranked = sorted(per.items(), key=lambda x: -x[1])
  return {"gpu_ms_per_step": sum(per.values()), "wall_ms_per_step": 1e3 * wall / steps,
          "top_kernels": [[name[:120], ms] for name, ms in ranked[:top]]}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--tasks", nargs="*", default=list(TASKS))
  parser.add_argument("--num-envs", type=int, nargs="*", default=[1024, 4096])
  parser.add_argument("--impl", nargs="*", default=["stock", "plugin"], choices=["stock", "plugin"])
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--warmup", type=int, default=20)
  parser.add_argument("--profile", type=int, default=0, help="env steps timed kernel by kernel (CUDA only)")
  parser.add_argument("--top", type=int, default=25, help="kernels listed by --profile")
  parser.add_argument("--device", default="cuda:0")
  parser.add_argument("--json", default=None)
  args = parser.parse_args(argv)
  stubbed = stub_optional_imports()
  import torch
  import warp as wp

  wp.config.log_level = wp.LOG_WARNING
  gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "cpu"
  report = {"device": gpu, "stubbed_imports": stubbed, "rows": []}
  for task in args.tasks:
    for num_envs in args.num_envs:
      for impl in args.impl:
        env = make_env(task, num_envs, args.device, impl == "plugin")
        row = {"task": task, "num_envs": num_envs, "impl": impl, **run(env, args.steps, args.warmup)}
        if args.profile and args.device.startswith("cuda"):
          row["profile"] = profile(env, args.profile, args.top)
        report["rows"].append(row)
        print(json.dumps(row), flush=True)
        env.close()
        del env
        if args.json:
          with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
