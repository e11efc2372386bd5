"""Contact fidelity on real robot models: the plugin (default options and narrowphase="gjk") and
stock MuJoCo Warp against MuJoCo C on the scenes of models/real/.

  python benchmarks/fidelity.py [--scenes gripper_grasp,bin_drop] [--states 20] [--worlds 3]
                                [--json PATH] [--no-rollout]

For each scene:
1. MuJoCo C rolls the scene out from its keyframe (or qpos0) under the scene's scripted controls.
2. States: ``--states`` qpos evenly spaced over that rollout ("sampled"), and each of them
   "squeezed": every free body moved down along gravity by 1 mm (the lowest) to 3 mm (the
   highest), in proportion to its height among the free bodies. Bodies resting on static geoms
   sink into them, and a body resting on another sinks into it too, as the upper one moves
   further: what gravity presses together is pressed deeper, without running a different
   simulation. Articulated robots keep their joints (the Go1's floating base is a free
   body and sinks into the terrain).
3. ``mjx_supportfield.compare.compare_states`` on both sets for each implementation: MuJoCo C's
   deep points (>= 0.5 mm) missed (no contact of the same geom pair within 3 mm), normals more
   than 5 deg from MuJoCo C's and worse by exact overlap, contact points off their shapes.
4. Unless ``--no-rollout``: ``--worlds`` worlds rolled out through ``mjw.step`` with each
   implementation under the same controls as MuJoCo C, from the keyframe (world 0) and from
   copies whose free bodies are shifted by up to 1 mm horizontally (the other worlds); MuJoCo C
   rolls out the same initial states. Every ``RECORD_EVERY`` steps the state is judged by MuJoCo
   C's own collision (``mj_fwdPosition`` on the rollout's qpos): the deepest penetration. At the
   end: the free bodies' positions against MuJoCo C's from the same initial state (median and
   largest distance), worlds with a non-finite qpos, free bodies whose centre of mass went inside
   a static box or under the floor or terrain (fall-through), and a figure of the task (can
   lifted, objects in the bin, ...).

Writes a JSON (default ``benchmarks/results/<date>-cpu-fidelity.json``) and prints markdown
tables (docs/fidelity.md holds the committed run's).
"""

import argparse
import dataclasses
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from typing import Callable, Optional

import mujoco
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import mujoco_warp as mjw  # noqa: E402
import warp as wp  # noqa: E402

import mjx_supportfield  # noqa: E402
from mjx_supportfield import exact  # noqa: E402
from mjx_supportfield.compare import compare_states  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402

wp.config.quiet = True  # Warp's line per module loaded would drown the progress lines
if hasattr(wp.config, "log_level"):
  wp.config.log_level = wp.LOG_WARNING

