"""Heightfield contact coverage: MuJoCo C's deep points on terrain and how many contacts a pair gets.

  python benchmarks/terrain_coverage.py [--scenes terrain,hfield,quadruped_terrain] [--json PATH]

For each scene MuJoCo C rolls the bodies out while they land (and, for the Go1, while it stands,
crouches and steps; benchmarks/fidelity.py's script), and on the sampled states and on squeezed
copies of them (free bodies moved 1-3 mm along gravity, fidelity.squeeze) the plugin (default
options) and stock MuJoCo Warp collide once. Only heightfield pairs are counted. A deep point is a
MuJoCo C contact at least MIN_DEPTH deep; it is missed when no contact of the same geom pair lies
within RADIUS (compare.py's rule). Per scene and per type of the geom on the terrain: C's deep
points, those missed by the plugin and by stock, and the contacts per touching pair (mean and
largest; a pair touches at a state when any of C, plugin or stock has a contact for it).

The JSON holds these counts and the plugin's missed points (state, pair, depth, position, MuJoCo
C's normal, distance to the nearest contact of the pair).

Scenes: ``terrain`` (models/terrain.xml: spheres, capsules, boxes, a cylinder, an ellipsoid and
two hulls dropped on a 48 x 48 heightfield), ``hfield`` (MuJoCo Warp's test_data hfield.xml: a
sphere dropped on a 3 x 3 bump, from its own start and from shifted ones so that it lands on
different slopes), ``quadruped_terrain`` (models/real/, mjlab's Go1).
"""

import argparse
import datetime
import json
import os
import sys
import time

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

import mujoco_warp as mjw  # noqa: E402
import warp as wp  # noqa: E402

import fidelity  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools.compare import mujoco_reference  # noqa: E402
from mjx_supportfield.tools.compare import warp_contacts  # noqa: E402

wp.config.quiet = True

MIN_DEPTH = 5e-4  # m: a MuJoCo C contact this deep is a deep point
RADIUS = 3e-3  # m: covered when a contact of the same pair lies this close
IMPLS = {"plugin": Options(), "stock": None}
TEST_DATA = os.path.join(os.path.dirname(mjw.__file__), "test_data")
HFIELD_STARTS = [(0.0, 0.1), (0.05, 0.0), (-0.3, 0.25), (0.4, -0.4), (0.2, 0.6), (-0.5, -0.1)]  # sphere x, y


def _free_xy_starts(mjm: mujoco.MjModel, starts) -> list[np.ndarray]:
  """qpos0 with the (single) free body placed at each (x, y) of starts."""
  out = []
  for x, y in starts:
    q = mjm.qpos0.copy()
    q[0:2] = (x, y)
    out.append(q)
  return out


def _rollout(mjm: mujoco.MjModel, qpos0: np.ndarray, nstep: int, control=None) -> np.ndarray:
  """MuJoCo C's qpos at every step from qpos0 (zero velocity)."""
  mjd = mujoco.MjData(mjm)
  if mjm.nkey:
    mujoco.mj_resetDataKeyframe(mjm, mjd, 0)
  mjd.qpos[:] = qpos0
  out = np.empty((nstep + 1, mjm.nq))
  for step in range(nstep + 1):
    out[step] = mjd.qpos
    if step < nstep:
      if control is not None:
        mjd.ctrl[:] = control(mjm, step * mjm.opt.timestep)
      mujoco.mj_step(mjm, mjd)
  return out


