#!/usr/bin/env python3
"""Writes models/real/humanoid_rough.xml: two of mjlab's Unitree G1 (g1.xml) on the rough grid of
make_quadruped_rough.py (deterministic; numpy and MuJoCo only).

    python models/real/make_humanoid_rough.py

Each robot gets mjlab's drives (armature, stiffness and damping of a 10 Hz, damping-ratio-2
position drive and effort limits, from mjlab 1.6.0's g1_constants.py) and mjlab's home pose, on
the rough and the wave tiles, its lowest foot capsule 0.5 mm into the ground under it; the
controls are scripted in benchmarks/scenelib/real_scenes.py.
"""

import math
import os
import re
import sys

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_quadruped_rough as grid  # noqa: E402
import make_quadruped_terrain as single  # noqa: E402

NATURAL_FREQ = 10 * 2.0 * math.pi
DAMPING_RATIO = 2.0
FOOT_OVERLAP = 5e-4


def _armature(rotor_inertia, gears) -> float:
  """mjlab's reflected_inertia_from_two_stage_planetary."""
  return rotor_inertia[0] * (gears[1] * gears[2]) ** 2 + rotor_inertia[1] * gears[2] ** 2 + rotor_inertia[2]


# mjlab 1.6.0, asset_zoo/robots/unitree_g1/g1_constants.py: (armature, effort limit) of each motor
MOTORS = {
  "5020": (_armature((0.139e-4, 0.017e-4, 0.169e-4), (1, 1 + 46 / 18, 1 + 56 / 16)), 25.0),
  "7520_14": (_armature((0.489e-4, 0.098e-4, 0.533e-4), (1, 4.5, 1 + 48 / 22)), 88.0),
  "7520_22": (_armature((0.489e-4, 0.109e-4, 0.738e-4), (1, 4.5, 5)), 139.0),
  "4010": (_armature((0.068e-4, 0.0, 0.0), (1, 5, 5)), 5.0),
}
# joint name patterns -> (motor, how many drive the joint: the ankles and waist are linkages of two)
DRIVES = (
  (r".*_(elbow|shoulder_pitch|shoulder_roll|shoulder_yaw|wrist_roll)_joint", "5020", 1),
  (r"(.*_hip_pitch|.*_hip_yaw|waist_yaw)_joint", "7520_14", 1),
  (r".*_(hip_roll|knee)_joint", "7520_22", 1),
  (r".*_wrist_(pitch|yaw)_joint", "4010", 1),
  (r"(waist_pitch|waist_roll|.*_ankle_pitch|.*_ankle_roll)_joint", "5020", 2),
)
HOME = {  # mjlab's HOME_KEYFRAME
  r".*_hip_pitch_joint": -0.1, r".*_knee_joint": 0.3, r".*_ankle_pitch_joint": -0.2,
  r".*_shoulder_pitch_joint": 0.2, r".*_elbow_joint": 1.28, r"left_shoulder_roll_joint": 0.2,
  r"right_shoulder_roll_joint": -0.2,
}
TILES = (0, 2)  # the robots' tiles (make_quadruped_rough.KINDS: rough, waves)


def _drive(joint: str) -> tuple[float, float, float, float]:
  """(armature, stiffness, damping, effort limit) of the joint's drive."""
  for pattern, motor, count in DRIVES:
    if re.fullmatch(pattern, joint):
      armature, effort = MOTORS[motor]
      armature *= count
      return armature, armature * NATURAL_FREQ**2, 2 * DAMPING_RATIO * armature * NATURAL_FREQ, effort * count
  raise ValueError(f"g1.xml: no drive for joint {joint}")


def home_angle(joint: str) -> float:
  """The joint's angle in mjlab's home pose."""
  return next((v for pattern, v in HOME.items() if re.fullmatch(pattern, joint)), 0.0)


def build() -> mujoco.MjSpec:
  """The scene as an MjSpec: the tiles and the two robots with their drives."""
  spec = mujoco.MjSpec()
  spec.modelname = "humanoid_rough"
  spec.option.timestep = 0.002
  spec.compiler.degree = False
  grid.add_tiles(spec)
  for k, tile in enumerate(TILES):
    g1 = mujoco.MjSpec.from_file(os.path.join(HERE, "g1.xml"))
    centre = grid.CENTRES[tile]
    frame = spec.worldbody.add_frame(pos=[centre[0], centre[1], 0.0])
    frame.attach_body(g1.body("pelvis"), f"h{k}_", "")
  for geom in spec.geoms:
    if geom.name.startswith("h"):
      # the robots collide with the ground only, not with themselves or each other (their links'
      # capsules overlap at the joints)
      geom.contype, geom.conaffinity = 2, 1
  for joint in spec.joints:
    if joint.type != mujoco.mjtJoint.mjJNT_HINGE:
      continue
    armature, kp, kv, effort = _drive(joint.name.split("_", 1)[1])
    joint.armature = armature
    act = spec.add_actuator(name=joint.name[:-len("_joint")], target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_position(kp=kp, kv=kv)
    act.forcerange = [-effort, effort]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
  return spec


def _foot_gap(mjm: mujoco.MjModel, qpos: np.ndarray, prefix: str) -> float:
  """Smallest distance from one robot's foot capsules to the ground under them (negative: sunk)."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  gaps = []
  for g in range(mjm.ngeom):
    name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
    if not (name.startswith(prefix) and "_foot" in name):
      continue
    axis_z = abs(mjd.geom_xmat[g][8])
    lowest = mjd.geom_xpos[g][2] - mjm.geom_size[g][0] - mjm.geom_size[g][1] * axis_z
    height, hit = single.ground_under(mjm, mjd, mjd.geom_xpos[g], 2.0)
    assert hit >= 0, f"the ray under {name} missed the ground"
    gaps.append(lowest - height)
  return min(gaps)


def main() -> None:
  spec = build()
  mjm = spec.compile()
  qpos = mjm.qpos0.copy()
  for j in range(mjm.njnt):
    if mjm.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
      qpos[mjm.jnt_qposadr[j]] = home_angle(mjm.joint(j).name.split("_", 1)[1])
  ctrl = [qpos[mjm.jnt_qposadr[mjm.actuator_trnid[a][0]]] for a in range(mjm.nu)]
  for k in range(len(TILES)):
    adr = mjm.jnt_qposadr[mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, f"h{k}_floating_base_joint")]
    qpos[adr + 2] = 1.0
    qpos[adr + 2] -= _foot_gap(mjm, qpos, f"h{k}_") + FOOT_OVERLAP
  spec.add_key(name="init", qpos=qpos.tolist(), ctrl=ctrl)
  header = (
    "<!-- Written by make_humanoid_rough.py (do not edit): two of mjlab 1.6.0's Unitree G1 (g1.xml) with\n"
    "     mjlab's drives on the rough grid of make_quadruped_rough.py, on its rough and wave tiles. The\n"
    "     controls are scripted in real_scenes.py. -->\n"
  )
  with open(os.path.join(HERE, "humanoid_rough.xml"), "w") as f:
    f.write(header + spec.to_xml())


if __name__ == "__main__":
  main()