MODELS = os.path.join(ROOT, "models", "real")
RESULTS = os.path.join(ROOT, "benchmarks", "results")
RECORD_EVERY = 5  # steps between the rollout states judged by MuJoCo C's collision
SQUEEZE_MIN, SQUEEZE_MAX = 1e-3, 3e-3  # m along gravity: lowest and highest free body
JITTER = 1e-3  # m: horizontal shift of the free bodies in worlds 1.. of the rollouts
IMPLS = {"plugin": Options(), "plugin_gjk": Options(narrowphase="gjk"), "stock": None}


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
  calf."""
  ctrl = mjm.key_ctrl[0].copy()
  crouch = _smooth(t, 0.3, 0.6) - _smooth(t, 0.6, 0.9)
  ctrl[1::3] += 0.3 * crouch
  ctrl[2::3] -= 0.6 * crouch
  gait = _smooth(t, 1.0, 1.2)
  for leg, phase in enumerate((0.0, np.pi, np.pi, 0.0)):  # FR, FL, RR, RL
    lift = max(0.0, np.sin(2.0 * np.pi * 2.0 * (t - 1.0) + phase)) * gait
    ctrl[3 * leg + 1] += 0.2 * lift
    ctrl[3 * leg + 2] -= 0.6 * lift
  return ctrl


# ---------------------------------------------------------------------------------------------
# task figures at the end of a rollout


def _body_pos(mjm, mjd, name):
  return mjd.xpos[mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, name)]


def _free_bodies(mjm: mujoco.MjModel) -> list[int]:
  """Bodies with a free joint."""
  return [b for b in range(mjm.nbody)
          if mjm.body_jntnum[b] and mjm.jnt_type[mjm.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]


def grasp_outcome(mjm, mjd, start) -> dict:
  """How far the can was lifted."""
  return {"can_lift_m": float(_body_pos(mjm, mjd, "can")[2] - _body_pos(mjm, start, "can")[2])}


def _objects_in_box(mjm, mjd, lo, hi) -> int:
  return int(sum(np.all((mjd.xpos[b] > lo) & (mjd.xpos[b] < hi)) for b in _free_bodies(mjm)))


def bin_outcome(mjm, mjd, start) -> dict:
  """Free bodies inside the bin."""
  return {"objects_in_bin": _objects_in_box(mjm, mjd, np.array([-0.12, -0.15, 0.04]), np.array([0.12, 0.15, 0.3])),
          "objects": len(_free_bodies(mjm))}


def sweep_outcome(mjm, mjd, start) -> dict:
  """Objects still on the table."""
  return {"objects_on_table": _objects_in_box(mjm, mjd, np.array([0.15, -0.6, 0.4]), np.array([1.05, 0.6, 0.7])),
          "objects": len(_free_bodies(mjm))}


def quadruped_outcome(mjm, mjd, start) -> dict:
  """The trunk's height and how upright it is (z of its up axis), and how far it wandered."""
  trunk = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, "trunk")
  return {"trunk_z_m": float(mjd.xpos[trunk][2]), "trunk_up_z": float(mjd.xmat[trunk][8]),
          "trunk_travel_m": float(np.linalg.norm(mjd.xpos[trunk][:2] - start.xpos[trunk][:2]))}


def polyhedra_outcome(mjm, mjd, start) -> dict:
  """Polyhedra inside the mug (within its inner radius, below its rim)."""
  mug = _body_pos(mjm, mjd, "mug")
  inside = 0
  for b in _free_bodies(mjm):
    p = mjd.xpos[b] - mug
    inside += mjm.body(b).name != "mug" and np.hypot(p[0], p[1]) < 0.039 and p[2] < 0.071
  return {"polyhedra_in_mug": int(inside), "polyhedra": len(_free_bodies(mjm)) - 1}


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
  for b in _free_bodies(mjm):
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


def squeeze(mjm: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
  """qpos with each free body moved down along gravity, from SQUEEZE_MIN (the lowest body) to
  SQUEEZE_MAX (the highest), in proportion to its height (module docstring)."""
  free = _free_bodies(mjm)
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


def _static_geoms(mjm: mujoco.MjModel) -> list[int]:
  """Collidable geoms of bodies welded to the world: boxes, planes, heightfields."""
  kinds = {int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)}
  return [g for g in range(mjm.ngeom) if mjm.body_weldid[mjm.geom_bodyid[g]] == 0 and int(mjm.geom_type[g]) in kinds
          and (mjm.geom_contype[g] or mjm.geom_conaffinity[g])]