def terrain_states(nstates: int) -> tuple[mujoco.MjModel, list[np.ndarray]]:
  """models/terrain.xml: states over the first 0.5 s (the bodies fall, land, bounce and settle)."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "terrain.xml"))
  qpos = _rollout(mjm, mjm.qpos0.copy(), 250)
  at = np.linspace(40, 250, nstates).round().astype(int)  # from just before the first landing
  return mjm, [qpos[i] for i in at]


def hfield_states(nstates: int) -> tuple[mujoco.MjModel, list[np.ndarray]]:
  """test_data hfield.xml: the sphere dropped from each of HFIELD_STARTS, states over its
  landing and roll (0.2-0.6 s)."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(TEST_DATA, "hfield", "hfield.xml"))
  states = []
  per_start = max(1, nstates // len(HFIELD_STARTS))
  for q0 in _free_xy_starts(mjm, HFIELD_STARTS):
    qpos = _rollout(mjm, q0, 300)
    states += [qpos[i] for i in np.linspace(90, 300, per_start).round().astype(int)]
  return mjm, states


def quadruped_states(nstates: int) -> tuple[mujoco.MjModel, list[np.ndarray]]:
  """fidelity.py's quadruped_terrain scene: states evenly over its scripted rollout."""
  scene = fidelity.SCENES["quadruped_terrain"]
  mjm = fidelity.load("quadruped_terrain")
  nstep = int(round(scene.seconds / mjm.opt.timestep))
  qpos = _rollout(mjm, fidelity.initial_data(mjm).qpos.copy(), nstep, scene.control)
  return mjm, [qpos[i] for i in np.linspace(0, nstep, nstates).round().astype(int)]


SCENES = {"terrain": terrain_states, "hfield": hfield_states, "quadruped_terrain": quadruped_states}


def _type_name(mjm: mujoco.MjModel, g: int) -> str:
  return mujoco.mjtGeom(int(mjm.geom_type[g])).name.removeprefix("mjGEOM_").lower()


def _hfield_pairs(mjm: mujoco.MjModel, contacts) -> dict:
  """Contact positions per heightfield pair (heightfield geom, other geom)."""
  hfield = mjm.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD
  out = {}
  for c in contacts:
    g1, g2 = c.geom
    if hfield[g1] == hfield[g2]:
      continue
    key = (g1, g2) if hfield[g1] else (g2, g1)
    out.setdefault(key, []).append(np.asarray(c.pos, dtype=np.float64))
  return out


def measure(mjm: mujoco.MjModel, states: list[np.ndarray]) -> dict:
  """Deep points and contacts per pair on the heightfield pairs of ``states`` (module docstring)."""
  refs = [mujoco_reference(mjm, q).contacts for q in states]
  found = {name: warp_contacts(mjm, states, plugin=opts) for name, opts in IMPLS.items()}
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}" for g in range(mjm.ngeom)]
  by_type = {}
  missed_list = []
  for s, ref in enumerate(refs):
    pairs = {"mujoco": _hfield_pairs(mjm, ref), **{n: _hfield_pairs(mjm, found[n][s]) for n in IMPLS}}
    for c in ref:
      if c.dist > -MIN_DEPTH:
        continue
      key = next((k for k in pairs["mujoco"] if set(k) == set(c.geom)), None)
      if key is None:
        continue
      row = by_type.setdefault(_type_name(mjm, key[1]), _empty_row())
      row["deep_points"] += 1
      for n in IMPLS:
        near = pairs[n].get(key)
        dist = min(np.linalg.norm(p - c.pos) for p in near) if near else np.inf
        if not dist <= RADIUS:
          row[f"missed_{n}"] += 1
          if n == "plugin":  # stock's are counted only (they are many)
            missed_list.append({"state": s, "pair": f"{names[key[0]]}-{names[key[1]]}", "type": _type_name(mjm, key[1]),
                                "depth": round(-c.dist, 7), "pos": np.round(c.pos, 6).tolist(),
                                "normal": np.round(c.normal, 4).tolist(),
                                "nearest": None if np.isinf(dist) else round(float(dist), 6)})
    for key in set().union(*[set(p) for p in pairs.values()]):
      row = by_type.setdefault(_type_name(mjm, key[1]), _empty_row())
      row["pairs_touching"] += 1
      for n, p in pairs.items():
        count = len(p.get(key, ()))
        row[f"contacts_{n}"] += count
        row[f"max_contacts_{n}"] = max(row[f"max_contacts_{n}"], count)
  total = _empty_row()
  for row in by_type.values():
    for k, v in row.items():
      total[k] = max(total[k], v) if k.startswith("max_") else total[k] + v
  return {"states": len(states), "by_type": dict(sorted(by_type.items())), "all": total, "missed_plugin": missed_list}


def _empty_row() -> dict:
  row = {"deep_points": 0, "pairs_touching": 0}
  for n in ("mujoco", *IMPLS):
    row[f"contacts_{n}"] = 0
    row[f"max_contacts_{n}"] = 0
  for n in IMPLS:
    row[f"missed_{n}"] = 0
  return row


def _pct(missed: int, total: int) -> str:
  return f"{missed} ({100.0 * (1 - missed / total):.1f} %)" if total else f"{missed}"


def table(results: dict) -> str:
  """Markdown: per scene, state set and geom type, deep points covered and contacts per pair."""
  lines = ["| scene | states | geom | deep points (C) | missed (covered): plugin / stock | contacts a touching pair, "
           "mean (max): C / plugin / stock |", "|---|---|---|---|---|---|"]
  for scene, sets in results.items():
    for label, r in sets.items():
      for geom, row in [*r["by_type"].items(), ("all", r["all"])]:
        n = max(1, row["pairs_touching"])
        per = " / ".join(f"{row[f'contacts_{i}'] / n:.2f} ({row[f'max_contacts_{i}']})" for i in ("mujoco", *IMPLS))
        missed = " / ".join(_pct(row[f"missed_{i}"], row["deep_points"]) for i in IMPLS)
        lines.append(f"| {scene} | {label} | {geom} | {row['deep_points']} | {missed} | {per} |")
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated, of: " + ", ".join(SCENES))
  parser.add_argument("--states", type=int, default=30, help="sampled states a scene (and as many squeezed)")
  parser.add_argument("--json", default=os.path.join(HERE, "results",
                                                     f"{datetime.date.today()}-cpu-terrain-coverage.json"))
  args = parser.parse_args(argv)
  names = [s for s in args.scenes.split(",") if s]
  unknown = [s for s in names if s not in SCENES]
  if unknown:
    parser.error(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(SCENES)}")
  meta = {"date": str(datetime.date.today()), "commit": fidelity._commit(), "device": str(wp.get_device()),
          "mujoco": mujoco.__version__, "warp": wp.__version__, "min_depth": MIN_DEPTH, "radius": RADIUS,
          "states": args.states, "squeeze_m": [fidelity.SQUEEZE_MIN, fidelity.SQUEEZE_MAX]}
  results = {}
  for name in names:
    t = time.time()
    mjm, sampled = SCENES[name](args.states)
    squeezed = [fidelity.squeeze(mjm, q) for q in sampled]
    results[name] = {"sampled": measure(mjm, sampled), "squeezed": measure(mjm, squeezed)}
    print(f"{name}: {time.time() - t:.0f} s", flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
      json.dump({"meta": meta, "scenes": results}, f, indent=1)
  print(table(results))
  print(f"wrote {args.json}")


if __name__ == "__main__":
  main()
