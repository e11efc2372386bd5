"""How often a soak's ground check fires, in MuJoCo C and in MuJoCo Warp with and without the plugin.

  python benchmarks/soak_rate.py [--engine mujoco_c|plugin|stock] [--scene models/real/quadruped_rough.xml]
                                 [--nworld 64] [--steps 10000] [--check-every 50] [--device cpu] [--json OUT]

soak.py judges a terrain robot's run by soak.Ground: no moving collision geom's centre inside a
static box or under a heightfield's surface at the end of a chunk. Driven as soak.py drives it
(``--ctrl-noise 0.5 --reset-every 8``: random controls about the keyframe's, redrawn every 500
steps, staggered resets to shifted and lifted spawns, a robot that leaves the terrain reset), a
Go1 can jam a foot or a calf into a stair or a slope harder than its soft contacts push back.
This script runs the same driving on ``nworld`` worlds of one engine: MuJoCo C (one MjData a
world, on the CPU), or MuJoCo Warp on a Warp device with the plugin installed or stock, and
applies the same check every ``check_every`` steps, so that a soak's count has the engines'
rates beside it. A geom found at two checks in a row in one world is counted apart (``stuck``):
a transient jam comes out again, a geom through the ground does not.
"""

import argparse
import json
import os
import sys
import time
import types

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import soak  # noqa: E402

CHUNK = 500  # steps between new controls and between resets, as soak.py's default chunk
NOISE = 0.5  # soak.py's --ctrl-noise for the terrain robots
EVERY = 8  # soak.py's --reset-every for them


def _respawn(episodes, d, speed: bool):
  """MuJoCo C world ``d`` reset to one of the soak's spawns: the keyframe shifted and lifted clear
  of the ground."""
  mjm = episodes.mjm
  mujoco.mj_resetData(mjm, d)
  d.qpos[:] = episodes.lifted(episodes.shifted())
  d.ctrl[:] = episodes.ctrl0
  if speed:
    d.qvel[:] = soak.SPEED * episodes.rng.uniform(-1, 1, size=mjm.nv)
  mujoco.mj_forward(mjm, d)


def _batch(worlds, field: str):
  """A stand-in for a Data's array of ``field`` over the worlds (what soak.Ground reads)."""
  return types.SimpleNamespace(numpy=lambda: np.stack([getattr(d, field) for d in worlds]))


class MujocoC:
  """The worlds as MjData, stepped one after another on the CPU."""

  def __init__(self, mjm, nworld: int):
    self.episodes = soak.Episodes(mjm, None, nworld, NOISE, EVERY)
    self.worlds = [mujoco.MjData(mjm) for _ in range(nworld)]
    for d in self.worlds:
      _respawn(self.episodes, d, speed=True)
    self.view = types.SimpleNamespace(nworld=nworld, geom_xpos=_batch(self.worlds, "geom_xpos"),
                                      xpos=_batch(self.worlds, "xpos"))

  def drive(self):
    mjm, ep = self.episodes.mjm, self.episodes
    for d in self.worlds:
      d.ctrl[:] = ep.ctrl0 + NOISE * ep.rng.uniform(-1, 1, size=mjm.nu)

  def step(self):
    for d in self.worlds:
      mujoco.mj_step(self.episodes.mjm, d)

  def respawn(self, mask, speed: bool):
    for w in np.nonzero(mask)[0]:
      _respawn(self.episodes, self.worlds[w], speed)