def _hfield_height(mjm: mujoco.MjModel, g: int, x: float, y: float) -> Optional[float]:
  """The heightfield's surface height over (x, y) in its frame (bilinear in the samples), or
  None outside it."""
  h = mjm.geom_dataid[g]
  nrow, ncol = mjm.hfield_nrow[h], mjm.hfield_ncol[h]
  sx, sy, sz, _ = mjm.hfield_size[h]
  if abs(x) > sx or abs(y) > sy:
    return None
  data = mjm.hfield_data[mjm.hfield_adr[h]:mjm.hfield_adr[h] + nrow * ncol].reshape(nrow, ncol)
  u, v = (x + sx) / (2 * sx) * (ncol - 1), (y + sy) / (2 * sy) * (nrow - 1)
  c, r = min(int(u), ncol - 2), min(int(v), nrow - 2)
  fu, fv = u - c, v - r
  top = data[r, c] * (1 - fu) + data[r, c + 1] * fu
  bottom = data[r + 1, c] * (1 - fu) + data[r + 1, c + 1] * fu
  return float((top * (1 - fv) + bottom * fv) * sz)


def fallen_through(mjm: mujoco.MjModel, mjd: mujoco.MjData, static: list[int]) -> list[int]:
  """Free bodies whose centre of mass lies inside a static box, under a static plane or under
  the heightfield's surface (mjd forward-computed)."""
  out = []
  for b in _free_bodies(mjm):
    p = mjd.xipos[b]
    for g in static:
      local = mjd.geom_xmat[g].reshape(3, 3).T @ (p - mjd.geom_xpos[g])
      kind = int(mjm.geom_type[g])
      if kind == mujoco.mjtGeom.mjGEOM_BOX:
        inside = np.all(np.abs(local) < mjm.geom_size[g])
      elif kind == mujoco.mjtGeom.mjGEOM_PLANE:
        inside = local[2] < 0.0
      else:
        height = _hfield_height(mjm, g, local[0], local[1])
        inside = height is not None and local[2] < height
      if inside:
        out.append(b)
        break
  return out


# ---------------------------------------------------------------------------------------------
# MuJoCo Warp


def rollout_warp(scene: Scene, mjm: mujoco.MjModel, opts: Optional[Options], qpos0: np.ndarray, nstep: int,
                 nconmax: int, njmax: int) -> dict:
  """Worlds rolled out through mjw.step (plugin installed unless opts is None) from the rows of
  qpos0 (nworld, nq), zero velocity; qpos every RECORD_EVERY steps and the last."""
  nworld = len(qpos0)
  m = mjw.put_model(mjm)
  if opts is not None:
    mjx_supportfield.install(mjm, m, opts)
  d = mjw.put_data(mjm, initial_data(mjm), nworld=nworld, nconmax=nconmax, njmax=njmax)
  wp.copy(d.qpos, wp.array(qpos0.astype(np.float32), dtype=float))
  records, overflow, max_nacon = {}, 0, 0
  start = time.time()
  for step in range(nstep + 1):
    if step % RECORD_EVERY == 0 or step == nstep:
      records[step] = d.qpos.numpy().astype(np.float64)
    if step == nstep:
      break
    ctrl = control(scene, mjm, step)
    if ctrl is not None:
      wp.copy(d.ctrl, wp.array(np.tile(ctrl, (nworld, 1)).astype(np.float32), dtype=float))
    mjw.step(m, d)
    if step % RECORD_EVERY == 0:
      max_nacon = max(max_nacon, int(d.nacon.numpy()[0]))
      overflow |= int(np.bitwise_or.reduce(d.overflow.numpy()))
  wp.synchronize()
  if opts is not None:
    mjx_supportfield.uninstall(m)
  flags = [f.name for f in mjw.OverflowType if f.value and f.value & overflow and f.name != "ALL"]
  return {"records": records, "seconds": time.time() - start, "max_nacon": max_nacon, "naconmax": d.naconmax,
          "overflow": flags}


