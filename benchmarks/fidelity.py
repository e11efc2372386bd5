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
3. ``mjx_supportfield.tools.compare.compare_states`` on both sets for each implementation: MuJoCo C's
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
5. The rollouts' penetration apart from their trajectories: each world's deepest (and its geom
   pair), their median, 90th percentile and largest over worlds (the largest is one rare
   impact's: an object toppled or pushed off the table in one world), the worlds that lost an
   object (off the table, out of the bin), and each implementation's deepest state replayed by
   MuJoCo C from the rollout's own states (qpos, qvel) ``REPLAY_STEPS`` before it. Where the
   replay sinks as deep, the depth came from how hard the bodies met, not from the
   implementation's contacts.

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
from typing import Optional

import mujoco
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import mujoco_warp as mjw  # noqa: E402
import warp as wp  # noqa: E402

import mjx_supportfield  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools.compare import compare_states  # noqa: E402
from scenelib.real_scenes import JITTER  # noqa: E402
from scenelib.real_scenes import MODELS  # noqa: E402
from scenelib.real_scenes import SCENES  # noqa: E402
from scenelib.real_scenes import SQUEEZE_MAX  # noqa: E402
from scenelib.real_scenes import SQUEEZE_MIN  # noqa: E402
from scenelib.real_scenes import Scene  # noqa: E402
from scenelib.real_scenes import control  # noqa: E402
from scenelib.real_scenes import deepest_penetration  # noqa: E402
from scenelib.real_scenes import fallen_through  # noqa: E402
from scenelib.real_scenes import free_bodies  # noqa: E402
from scenelib.real_scenes import initial_data  # noqa: E402
from scenelib.real_scenes import jittered  # noqa: E402
from scenelib.real_scenes import load  # noqa: E402
from scenelib.real_scenes import replay_mujoco  # noqa: E402
from scenelib.real_scenes import rollout_mujoco  # noqa: E402
from scenelib.real_scenes import squeeze  # noqa: E402
from scenelib.real_scenes import static_geoms  # noqa: E402

wp.config.quiet = True  # Warp's line per module loaded would drown the progress lines
if hasattr(wp.config, "log_level"):
  wp.config.log_level = wp.LOG_WARNING

RESULTS = os.path.join(ROOT, "benchmarks", "results")
RECORD_EVERY = 5  # steps between the rollout states judged by MuJoCo C's collision
# the deepest judged state is replayed by MuJoCo C from the implementation's own recorded states
# these many steps before it, to REPLAY_STEPS[-1] after: long enough for the approach to the
# impact, short enough that the replay's trajectory has not yet diverged from the rollout's. Two
# starts, because a body tumbling into another diverges within a few steps: a replay from 10 steps
# before can miss an impact that the one from 5 steps before meets as hard
REPLAY_STEPS = (RECORD_EVERY, 2 * RECORD_EVERY)
IMPLS = {"plugin": Options(), "plugin_gjk": Options(narrowphase="gjk"), "stock": None}


# ---------------------------------------------------------------------------------------------
# MuJoCo Warp


def rollout_warp(scene: Scene, mjm: mujoco.MjModel, opts: Optional[Options], qpos0: np.ndarray, nstep: int,
                 nconmax: int, njmax: int) -> dict:
  """Worlds rolled out through mjw.step (plugin installed unless opts is None) from the rows of
  qpos0 (nworld, nq), zero velocity; qpos and qvel every RECORD_EVERY steps and the last."""
  nworld = len(qpos0)
  m = mjw.put_model(mjm)
  if opts is not None:
    mjx_supportfield.install(mjm, m, opts)
  d = mjw.put_data(mjm, initial_data(mjm), nworld=nworld, nconmax=nconmax, njmax=njmax)
  wp.copy(d.qpos, wp.array(qpos0.astype(np.float32), dtype=float))
  records, velocities, overflow, max_nacon = {}, {}, 0, 0
  start = time.time()
  for step in range(nstep + 1):
    if step % RECORD_EVERY == 0 or step == nstep:
      records[step] = d.qpos.numpy().astype(np.float64)
      velocities[step] = d.qvel.numpy().astype(np.float64)
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
  return {"records": records, "velocities": velocities, "seconds": time.time() - start, "max_nacon": max_nacon,
          "naconmax": d.naconmax, "overflow": flags}


def judge_rollout(scene: Scene, mjm: mujoco.MjModel, records: dict, reference_final: np.ndarray) -> dict:
  """Penetration by MuJoCo C's collision on the recorded states, NaN worlds, fall-through,
  final free-body positions against MuJoCo C's (reference_final: (nworld, nq)) and the task."""
  mjd = mujoco.MjData(mjm)
  static = static_geoms(mjm)
  free = free_bodies(mjm)
  adr = [mjm.jnt_qposadr[mjm.body_jntadr[b]] for b in free]
  steps = sorted(records)
  nworld = records[steps[0]].shape[0]
  nan_worlds = set()
  deepest, deepest_at = 0.0, None
  per_state = []
  per_world = np.zeros(nworld)
  per_world_pair = [""] * nworld
  fell = set()
  for step in steps:
    for w in range(nworld):
      q = records[step][w]
      if not np.all(np.isfinite(q)):
        nan_worlds.add(w)
        continue
      depth, pair = deepest_penetration(mjm, mjd, q)
      per_state.append(depth)
      if depth > per_world[w]:
        per_world[w], per_world_pair[w] = depth, pair
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
    "max_penetration_per_world": per_world.tolist(),
    "max_penetration_pair_per_world": per_world_pair,
    "max_penetration_median_world": float(np.median(per_world)),
    "mean_deepest_penetration": float(np.mean(per_state)) if per_state else 0.0,
    "nan_worlds": len(nan_worlds),
    "fell_through": sorted(f"world {w}: {b}" for w, b in fell),
    "final_position_error_median": float(np.median(errors)) if errors else None,
    "final_position_error_max": float(np.max(errors)) if errors else None,
    "outcome": outcomes,
  }