class MujocoWarp:
  """The worlds as one MuJoCo Warp Data on a Warp device, with the plugin installed or stock."""

  def __init__(self, mjm, nworld: int, plugin: bool):
    import mujoco_warp as mjw

    from mjx_supportfield.driver import install

    self.mjw = mjw
    self.m = mjw.put_model(mjm)
    if plugin:
      install(mjm, self.m)
    start = soak.real_scenes.initial_data(mjm)
    self.view = mjw.put_data(mjm, start, nworld=nworld, nconmax=4 * mjm.ngeom, njmax=24 * mjm.ngeom)
    # resets only where asked (respawn): the staggering is run()'s, as for MuJoCo C
    self.episodes = soak.Episodes(mjm, self.m, nworld, NOISE, 0)
    self.episodes.reset(self.view, 0, np.ones(nworld, dtype=bool))

  def drive(self):
    self.episodes.drive(self.view)

  def step(self):
    self.mjw.step(self.m, self.view)

  def respawn(self, mask, speed: bool):  # Episodes.reset always gives the soak's small velocities
    self.episodes.reset(self.view, 0, mask)


def run(scene: str, nworld: int, steps: int, check_every: int, engine: str = "mujoco_c") -> dict:
  """The check's findings over the run: world-checks, each check that found geoms in the ground,
  and how many of those were in the ground at the check before too (``stuck``)."""
  mjm = mujoco.MjModel.from_xml_path(scene)
  worlds = MujocoC(mjm, nworld) if engine == "mujoco_c" else MujocoWarp(mjm, nworld, engine == "plugin")
  ground = soak.Ground(mjm)
  found, checks, stuck, before, start = [], 0, 0, set(), time.perf_counter()
  for step in range(1, steps + 1):
    if (step - 1) % CHUNK == 0:
      worlds.drive()
    worlds.step()
    if step % check_every == 0:
      off = ground.off_terrain(worlds.view)
      through = ground.geoms_through(worlds.view, skip=off)
      checks += nworld - int(off.sum())
      now = set(through)
      stuck += len(now & before)
      before = now
      if through:
        found.append({"step": step, "geoms": through})
      worlds.respawn(off, speed=False)
      before = {(w, g) for w, g in before if not off[w]}
    if step % CHUNK == 0:
      ends = (step // CHUNK - 1 + np.arange(nworld)) % EVERY == EVERY - 1
      worlds.respawn(ends, speed=True)
      before = {(w, g) for w, g in before if not ends[w]}
  ngeom = sum(len(f["geoms"]) for f in found)
  engines = {"mujoco_c": f"MuJoCo C {mujoco.__version__}", "plugin": "MuJoCo Warp with the plugin",
             "stock": "stock MuJoCo Warp"}
  return {"scene": os.path.basename(scene), "engine": engines[engine], "nworld": nworld,
          "steps": steps, "check_every": check_every, "ctrl_noise": NOISE, "reset_every_chunks": EVERY,
          "chunk": CHUNK, "world_checks": checks, "geoms_in_ground": ngeom,
          "geoms_in_ground_per_world_check": ngeom / max(checks, 1), "stuck": stuck, "found": found,
          "seconds": time.perf_counter() - start}


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=os.path.join(os.path.dirname(HERE), "models", "real", "quadruped_rough.xml"))
  p.add_argument("--nworld", type=int, default=64)
  p.add_argument("--steps", type=int, default=10_000)
  p.add_argument("--check-every", type=int, default=50)
  p.add_argument("--engine", choices=("mujoco_c", "plugin", "stock"), default="mujoco_c")
  p.add_argument("--device", default="cpu", help="Warp device of the plugin and stock engines")
  p.add_argument("--json", default=None)
  args = p.parse_args()
  if args.engine == "mujoco_c":
    report = run(args.scene, args.nworld, args.steps, args.check_every)
  else:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    with wp.ScopedDevice(args.device):
      report = run(args.scene, args.nworld, args.steps, args.check_every, args.engine)
    report["device"] = args.device
  print(f"{report['engine']}: {args.nworld} worlds x {args.steps} steps, {report['world_checks']} world-checks:"
        f" {report['geoms_in_ground']} geoms with their centre in the ground"
        f" ({report['geoms_in_ground_per_world_check']:.2e} a world-check; {report['stuck']} at the check before"
        f" too), {report['seconds']:.0f} s")
  for f in report["found"]:
    print(f"  step {f['step']}: {f['geoms']}")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)


if __name__ == "__main__":
  main()