def judge_rollout(scene: Scene, mjm: mujoco.MjModel, records: dict, reference_final: np.ndarray) -> dict:
  """Penetration by MuJoCo C's collision on the recorded states, NaN worlds, fall-through,
  final free-body positions against MuJoCo C's (reference_final: (nworld, nq)) and the task."""
  mjd = mujoco.MjData(mjm)
  static = _static_geoms(mjm)
  free = _free_bodies(mjm)
  adr = [mjm.jnt_qposadr[mjm.body_jntadr[b]] for b in free]
  steps = sorted(records)
  nworld = records[steps[0]].shape[0]
  nan_worlds = set()
  deepest, deepest_at = 0.0, None
  per_state = []
  fell = set()
  for step in steps:
    for w in range(nworld):
      q = records[step][w]
      if not np.all(np.isfinite(q)):
        nan_worlds.add(w)
        continue
      depth, pair = deepest_penetration(mjm, mjd, q)
      per_state.append(depth)
      if depth > deepest:
        deepest, deepest_at = depth, {"step": step, "world": w, "pair": pair}
      fell |= {(w, mjm.body(b).name) for b in fallen_through(mjm, mjd, static)}
  final = records[steps[-1]]
  errors = [float(np.linalg.norm(final[w][a:a + 3] - reference_final[w][a:a + 3]))
            for w in range(nworld) if w not in nan_worlds for a in adr]
  start = initial_data(mjm)
  outcomes = []
  for w in range(nworld):
    if w in nan_worlds:
      continue
    mjd.qpos[:] = final[w]
    mujoco.mj_forward(mjm, mjd)
    outcomes.append(scene.outcome(mjm, mjd, start))
  return {
    "max_penetration": deepest,
    "max_penetration_at": deepest_at,
    "mean_deepest_penetration": float(np.mean(per_state)) if per_state else 0.0,
    "nan_worlds": len(nan_worlds),
    "fell_through": sorted(f"world {w}: {b}" for w, b in fell),
    "final_position_error_median": float(np.median(errors)) if errors else None,
    "final_position_error_max": float(np.max(errors)) if errors else None,
    "outcome": outcomes,
  }


# ---------------------------------------------------------------------------------------------
# one scene


def _log(msg: str) -> None:
  print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _state_summary(report: dict) -> dict:
  """compare_states' summaries (with their lists of misses), without the per-state rows."""
  return {"reference": report["reference"], "impls": {k: v["summary"] for k, v in report["impls"].items()}}


def run_scene(name: str, nstates: int, nworld: int, rollout: bool) -> dict:
  """All the figures of one scene (module docstring)."""
  scene = SCENES[name]
  mjm = load(name)
  nstep = int(round(scene.seconds / mjm.opt.timestep))
  qpos0 = initial_data(mjm).qpos.copy()
  t0 = time.time()
  ref = rollout_mujoco(scene, mjm, qpos0, nstep)
  _log(f"{name}: MuJoCo C, {nstep} steps in {time.time() - t0:.2f} s; contacts {ref['ncon'].mean():.1f} a step "
       f"(max {ref['ncon'].max()}), deepest {ref['deepest'] * 1e3:.2f} mm")
  at = np.linspace(0, nstep, nstates).round().astype(int)
  sampled = [ref["qpos"][i] for i in at]
  squeezed = [squeeze(mjm, q) for q in sampled]
  out = {
    "xml": os.path.relpath(os.path.join(MODELS, scene.xml), ROOT), "summary": scene.summary, "steps": nstep,
    "timestep": mjm.opt.timestep, "ngeom": mjm.ngeom, "nmesh": mjm.nmesh, "free_bodies": len(_free_bodies(mjm)),
    "mujoco": {"contacts_mean": float(ref["ncon"].mean()), "contacts_max": int(ref["ncon"].max()),
               "deepest": ref["deepest"], "seconds": time.time() - t0},
    "state_steps": at.tolist(), "states": {},
  }
  for label, states in (("sampled", sampled), ("squeezed", squeezed)):
    t = time.time()
    _log(f"{name}: contacts on {len(states)} {label} states (plugin, plugin gjk, stock; the first run compiles "
         "kernels for minutes)")
    out["states"][label] = _state_summary(compare_states(mjm, states, IMPLS))
    _log(f"{name}: {label} states done in {time.time() - t:.0f} s")
  if not rollout:
    return out
  starts = np.stack([jittered(mjm, qpos0, w) for w in range(nworld)])
  c_qpos = np.stack([rollout_mujoco(scene, mjm, q, nstep)["qpos"] for q in starts], axis=1)  # (step, world, nq)
  c_records = {step: c_qpos[step] for step in sorted(set(range(0, nstep + 1, RECORD_EVERY)) | {nstep})}
  finals = c_qpos[-1]
  out["rollouts"] = {"worlds": nworld, "record_every": RECORD_EVERY, "mujoco": judge_rollout(scene, mjm, c_records, finals)}
  nconmax = max(64, 4 * int(ref["ncon"].max()))
  njmax = max(256, 4 * ref["max_nefc"])
  for impl, opts in IMPLS.items():
    t = time.time()
    _log(f"{name}: rollout, {impl}, {nworld} worlds x {nstep} steps")
    run = rollout_warp(scene, mjm, opts, starts, nstep, nconmax, njmax)
    judged = judge_rollout(scene, mjm, run["records"], finals)
    judged.update({"seconds": run["seconds"], "max_nacon": run["max_nacon"], "naconmax": run["naconmax"],
                   "overflow": run["overflow"]})
    out["rollouts"][impl] = judged
    _log(f"{name}: {impl} rollout done in {time.time() - t:.0f} s: max penetration "
         f"{judged['max_penetration'] * 1e3:.2f} mm, final position error median "
         f"{(judged['final_position_error_median'] or 0) * 1e3:.1f} mm")
  return out


