"""Worlds are independent: a world's trajectory through ``mjw.step`` with the plugin installed
depends on its own state and history alone, not on the other worlds of the batch nor on its place
in it.

  python benchmarks/independence.py [--scenes NAME ...] [--presets NAME ...] [--steps 500]
                                    [--nworld 4] [--device cpu] [--json OUT]

Each scene and preset of options is stepped twice from the same world X:
  - a batch of ``nworld`` worlds that holds X in worlds 0 and ``nworld`` - 1 and other worlds
    (X's free bodies set moving at seeded, different velocities) between them, and
  - a batch of ``nworld`` copies of X.
X's qpos must stay bitwise equal in both places of the first batch and in the second batch at
every step (the first batch's last world against the second's first: among others or among
copies of itself, and elsewhere in the batch). The batches
have the same size because MuJoCo Warp's own step is not bitwise invariant to the batch size on
the CPU (stock: a world stepped alone and among others parts ways within a few dozen steps).

With ``--reset K`` the first batch also resets its worlds 1 .. nworld - 2 with a mask at step K
(``mjw.reset_data(m, d, reset=mask)``): X must not notice, and each reset world must repeat,
bit for bit, the run of a fresh Data reset at step 0.

On the CPU everything is bitwise. On a GPU the contact order depends on atomics, so the script
sets MuJoCo Warp's determinism bits (``m.opt.deterministic``), under which the plugin sorts its
contacts; prints the first step where a property fails and exits 1, or says it held.
"""

import argparse
import dataclasses
import json
import os
import sys
from typing import Callable, Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src.types import DeterminismType

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from scenelib import real_scenes  # noqa: E402
from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools.bench import settled_state  # noqa: E402

PRESETS = {  # as benchmarks/equivalence.py's
  "default": {},
  "gjk": {"narrowphase": "gjk"},
  "single_contact": {"multi_contact": False},
  "cold": {"warm_start": False, "broadphase": "nxn"},
  "field": {"support_mode": "field", "mpr_refine": 0},
}
SPEED = 0.3  # m/s (rad/s) of the other worlds' seeded velocities: enough to put them elsewhere


@dataclasses.dataclass(frozen=True)
class Scene:
  """A scene of the check: its MJCF and, for robots, the scripted ctrl at a step."""

  path: str
  control: Optional[Callable[[mujoco.MjModel, int], np.ndarray]] = None


def _real(name: str) -> Scene:
  scene = real_scenes.SCENES[name]
  ctrl = None if scene.control is None else (lambda mjm, step, s=scene: real_scenes.control(s, mjm, step))
  return Scene(os.path.join(real_scenes.MODELS, scene.xml), ctrl)


SCENES = {
  "convex_pile": Scene(os.path.join(ROOT, "models", "convex_pile.xml")),
  "terrain": Scene(os.path.join(ROOT, "models", "terrain.xml")),
  **{name: _real(name) for name in real_scenes.SCENES},
}


def initial_state(mjm: mujoco.MjModel) -> mujoco.MjData:
  """X: the scene's keyframe (qpos0 without one), forward-computed."""
  return real_scenes.initial_data(mjm)


