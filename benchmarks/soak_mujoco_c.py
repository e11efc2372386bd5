"""The soak's driving in MuJoCo C: how often MuJoCo itself puts a geom's centre in the ground.

  python benchmarks/soak_mujoco_c.py [--scene models/real/quadruped_rough.xml] [--nworld 64]
                                     [--steps 10000] [--check-every 50] [--json OUT]

soak.py judges a terrain robot's run by soak.Ground: no moving collision geom's centre inside a
static box or under a heightfield's surface at the end of a chunk. Driven as soak.py drives it
(``--ctrl-noise 0.5 --reset-every 8``: random controls about the keyframe's, redrawn every 500
steps, staggered resets to shifted and lifted spawns, a robot that leaves the terrain reset), a
Go1 can jam a foot or a calf into a stair or a slope harder than its soft contacts push back.
This script runs the same driving on ``nworld`` MuJoCo C worlds on the CPU and applies the same
check every ``check_every`` steps, so that the plugin's count has MuJoCo C's beside it.
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
  """World ``d`` reset to one of the soak's spawns: the keyframe shifted and lifted clear of the ground."""
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


def run(scene: str, nworld: int, steps: int, check_every: int) -> dict:
  """The check's findings over the run: world-checks, and each check that found geoms in the ground."""
  mjm = mujoco.MjModel.from_xml_path(scene)
  episodes = soak.Episodes(mjm, None, nworld, NOISE, EVERY)
  ground = soak.Ground(mjm)
  worlds = [mujoco.MjData(mjm) for _ in range(nworld)]
  for d in worlds:
    _respawn(episodes, d, speed=True)
  found, checks, start = [], 0, time.perf_counter()
  for step in range(1, steps + 1):
    if (step - 1) % CHUNK == 0:
      for d in worlds:
        d.ctrl[:] = episodes.ctrl0 + NOISE * episodes.rng.uniform(-1, 1, size=mjm.nu)
    for d in worlds:
      mujoco.mj_step(mjm, d)
    if step % check_every == 0:
      view = types.SimpleNamespace(nworld=nworld, geom_xpos=_batch(worlds, "geom_xpos"), xpos=_batch(worlds, "xpos"))
      off = ground.off_terrain(view)
      through = ground.geoms_through(view, skip=off)
      checks += nworld - int(off.sum())
      if through:
        found.append({"step": step, "geoms": through})
      for w in np.nonzero(off)[0]:
        _respawn(episodes, worlds[w], speed=False)
    if step % CHUNK == 0:
      for w in range(nworld):
        if (step // CHUNK - 1 + w) % EVERY == EVERY - 1:
          _respawn(episodes, worlds[w], speed=True)
  ngeom = sum(len(f["geoms"]) for f in found)
  return {"scene": os.path.basename(scene), "engine": f"MuJoCo C {mujoco.__version__}", "nworld": nworld,
          "steps": steps, "check_every": check_every, "ctrl_noise": NOISE, "reset_every_chunks": EVERY,
          "chunk": CHUNK, "world_checks": checks, "geoms_in_ground": ngeom,
          "geoms_in_ground_per_world_check": ngeom / max(checks, 1), "found": found,
          "seconds": time.perf_counter() - start}


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=os.path.join(os.path.dirname(HERE), "models", "real", "quadruped_rough.xml"))
  p.add_argument("--nworld", type=int, default=64)
  p.add_argument("--steps", type=int, default=10_000)
  p.add_argument("--check-every", type=int, default=50)
  p.add_argument("--json", default=None)
  args = p.parse_args()
  report = run(args.scene, args.nworld, args.steps, args.check_every)
  print(f"{report['engine']}: {args.nworld} worlds x {args.steps} steps, {report['world_checks']} world-checks:"
        f" {report['geoms_in_ground']} geoms with their centre in the ground"
        f" ({report['geoms_in_ground_per_world_check']:.2e} a world-check), {report['seconds']:.0f} s")
  for f in report["found"]:
    print(f"  step {f['step']}: {f['geoms']}")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)


if __name__ == "__main__":
  main()
