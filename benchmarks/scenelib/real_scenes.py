"""The real-model scenes of models/real/ as MuJoCo C runs them: their scripted controls, task
figures, keyframes and rollouts, the squeezed states, and MuJoCo C's penetration and
fall-through measured on a state.

benchmarks/fidelity.py judges the plugin and stock MuJoCo Warp on these scenes, and
tests/test_real_models.py checks the scenes themselves with the same functions. The MJCF files
are the repository's (a source checkout: they are not part of an installed package).
"""

import dataclasses
import os
from typing import Callable, Optional

import mujoco
import numpy as np

from mjx_supportfield.tools import exact

MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models", "real")
SQUEEZE_MIN, SQUEEZE_MAX = 1e-3, 3e-3  # m along gravity: lowest and highest free body
JITTER = 1e-3  # m: horizontal shift of the free bodies in worlds 1.. of the rollouts


def _smooth(t: float, t0: float, t1: float) -> float:
  """0 before t0, 1 after t1, a smoothstep between."""
  s = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
  return s * s * (3.0 - 2.0 * s)


# ---------------------------------------------------------------------------------------------
# scripted controls, one function a scene: ctrl at time t (deterministic)


def grasp_control(mjm: mujoco.MjModel, t: float) -> np.ndarray:
  """Carriage down 10 cm over the can (0.1-0.5 s), fingers closed (0.5-0.8 s), lifted 15 cm
  (0.8-1.4 s), held."""
  z = -0.10 * _smooth(t, 0.1, 0.5) + 0.15 * _smooth(t, 0.8, 1.4)
  finger = 0.04 * (1.0 - _smooth(t, 0.5, 0.8))
  return np.array([0.0, 0.0, z, finger, -finger])


SWEEP_HIGH = np.array([0.1, 0.0, -2.4, 0.0, 2.5, -0.785])  # joints 2-7: hand 15 cm above the table
SWEEP_LOW = np.array([0.8, 0.0, -1.7, 0.0, 2.5, -0.785])  # the fingertips 2 cm above it


def sweep_control(mjm: mujoco.MjModel, t: float) -> np.ndarray:
  """Hand lowered (0.2-0.6 s), joint 1 swept from -0.85 to 0.7 rad (0.6-3.0 s), hand raised
  (3.0-3.3 s); fingers held 1 cm apart."""
  q1 = -0.85 + 1.55 * _smooth(t, 0.6, 3.0)
  down = _smooth(t, 0.2, 0.6) - _smooth(t, 3.0, 3.3)
  return np.concatenate([[q1], SWEEP_HIGH + (SWEEP_LOW - SWEEP_HIGH) * down, [0.01, -0.01]])


def quadruped_control(mjm: mujoco.MjModel, t: float) -> np.ndarray:
  """mjlab's standing pose (the keyframe's ctrl), a crouch (0.3-0.9 s), then stepping in place
  from 1.0 s: diagonal leg pairs (FR+RL, FL+RR) lifted in turn at 2 Hz by bending thigh and
  calf; every robot of the scene alike (its actuators in groups of 12)."""
  ctrl = mjm.key_ctrl[0].copy()
  crouch = _smooth(t, 0.3, 0.6) - _smooth(t, 0.6, 0.9)
  ctrl[1::3] += 0.3 * crouch
  ctrl[2::3] -= 0.6 * crouch
  gait = _smooth(t, 1.0, 1.2)
  for leg in range(len(ctrl) // 3):  # each robot's FR, FL, RR, RL
    phase = (0.0, np.pi, np.pi, 0.0)[leg % 4]
    lift = max(0.0, np.sin(2.0 * np.pi * 2.0 * (t - 1.0) + phase)) * gait
    ctrl[3 * leg + 1] += 0.2 * lift
    ctrl[3 * leg + 2] -= 0.6 * lift
  return ctrl


# ---------------------------------------------------------------------------------------------
# task figures at the end of a rollout


def _body_pos(mjm, mjd, name):
  return mjd.xpos[mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, name)]


