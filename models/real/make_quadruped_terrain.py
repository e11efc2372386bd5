#!/usr/bin/env python3
"""Writes models/real/quadruped_terrain.xml: mjlab's Unitree Go1 (go1.xml) standing on a bumpy
heightfield (deterministic; numpy and MuJoCo only).

    python models/real/make_quadruped_terrain.py

The robot gets mjlab's joint armature and position actuators (gains, damping and effort limits from
mjlab 1.6.0's go1_constants.py), the heightfield's elevation is written into the MJCF, and a keyframe
puts the robot in mjlab's initial pose (thighs 0.9, calves -1.8, hips +-0.1 rad) with its lowest foot
0.5 mm into the terrain. The scene is composed with MuJoCo's MjSpec and saved with MjSpec.to_xml.
"""

import os

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
N = 48  # heightfield samples per side
SIZE = (0.6, 0.6, 0.06, 0.05)  # x, y radii, elevation range, base (MuJoCo's hfield size)
LEGS = ("FR", "FL", "RR", "RL")
FOOT_OVERLAP = 5e-4

# mjlab 1.6.0, asset_zoo/robots/unitree_go1/go1_constants.py: reflected rotor inertia (armature),
# stiffness and damping of a 10 Hz critically damped (ratio 2) drive, effort limits.
ROTOR_INERTIA = 0.000111842
HIP_GEAR, KNEE_GEAR = 6, 9
NATURAL_FREQ = 10 * 2.0 * 3.1415926535
DAMPING_RATIO = 2.0
HIP_EFFORT, KNEE_EFFORT = 23.7, 35.55
INIT_JOINTS = {"hip": 0.1, "thigh": 0.9, "calf": -1.8}  # hip sign: + for right legs, - for left


def elevation() -> np.ndarray:
  """Samples in [0, 1], row-major from -y to +y: smooth bumps, a shallow ridge and a little noise."""
  rng = np.random.default_rng(20)
  x = np.linspace(-1.0, 1.0, N)
  gx, gy = np.meshgrid(x, x)
  z = 0.5 + 0.2 * np.sin(5.0 * gx + 1.0) * np.cos(4.0 * gy) + 0.15 * np.exp(-((gx - 0.3 * gy) ** 2) / 0.05)
  z += 0.05 * rng.uniform(-1, 1, size=(N, N))
  return np.clip(z, 0.0, 1.0)


def _drive(gear: float) -> tuple[float, float, float]:
  """Armature, stiffness and damping of one of mjlab's Go1 drives."""
  armature = ROTOR_INERTIA * gear**2
  return armature, armature * NATURAL_FREQ**2, 2 * DAMPING_RATIO * armature * NATURAL_FREQ


def add_actuators(spec: mujoco.MjSpec, prefix: str = "") -> None:
  """mjlab's drives on the joints of the Go1 whose names start with ``prefix``."""
  for leg in LEGS:
    for part, gear, effort in (("hip", HIP_GEAR, HIP_EFFORT), ("thigh", HIP_GEAR, HIP_EFFORT),
                               ("calf", KNEE_GEAR, KNEE_EFFORT)):
      joint = spec.joint(f"{prefix}{leg}_{part}_joint")
      armature, kp, kv = _drive(gear)
      joint.armature = armature
      act = spec.add_actuator(name=f"{prefix}{leg}_{part}", target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
      act.set_to_position(kp=kp, kv=kv)
      act.forcerange = [-effort, effort]
      act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def _init_joints() -> list[float]:
  q = []
  for leg in LEGS:
    q += [INIT_JOINTS["hip"] if leg[1] == "R" else -INIT_JOINTS["hip"], INIT_JOINTS["thigh"], INIT_JOINTS["calf"]]
  return q


def ground_under(mjm: mujoco.MjModel, mjd: mujoco.MjData, point: np.ndarray, top: float) -> tuple[float, int]:
  """The height of the ground (geom group 0: the terrain; the robots' geoms are group 3) straight
  under ``point``, cast down from height ``top``, and the geom it hit (-1: none)."""
  geomid = np.array([-1], dtype=np.int32)
  start = np.array([point[0], point[1], top])
  ground = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)
  height = top - mujoco.mj_ray(mjm, mjd, start, np.array([0.0, 0.0, -1.0]), ground, 1, -1, geomid)
  return height, int(geomid[0])


def _foot_gap(mjm: mujoco.MjModel, qpos: np.ndarray) -> float:
  """Smallest distance from a foot sphere to the terrain, straight down (negative: sunk)."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  terrain = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, "terrain")
  gaps = []
  for leg in LEGS:
    foot = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_foot_collision")
    height, hit = ground_under(mjm, mjd, mjd.geom_xpos[foot], 1.0)
    assert hit == terrain, f"the ray under {leg} missed the terrain"
    gaps.append(mjd.geom_xpos[foot][2] - mjm.geom_size[foot][0] - height)
  return min(gaps)


def build() -> mujoco.MjSpec:
  """The scene as an MjSpec, with the keyframe's trunk height still to set."""
  spec = mujoco.MjSpec.from_file(os.path.join(HERE, "go1.xml"))
  spec.modelname = "quadruped_terrain"
  spec.option.timestep = 0.002
  hfield = spec.add_hfield(name="bumps", nrow=N, ncol=N, size=list(SIZE))
  hfield.userdata = elevation().ravel().tolist()
  spec.worldbody.add_geom(name="terrain", type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname="bumps")
  spec.worldbody.add_light(pos=[0, 0, 2], dir=[0, 0, -1])
  add_actuators(spec)
  return spec


def main() -> None:
  spec = build()
  q = _init_joints()
  mjm = spec.compile()
  qpos = np.concatenate([[0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], q])
  qpos[2] -= _foot_gap(mjm, qpos) + FOOT_OVERLAP
  spec.add_key(name="init", qpos=qpos.tolist(), ctrl=q)
  text = spec.to_xml()
  header = (
    "<!-- Written by make_quadruped_terrain.py (do not edit): mjlab 1.6.0's Unitree Go1 (go1.xml) with mjlab's\n"
    "     armature and position actuators, standing on a 48 x 48 heightfield over 1.2 m x 1.2 m (bumps\n"
    "     up to 6 cm). The controls are scripted in benchmarks/fidelity.py. -->\n"
  )
  with open(os.path.join(HERE, "quadruped_terrain.xml"), "w") as f:
    f.write(header + text)


if __name__ == "__main__":
  main()