# ---------------------------------------------------------------------------------------------
# tables


def _mm(x) -> str:
  return "–" if x is None else f"{x * 1e3:.2f}"


def _pct(missed: int, total: int) -> str:
  return f"{missed} ({100.0 * missed / total:.1f} %)" if total else str(missed)


def _states_rows(name: str, r: dict, impls: list, totals: dict) -> list[str]:
  rows = []
  for label, st in r["states"].items():
    s = st["impls"]
    deep = s[impls[0]]["deep_points_reference"]
    totals["deep"] += deep
    for i in impls:
      totals[i] += s[i]["deep_points_missed"]
    contacts = s[impls[0]]["contacts_reference"] / max(1, len(r["state_steps"]))
    missed = " / ".join(_pct(s[i]["deep_points_missed"], deep) for i in impls)
    worse = " / ".join(str(s[i]["pairs_normal_worse"]) for i in impls)
    ref = st["reference"]
    off = " / ".join([f"{ref['contacts_outside']} ({ref['max_outside'] * 1e3:.1f})"]
                     + [f"{s[i]['contacts_outside']} ({s[i]['max_outside'] * 1e3:.1f})" for i in impls])
    rows.append(f"| {name} | {label} | {contacts:.1f} | {deep} | {missed} | {worse} | {off} |")
  return rows


def _task(outcomes: list) -> str:
  """The task figure of the worst world, short."""
  if not outcomes:
    return "–"
  if "can_lift_m" in outcomes[0]:
    return f"lift {min(o['can_lift_m'] for o in outcomes) * 100:.1f} cm"
  if "objects_in_bin" in outcomes[0]:
    return f"{min(o['objects_in_bin'] for o in outcomes)}/{outcomes[0]['objects']} in bin"
  if "objects_on_table" in outcomes[0]:
    return f"{min(o['objects_on_table'] for o in outcomes)}/{outcomes[0]['objects']} on table"
  if "trunk_up_z" in outcomes[0]:
    worst = min(outcomes, key=lambda o: o["trunk_up_z"])
    return f"up {worst['trunk_up_z']:.2f}, z {worst['trunk_z_m']:.2f} m"
  if "polyhedra_in_mug" in outcomes[0]:
    return f"{min(o['polyhedra_in_mug'] for o in outcomes)}/{outcomes[0]['polyhedra']} in mug"
  return json.dumps(outcomes[0])


