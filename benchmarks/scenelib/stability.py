"""Resting-contact stability: a scene stepped by the plugin, stock MuJoCo Warp or MuJoCo C, and
its figures after settling (drift, contact motion, whether the stack stands).

benchmarks/stability.py prints these figures for the three engines and tests/test_stability.py
holds the plugin to them, so the table and the test measure the same thing. The figures, all
over the window after settling (steps ``settle`` to the end):

- drift: the largest distance of a body's origin from where it was at step ``settle``
  (max_t |p(t) - p(settle)|); slow creep and oscillation both count.
- contact motion: for each contact of a step, the distance to the nearest contact of the same
  geom pair in the step before; the largest over contacts, pairs and steps. A contact of a pair
  that had none the step before is counted as an appearance, not as motion.
- stack standing: every box still within 1 cm (horizontally and vertically) of where it
  started and tilted less than 2 degrees.
"""

import dataclasses
import os
import time
from typing import Optional

import mujoco
import numpy as np

# the repository's models/ (a source checkout: the scenes are not part of an installed package)
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")

# scene: (MJCF in models/, bodies to measure)
SCENES = {
  "resting": ("resting.xml", ("box", "cylinder", "convex", "meshcube0", "meshcube1")),
  "box_stack": ("box_stack.xml", ("box0", "box1", "box2", "box3", "box4", "boxmesh")),
}
STACK = ("box0", "box1", "box2", "box3", "box4")
ENGINES = ("plugin", "mjw", "mujoco")

# thresholds of issue #4
MAX_DRIFT = 1e-4  # m, after settling
MAX_CONTACT_MOTION = 1e-3  # m between consecutive steps
STAND_XY, STAND_Z, STAND_TILT = 1e-2, 1e-2, 2.0  # m, m, degrees


@dataclasses.dataclass
class Trajectory:
  """One run: qpos of the measured bodies and the contacts of every step.

  pos: (nstep + 1, nbody, 3) body origins; quat: (nstep + 1, nbody, 4) orientations (w, x, y, z);
  contacts[t]: {(g1, g2): (n, 3) positions} of the collision run by step t + 1 (MuJoCo and MuJoCo
  Warp both collide at the start of a step, so these belong to state t); seconds: stepping time
  without the first step (which compiles Warp's kernels); first_seconds: the first step.
  """

  bodies: tuple
  pos: np.ndarray
  quat: np.ndarray
  contacts: list
  seconds: float
  first_seconds: float


def model_path(scene: str) -> str:
  """Path of a scene of SCENES."""
  return os.path.join(MODELS, SCENES[scene][0])


def _qpos_adr(mjm, bodies):
  adr = []
  for name in bodies:
    b = mjm.body(name).id
    jnt = int(mjm.body_jntadr[b])
    assert jnt >= 0 and mjm.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE, f"{name} has no free joint"
    adr.append(int(mjm.jnt_qposadr[jnt]))
  return np.array(adr)


def _by_pair(geom: np.ndarray, pos: np.ndarray) -> dict:
  """{(g1, g2) with g1 < g2: (n, 3) positions}."""
  out = {}
  for g, p in zip(geom, pos):
    key = (int(min(g)), int(max(g)))
    out.setdefault(key, []).append(np.asarray(p, dtype=np.float64))
  return {k: np.array(v) for k, v in out.items()}


def _mujoco_runner(mjm):
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)

  def step():
    mujoco.mj_step(mjm, mjd)
    n = mjd.ncon
    return np.array(mjd.qpos), _by_pair(mjd.contact.geom[:n], mjd.contact.pos[:n])

  return np.array(mjd.qpos), step


def _warp_runner(mjm, plugin: bool):
  import mujoco_warp as mjw

  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  m = mjw.put_model(mjm)
  if plugin:
    from mjx_supportfield.driver import install

    install(mjm, m)
  ncon = 8 * mjm.ngeom + 16
  d = mjw.put_data(mjm, mjd, nworld=1, nconmax=ncon, njmax=6 * ncon)

  def step():
    mjw.step(m, d)
    n = min(int(d.nacon.numpy()[0]), d.naconmax)
    return d.qpos.numpy()[0].astype(np.float64), _by_pair(d.contact.geom.numpy()[:n], d.contact.pos.numpy()[:n])

  return np.array(mjd.qpos), step


