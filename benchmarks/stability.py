"""Resting-contact stability of the plugin, stock MuJoCo Warp and MuJoCo C on the same scenes.

  python benchmarks/stability.py [--steps 2000] [--settle 200] [--engines plugin,mjw,mujoco]
                                 [--scenes resting,box_stack] [--json OUT]

Every engine steps the scene from its initial state (nworld=1 for MuJoCo Warp) and records, at
each step, the free bodies' positions and orientations (qpos) and the contacts (geom pair,
position). The figures, all over the window after settling (steps ``settle`` to ``steps``):

- drift: the largest distance of a body's origin from where it was at step ``settle``
  (max_t |p(t) - p(settle)|); slow creep and oscillation both count.
- contact motion: for each contact of a step, the distance to the nearest contact of the same
  geom pair in the step before; the largest over contacts, pairs and steps. A contact of a pair
  that had none the step before is counted as an appearance, not as motion.
- stack standing: every box still within 1 cm (horizontally and vertically) of where it
  started and tilted less than 2 degrees.

tests/test_stability.py imports ``simulate`` and ``measure`` from here, so the test and this
table measure the same thing.
"""

import argparse
import dataclasses
import json
import os
import platform
import time
from typing import Optional

import mujoco
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODELS = os.path.join(ROOT, "models")

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
    import mjx_supportfield

    mjx_supportfield.install(mjm, m)
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


def run(scenes, engines, nstep: int, settle: int, log=print) -> dict:
  """{scene: {engine: measure(...)}} for every scene and engine."""
  results = {}
  for scene in scenes:
    mjm = mujoco.MjModel.from_xml_path(model_path(scene))
    names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(mjm.ngeom)]
    for engine in engines:
      t0 = time.perf_counter()
      traj = simulate(scene, engine, nstep, mjm=mjm)
      res = measure(traj, settle, names)
      res["wall_seconds"] = time.perf_counter() - t0
      results.setdefault(scene, {})[engine] = res
      log(f"# {scene} / {engine}: {res['ms_per_step']:.2f} ms/step after the first, which took"
          f" {traj.first_seconds:.1f} s; {res['wall_seconds']:.1f} s in all")
  return results


def table(results: dict) -> str:
  """Markdown tables of run()'s results: bodies, geom pairs and the stack, per scene."""
  lines = []
  for scene, by_engine in results.items():
    engines = list(by_engine)
    lines += _body_rows(scene, by_engine, engines) + _pair_rows(scene, by_engine, engines)
    if "stack" in by_engine[engines[0]]:
      lines += _stack_rows(by_engine, engines)
    lines.append(f"\n* over the threshold (drift {MAX_DRIFT:g} m, contact motion {MAX_CONTACT_MOTION:g} m)")
    lines.append("ms per step (after the first): " + ", ".join(f"{e} {by_engine[e]['ms_per_step']:.2f}" for e in engines))
  return "\n".join(lines)


def _row(label, cells) -> str:
  return f"| {label} | " + " | ".join(cells) + " |"


def _body_rows(scene, by_engine, engines) -> list:
  lines = [f"\n{scene}: drift [m] after settling, final z [m], final tilt [deg] ({' / '.join(engines)})",
           _row("body", [f"{k} {e}" for k in ("drift", "z", "tilt") for e in engines]),
           "|---" * (1 + 3 * len(engines)) + "|"]
  for body in by_engine[engines[0]]["bodies"]:
    b = [by_engine[e]["bodies"][body] for e in engines]
    lines.append(_row(body, [_flag(x["drift"], MAX_DRIFT) for x in b] + [f"{x['final_z']:.5f}" for x in b]
                      + [f"{x['final_tilt_deg']:.3f}" for x in b]))
  return lines


def _pair_rows(scene, by_engine, engines) -> list:
  lines = [f"\n{scene}: max contact-point motion per step [m] (count changes, appearances)",
           _row("pair", engines), "|---" * (1 + len(engines)) + "|"]
  for pair in sorted({p for e in engines for p in by_engine[e]["pairs"]}):
    recs = [by_engine[e]["pairs"].get(pair) for e in engines]
    lines.append(_row(pair, ["-" if r is None else
                             f"{_flag(r['max_motion'], MAX_CONTACT_MOTION)} ({r['count_changes']}, {r['appearances']})"
                             for r in recs]))
  return lines


def _stack_rows(by_engine, engines) -> list:
  st = [by_engine[e]["stack"] for e in engines]
  return ["", _row("stack", engines), "|---" * (1 + len(engines)) + "|",
          _row("standing", ["yes" if s["standing"] else "NO" for s in st]),
          _row("max xy move [m]", [f"{s['max_xy']:.2e}" for s in st]),
          _row("max z move [m]", [f"{s['max_dz']:.2e}" for s in st]),
          _row("max tilt [deg]", [f"{s['max_tilt_deg']:.3f}" for s in st])]


def _flag(value: float, limit: float) -> str:
  return f"{value:.2e}" + ("*" if not value < limit else "")


def _csv(value: str, allowed) -> list:
  items = [x for x in value.split(",") if x]
  bad = [x for x in items if x not in allowed]
  if bad or not items:
    raise argparse.ArgumentTypeError(f"expected a comma-separated subset of {', '.join(allowed)}, got {value!r}")
  return items


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--steps", type=int, default=2000)
  p.add_argument("--settle", type=int, default=200, help="steps before drift and contact motion are measured")
  p.add_argument("--engines", type=lambda v: _csv(v, ENGINES), default=list(ENGINES))
  p.add_argument("--scenes", type=lambda v: _csv(v, SCENES), default=list(SCENES))
  p.add_argument("--json", metavar="OUT", help="write the results as JSON")
  args = p.parse_args(argv)
  if not 0 <= args.settle < args.steps:
    p.error(f"--settle must be in [0, --steps), got {args.settle}")
  if any(e != "mujoco" for e in args.engines):
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
  results = run(args.scenes, args.engines, args.steps, args.settle)
  print(table(results))
  if args.json:
    import mujoco_warp
    import warp as wp

    meta = {"steps": args.steps, "settle": args.settle, "mujoco": mujoco.__version__,
            "warp": wp.config.version, "mujoco_warp": getattr(mujoco_warp, "__version__", "?"),
            "device": str(wp.get_device()), "machine": platform.platform(),
            "thresholds": {"drift": MAX_DRIFT, "contact_motion": MAX_CONTACT_MOTION,
                           "stand_xy": STAND_XY, "stand_z": STAND_Z, "stand_tilt_deg": STAND_TILT}}
    with open(args.json, "w") as f:
      json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
  main()