def tables(results: dict) -> str:
  """Markdown: contacts on the sampled and squeezed states, then the rollouts."""
  impls = list(IMPLS)
  lines = [
    "| scene | states | MuJoCo C contacts a state | deep points (C) | missed: plugin / gjk / stock | "
    "worse normals > 5°: plugin / gjk / stock | points off shapes (max mm): C / plugin / gjk / stock |",
    "|---|---|---|---|---|---|---|",
  ]
  totals = {"deep": 0, **{i: 0 for i in impls}}
  for name, r in results.items():
    lines += _states_rows(name, r, impls, totals)
  lines.append(f"| all | | | {totals['deep']} | " + " / ".join(_pct(totals[i], totals["deep"]) for i in impls)
               + " | | |")
  if any("rollouts" in r for r in results.values()):
    lines += [
      "",
      "| scene | max penetration mm: C / plugin / gjk / stock | final position error mm, median (max): plugin / "
      "gjk / stock | NaN worlds | fall-through: C / plugin / gjk / stock | task, worst world: C / plugin / gjk / stock |",
      "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
      if "rollouts" not in r:
        continue
      ro = r["rollouts"]
      pen = " / ".join(_mm(ro[i]["max_penetration"]) for i in ["mujoco"] + impls)
      err = " / ".join(f"{_mm(ro[i]['final_position_error_median'])} ({_mm(ro[i]['final_position_error_max'])})"
                       for i in impls)
      nan = " / ".join(str(ro[i]["nan_worlds"]) for i in impls)
      fell = " / ".join(str(len(ro[i]["fell_through"])) for i in ["mujoco"] + impls)
      task = " / ".join(_task(ro[i]["outcome"]) for i in ["mujoco"] + impls)
      lines.append(f"| {name} | {pen} | {err} | {nan} | {fell} | {task} |")
  return "\n".join(lines)


def _commit() -> str:
  """The repository's HEAD commit, with "+dirty" when tracked files differ from it ("?" outside git)."""
  try:
    head = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                           text=True, check=True).stdout.strip()
    return head + ("+dirty" if dirty else "")
  except (OSError, subprocess.CalledProcessError):
    return "?"


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated, of: " + ", ".join(SCENES))
  parser.add_argument("--states", type=int, default=20, help="states sampled from MuJoCo C's rollout (and as many squeezed)")
  parser.add_argument("--worlds", type=int, default=3, help="worlds of the mjw.step rollouts")
  parser.add_argument("--json", default=os.path.join(RESULTS, f"{datetime.date.today()}-cpu-fidelity.json"))
  parser.add_argument("--no-rollout", action="store_true", help="contacts on states only")
  args = parser.parse_args(argv)
  names = [s for s in args.scenes.split(",") if s]
  unknown = [s for s in names if s not in SCENES]
  if unknown:
    parser.error(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(SCENES)}")
  results = {}
  meta = {"date": str(datetime.date.today()), "commit": _commit(), "device": str(wp.get_device()),
          "machine": platform.machine(),
          "mujoco": mujoco.__version__, "mujoco_warp": getattr(mjw, "__version__", "?"), "warp": wp.__version__,
          "states": args.states, "worlds": args.worlds, "impls": {k: (None if v is None else dataclasses.asdict(v))
                                                                  for k, v in IMPLS.items()},
          "squeeze_m": [SQUEEZE_MIN, SQUEEZE_MAX], "jitter_m": JITTER, "record_every": RECORD_EVERY}
  for name in names:
    results[name] = run_scene(name, args.states, args.worlds, not args.no_rollout)
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:  # after every scene, so that a long run leaves what it has
      json.dump({"meta": meta, "scenes": results}, f, indent=1, default=lambda x: x.tolist() if hasattr(x, "tolist")
                else str(x))
  print(tables(results))
  print(f"wrote {args.json}")


if __name__ == "__main__":
  main()
