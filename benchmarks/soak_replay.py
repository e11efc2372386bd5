"""Replays one world of a soak's failing chunk on the CPU and reports when its geoms go into the ground.

  python benchmarks/soak_replay.py FAILING.npz [--world W] [--steps 1000] [--check-every 10]
                                   [--engine plugin|stock|mujoco_c] [--scene SCENE.xml] [--json OUT]

``soak.py --save-failing FAILING.npz`` keeps the state and the controls at the start of the chunk
before the first failing one. This script puts world ``W`` of it (default: the first world the
failure names) into one world of the engine asked for: MuJoCo Warp with the plugin, stock MuJoCo
Warp, or MuJoCo C, with the same controls, steps it, and applies soak.Ground's check every
``--check-every`` steps. A GPU and the CPU round differently, so the replay leaves the soak's
trajectory after a while; what it shows is whether the engine, from that state and under those
controls, lets the robot into the ground, and the same start in MuJoCo C says whether C does too.
"""

import argparse
import json
import os
import re
import sys

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import soak  # noqa: E402
from scenelib.checkpoint import WARMSTART  # noqa: E402
from scenelib.checkpoint import load_checkpoint  # noqa: E402
from soak_rate import _batch  # noqa: E402

ENGINES = ("plugin", "stock", "mujoco_c")


def failing_world(meta: dict) -> int:
  """The first world a failing chunk's message names ("... first (world, geom) [(1039, ..."), or 0."""
  for what in meta.get("what", []):
    found = re.search(r"\[\((\d+), '", what)
    if found:
      return int(found.group(1))
  return 0


def scene_of(meta: dict, scene=None) -> str:
  """The scene: ``scene``, else the checkpoint's path, else its file name among ours."""
  root = os.path.dirname(HERE)
  for path in (scene, meta["scene_path"], os.path.join(HERE, "scenes", meta["scene"]),
               os.path.join(root, "models", "real", meta["scene"]), os.path.join(root, "models", meta["scene"])):
    if path and os.path.exists(path):
      return path
  raise FileNotFoundError(f"the checkpoint's scene {meta['scene']} is not here: give --scene")


def world_data(mjm, state: dict, world: int) -> mujoco.MjData:
  """MuJoCo C's data holding world ``world`` of the checkpoint's state and controls."""
  d = mujoco.MjData(mjm)
  d.time = float(state["time"][world])
  for field in ("qpos", "qvel", "act", "ctrl"):
    if field in state and state[field].shape[1]:
      getattr(d, field)[:] = state[field][world]
  mujoco.mj_forward(mjm, d)
  return d


def replay(path: str, world=None, steps: int = 1000, check_every: int = 10, engine: str = "plugin",
           scene=None) -> dict:
  """The replay's findings: each check that found geoms of the world in the ground."""
  meta, state = load_checkpoint(path)
  if "ctrl" not in state:
    raise ValueError(f"{path} holds no controls: write it with soak.py --save-failing")
  world = failing_world(meta) if world is None else world
  if not 0 <= world < meta["nworld"]:
    raise ValueError(f"--world {world}: the checkpoint has {meta['nworld']} worlds")
  scene = scene_of(meta, scene)
  mjm = mujoco.MjModel.from_xml_path(scene)
  mjd = world_data(mjm, state, world)
  ground = soak.Ground(mjm)
  if engine == "mujoco_c":
    step = lambda: mujoco.mj_step(mjm, mjd)  # noqa: E731
    view = type("View", (), {"nworld": 1, "geom_xpos": _batch([mjd], "geom_xpos"), "xpos": _batch([mjd], "xpos")})
  else:
    import mujoco_warp as mjw

    from mjx_supportfield.driver import install

    m = mjw.put_model(mjm)
    if engine == "plugin":
      install(mjm, m)
    nconmax = meta["ref"]["nconmax"]
    view = mjw.put_data(mjm, mjd, nworld=1, nconmax=nconmax, njmax=6 * nconmax)
    if WARMSTART in state:
      view.qacc_warmstart.assign(state[WARMSTART][world:world + 1])
    step = lambda: mjw.step(m, view)  # noqa: E731
  found = []
  for k in range(1, steps + 1):
    step()
    if k % check_every == 0:
      through = [name for _, name in ground.geoms_through(view)]
      if through:
        found.append({"step": meta["start_step"] + k, "geoms": through})
  return {"checkpoint": path, "scene": os.path.basename(scene), "world": world, "engine": engine,
          "start_step": meta["start_step"], "failed_at": meta.get("failed_at"), "soak_said": meta.get("what"),
          "steps": steps, "check_every": check_every, "found": found,
          "first_in_ground": found[0]["step"] if found else None,
          "most_in_ground": max((len(f["geoms"]) for f in found), default=0)}


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("checkpoint")
  p.add_argument("--world", type=int, default=None, help="default: the first world the failure names")
  p.add_argument("--steps", type=int, default=1000, help="two chunks of 500: the chunk before and the failing one")
  p.add_argument("--check-every", type=int, default=10)
  p.add_argument("--engine", choices=ENGINES, default="plugin")
  p.add_argument("--scene", default=None, help="default: the checkpoint's")
  p.add_argument("--json", default=None)
  args = p.parse_args()
  try:
    result = replay(args.checkpoint, args.world, args.steps, args.check_every, args.engine, args.scene)
  except (ValueError, FileNotFoundError) as e:
    print(f"soak_replay: {e}", file=sys.stderr)
    return 2
  print(f"world {result['world']} from step {result['start_step']} ({result['engine']}, {args.steps} steps): "
        + (f"first in the ground at step {result['first_in_ground']}, at most {result['most_in_ground']} geoms"
           if result["found"] else "no geom in the ground"))
  for f in result["found"][:20]:
    print(f"  step {f['step']}: {', '.join(f['geoms'])}")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(result, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
