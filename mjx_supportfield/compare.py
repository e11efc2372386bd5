"""Contacts of the plugin and of stock MuJoCo Warp against MuJoCo C on the same states."""

import dataclasses
import json
import math
from typing import Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from mjx_supportfield.install import collision as plugin_collision
from mjx_supportfield.install import install
from mjx_supportfield.options import Options


@dataclasses.dataclass
class Contact:
  """One contact on the host, normal pointing from geom[0] to geom[1]."""

  geom: tuple
  dist: float
  pos: np.ndarray
  normal: np.ndarray


def sample_states(mjm: mujoco.MjModel, steps: int, samples: int) -> list[np.ndarray]:
  """qpos at ``samples`` evenly spaced times of a MuJoCo C rollout of ``steps`` steps."""
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  at = set(np.linspace(0, steps, samples).round().astype(int).tolist())
  states = []
  for i in range(steps + 1):
    if i in at:
      states.append(mjd.qpos.copy())
    if i < steps:
      mujoco.mj_step(mjm, mjd)
  return states


def mujoco_contacts(mjm: mujoco.MjModel, qpos: np.ndarray) -> list[Contact]:
  """MuJoCo C's contacts (mj_forward runs mj_collision) at one state."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  return [
    Contact((int(c.geom[0]), int(c.geom[1])), float(c.dist), np.array(c.pos), np.array(c.frame[:3]))
    for c in mjd.contact[: mjd.ncon]
  ]


def warp_contacts(mjm: mujoco.MjModel, states: list[np.ndarray], nworld: int, plugin: Optional[Options]) -> list[list[Contact]]:
  """Contacts per world from MuJoCo Warp, stock (plugin=None) or with the plugin installed.

  World w holds state w % len(states).
  """
  m = mjw.put_model(mjm)
  if plugin is not None:
    install(mjm, m, plugin)
  d = mjw.make_data(mjm, nworld=nworld, nconmax=max(64, 4 * mjm.ngeom))
  qpos = np.stack([states[w % len(states)] for w in range(nworld)]).astype(np.float32)
  wp.copy(d.qpos, wp.array(qpos, dtype=float, device=d.qpos.device))
  mjw.kinematics(m, d)
  if plugin is not None:
    plugin_collision(m, d)
    plugin_collision(m, d)  # the second call is warm-started from the first, as in a rollout
  else:
    mjw.collision(m, d)
  wp.synchronize()
  n = min(int(d.nacon.numpy()[0]), d.naconmax)
  c = d.contact
  geom, dist, pos = c.geom.numpy()[:n], c.dist.numpy()[:n], c.pos.numpy()[:n]
  frame, world = c.frame.numpy()[:n], c.worldid.numpy()[:n]
  out = [[] for _ in range(nworld)]
  for i in range(n):
    out[world[i]].append(Contact((int(geom[i][0]), int(geom[i][1])), float(dist[i]), pos[i], frame[i][0]))
  return out


def _deepest_by_pair(contacts: list[Contact]) -> dict:
  """Deepest contact per unordered geom pair, its normal oriented from the lower geom id."""
  best = {}
  for c in contacts:
    key = tuple(sorted(c.geom))
    normal = c.normal if c.geom[0] <= c.geom[1] else -c.normal
    if key not in best or c.dist < best[key].dist:
      best[key] = Contact(key, c.dist, c.pos, normal)
  return best


def _angle_deg(a, b) -> float:
  cos = float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30))
  return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def _count_by_pair(contacts: list[Contact]) -> dict:
  counts = {}
  for c in contacts:
    key = tuple(sorted(c.geom))
    counts[key] = counts.get(key, 0) + 1
  return counts


def match(reference: list[Contact], other: list[Contact], min_depth: float, geom_size: np.ndarray) -> dict:
  """Per-pair comparison of one state; pairs keyed by sorted geom ids.

  geom_size: a length per geom (its bounding diameter; 0 for planes and heightfields); the
  relative depth error divides by the smaller size of the pair's geoms that have one.
  """
  ref, oth = _deepest_by_pair(reference), _deepest_by_pair(other)
  nref, noth = _count_by_pair(reference), _count_by_pair(other)
  deep = {k for k, c in ref.items() if -c.dist >= min_depth}
  rows = []
  for key in sorted(set(ref) & set(oth)):
    r, o = ref[key], oth[key]
    sizes = [geom_size[g] for g in key if geom_size[g] > 0]
    rows.append({
      "pair": key,
      "contacts_reference": nref[key],
      "contacts": noth[key],
      "depth_error": abs(o.dist - r.dist),
      "depth_error_rel": abs(o.dist - r.dist) / min(sizes) if sizes else 0.0,
      "normal_angle_deg": _angle_deg(r.normal, o.normal),
      "position_error": float(np.linalg.norm(o.pos - r.pos)),
    })
  return {
    "pairs_reference": len(ref),
    "pairs_deep": len(deep),
    "found": len(set(ref) & set(oth)),
    "missed": sorted(set(ref) - set(oth)),
    "missed_deep": sorted(deep - set(oth)),
    "extra": sorted(set(oth) - set(ref)),
    "contacts_reference": len(reference),
    "contacts": len(other),
    "rows": rows,
  }


def _summary(per_state: list[dict]) -> dict:
  rows = [r for s in per_state for r in s["rows"]]

  def stat(key, fn):
    vals = [r[key] for r in rows]
    return float(fn(vals)) if vals else 0.0

  return {
    "pairs_reference": sum(s["pairs_reference"] for s in per_state),
    "pairs_deep": sum(s["pairs_deep"] for s in per_state),
    "found": sum(s["found"] for s in per_state),
    "missed": sum(len(s["missed"]) for s in per_state),
    "missed_deep": sum(len(s["missed_deep"]) for s in per_state),
    "extra": sum(len(s["extra"]) for s in per_state),
    "contacts_reference": sum(s["contacts_reference"] for s in per_state),
    "contacts": sum(s["contacts"] for s in per_state),
    "pairs_same_contact_count": sum(1 for r in rows if r["contacts"] == r["contacts_reference"]),
    "mean_contact_count_difference": float(np.mean([abs(r["contacts"] - r["contacts_reference"]) for r in rows]))
    if rows else 0.0,
    "median_depth_error": stat("depth_error", np.median),
    "median_depth_error_rel": stat("depth_error_rel", np.median),
    "max_depth_error": stat("depth_error", np.max),
    "median_normal_angle_deg": stat("normal_angle_deg", np.median),
    "pairs_normal_angle_over_5deg": sum(1 for r in rows if r["normal_angle_deg"] > 5.0),
    "max_normal_angle_deg": stat("normal_angle_deg", np.max),
    "median_position_error": stat("position_error", np.median),
    "max_position_error": stat("position_error", np.max),
  }


def compare(
  path: str, steps: int = 200, samples: int = 5, nworld: Optional[int] = None, min_depth: float = 5e-4,
  options: Optional[Options] = None
) -> dict:
  """Runs the comparison and returns the report (see ``format_report`` / the CLI)."""
  mjm = mujoco.MjModel.from_xml_path(path)
  states = sample_states(mjm, steps, samples)
  nworld = nworld or len(states)
  reference = [mujoco_contacts(mjm, q) for q in states]
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, i) or f"geom{i}" for i in range(mjm.ngeom)]
  unbounded = np.isin(mjm.geom_type, [mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_HFIELD])
  geom_size = np.where(unbounded, 0.0, 2.0 * mjm.geom_rbound)
  report = {"model": path, "steps": steps, "states": len(states), "nworld": nworld, "min_depth": min_depth,
            "device": str(wp.get_device()), "impls": {}}
  for impl, opts in (("plugin", options or Options()), ("stock", None)):
    worlds = warp_contacts(mjm, states, nworld, opts)
    per_state = [match(reference[w % len(states)], worlds[w], min_depth, geom_size) for w in range(nworld)]
    for s in per_state:
      for key in ("missed", "missed_deep", "extra"):
        s[key] = [f"{names[a]}-{names[b]}" for a, b in s[key]]
      for r in s["rows"]:
        r["pair"] = f"{names[r['pair'][0]]}-{names[r['pair'][1]]}"
    report["impls"][impl] = {"summary": _summary(per_state), "states": per_state}
  return report


def format_report(report: dict) -> str:
  """A table of the summary figures, plugin and stock side by side."""
  keys = [
    ("pairs_reference", "pairs in contact (MuJoCo C)", "d"),
    ("pairs_deep", f"  of which depth >= {report['min_depth']:g} m", "d"),
    ("found", "pairs found", "d"),
    ("missed", "pairs missed", "d"),
    ("missed_deep", "deep pairs missed", "d"),
    ("extra", "extra pairs", "d"),
    ("contacts_reference", "contacts (MuJoCo C)", "d"),
    ("contacts", "contacts", "d"),
    ("pairs_same_contact_count", "pairs with MuJoCo's contact count", "d"),
    ("mean_contact_count_difference", "mean |contact count difference|", ".2f"),
    ("median_depth_error", "median depth error [m]", ".2e"),
    ("median_depth_error_rel", "  relative to the smaller geom", ".2e"),
    ("max_depth_error", "max depth error [m]", ".2e"),
    ("median_normal_angle_deg", "median normal angle [deg]", ".3f"),
    ("max_normal_angle_deg", "max normal angle [deg]", ".3f"),
    ("pairs_normal_angle_over_5deg", "pairs with normal angle > 5 deg", "d"),
    ("median_position_error", "median position error [m]", ".2e"),
    ("max_position_error", "max position error [m]", ".2e"),
  ]
  p, s = report["impls"]["plugin"]["summary"], report["impls"]["stock"]["summary"]
  lines = [
    f"{report['model']}: {report['states']} states over {report['steps']} steps, {report['nworld']} worlds, "
    f"device {report['device']}",
    f"{'':32s} {'plugin':>12s} {'stock mjw':>12s}",
  ]
  for key, label, fmt in keys:
    lines.append(f"{label:32s} {format(p[key], fmt):>12s} {format(s[key], fmt):>12s}")
  missed = sorted({x for st in report["impls"]["plugin"]["states"] for x in st["missed_deep"]})
  if missed:
    lines.append("plugin missed deep pairs: " + ", ".join(missed))
  return "\n".join(lines)


def write_json(report: dict, path: str) -> None:
  """Writes the report as JSON."""
  with open(path, "w") as f:
    json.dump(report, f, indent=1, default=lambda x: x.tolist() if hasattr(x, "tolist") else str(x))
