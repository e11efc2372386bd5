#!/usr/bin/env python3
"""Writes models/real/quadruped_rough.xml: four of mjlab's Unitree Go1 (go1.xml) on an mjlab-style
rough grid, one robot a tile (deterministic; numpy and MuJoCo only).

    python models/real/make_quadruped_rough.py

mjlab's rough-terrain tasks put the robots on a grid of tiles of several kinds, heightfields and
box stairs; this is a small grid of the same kinds: random rough ground, a pyramid slope, waves
(each a heightfield) and pyramid stairs (boxes on a flat heightfield), 2 m a tile. Each robot gets
mjlab's drives and initial pose as in make_quadruped_terrain.py, its lowest foot 0.5 mm into the
ground under it; the controls are scripted in benchmarks/scenelib/real_scenes.py.
"""

import os
import sys

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_quadruped_terrain as single  # noqa: E402

N = 40  # heightfield samples per side: 5 cm cells, as mjlab's 10 cm at half the tile
TILE = 2.0  # m, a tile's side
HEIGHT = 0.15  # m, elevation range of a heightfield tile
BASE = 0.05  # m, depth of a heightfield's base under its lowest point
STEPS = 3  # pyramid stairs: steps up from the tile's edge
STEP_RISE, STEP_RUN = 0.05, 0.25  # m
KINDS = ("rough", "slope", "waves", "stairs")
CENTRES = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))  # tile centres, in KINDS' order
# where each robot stands on its tile: the slope's side, the stairs' top platform
OFFSETS = ((0.2, 0.15), (0.5, 0.0), (0.2, 0.15), (0.0, 0.0))


def elevation(kind: str) -> np.ndarray:
  """A tile's samples in [0, 1] (times HEIGHT), row-major from -y to +y."""
  x = np.linspace(-1.0, 1.0, N)
  gx, gy = np.meshgrid(x, x)
  if kind == "rough":  # mjlab's random_rough: uniform noise, here smoothed over a cell's neighbours
    z = np.random.default_rng(36).uniform(0.0, 1.0, size=(N, N))
    z = (z + np.roll(z, 1, 0) + np.roll(z, 1, 1) + np.roll(np.roll(z, 1, 0), 1, 1)) / 4.0
    return 0.4 * (z - z.min()) / np.ptp(z)  # bumps up to 6 cm
  if kind == "slope":  # mjlab's pyramid_slope: rising to a flat top at the centre
    return np.clip(1.2 * (1.0 - np.maximum(np.abs(gx), np.abs(gy))), 0.0, 1.0)
  if kind == "waves":
    return 0.2 + 0.2 * np.sin(2.0 * np.pi * gx / 0.7) * np.cos(2.0 * np.pi * gy / 0.9)
  return np.zeros((N, N))  # stairs: flat ground, the steps are boxes


def _add_stairs(spec: mujoco.MjSpec, centre) -> None:
  """Pyramid stairs: square slabs stacked, each STEP_RUN smaller a side than the one under it."""
  for k in range(STEPS):
    half = TILE / 2.0 - STEP_RUN * (k + 1)
    spec.worldbody.add_geom(name=f"stairs_{k}", type=mujoco.mjtGeom.mjGEOM_BOX,
                            size=[half, half, STEP_RISE / 2.0],
                            pos=[centre[0], centre[1], STEP_RISE * (k + 0.5)])


def add_tiles(spec: mujoco.MjSpec) -> None:
  """The grid: a heightfield a tile (named terrain_<kind>) and the stairs' boxes, in group 0."""
  for kind, centre in zip(KINDS, CENTRES):
    hfield = spec.add_hfield(name=kind, nrow=N, ncol=N, size=[TILE / 2.0, TILE / 2.0, HEIGHT, BASE])
    hfield.userdata = elevation(kind).ravel().tolist()
    spec.worldbody.add_geom(name=f"terrain_{kind}", type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname=kind,
                            pos=[centre[0], centre[1], 0.0])
    if kind == "stairs":
      _add_stairs(spec, centre)
  spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])


def build() -> mujoco.MjSpec:
  """The scene as an MjSpec: the tiles and the four robots with their drives."""
  spec = mujoco.MjSpec()
  spec.modelname = "quadruped_rough"
  spec.option.timestep = 0.002
  spec.compiler.degree = False
  add_tiles(spec)
  for k, (centre, offset) in enumerate(zip(CENTRES, OFFSETS)):
    go1 = mujoco.MjSpec.from_file(os.path.join(HERE, "go1.xml"))  # attaching moves its bodies over
    frame = spec.worldbody.add_frame(pos=[centre[0] + offset[0], centre[1] + offset[1], 0.0])
    frame.attach_body(go1.body("trunk"), f"r{k}_", "")
  for k in range(len(CENTRES)):
    single.add_actuators(spec, f"r{k}_")
  return spec


def _foot_gap(mjm: mujoco.MjModel, qpos: np.ndarray, prefix: str) -> float:
  """Smallest distance from one robot's foot spheres to the ground under them (negative: sunk)."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  gaps = []
  for leg in single.LEGS:
    foot = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, f"{prefix}{leg}_foot_collision")
    height, hit = single.ground_under(mjm, mjd, mjd.geom_xpos[foot], 2.0)
    assert hit >= 0, f"the ray under {prefix}{leg} missed the ground"
    gaps.append(mjd.geom_xpos[foot][2] - mjm.geom_size[foot][0] - height)
  return min(gaps)


def main() -> None:
  spec = build()
  mjm = spec.compile()
  joints = single._init_joints()
  qpos = mjm.qpos0.copy()
  for k in range(len(CENTRES)):
    adr = mjm.jnt_qposadr[mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, f"r{k}_floating_base_joint")]
    qpos[adr + 2] = 0.6
    qpos[adr + 7:adr + 19] = joints
  for k in range(len(CENTRES)):
    adr = mjm.jnt_qposadr[mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, f"r{k}_floating_base_joint")]
    qpos[adr + 2] -= _foot_gap(mjm, qpos, f"r{k}_") + single.FOOT_OVERLAP
  spec.add_key(name="init", qpos=qpos.tolist(), ctrl=joints * len(CENTRES))
  header = (
    "<!-- Written by make_quadruped_rough.py (do not edit): four of mjlab 1.6.0's Unitree Go1 (go1.xml)\n"
    "     with mjlab's armature and position actuators on a 2 x 2 grid of 2 m tiles: rough, slope and\n"
    "     wave heightfields and pyramid stairs of boxes. The controls are scripted in real_scenes.py. -->\n"
  )
  with open(os.path.join(HERE, "quadruped_rough.xml"), "w") as f:
    f.write(header + spec.to_xml())


if __name__ == "__main__":
  main()