def free_bodies(mjm: mujoco.MjModel) -> list[int]:
  """Bodies with a free joint."""
  return [b for b in range(mjm.nbody)
          if mjm.body_jntnum[b] and mjm.jnt_type[mjm.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]


def grasp_outcome(mjm, mjd, start) -> dict:
  """How far the can was lifted."""
  return {"can_lift_m": float(_body_pos(mjm, mjd, "can")[2] - _body_pos(mjm, start, "can")[2])}


def _objects_in_box(mjm, mjd, lo, hi) -> int:
  return int(sum(np.all((mjd.xpos[b] > lo) & (mjd.xpos[b] < hi)) for b in free_bodies(mjm)))


def bin_outcome(mjm, mjd, start) -> dict:
  """Free bodies inside the bin."""
  return {"objects_in_bin": _objects_in_box(mjm, mjd, np.array([-0.12, -0.15, 0.04]), np.array([0.12, 0.15, 0.3])),
          "objects": len(free_bodies(mjm))}


def sweep_outcome(mjm, mjd, start) -> dict:
  """Objects still on the table."""
  return {"objects_on_table": _objects_in_box(mjm, mjd, np.array([0.15, -0.6, 0.4]), np.array([1.05, 0.6, 0.7])),
          "objects": len(free_bodies(mjm))}


def quadruped_outcome(mjm, mjd, start) -> dict:
  """The trunk's height and how upright it is (z of its up axis), and how far it wandered."""
  trunk = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, "trunk")
  return {"trunk_z_m": float(mjd.xpos[trunk][2]), "trunk_up_z": float(mjd.xmat[trunk][8]),
          "trunk_travel_m": float(np.linalg.norm(mjd.xpos[trunk][:2] - start.xpos[trunk][:2]))}


def quadrupeds_outcome(mjm, mjd, start) -> dict:
  """Of several Go1s (bodies r<k>_trunk): how many stand upright (trunk's up axis z > 0.8), the
  lowest trunk's rise over its start (negative: sunk) and the farthest any wandered."""
  trunks = [b for b in range(mjm.nbody) if mjm.body(b).name.endswith("_trunk")]
  return {"robots": len(trunks), "robots_upright": int(sum(mjd.xmat[b][8] > 0.8 for b in trunks)),
          "lowest_trunk_rise_m": float(min(mjd.xpos[b][2] - start.xpos[b][2] for b in trunks)),
          "max_travel_m": float(max(np.linalg.norm(mjd.xpos[b][:2] - start.xpos[b][:2]) for b in trunks))}


def hold_pose(mjm: mujoco.MjModel, t: float) -> np.ndarray:
  """The keyframe's controls throughout (position targets: the robots hold their initial pose)."""
  return mjm.key_ctrl[0].copy()


def humanoids_outcome(mjm, mjd, start) -> dict:
  """Of several G1s (bodies h<k>_pelvis): how many are down (pelvis's up axis z < 0.5) and the
  lowest pelvis's height."""
  pelvises = [b for b in range(mjm.nbody) if mjm.body(b).name.endswith("_pelvis")]
  return {"robots": len(pelvises), "robots_down": int(sum(mjd.xmat[b][8] < 0.5 for b in pelvises)),
          "lowest_pelvis_z_m": float(min(mjd.xpos[b][2] for b in pelvises))}


def polyhedra_outcome(mjm, mjd, start) -> dict:
  """Polyhedra inside the mug (within its inner radius, below its rim)."""
  mug = _body_pos(mjm, mjd, "mug")
  inside = 0
  for b in free_bodies(mjm):
    p = mjd.xpos[b] - mug
    inside += mjm.body(b).name != "mug" and np.hypot(p[0], p[1]) < 0.039 and p[2] < 0.071
  return {"polyhedra_in_mug": int(inside), "polyhedra": len(free_bodies(mjm)) - 1}


@dataclasses.dataclass(frozen=True)
class Scene:
  """A scene of models/real/: its MJCF, how long it runs, its controls and its task figure."""

  xml: str
  seconds: float
  control: Optional[Callable[[mujoco.MjModel, float], np.ndarray]]
  outcome: Callable[[mujoco.MjModel, mujoco.MjData, mujoco.MjData], dict]
  summary: str