def simulate(scene: str, engine: str, nstep: int, mjm: Optional[mujoco.MjModel] = None) -> Trajectory:
  """Steps ``scene`` ``nstep`` times with ``engine`` ("plugin", "mjw" or "mujoco")."""
  if engine not in ENGINES:
    raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
  mjm = mujoco.MjModel.from_xml_path(model_path(scene)) if mjm is None else mjm
  bodies = SCENES[scene][1]
  adr = _qpos_adr(mjm, bodies)
  qpos0, step = _mujoco_runner(mjm) if engine == "mujoco" else _warp_runner(mjm, engine == "plugin")
  qpos, contacts, times = [qpos0], [], [time.perf_counter()]
  for _ in range(nstep):
    q, c = step()
    qpos.append(q)
    contacts.append(c)
    times.append(time.perf_counter())
  qpos = np.array(qpos)
  pos = np.stack([qpos[:, a : a + 3] for a in adr], axis=1)
  quat = np.stack([qpos[:, a + 3 : a + 7] for a in adr], axis=1)
  quat /= np.linalg.norm(quat, axis=2, keepdims=True)
  return Trajectory(bodies, pos, quat, contacts, times[-1] - times[1], times[1] - times[0])


def _tilt_deg(quat: np.ndarray) -> np.ndarray:
  """Angle between the body z axis and the world z axis, for (..., 4) quaternions (w, x, y, z)."""
  x, y = quat[..., 1], quat[..., 2]
  return np.degrees(np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))


def contact_motion(contacts: list, start: int) -> dict:
  """Per geom pair over steps ``start``..end: the largest nearest-point move between consecutive
  steps (m), the step where it happened, how often the pair's contact count changed and how many
  times the pair (re)appeared."""
  out = {}
  for t in range(max(start, 1), len(contacts)):
    prev, cur = contacts[t - 1], contacts[t]
    for pair, pts in cur.items():
      rec = out.setdefault(pair, {"max_motion": 0.0, "step": None, "count_changes": 0, "appearances": 0})
      if pair not in prev:
        rec["appearances"] += 1
        continue
      old = prev[pair]
      if len(old) != len(pts):
        rec["count_changes"] += 1
      move = np.linalg.norm(pts[:, None, :] - old[None, :, :], axis=2).min(axis=1).max()
      if move > rec["max_motion"]:
        rec["max_motion"], rec["step"] = float(move), t + 1
  return out


def measure(traj: Trajectory, settle: int, geom_names: Optional[list] = None) -> dict:
  """Figures of a run after step ``settle`` (see the module doc): per body drift, final height and
  tilt; per geom pair contact motion; the stack check when the run has the STACK bodies."""
  if not 0 <= settle < len(traj.pos) - 1:
    raise ValueError(f"settle must be in [0, {len(traj.pos) - 2}], got {settle}")
  drift = np.linalg.norm(traj.pos[settle:] - traj.pos[settle], axis=2).max(axis=0)
  tilt = _tilt_deg(traj.quat[-1])
  bodies = {
    name: {"drift": float(drift[i]), "final_z": float(traj.pos[-1, i, 2]), "final_tilt_deg": float(tilt[i])}
    for i, name in enumerate(traj.bodies)
  }
  motion = contact_motion(traj.contacts, settle)
  if geom_names is not None:
    motion = {f"{geom_names[a]}-{geom_names[b]}": v for (a, b), v in motion.items()}
  else:
    motion = {f"{a}-{b}": v for (a, b), v in motion.items()}
  nstep = len(traj.pos) - 1
  out = {"bodies": bodies, "pairs": motion, "steps": nstep, "settle": settle,
         "ms_per_step": 1e3 * traj.seconds / max(nstep - 1, 1), "first_step_seconds": traj.first_seconds}
  if all(b in traj.bodies for b in STACK):
    out["stack"] = stack_check(traj)
  return out


def stack_check(traj: Trajectory) -> dict:
  """Whether the STACK bodies still stand at the end: worst horizontal and vertical displacement
  from the start, worst tilt, and the verdict against STAND_XY, STAND_Z, STAND_TILT."""
  idx = [traj.bodies.index(b) for b in STACK]
  delta = traj.pos[-1, idx] - traj.pos[0, idx]
  xy = float(np.linalg.norm(delta[:, :2], axis=1).max())
  z = float(np.abs(delta[:, 2]).max())
  tilt = float(_tilt_deg(traj.quat[-1, idx]).max())
  ok = bool(np.all(np.isfinite(traj.pos))) and xy < STAND_XY and z < STAND_Z and tilt < STAND_TILT
  return {"standing": ok, "max_xy": xy, "max_dz": z, "max_tilt_deg": tilt}