def objects_lost(outcome: dict) -> Optional[bool]:
  """Whether a world's task figure lost an object: one off the table (arm_sweep: onto the floor)
  or out of the bin; None for scenes without such a count."""
  for kept in ("objects_on_table", "objects_in_bin"):
    if kept in outcome:
      return outcome[kept] < outcome["objects"]
  return None


def world_spread(judged: dict) -> dict:
  """The spread over worlds of a judge_rollout result: each world's deepest penetration's median,
  90th percentile and largest, and how many worlds lost an object (objects_lost; None where the
  scene counts none). The median alone hides the rare impact that sets the largest: an object
  knocked off the table in a few worlds."""
  per_world = np.asarray(judged["max_penetration_per_world"], dtype=float)
  if per_world.size == 0:
    raise ValueError("world_spread: judge_rollout result without worlds (max_penetration_per_world empty)")
  lost = [objects_lost(o) for o in judged["outcome"]]
  return {
    "max_penetration_median_world": float(np.median(per_world)),
    "max_penetration_p90_world": float(np.percentile(per_world, 90)),
    "max_penetration_max_world": float(per_world.max()),
    "worlds_object_lost": None if None in lost or not lost else int(sum(lost)),
  }


def replay_deepest(scene: Scene, mjm: mujoco.MjModel, run: dict, judged: dict, nstep: int) -> list[dict]:
  """MuJoCo C replaying an implementation's deepest judged state: from the rollout's recorded
  states (qpos and qvel) REPLAY_STEPS before it to REPLAY_STEPS[-1] after, judged every step; one
  entry a start. ``ratio`` is the rollout's deepest over the replay's: near 1 (or below) when
  MuJoCo C's contacts, put in the place of the implementation's for those steps, let the bodies
  sink as deep; well above 1 when the implementation's contacts resisted the impact less. Empty
  without a deepest state."""
  at = judged["max_penetration_at"]
  if at is None:
    return []
  out = []
  for before in REPLAY_STEPS:
    start = max(0, (at["step"] - before) // RECORD_EVERY * RECORD_EVERY)
    steps = min(nstep, at["step"] + REPLAY_STEPS[-1]) - start
    w = at["world"]
    rep = replay_mujoco(scene, mjm, run["records"][start][w], run["velocities"][start][w], start, steps)
    rep["from_step"] = start
    rep["ratio"] = judged["max_penetration"] / rep["max_penetration"] if rep["max_penetration"] > 0.0 else None
    out.append(rep)
  return out


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
    "timestep": mjm.opt.timestep, "ngeom": mjm.ngeom, "nmesh": mjm.nmesh, "free_bodies": len(free_bodies(mjm)),
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
  c_judged = judge_rollout(scene, mjm, c_records, finals)
  c_judged.update(world_spread(c_judged))
  out["rollouts"] = {"worlds": nworld, "record_every": RECORD_EVERY, "mujoco": c_judged}
  nconmax = max(64, 4 * int(ref["ncon"].max()))
  njmax = max(256, 4 * ref["max_nefc"])
  for impl, opts in IMPLS.items():
    t = time.time()
    _log(f"{name}: rollout, {impl}, {nworld} worlds x {nstep} steps")
    run = rollout_warp(scene, mjm, opts, starts, nstep, nconmax, njmax)
    judged = judge_rollout(scene, mjm, run["records"], finals)
    judged.update({"seconds": run["seconds"], "max_nacon": run["max_nacon"], "naconmax": run["naconmax"],
                   "overflow": run["overflow"]})
    judged.update(world_spread(judged))
    judged["deepest_replayed"] = replay_deepest(scene, mjm, run, judged, nstep)
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
    lines += _impact_rows(results, impls)
    lines += _spread_rows(results, impls)
  return "\n".join(lines)


def _replayed(judged: dict) -> str:
  """An implementation's deepest penetration and MuJoCo C's replay of it, short."""
  reps = judged.get("deepest_replayed")
  if not reps:
    return "–"
  at = judged["max_penetration_at"]
  return (f"{_mm(judged['max_penetration'])} → " + ", ".join(_mm(r["max_penetration"]) for r in reps)
          + f" (w{at['world']}, step {at['step']}, {at['pair']})")


def _impact_rows(results: dict, impls: list) -> list[str]:
  """The rollouts' penetration apart from the trajectory: the median over worlds of each world's
  deepest, and each implementation's deepest state replayed by MuJoCo C."""
  lines = [
    "",
    "| scene | deepest per world, median over worlds mm: C / plugin / gjk / stock | deepest, and MuJoCo C's replays "
    f"of it from {' and '.join(str(k) for k in REPLAY_STEPS)} steps before, mm: plugin / gjk / stock |",
    "|---|---|---|",
  ]
  for name, r in results.items():
    if "rollouts" not in r:
      continue
    ro = r["rollouts"]
    median = " / ".join(_mm(ro[i].get("max_penetration_median_world")) for i in ["mujoco"] + impls)
    replays = " / ".join(_replayed(ro[i]) for i in impls)
    lines.append(f"| {name} | {median} | {replays} |")
  return lines


def _spread_rows(results: dict, impls: list) -> list[str]:
  """Each world's deepest penetration over the worlds (world_spread), a row an implementation;
  results written before world_spread have the median only."""
  lines = [
    "",
    "| scene | rolled out by | deepest per world, median mm | 90th percentile mm | max mm | "
    "worlds that lost an object |",
    "|---|---|---|---|---|---|",
  ]
  names = {"mujoco": "MuJoCo C", "plugin": "plugin", "plugin_gjk": "plugin gjk", "stock": "stock"}
  for name, r in results.items():
    if "rollouts" not in r:
      continue
    ro = r["rollouts"]
    for i in ["mujoco"] + impls:
      lost = ro[i].get("worlds_object_lost")
      lost = "–" if lost is None else f"{lost} of {ro['worlds']}"
      lines.append(f"| {name} | {names.get(i, i)} | {_mm(ro[i].get('max_penetration_median_world'))} | "
                   f"{_mm(ro[i].get('max_penetration_p90_world'))} | {_mm(ro[i].get('max_penetration_max_world'))} | "
                   f"{lost} |")
  return lines


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


# robosuite's arms as shipped (benchmarks/robosuite_arms.py): built in its cache on first use, as
# robosuite's visual meshes are too large for the repository; not in the default --scenes
ROBOSUITE_SCENES = tuple(f"robosuite_{arm}" for arm in ("panda", "ur5e", "sawyer"))
ROBOSUITE_SECONDS = 1.0  # the arm slumps onto the table and the objects under zero torques


def add_robosuite_scenes() -> None:
  """Registers the robosuite scenes with real_scenes (their MJCF files live in the cache)."""
  sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
  import robosuite_arms

  for arm, path in robosuite_arms.write_scenes().items():
    SCENES[f"robosuite_{arm}"] = Scene(path, ROBOSUITE_SECONDS, None, robosuite_arms.objects_on_table,
                                       f"robosuite's {arm} arm with its hand, as shipped (visual meshes kept), "
                                       "slumping onto a table with a can, a milk carton and a cereal box")


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--scenes", default=",".join(SCENES),
                      help="comma-separated, of: " + ", ".join([*SCENES, *ROBOSUITE_SCENES]))
  parser.add_argument("--states", type=int, default=20, help="states sampled from MuJoCo C's rollout (and as many squeezed)")
  parser.add_argument("--worlds", type=int, default=3, help="worlds of the mjw.step rollouts")
  parser.add_argument("--json", default=os.path.join(RESULTS, f"{datetime.date.today()}-cpu-fidelity.json"))
  parser.add_argument("--no-rollout", action="store_true", help="contacts on states only")
  args = parser.parse_args(argv)
  names = [s for s in args.scenes.split(",") if s]
  unknown = [s for s in names if s not in SCENES and s not in ROBOSUITE_SCENES]
  if unknown:
    parser.error(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join([*SCENES, *ROBOSUITE_SCENES])}")
  if any(s in ROBOSUITE_SCENES for s in names):
    add_robosuite_scenes()
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