SCENES = {
  "gripper_grasp": Scene("gripper_grasp.xml", 1.6, grasp_control, grasp_outcome,
                         "robosuite's Panda hand on a slide carriage grasps and lifts a can"),
  "bin_drop": Scene("bin_drop.xml", 1.5, None, bin_outcome,
                    "11 robosuite mesh objects and primitives dropped into a bin"),
  "arm_sweep": Scene("arm_sweep.xml", 3.3, sweep_control, sweep_outcome,
                     "robosuite's Panda arm (mesh links) sweeps 7 objects across a table"),
  "quadruped_terrain": Scene("quadruped_terrain.xml", 2.2, quadruped_control, quadruped_outcome,
                             "mjlab's Unitree Go1 stands, crouches and steps on a heightfield"),
  "quadruped_rough": Scene("quadruped_rough.xml", 2.2, quadruped_control, quadrupeds_outcome,
                           "four of mjlab's Go1s stand, crouch and step on an mjlab-style grid of tiles: rough, "
                           "slope and wave heightfields and box stairs"),
  "humanoid_rough": Scene("humanoid_rough.xml", 2.2, hold_pose, humanoids_outcome,
                          "two of mjlab's G1s hold mjlab's home pose on rough and wave heightfields and, with no "
                          "balance controller, topple onto the terrain"),
  "polyhedra": Scene("polyhedra.xml", 1.5, None, polyhedra_outcome,
                     "MuJoCo Warp's test polyhedra dropped into a mug and slid down a ramp"),
}


# ---------------------------------------------------------------------------------------------
# MuJoCo C


def load(name: str) -> mujoco.MjModel:
  """The MuJoCo model of a scene of SCENES."""
  return mujoco.MjModel.from_xml_path(os.path.join(MODELS, SCENES[name].xml))


def initial_data(mjm: mujoco.MjModel) -> mujoco.MjData:
  """MjData at the scene's keyframe (qpos0 without one), forward-computed."""
  mjd = mujoco.MjData(mjm)
  if mjm.nkey:
    mujoco.mj_resetDataKeyframe(mjm, mjd, 0)
  mujoco.mj_forward(mjm, mjd)
  return mjd


def jittered(mjm: mujoco.MjModel, qpos: np.ndarray, world: int) -> np.ndarray:
  """qpos with every free body shifted horizontally by up to JITTER (world 0: unchanged)."""
  if world == 0:
    return qpos.copy()
  rng = np.random.default_rng(world)
  q = qpos.copy()
  for b in free_bodies(mjm):
    adr = mjm.jnt_qposadr[mjm.body_jntadr[b]]
    q[adr:adr + 2] += rng.uniform(-JITTER, JITTER, size=2)
  return q


def control(scene: Scene, mjm: mujoco.MjModel, step: int) -> Optional[np.ndarray]:
  """The scene's ctrl before ``step`` (time step * timestep)."""
  return None if scene.control is None else scene.control(mjm, step * mjm.opt.timestep)


def rollout_mujoco(scene: Scene, mjm: mujoco.MjModel, qpos0: np.ndarray, nstep: int) -> dict:
  """MuJoCo C from qpos0 (zero velocity, the keyframe's act): qpos every step, and contact
  counts, depth and constraint rows along the way."""
  mjd = initial_data(mjm)
  mjd.qpos[:] = qpos0
  mujoco.mj_forward(mjm, mjd)
  qpos = np.empty((nstep + 1, mjm.nq))
  ncon, deepest, nefc = [], 0.0, 0
  for step in range(nstep + 1):
    qpos[step] = mjd.qpos
    ncon.append(mjd.ncon)
    if mjd.ncon:
      deepest = max(deepest, -float(mjd.contact.dist[: mjd.ncon].min()))
    nefc = max(nefc, mjd.nefc)
    if step < nstep:
      ctrl = control(scene, mjm, step)
      if ctrl is not None:
        mjd.ctrl[:] = ctrl
      mujoco.mj_step(mjm, mjd)
  return {"qpos": qpos, "ncon": np.array(ncon), "deepest": deepest, "max_nefc": nefc}


def replay_mujoco(scene: Scene, mjm: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, start: int,
                  nstep: int) -> dict:
  """MuJoCo C from another implementation's state (qpos, qvel at step ``start``) for ``nstep``
  steps under the scene's controls, every state judged by deepest_penetration: the deepest (m)
  and the step it was reached at.

  A rollout's deepest penetration mixes two things: how hard the bodies met (the trajectory:
  where a sweep or a drop sends them, which diverges between implementations within a second)
  and how the contacts resisted the impact. Replaying the last few steps before an implementation's
  deepest state with MuJoCo C keeps the first and puts MuJoCo C's contacts in place of the
  implementation's, so the two depths differ only by the contacts' doing over those steps."""
  mjd = initial_data(mjm)
  mjd.qpos[:] = qpos
  mjd.qvel[:] = qvel
  judge = mujoco.MjData(mjm)
  deepest, deepest_at, pair_at = 0.0, start, ""
  for step in range(start, start + nstep + 1):
    depth, pair = deepest_penetration(mjm, judge, mjd.qpos)
    if depth > deepest:
      deepest, deepest_at, pair_at = depth, step, pair
    if step == start + nstep:
      break
    ctrl = control(scene, mjm, step)
    if ctrl is not None:
      mjd.ctrl[:] = ctrl
    mujoco.mj_step(mjm, mjd)
  return {"max_penetration": deepest, "step": deepest_at, "pair": pair_at}


