"""Contacts of the plugin and of stock MuJoCo Warp against MuJoCo C on the same states.

MuJoCo C is a reference, not ground truth. Besides pair-level agreement (pairs found, depth,
normal angle, position), ``compare_states`` measures fidelity with exact float64 geometry on
MuJoCo C's poses (exact.py):
- deep points: each of MuJoCo C's contact points at least ``min_depth`` deep should have a
  contact of the same geom pair within ``radius`` (manifold completeness);
- normals: where a pair's deepest-contact normal differs from MuJoCo C's by more than
  ``NORMAL_DIFFER_DEG``, the exact overlap of the two convex shapes along each normal decides
  which is the better separating direction (the smaller overlap);
- points on shapes: a contact point should lie within |dist| / 2 + ``OUTSIDE_SLACK`` of both
  of its geoms.
Heightfield pairs are not convex: their normals are not adjudicated (counted as skipped); their
deep points are counted. Pairs with a geom the plugin collides as a non-convex mesh are not
comparable with MuJoCo C, which collides that mesh's convex hull: they are kept out of the
deep-point and normal counts (reported apart) and judged by points on the true mesh only.
"""

import dataclasses
import json
import math
from typing import Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src.types import OverflowType

from mjx_supportfield.driver import collision as plugin_collision
from mjx_supportfield.driver import install
from mjx_supportfield.options import Options
from mjx_supportfield.stages.nonconvex import nonconvex_geom_ids
from mjx_supportfield.tools import exact
from mjx_supportfield.tools.model_file import load_model

NORMAL_DIFFER_DEG = 1.0  # normals closer than this to MuJoCo C's are not adjudicated
NORMAL_FAR_DEG = 5.0  # a normal this far off and worse than MuJoCo C's fails the check
TIE_REL = 1e-6  # overlaps within TIE_REL x the pair's size + TIE_ABS are a tie: float32 normals
TIE_ABS = 1e-7  # and float32 contact data cannot resolve finer
OUTSIDE_SLACK = 1e-3  # a contact point may lie |dist| / 2 + this outside each of its geoms
MAX_MISSED_FRACTION = 0.02  # --check: at most this fraction of MuJoCo C's deep points missed
NONCONVEX_LABEL = "MuJoCo C collides this mesh's convex hull"
HFIELD_LABEL = "heightfield: not convex, no exact overlap"


@dataclasses.dataclass
class Contact:
  """One contact on the host, normal pointing from geom[0] to geom[1]."""

  geom: tuple
  dist: float
  pos: np.ndarray
  normal: np.ndarray


@dataclasses.dataclass
class Reference:
  """MuJoCo C at one state: its contacts and every geom's float64 pose."""

  contacts: list
  xpos: np.ndarray  # (ngeom, 3)
  xmat: np.ndarray  # (ngeom, 3, 3)


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


def mujoco_reference(mjm: mujoco.MjModel, qpos: np.ndarray) -> Reference:
  """MuJoCo C's contacts (mj_forward runs mj_collision) and geom poses at one state."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  contacts = [
    Contact((int(c.geom[0]), int(c.geom[1])), float(c.dist), np.array(c.pos), np.array(c.frame[:3]))
    for c in mjd.contact[: mjd.ncon]
  ]
  return Reference(contacts, mjd.geom_xpos.copy(), mjd.geom_xmat.reshape(-1, 3, 3).copy())


def mujoco_contacts(mjm: mujoco.MjModel, qpos: np.ndarray) -> list[Contact]:
  """MuJoCo C's contacts at one state."""
  return mujoco_reference(mjm, qpos).contacts