def other_velocities(mjm: mujoco.MjModel, nworld: int, seed: int = 0) -> np.ndarray:
  """qvel of the batch: 0 (X) in worlds 0 and nworld - 1, seeded random elsewhere, on the free
  joints' dofs (or on every dof of a model without free joints)."""
  free = [j for j in range(mjm.njnt) if mjm.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
  dofs = [mjm.jnt_dofadr[j] + k for j in free for k in range(6)] if free else list(range(mjm.nv))
  qvel = np.zeros((nworld, mjm.nv))
  rng = np.random.default_rng(seed)
  for w in range(1, nworld - 1):
    qvel[w, dofs] = SPEED * rng.uniform(-1.0, 1.0, len(dofs))
  return qvel


class Batch:
  """A Data of ``nworld`` worlds of one model with the plugin installed, stepped by ``mjw.step``."""

  def __init__(self, mjm: mujoco.MjModel, mjd: mujoco.MjData, nworld: int, options: dict, control=None):
    self.mjm, self.control, self.step_count = mjm, control, 0
    self.m = mjw.put_model(mjm)
    install(mjm, self.m, Options(**options))
    # room for every world's contacts and rows: an overflow would couple the worlds through MuJoCo
    # Warp's shared contact buffer, which is not what is checked here
    nconmax = 4 * max(mjd.ncon, settled_state(mjm, 300).ncon) + 64
    self.d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
    if wp.get_device().is_cuda:
      self.m.opt.deterministic = DeterminismType.ALL

  def set_qvel(self, qvel: np.ndarray) -> None:
    self.d.qvel.assign(qvel.astype(np.float32))

  def step(self) -> np.ndarray:
    """One step of every world; qpos after it."""
    if self.control is not None:
      ctrl = self.control(self.mjm, self.step_count)
      self.d.ctrl.assign(np.tile(ctrl, (self.d.nworld, 1)).astype(np.float32))
    mjw.step(self.m, self.d)
    self.step_count += 1
    if self.d.overflow.numpy().any():
      raise RuntimeError("a buffer overflowed (d.overflow): dropped contacts would couple the worlds")
    return self.d.qpos.numpy()

  def reset(self, mask: np.ndarray) -> None:
    """MuJoCo Warp's masked reset (the plugin's history of the masked worlds goes with it)."""
    mjw.reset_data(self.m, self.d, reset=wp.array(mask.astype(bool), dtype=bool))


def check(scene: Scene, options: dict, steps: int, nworld: int, reset_at: Optional[int] = None) -> dict:
  """Steps the batches of the module docstring; the first step where each property fails (None:
  it held) and how far X's copies ended apart."""
  if nworld < 3:
    raise ValueError("--nworld: at least 3 (X twice and another world between)")
  mjm = mujoco.MjModel.from_xml_path(scene.path)
  mjd = initial_state(mjm)
  mixed = Batch(mjm, mjd, nworld, options, scene.control)
  mixed.set_qvel(other_velocities(mjm, nworld))
  copies = Batch(mjm, mjd, nworld, options, scene.control)
  fresh = None
  masked = np.zeros(nworld, bool)
  if reset_at is not None:
    masked[1:nworld - 1] = True
    fresh = Batch(mjm, mjd, nworld, options, scene.control)
    fresh.reset(np.ones(nworld, bool))  # reset at step 0: what a masked world must repeat
  out = {"steps": steps, "nworld": nworld, "identical_worlds": None, "among_copies": None, "reset_worlds": None}
  fresh_traj = []
  for step in range(steps):
    if reset_at is not None and step == reset_at:
      mixed.reset(masked)
      mixed.step_count = 0  # the scripted controls start again with the reset worlds
      copies.step_count = 0
    q, qc = mixed.step(), copies.step()
    if out["identical_worlds"] is None and not np.array_equal(q[0], q[nworld - 1]):
      out["identical_worlds"] = step
    if out["among_copies"] is None and not np.array_equal(q[nworld - 1], qc[0]):
      out["among_copies"] = step
    if fresh is not None:
      fresh_traj.append(fresh.step()[masked] if step < steps - reset_at else None)
      if step >= reset_at and out["reset_worlds"] is None and not np.array_equal(q[masked],
                                                                                  fresh_traj[step - reset_at]):
        out["reset_worlds"] = step
  out["apart_m"] = float(np.abs(q[0] - q[nworld - 1]).max())
  return out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--scenes", nargs="*", default=sorted(SCENES), choices=sorted(SCENES))
  parser.add_argument("--presets", nargs="*", default=list(PRESETS), choices=list(PRESETS))
  parser.add_argument("--steps", type=int, default=500)
  parser.add_argument("--nworld", type=int, default=4)
  parser.add_argument("--reset", type=int, default=None, help="masked reset of the other worlds at this step")
  parser.add_argument("--device", default="cpu")
  parser.add_argument("--json", default=None)
  args = parser.parse_args(argv)
  wp.config.log_level = wp.LOG_WARNING
  wp.set_device(args.device)
  report = {"device": wp.get_device().name if wp.get_device().is_cuda else "cpu", "runs": {}}
  failed = 0
  for name in args.scenes:
    for preset in args.presets:
      r = check(SCENES[name], PRESETS[preset], args.steps, args.nworld, args.reset)
      report["runs"][f"{name} {preset}"] = r
      bad = {k: r[k] for k in ("identical_worlds", "among_copies", "reset_worlds") if r[k] is not None}
      failed += bool(bad)
      print(f"{name} {preset}: " + (f"parted at steps {bad}, X's copies {r['apart_m']:.3g} m apart" if bad else
                                     f"independent for {args.steps} steps"), flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)
  print(f"{failed} of {len(report['runs'])} runs coupled worlds" if failed else
        f"all {len(report['runs'])} runs kept their worlds independent")
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