def squeeze(mjm: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
  """qpos with each free body moved down along gravity, from SQUEEZE_MIN (the lowest body) to
  SQUEEZE_MAX (the highest), in proportion to its height: bodies resting on static geoms sink
  into them, and a body resting on another sinks into it too, as the upper one moves further, so
  what gravity presses together is pressed deeper without running a different simulation."""
  free = free_bodies(mjm)
  q = qpos.copy()
  if not free:
    return q
  adr = [mjm.jnt_qposadr[mjm.body_jntadr[b]] for b in free]
  z = np.array([qpos[a + 2] for a in adr])
  span = z.max() - z.min()
  frac = (z - z.min()) / span if span > 0 else np.ones_like(z)
  down = mjm.opt.gravity / max(np.linalg.norm(mjm.opt.gravity), 1e-12)
  for a, f in zip(adr, frac):
    q[a:a + 3] += (SQUEEZE_MIN + f * (SQUEEZE_MAX - SQUEEZE_MIN)) * down
  return q


def penetration(mjm: mujoco.MjModel, mjd: mujoco.MjData, i: int) -> float:
  """Penetration (m, positive) of MuJoCo C's contact i, held to the exact geometry: -dist, but no
  more than the exact overlap of the pair's convex shapes along any of a few directions (MuJoCo
  C's normal, each geom's frame axes, the line between their centres). The true depth is the
  smallest overlap over all directions, so this never reports less than it; it keeps a wrong
  normal of MuJoCo C's (a sideways answer on a thin disk, say) from passing as a deep overlap."""
  depth = -float(mjd.contact.dist[i])
  g1, g2 = (int(g) for g in mjd.contact.geom[i])
  xpos, xmat = mjd.geom_xpos, mjd.geom_xmat.reshape(-1, 3, 3)
  centres = xpos[g2] - xpos[g1]
  directions = [mjd.contact.frame[i][:3], *xmat[g1].T, *xmat[g2].T]
  if np.linalg.norm(centres) > 0.0:
    directions.append(centres)
  try:
    for n in directions:
      depth = min(depth, exact.overlap_along(mjm, g1, g2, xpos, xmat, n),
                  exact.overlap_along(mjm, g1, g2, xpos, xmat, -np.asarray(n)))
  except exact.NotConvexError:  # a heightfield: MuJoCo C's own depth
    pass
  return depth


def deepest_penetration(mjm: mujoco.MjModel, mjd: mujoco.MjData, qpos: np.ndarray) -> tuple[float, str]:
  """MuJoCo C's deepest contact (m, positive = penetration; held to the exact geometry, see
  penetration) at qpos, and its geom pair."""
  mjd.qpos[:] = qpos
  mujoco.mj_fwdPosition(mjm, mjd)
  if not mjd.ncon:
    return 0.0, ""
  depths = [penetration(mjm, mjd, i) for i in range(mjd.ncon)]
  i = int(np.argmax(depths))
  g1, g2 = mjd.contact.geom[i]
  pair = f"{mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g1)}-{mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g2)}"
  return max(0.0, depths[i]), pair


def static_geoms(mjm: mujoco.MjModel) -> list[int]:
  """Collidable geoms of bodies welded to the world: boxes, planes, heightfields."""
  kinds = {int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)}
  return [g for g in range(mjm.ngeom) if mjm.body_weldid[mjm.geom_bodyid[g]] == 0 and int(mjm.geom_type[g]) in kinds
          and (mjm.geom_contype[g] or mjm.geom_conaffinity[g])]