def warp_contacts(mjm: mujoco.MjModel, states: list[np.ndarray], nworld: Optional[int] = None,
                  plugin: Optional[Options] = None) -> list[list[Contact]]:
  """Contacts per world from MuJoCo Warp, stock (plugin=None) or with the plugin installed.

  World w holds state w % len(states); nworld defaults to one world per state.
  """
  nworld = nworld or len(states)
  qpos = np.stack([states[w % len(states)] for w in range(nworld)]).astype(np.float32)
  nconmax = max(64, 4 * mjm.ngeom)
  d, n = _collide(mjm, qpos, plugin, nconmax)
  if _overflowed(d, n):  # MuJoCo Warp counts what it had no room for: rerun with room for all
    need = max(n, int(d.ncollision.numpy()[0]))
    d, n = _collide(mjm, qpos, plugin, max(2 * nconmax, -(-need // nworld) + nconmax))
  if _overflowed(d, n):
    flags = int(np.bitwise_or.reduce(d.overflow.numpy()))
    names = [t.name for t in OverflowType if t.value and t.name != "ALL" and flags & t.value]
    raise RuntimeError(f"warp_contacts: buffers overflowed ({', '.join(names) or 'contacts'}) after a rerun with "
                       f"room for {d.naconmax} contacts; with the plugin, raise Options.max_collision_pairs")
  c = d.contact
  geom, dist, pos = c.geom.numpy()[:n], c.dist.numpy()[:n], c.pos.numpy()[:n]
  frame, world = c.frame.numpy()[:n], c.worldid.numpy()[:n]
  out = [[] for _ in range(nworld)]
  for i in range(n):
    out[world[i]].append(Contact((int(geom[i][0]), int(geom[i][1])), float(dist[i]), pos[i], frame[i][0]))
  return out


def _overflowed(d, n: int) -> bool:
  """Whether a collision pass dropped pairs or contacts for want of room (stock MuJoCo Warp
  counts the broad phase's pairs past its room in d.ncollision)."""
  return n > d.naconmax or int(d.ncollision.numpy()[0]) > d.naconmax or bool(d.overflow.numpy().any())


def _collide(mjm: mujoco.MjModel, qpos: np.ndarray, plugin: Optional[Options], nconmax: int):
  """MuJoCo Warp's Data after collision at the given qpos (one world a row) and the number of
  contacts it found (more than d.naconmax when they did not fit)."""
  m = mjw.put_model(mjm)
  if plugin is not None:
    install(mjm, m, plugin)
  d = mjw.make_data(mjm, nworld=len(qpos), nconmax=nconmax)
  wp.copy(d.qpos, wp.array(qpos, dtype=float, device=d.qpos.device))
  mjw.kinematics(m, d)
  if plugin is not None:
    plugin_collision(m, d)
    plugin_collision(m, d)  # the second call is warm-started from the first, as in a rollout
  else:
    mjw.collision(m, d)
  wp.synchronize()
  return d, int(d.nacon.numpy()[0])


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


def _positions_by_pair(contacts: list[Contact]) -> dict:
  """Contact positions (k, 3) per unordered geom pair."""
  grouped = {}
  for c in contacts:
    grouped.setdefault(tuple(sorted(c.geom)), []).append(c.pos)
  return {k: np.asarray(v, dtype=np.float64) for k, v in grouped.items()}


def _nearest(positions: Optional[np.ndarray], p: np.ndarray) -> float:
  """Distance from p to the nearest of ``positions`` (inf when there are none)."""
  if positions is None or not len(positions):
    return math.inf
  return float(np.sqrt(((positions - p) ** 2).sum(axis=1).min()))


def match(reference: list[Contact], other: list[Contact], min_depth: float, geom_size: np.ndarray) -> dict:
  """Per-pair comparison of one state; pairs keyed by sorted geom ids.

  geom_size: a length per geom (its bounding diameter; 0 for planes and heightfields); the
  relative depth error divides by the smaller size of the pair's geoms that have one. Depth
  and normal compare the pairs' deepest contacts; position error is, for each of the
  reference's contacts, the distance to the nearest contact of the same pair (so that equally
  deep points are not paired crosswise): ``position_errors`` per point, ``position_error``
  their largest.
  """
  ref, oth = _deepest_by_pair(reference), _deepest_by_pair(other)
  ref_pos, oth_pos = _positions_by_pair(reference), _positions_by_pair(other)
  deep = {k for k, c in ref.items() if -c.dist >= min_depth}
  rows = []
  for key in sorted(set(ref) & set(oth)):
    r, o = ref[key], oth[key]
    sizes = [geom_size[g] for g in key if geom_size[g] > 0]
    errors = [_nearest(oth_pos[key], p) for p in ref_pos[key]]
    rows.append({
      "pair": key,
      "contacts_reference": len(ref_pos[key]),
      "contacts": len(oth_pos[key]),
      "depth_error": abs(o.dist - r.dist),
      "depth_error_rel": abs(o.dist - r.dist) / min(sizes) if sizes else 0.0,
      "normal_angle_deg": _angle_deg(r.normal, o.normal),
      "position_error": max(errors),
      "position_errors": errors,
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


# ---------------------------------------------------------------------------------------------
# fidelity with exact geometry


@dataclasses.dataclass
class _Scene:
  """What the fidelity metrics need to know about the model, computed once."""

  mjm: mujoco.MjModel
  names: list
  size: np.ndarray  # bounding diameter per geom, 0 for planes and heightfields
  hfield: set  # heightfield geom ids
  steepest: dict  # heightfield geom id -> steepest_facet_nz
  nonconvex: set  # geoms some plugin implementation collides as non-convex meshes
  min_depth: float
  radius: float

  def label(self, pair) -> str:
    return f"{self.names[pair[0]]}-{self.names[pair[1]]}"

  def kind(self, pair) -> str:
    """'nonconvex', 'hfield' or 'convex': how a pair is judged."""
    if self.nonconvex & set(pair):
      return "nonconvex"
    if self.hfield & set(pair):
      return "hfield"
    return "convex"


def deep_points(scene: _Scene, ref: Reference, contacts: list[Contact]) -> list[dict]:
  """MuJoCo C's contact points at least min_depth deep, each with the distance to the nearest
  contact of the same (unordered) pair in ``contacts``; missed when farther than radius. A
  missed heightfield point that is not an inner wall's carries ``prism_answered``
  (_prism_answered)."""
  positions = _positions_by_pair(contacts)
  rows = []
  for c in ref.contacts:
    if c.dist > -scene.min_depth:
      continue
    pair = tuple(sorted(c.geom))
    nearest = _nearest(positions.get(pair), c.pos)
    row = {"pair": scene.label(pair), "geoms": pair, "kind": scene.kind(pair), "dist": c.dist,
           "pos": c.pos.tolist(), "nearest": None if math.isinf(nearest) else nearest,
           "missed": not nearest <= scene.radius, "inner_wall": _inner_wall(scene, ref, c)}
    if row["missed"] and row["kind"] == "hfield" and not row["inner_wall"]:
      row["prism_answered"] = _prism_answered(scene, ref, c, contacts)
    rows.append(row)
  return rows


def _triangle_of(scene: _Scene, ref: Reference, g: int, pos: np.ndarray) -> Optional[tuple[int, int, int]]:
  """Heightfield geom g's triangle whose prism's column holds world point ``pos``
  (exact.hfield_triangle_at), or None off the grid."""
  local = ref.xmat[g].T @ (np.asarray(pos, dtype=np.float64) - ref.xpos[g])
  return exact.hfield_triangle_at(scene.mjm, int(scene.mjm.geom_dataid[g]), local)


def _prism_answered(scene: _Scene, ref: Reference, c: Contact, contacts: list[Contact]) -> bool:
  """Whether MuJoCo C's heightfield contact ``c`` is answered on its own prism: MuJoCo C writes
  one contact a triangle's prism, at EPA's witness, which on a face lying on the triangle can end
  anywhere on their overlap. The prism is answered when a contact of the same pair in
  ``contacts`` lies over the same triangle with a normal whose exact overlap of the geom and the
  (convex) prism is no larger than along MuJoCo C's normal."""
  g = c.geom[0] if c.geom[0] in scene.hfield else c.geom[1]
  other = c.geom[1] if g == c.geom[0] else c.geom[0]
  triangle = _triangle_of(scene, ref, g, c.pos)
  if triangle is None or other in scene.hfield:
    return False
  row, col, t = triangle
  local = exact.hfield_prisms(scene.mjm, int(scene.mjm.geom_dataid[g]), row, row + 1, col, col + 1)[t]
  prism = ref.xpos[g] + local @ ref.xmat[g].T

  def overlap(contact: Contact) -> float:  # along the normal from the terrain into the geom
    n = np.asarray(contact.normal, dtype=np.float64) * (1.0 if contact.geom[0] == g else -1.0)
    n /= np.linalg.norm(n)
    return float((prism @ n).max()) + exact.support(scene.mjm, other, ref.xpos[other], ref.xmat[other], -n)

  bound = overlap(c) + TIE_REL * scene.size[other] + TIE_ABS
  pair = tuple(sorted(c.geom))
  return any(tuple(sorted(o.geom)) == pair and _triangle_of(scene, ref, g, o.pos) == triangle and overlap(o) <= bound
             for o in contacts)


# a heightfield contact normal steeper than the grid's steepest facet by this much (its z in the
# terrain's frame) is a prism's side wall
WALL_NZ = 1e-3


def steepest_facet_nz(mjm: mujoco.MjModel, g: int) -> float:
  """The smallest z component (in the terrain's frame) of the normals of heightfield geom ``g``'s
  triangles, as MuJoCo splits each cell: no point of the terrain's surface has a steeper normal."""
  data = int(mjm.geom_dataid[g])
  nrow, ncol = int(mjm.hfield_nrow[data]), int(mjm.hfield_ncol[data])
  size = mjm.hfield_size[data]
  adr = int(mjm.hfield_adr[data])
  z = np.asarray(mjm.hfield_data[adr:adr + nrow * ncol], dtype=float).reshape(nrow, ncol) * size[2]
  dx, dy = 2.0 * size[0] / (ncol - 1), 2.0 * size[1] / (nrow - 1)
  z00, z01, z10, z11 = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
  # (p00, p10, p11) and (p00, p11, p01): each triangle's slope along x and y
  slopes = [((z11 - z10) / dx, (z10 - z00) / dy), ((z01 - z00) / dx, (z11 - z01) / dy)]
  return float(min((1.0 / np.sqrt(1.0 + gx * gx + gy * gy)).min() for gx, gy in slopes))


def _inner_wall(scene: _Scene, ref: Reference, c: Contact) -> bool:
  """Whether MuJoCo C's heightfield contact ``c`` is a side wall's of a prism inside the grid: its
  normal steeper (in the terrain's frame) than every triangle of the grid, its point a cell or
  more from the outer edge. The terrain's surface has no such normal anywhere (a heightfield is a
  graph over its grid): C's penetration of a prism left through a wall, or EPA ended tilted
  toward one (its answer for a geom sunk past a steep facet), and those walls lie inside the
  solid, between two prisms; only the outer ones bound it."""
  hf = [g for g in c.geom if g in scene.hfield]
  if not hf:
    return False
  g = hf[0]
  rot = ref.xmat[g]
  nz = float(np.dot(rot[:, 2], c.normal)) * (1.0 if c.geom[0] == g else -1.0)  # out of the terrain
  if nz >= scene.steepest[g] - WALL_NZ:
    return False
  data = int(scene.mjm.geom_dataid[g])
  size = scene.mjm.hfield_size[data]
  cell = 2.0 * size[:2] / (np.array([scene.mjm.hfield_ncol[data], scene.mjm.hfield_nrow[data]]) - 1)
  local = rot.T @ (np.asarray(c.pos) - ref.xpos[g])
  return bool(np.all(np.abs(local[:2]) <= size[:2] - cell))


def adjudicate_normals(scene: _Scene, ref: Reference, contacts: list[Contact]) -> list[dict]:
  """Pairs found by both whose deepest-contact normals differ by more than NORMAL_DIFFER_DEG,
  with the exact overlap along each normal (on MuJoCo C's poses) and a verdict: 'better',
  'worse' or 'tie' for the implementation's normal against MuJoCo C's, or 'skipped' with a
  reason for heightfield and non-convex pairs."""
  mine, theirs = _deepest_by_pair(contacts), _deepest_by_pair(ref.contacts)
  rows = []
  for pair in sorted(set(mine) & set(theirs)):
    r, o = theirs[pair], mine[pair]
    angle = _angle_deg(r.normal, o.normal)
    if angle <= NORMAL_DIFFER_DEG:
      continue
    row = {"pair": scene.label(pair), "geoms": pair, "angle_deg": angle, "dist_reference": r.dist, "dist": o.dist,
           "normal_reference": r.normal.tolist(), "normal": np.asarray(o.normal, dtype=np.float64).tolist()}
    kind = scene.kind(pair)
    if kind != "convex":
      rows.append({**row, "verdict": "skipped", "kind": kind,
                   "reason": NONCONVEX_LABEL if kind == "nonconvex" else HFIELD_LABEL})
      continue
    g1, g2 = pair
    ov_ref = exact.overlap_along(scene.mjm, g1, g2, ref.xpos, ref.xmat, r.normal)
    ov = exact.overlap_along(scene.mjm, g1, g2, ref.xpos, ref.xmat, o.normal)
    tol = TIE_REL * max(scene.size[g1], scene.size[g2]) + TIE_ABS
    if ov == ov_ref or abs(ov - ov_ref) <= tol:  # the first test: both infinite
      verdict = "tie"
    else:
      verdict = "worse" if ov > ov_ref else "better"
    rows.append({**row, "verdict": verdict, "kind": kind, "overlap_reference": ov_ref, "overlap": ov})
  return rows


def points_off_shapes(scene: _Scene, ref: Reference, contacts: list[Contact], true_mesh: set) -> dict:
  """How far each contact point lies outside its two geoms (MuJoCo C's poses): the meshes in
  ``true_mesh`` by their own triangles, others by their convex hull. A point is off its shapes
  when farther than |dist| / 2 + OUTSIDE_SLACK outside either geom."""
  worst, off = 0.0, []
  for c in contacts:
    far = [exact.distance_outside(scene.mjm, g, ref.xpos[g], ref.xmat[g], c.pos, hull=g not in true_mesh)
           for g in c.geom]
    worst = max(worst, *far)
    allowed = 0.5 * abs(c.dist) + OUTSIDE_SLACK
    if max(far) > allowed:
      pair = tuple(sorted(c.geom))
      off.append({"pair": scene.label(pair), "geoms": c.geom, "kind": scene.kind(pair), "dist": c.dist,
                  "pos": np.asarray(c.pos, dtype=np.float64).tolist(), "outside": far, "allowed": allowed})
  return {"checked": len(contacts), "max_outside": worst, "off": off}


def _fidelity_summary(per_state: list[dict]) -> dict:
  """The fidelity counts over all states (see compare_states)."""
  deep = [dict(r, world=s["world"], state=s["state"]) for s in per_state for r in s["deep_points"]]
  normals = [dict(r, world=s["world"], state=s["state"]) for s in per_state for r in s["normals"]]
  off = [dict(r, world=s["world"], state=s["state"]) for s in per_state for r in s["outside"]["off"]]

  def count(rows, kind=None, missed=None):
    return sum(1 for r in rows if (kind is None or r["kind"] in kind) and (missed is None or r["missed"] == missed))

  judged = [r for r in normals if r["verdict"] != "skipped"]
  far = [r for r in judged if r["angle_deg"] > NORMAL_FAR_DEG]
  counted = ("convex", "hfield")
  nref, nmissed = count(deep, counted), count(deep, counted, True)
  # pairs whose normal is far from MuJoCo C's and better by exact overlap: there C's points lie
  # on another feature, and a "missed" point says more about C than about the implementation
  c_worse = {(r["world"], r["state"], tuple(r["geoms"])) for r in far if r["verdict"] == "better"}
  return {
    "deep_points_reference": nref,
    "deep_points_missed": nmissed,
    "deep_points_missed_reference_worse": sum(
      1 for r in deep if r["missed"] and r["kind"] in counted and (r["world"], r["state"], tuple(r["geoms"])) in c_worse),
    "deep_points_missed_fraction": nmissed / nref if nref else 0.0,
    "deep_points_reference_hfield": count(deep, ("hfield",)),
    "deep_points_missed_hfield": count(deep, ("hfield",), True),
    # MuJoCo C's points whose normal is an inner prism wall's: no normal of the terrain's surface
    "deep_points_missed_hfield_inner_wall": sum(1 for r in deep if r["missed"] and r.get("inner_wall")),
    # the rest of those missed whose prism has a contact over it with a normal as good (exact overlap)
    "deep_points_missed_hfield_prism_answered": sum(1 for r in deep if r["missed"] and r.get("prism_answered")),
    "deep_points_reference_nonconvex": count(deep, ("nonconvex",)),
    "deep_points_missed_nonconvex": count(deep, ("nonconvex",), True),
    "normals_differ": len(judged),
    "normals_better": sum(1 for r in judged if r["verdict"] == "better"),
    "normals_tie": sum(1 for r in judged if r["verdict"] == "tie"),
    "normals_worse": sum(1 for r in judged if r["verdict"] == "worse"),
    "pairs_normal_over_5deg": len(far),
    "pairs_normal_worse": sum(1 for r in far if r["verdict"] == "worse"),
    "normals_skipped_hfield": sum(1 for r in normals if r["verdict"] == "skipped" and r["kind"] == "hfield"),
    "normals_skipped_nonconvex": sum(1 for r in normals if r["verdict"] == "skipped" and r["kind"] == "nonconvex"),
    "contacts_checked": sum(s["outside"]["checked"] for s in per_state),
    "contacts_outside": len(off),
    "max_outside": max((s["outside"]["max_outside"] for s in per_state), default=0.0),
    "deep_points_missed_list": [r for r in deep if r["missed"]],
    "normals_over_5deg_list": far,
    "contacts_outside_list": off,
  }


def _pair_summary(per_state: list[dict]) -> dict:
  rows = [r for s in per_state for r in s["rows"]]

  def stat(values, fn):
    return float(fn(values)) if len(values) else 0.0

  position_errors = [e for r in rows for e in r["position_errors"]]
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
    "mean_contact_count_difference": stat([abs(r["contacts"] - r["contacts_reference"]) for r in rows], np.mean),
    "median_depth_error": stat([r["depth_error"] for r in rows], np.median),
    "median_depth_error_rel": stat([r["depth_error_rel"] for r in rows], np.median),
    "max_depth_error": stat([r["depth_error"] for r in rows], np.max),
    "median_normal_angle_deg": stat([r["normal_angle_deg"] for r in rows], np.median),
    "pairs_normal_angle_over_5deg": sum(1 for r in rows if r["normal_angle_deg"] > NORMAL_FAR_DEG),
    "max_normal_angle_deg": stat([r["normal_angle_deg"] for r in rows], np.max),
    "median_position_error": stat(position_errors, np.median),
    "max_position_error": stat(position_errors, np.max),
  }


def collision_geoms(mjm: mujoco.MjModel) -> int:
  """Geoms that can collide: contype or conaffinity set, or named in an explicit <pair>."""
  can = (mjm.geom_contype != 0) | (mjm.geom_conaffinity != 0)
  if mjm.npair:
    can[mjm.pair_geom1] = True
    can[mjm.pair_geom2] = True
  return int(can.sum())


def _scene(mjm: mujoco.MjModel, impls: dict, min_depth: float, radius: float) -> _Scene:
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, i) or f"geom{i}" for i in range(mjm.ngeom)]
  unbounded = np.isin(mjm.geom_type, [mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_HFIELD])
  hfield = set(np.flatnonzero(mjm.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD).tolist())
  nonconvex = set(nonconvex_geom_ids(mjm, ()))  # the model's own marker
  for opts in impls.values():
    if opts is not None:
      nonconvex |= set(nonconvex_geom_ids(mjm, opts.nonconvex_geoms))
  steepest = {g: steepest_facet_nz(mjm, g) for g in hfield}
  return _Scene(mjm, names, np.where(unbounded, 0.0, 2.0 * mjm.geom_rbound), hfield, steepest, nonconvex, min_depth,
                radius)


def compare_states(mjm: mujoco.MjModel, states: list[np.ndarray], impls: dict, min_depth: float = 5e-4,
                   radius: float = 3e-3, nworld: Optional[int] = None) -> dict:
  """Compares implementations' contacts with MuJoCo C's on the given states (qpos arrays).

  impls maps a name to plugin ``Options`` or None (stock MuJoCo Warp); world w holds state
  w % len(states) (nworld defaults to one world per state). Returns ``{"states", "nworld",
  "min_depth", "radius", "device", "nonconvex_geoms", "reference", "impls": {name: {"summary",
  "states"}}}``. Each summary holds the pair-level figures of ``match`` (pairs_reference, found,
  missed, missed_deep, depth/normal/position errors, ...) and the fidelity figures:
  deep_points_reference / _missed / _missed_fraction (MuJoCo C's points >= min_depth deep
  without a contact of their pair within radius; heightfield pairs included, also counted
  apart as ..._hfield, and of those missed the ones whose MuJoCo C normal is an inner prism
  wall's as ..._hfield_inner_wall, the others answered over their own prism by as good a normal
  as ..._hfield_prism_answered; pairs with a non-convex mesh only in ..._nonconvex), normals_differ /
  _better / _tie / _worse (verdicts by exact overlap where the deepest normals differ by more
  than NORMAL_DIFFER_DEG), pairs_normal_over_5deg, pairs_normal_worse (over 5 deg and worse),
  normals_skipped_hfield / _nonconvex, contacts_checked, contacts_outside, max_outside [m],
  and the lists deep_points_missed_list, normals_over_5deg_list, contacts_outside_list (each
  row naming its world and state). Each entry of "states" (one per world) holds match's rows
  and the detail lists deep_points, normals, outside. ``reference`` judges MuJoCo C's own
  points against its shapes.
  """
  if not states:
    raise ValueError("compare_states: no states given")
  for name, opts in impls.items():
    if opts is not None and not isinstance(opts, Options):
      raise ValueError(f"compare_states: impls['{name}'] must be Options or None (stock), got {type(opts).__name__}")
  if collision_geoms(mjm) == 0:
    raise ValueError("the model has no collision geoms (every geom has contype = conaffinity = 0 and no <pair> "
                     "names one): there are no contacts to compare")
  scene = _scene(mjm, impls, min_depth, radius)
  nworld = nworld or len(states)
  refs = [mujoco_reference(mjm, q) for q in states]
  reference = {"contacts_checked": 0, "contacts_outside": 0, "max_outside": 0.0, "contacts_outside_list": []}
  for i, ref in enumerate(refs):
    own = points_off_shapes(scene, ref, ref.contacts, set())
    reference["contacts_checked"] += own["checked"]
    reference["contacts_outside"] += len(own["off"])
    reference["max_outside"] = max(reference["max_outside"], own["max_outside"])
    reference["contacts_outside_list"] += [dict(r, state=i) for r in own["off"]]
  report = {"states": len(states), "nworld": nworld, "min_depth": min_depth, "radius": radius,
            "device": str(wp.get_device()), "nonconvex_geoms": [scene.names[g] for g in sorted(scene.nonconvex)],
            "reference": reference, "impls": {}}
  for name, opts in impls.items():
    true_mesh = set(nonconvex_geom_ids(mjm, opts.nonconvex_geoms)) if opts is not None else set()
    worlds = warp_contacts(mjm, states, nworld, opts)
    per_state = []
    for w in range(nworld):
      ref = refs[w % len(states)]
      s = {"world": w, "state": w % len(states), **match(ref.contacts, worlds[w], min_depth, scene.size)}
      s["deep_points"] = deep_points(scene, ref, worlds[w])
      s["normals"] = adjudicate_normals(scene, ref, worlds[w])
      s["outside"] = points_off_shapes(scene, ref, worlds[w], true_mesh)
      per_state.append(s)
    summary = {**_pair_summary(per_state), **_fidelity_summary(per_state)}
    for s in per_state:
      for key in ("missed", "missed_deep", "extra"):
        s[key] = [scene.label(p) for p in s[key]]
      for r in s["rows"]:
        r["pair"] = scene.label(r["pair"])
    report["impls"][name] = {"summary": summary, "states": per_state}
  return report


def check(report: dict, impl: str = "plugin") -> list[str]:
  """Why ``impl`` fails issue #20's rules on this report (empty when it passes): more than
  MAX_MISSED_FRACTION of MuJoCo C's deep points missed, any normal more than NORMAL_FAR_DEG off
  and worse than MuJoCo C's by exact overlap, any contact off its shapes."""
  s = report["impls"][impl]["summary"]
  reasons = []
  if s["deep_points_missed"] > MAX_MISSED_FRACTION * s["deep_points_reference"]:
    reasons.append(f"{s['deep_points_missed']} of {s['deep_points_reference']} deep points missed "
                   f"(more than {MAX_MISSED_FRACTION:.0%})")
  if s["pairs_normal_worse"]:
    reasons.append(f"{s['pairs_normal_worse']} normals > {NORMAL_FAR_DEG:g} deg off and worse than MuJoCo C's")
  if s["contacts_outside"]:
    reasons.append(f"{s['contacts_outside']} contacts off their shapes (max {s['max_outside'] * 1e3:.2f} mm outside)")
  return reasons


def compare(
  path: str, steps: int = 200, samples: int = 5, nworld: Optional[int] = None, min_depth: float = 5e-4,
  options: Optional[Options] = None, radius: float = 3e-3
) -> dict:
  """Runs the comparison of the plugin (``options``) and stock MuJoCo Warp on states of a
  MuJoCo C rollout of the model at ``path`` and returns the report (see ``format_report``)."""
  mjm = load_model(path)
  if collision_geoms(mjm) == 0:
    raise ValueError(f"{path}: the model has no collision geoms (every geom has contype = conaffinity = 0 and no "
                     "<pair> names one): there are no contacts to compare")
  states = sample_states(mjm, steps, samples)
  impls = {"plugin": options or Options(), "stock": None}
  report = compare_states(mjm, states, impls, min_depth=min_depth, radius=radius, nworld=nworld)
  return {"model": path, "steps": steps, **report}


_IMPL_LABELS = {"plugin": "plugin", "stock": "stock mjw"}

_ROWS = [
  ("pairs_reference", "pairs in contact (MuJoCo C)", "d"),
  ("pairs_deep", "  of which depth >= {min_depth:g} m", "d"),
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
  ("deep_points_reference", "deep points (MuJoCo C)", "d"),
  ("deep_points_missed", "  missed (none within {radius_mm:g} mm)", "d"),
  ("deep_points_missed_reference_worse", "    on pairs where MuJoCo C's normal is > 5 deg off and worse", "d"),
  ("deep_points_reference_hfield", "  of which on heightfields", "d"),
  ("deep_points_missed_hfield", "    missed", "d"),
  ("deep_points_missed_hfield_inner_wall", "      of which MuJoCo C's normal an inner prism wall's", "d"),
  ("deep_points_missed_hfield_prism_answered", "      else answered over the same prism, as good a normal", "d"),
  ("deep_points_reference_nonconvex", "deep points, non-convex meshes", "d"),
  ("deep_points_missed_nonconvex", "  missed (not counted)", "d"),
  ("normals_differ", "normals > 1 deg off, adjudicated", "d"),
  ("normals_better", "  better than MuJoCo C's", "d"),
  ("normals_tie", "  as good", "d"),
  ("normals_worse", "  worse", "d"),
  ("pairs_normal_over_5deg", "normals > 5 deg off", "d"),
  ("pairs_normal_worse", "  and worse than MuJoCo C's", "d"),
  ("normals_skipped_hfield", "normals not adjudicated: heightfield", "d"),
  ("normals_skipped_nonconvex", "normals not adjudicated: non-convex", "d"),
  ("contacts_checked", "contacts checked against shapes", "d"),
  ("contacts_outside", "  off their shapes", "d"),
  ("max_outside", "  max distance outside a geom [m]", ".2e"),
]
_OPTIONAL_ROWS = {"deep_points_reference_hfield", "deep_points_missed_hfield", "deep_points_missed_hfield_inner_wall",
                  "deep_points_missed_hfield_prism_answered",
                  "deep_points_reference_nonconvex",
                  "deep_points_missed_nonconvex", "normals_skipped_hfield", "normals_skipped_nonconvex"}
LEGEND = ("deep point: a MuJoCo C contact >= min depth deep, missed when no contact of its pair lies within the radius; "
          "normal verdicts: exact overlap of the convex shapes along each normal on MuJoCo C's poses, the smaller is "
          "better; off its shapes: a point more than |dist|/2 + 1 mm outside either geom")


def verdict(report: dict, impl: str = "plugin", baseline: str = "stock") -> str:
  """One line: deep points missed (and the baseline's), worse normals, points off the shapes,
  and whether ``impl`` passes ``check``."""
  s = report["impls"][impl]["summary"]
  if s["contacts_reference"] == 0 and s["contacts"] == 0:
    return f"{impl}: MuJoCo C and {impl} find no contacts in these states: nothing to judge"
  base = report["impls"].get(baseline, {}).get("summary")
  stock = f" ({baseline} {base['deep_points_missed']})" if base else ""
  reasons = check(report, impl)
  if s.get("deep_points_missed_reference_worse"):
    stock += f", {s['deep_points_missed_reference_worse']} of them on pairs where MuJoCo C's normal is the worse one"
  if s["deep_points_reference_nonconvex"]:
    stock += f", {s['deep_points_reference_nonconvex']} more on non-convex meshes not counted"
  return (f"{impl}: {s['deep_points_missed']} deep points missed of {s['deep_points_reference']}{stock}; "
          f"{s['pairs_normal_worse']} worse normals; {s['contacts_outside']} points off the shapes: "
          + ("passes" if not reasons else "fails: " + "; ".join(reasons)))


def format_report(report: dict) -> str:
  """A table of the summary figures, one column per implementation, a legend and a verdict."""
  impls = list(report["impls"])
  summaries = [report["impls"][k]["summary"] for k in impls]
  fill = {"min_depth": report["min_depth"], "radius_mm": report.get("radius", 3e-3) * 1e3}
  head = f"{report.get('model', 'states')}: {report['states']} states"
  if "steps" in report:
    head += f" over {report['steps']} steps"
  lines = [f"{head}, {report['nworld']} worlds, device {report['device']}",
           f"{'':38s} " + " ".join(f"{_IMPL_LABELS.get(k, k):>12s}" for k in impls)]
  for key, label, fmt in _ROWS:
    if key in _OPTIONAL_ROWS and not any(s[key] for s in summaries):
      continue
    lines.append(f"{label.format(**fill):38s} " + " ".join(f"{format(s[key], fmt):>12s}" for s in summaries))
  ref = report.get("reference")
  if ref and ref["contacts_outside"]:
    lines.append(f"MuJoCo C's own contacts off their shapes: {ref['contacts_outside']} of {ref['contacts_checked']} "
                 f"(max {ref['max_outside'] * 1e3:.2f} mm)")
  if report.get("nonconvex_geoms"):
    lines.append(f"non-convex meshes ({NONCONVEX_LABEL}): " + ", ".join(report["nonconvex_geoms"]))
  main = impls[0]
  missed = sorted({x for st in report["impls"][main]["states"] for x in st["missed_deep"]})
  if missed:
    lines.append(f"{main} missed deep pairs: " + ", ".join(missed))
  for r in report["impls"][main]["summary"]["normals_over_5deg_list"]:
    if r["verdict"] == "worse":
      lines.append(f"{main} worse normal: state {r['state']} {r['pair']} {r['angle_deg']:.1f} deg off, overlap "
                   f"{r['overlap'] * 1e3:.3f} mm vs MuJoCo C's {r['overlap_reference'] * 1e3:.3f} mm")
  lines.append("legend: " + LEGEND)
  lines.append(verdict(report, main))
  return "\n".join(lines)


def write_json(report: dict, path: str) -> None:
  """Writes the report as JSON."""
  with open(path, "w") as f:
    json.dump(report, f, indent=1, default=lambda x: x.tolist() if hasattr(x, "tolist") else str(x))