def _hfield_heights(mjm: mujoco.MjModel, g: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
  """The heightfield's surface height over each (x, y) in its frame, NaN outside it: MuJoCo's
  surface, each cell split into two triangles along the diagonal from (row, col) to
  (row + 1, col + 1)."""
  h = mjm.geom_dataid[g]
  nrow, ncol = mjm.hfield_nrow[h], mjm.hfield_ncol[h]
  sx, sy, sz, _ = mjm.hfield_size[h]
  data = mjm.hfield_data[mjm.hfield_adr[h]:mjm.hfield_adr[h] + nrow * ncol].reshape(nrow, ncol)
  with np.errstate(invalid="ignore"):
    u, v = (x + sx) / (2 * sx) * (ncol - 1), (y + sy) / (2 * sy) * (nrow - 1)
    c = np.clip(np.floor(np.nan_to_num(u)).astype(int), 0, ncol - 2)
    r = np.clip(np.floor(np.nan_to_num(v)).astype(int), 0, nrow - 2)
  fu, fv = u - c, v - r
  h00, h01, h10, h11 = data[r, c], data[r, c + 1], data[r + 1, c], data[r + 1, c + 1]
  upper = h00 + fu * (h01 - h00) + fv * (h11 - h01)  # fu >= fv: (r, c), (r, c + 1), (r + 1, c + 1)
  lower = h00 + fv * (h10 - h00) + fu * (h11 - h10)  # fu < fv: (r, c), (r + 1, c), (r + 1, c + 1)
  height = np.where(fu >= fv, upper, lower) * sz
  return np.where((np.abs(x) > sx) | (np.abs(y) > sy), np.nan, height)


def static_extent(mjm: mujoco.MjModel, static: list[int], geom_xpos: np.ndarray, geom_xmat: np.ndarray):
  """Where the static ground lies, seen from above: a function of (..., 2) world xy points that
  is True over a static heightfield or box (anywhere, with a static plane)."""
  rects = []
  for g in static:
    kind = int(mjm.geom_type[g])
    if kind == mujoco.mjtGeom.mjGEOM_PLANE:
      return lambda xy: np.ones(np.shape(xy)[:-1], dtype=bool)
    half = mjm.hfield_size[mjm.geom_dataid[g]][:2] if kind == mujoco.mjtGeom.mjGEOM_HFIELD else mjm.geom_size[g][:2]
    rects.append((geom_xpos[g][:2], geom_xmat[g].reshape(3, 3)[:2, :2], half))

  def over(xy):
    xy = np.asarray(xy, dtype=float)
    inside = np.zeros(xy.shape[:-1], dtype=bool)
    for centre, rot, half in rects:  # boxes and heightfields lie level: their frame's xy axes in the world's xy
      local = (xy - centre) @ rot
      inside |= np.all(np.abs(local) <= half, axis=-1)
    return inside

  return over


def inside_static(mjm: mujoco.MjModel, points: np.ndarray, geom_xpos: np.ndarray, geom_xmat: np.ndarray,
                  static: list[int], below_slab: bool = True) -> np.ndarray:
  """Which of ``points`` (..., 3) lie inside a static box, under a static plane or under a
  heightfield's surface (geom_xpos and geom_xmat: one world's, (ngeom, 3) and (ngeom, 9)).
  Without ``below_slab``, a point under a heightfield counts only within its slab, down to its
  base (hfield_size[3] under the geom's origin): below that there is no ground, and a leg
  hanging over the terrain's edge can reach there without passing through it."""
  p = np.asarray(points, dtype=float)
  inside = np.zeros(p.shape[:-1], dtype=bool)
  for g in static:
    local = (p - geom_xpos[g]) @ geom_xmat[g].reshape(3, 3)  # rows: the points in the geom's frame
    kind = int(mjm.geom_type[g])
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
      inside |= np.all(np.abs(local) < mjm.geom_size[g], axis=-1)
    elif kind == mujoco.mjtGeom.mjGEOM_PLANE:
      inside |= local[..., 2] < 0.0
    else:
      with np.errstate(invalid="ignore"):
        under = local[..., 2] < _hfield_heights(mjm, g, local[..., 0], local[..., 1])
      if not below_slab:
        under &= local[..., 2] > -mjm.hfield_size[mjm.geom_dataid[g]][3]
      inside |= under
  return inside


def fallen_through(mjm: mujoco.MjModel, mjd: mujoco.MjData, static: list[int]) -> list[int]:
  """Free bodies whose centre of mass lies inside a static box, under a static plane or under
  the heightfield's surface (mjd forward-computed)."""
  free = free_bodies(mjm)
  if not free:
    return []
  inside = inside_static(mjm, mjd.xipos[free], mjd.geom_xpos, mjd.geom_xmat, static)
  return [b for b, i in zip(free, inside) if i]
