"""Why the plugin misses MuJoCo C's deep contact points: each missed point, classified.

  python benchmarks/manifold_misses.py MODEL [MODEL ...] [--steps 200] [--samples 5] [--json OUT]

On the states ``compare`` samples, each of MuJoCo C's contact points deeper than --min-depth
with no contact of the plugin's for its pair within --radius is put in one class, from the
geometry of the pair along MuJoCo C's normal and along the plugin's (its deepest contact of the
pair), with MuJoCo C's face tolerance (``FACE_TOL``: faces within ~5° of each other, or of the
normal, count as aligned) and the plugin's face-clipping rules (faceclip.py):

- ``normal``: the plugin's normal is more than 10° from MuJoCo C's: another contact direction
  (an edge crossing instead of a face, another face), so other points.
- ``no face``: no flat face of either shape lies along the plugin's normal within FACE_TOL, so
  the pair took the tilts; MuJoCo C found faces facing each other along its own.
- ``budget``: a face pair along the plugin's normal, over faceclip.FACE_PAIR_BUDGET corners
  (reference x incident), so the pair took the tilts.
- ``other corners``: a face pair within the budget, clipped, and the corners kept were others
  than MuJoCo C's (which are its climb's quadrilateral of the clipped polygon, from the polygon's
  first corners), spanning at least NARROW x the area C's span: the same patch, other corners.
- ``narrower``: as above, but the plugin's points span less than NARROW x C's area.
- ``curved``: a shape with no flat face along either normal (a sphere, capsule side, ellipsoid).
- ``no contact``: the plugin has no contact of the pair at all.

Rows give the pair, depth, both normals' angle, the faces' corner counts and their angles, and
``split``: whether a flat face of the pair is split into coplanar hull polygons (within
SPLIT_DEG), of which MuJoCo C clips the one its EPA's features name and the plugin the one
around its support vertex.
"""

import argparse
import collections
import json
import math
import os
import sys

import mujoco
import numpy as np

from mjx_supportfield.geometry.faceclip import DISK_CORNERS
from mjx_supportfield.geometry.faceclip import FACE_PAIR_BUDGET
from mjx_supportfield.options import Options
from mjx_supportfield.tools import compare

FACE_TOL = 0.996  # MuJoCo's multi-CCD tolerance (engine_collision_gjk.h), as faceclip imports it
NORMAL_APART_DEG = 10.0
NARROW = 0.7  # a patch spanning less than this fraction of MuJoCo C's area is narrower
SPLIT_DEG = 0.5  # hull polygons this near to parallel are pieces of one flat face
_GEOM = mujoco.mjtGeom


def flat_face(mjm: mujoco.MjModel, g: int, xmat: np.ndarray, direction: np.ndarray):
  """(cos to direction, corner count) of geom g's flat face whose outward normal is nearest to
  ``direction`` (world), or None where g has no flat face (sphere, capsule, ellipsoid, plane)."""
  rot = xmat[g].reshape(3, 3)
  local = rot.T @ direction
  gtype = mjm.geom_type[g]
  if gtype == _GEOM.mjGEOM_BOX:
    return float(np.abs(local).max()), 4
  if gtype == _GEOM.mjGEOM_CYLINDER:
    return float(abs(local[2])), DISK_CORNERS
  if gtype == _GEOM.mjGEOM_MESH:
    mesh = mjm.geom_dataid[g]
    adr, num = mjm.mesh_polyadr[mesh], mjm.mesh_polynum[mesh]
    normals = mjm.mesh_polynormal[adr:adr + num].reshape(-1, 3)
    cos = normals @ local
    best = int(np.argmax(cos))
    return float(cos[best]), int(mjm.mesh_polyvertnum[adr + best])
  return None


def split_faces(mjm: mujoco.MjModel, g: int, xmat: np.ndarray, direction: np.ndarray) -> int:
  """How many of mesh g's hull polygons lie within SPLIT_DEG of facing ``direction``: more than
  one where MuJoCo left a flat face split into coplanar pieces (0 for other geom types)."""
  if mjm.geom_type[g] != _GEOM.mjGEOM_MESH:
    return 0
  mesh = mjm.geom_dataid[g]
  adr, num = mjm.mesh_polyadr[mesh], mjm.mesh_polynum[mesh]
  normals = mjm.mesh_polynormal[adr:adr + num].reshape(-1, 3) @ xmat[g].reshape(3, 3).T
  return int((normals @ direction > math.cos(math.radians(SPLIT_DEG))).sum())


def classify(mjm, ref: compare.Reference, pair, c_normal, p_normal) -> dict:
  """The class of a missed point of ``pair`` (sorted geoms), normals from pair[0] to pair[1]."""
  row = {}
  if p_normal is None:
    return {"class": "no contact"}
  angle = compare._angle_deg(c_normal, p_normal)
  row["normal_angle_deg"] = round(angle, 2)
  fa = flat_face(mjm, pair[0], ref.xmat, p_normal)
  fb = flat_face(mjm, pair[1], ref.xmat, -p_normal)
  ca = flat_face(mjm, pair[0], ref.xmat, c_normal)
  cb = flat_face(mjm, pair[1], ref.xmat, -c_normal)
  deg = lambda f: None if f is None else round(math.degrees(math.acos(min(1.0, f[0]))), 2)
  row.update(plugin_faces_deg=[deg(fa), deg(fb)], c_faces_deg=[deg(ca), deg(cb)],
             corners=[None if fa is None else fa[1], None if fb is None else fb[1]],
             split=max(split_faces(mjm, pair[0], ref.xmat, c_normal), split_faces(mjm, pair[1], ref.xmat, -c_normal)) > 1)
  if angle > NORMAL_APART_DEG:
    row["class"] = "normal"
  elif fa is None and fb is None:
    row["class"] = "curved"
  elif max(fa[0] if fa else -2.0, fb[0] if fb else -2.0) < FACE_TOL:
    row["class"] = "no face"
  else:
    # faceclip.face_pair: A's face is the reference where it lies along the normal
    ref_face, inc_face = (fa, fb) if fa is not None and fa[0] >= FACE_TOL else (fb, fa)
    inc_corners = inc_face[1] if inc_face is not None else 2
    row["class"] = "budget" if ref_face[1] * inc_corners > FACE_PAIR_BUDGET else "clipped"
  return row


def patch_area(points: np.ndarray, normal: np.ndarray) -> float:
  """Area of the convex hull of contact points seen along the normal."""
  if len(points) < 3:
    return 0.0
  u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
  u /= np.linalg.norm(u)
  v = np.cross(normal, u)
  xy = np.stack([points @ u, points @ v], 1)
  order = np.lexsort((xy[:, 1], xy[:, 0]))
  pts = [tuple(p) for p in xy[order]]
  cross = lambda o, a, b: (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
  lower, upper = [], []
  for p in pts:
    while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
      lower.pop()
    lower.append(p)
  for p in reversed(pts):
    while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
      upper.pop()
    upper.append(p)
  hull = np.array(lower[:-1] + upper[:-1])
  if len(hull) < 3:
    return 0.0
  x, y = hull[:, 0], hull[:, 1]
  return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def missed_points(path: str, steps: int, samples: int, min_depth: float, radius: float, options: Options) -> dict:
  """Every missed deep point of the plugin on ``path``'s sampled states, classified."""
  mjm = mujoco.MjModel.from_xml_path(path)
  states = compare.sample_states(mjm, steps, samples)
  plugin = compare.warp_contacts(mjm, states, plugin=options)
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}" for g in range(mjm.ngeom)]
  rows, total = [], 0
  for s, qpos in enumerate(states):
    ref = compare.mujoco_reference(mjm, qpos)
    positions = compare._positions_by_pair(plugin[s])
    deepest = compare._deepest_by_pair(plugin[s])
    for c in ref.contacts:
      if c.dist > -min_depth:
        continue
      total += 1
      pair = tuple(sorted(c.geom))
      nearest = compare._nearest(positions.get(pair), c.pos)
      if nearest <= radius:
        continue
      c_normal = c.normal if c.geom[0] <= c.geom[1] else -c.normal
      p_normal = deepest[pair].normal if pair in deepest else None
      row = {"state": s, "pair": f"{names[pair[0]]}-{names[pair[1]]}",
             "types": [int(mjm.geom_type[g]) for g in pair], "depth_mm": round(-c.dist * 1e3, 2),
             "nearest_mm": None if math.isinf(nearest) else round(nearest * 1e3, 1)}
      row.update(classify(mjm, ref, pair, c_normal, p_normal))
      if row["class"] == "clipped":
        c_points = np.array([x.pos for x in ref.contacts if tuple(sorted(x.geom)) == pair])
        c_area = patch_area(c_points, c_normal)
        ratio = patch_area(positions[pair], c_normal) / c_area if c_area > 0 else 1.0
        row["area_ratio"] = round(ratio, 2)
        row["class"] = "other corners" if ratio >= NARROW else "narrower"
      rows.append(row)
  return {"model": path, "deep_points": total, "missed": len(rows),
          "classes": dict(collections.Counter(r["class"] for r in rows).most_common()),
          "on_split_faces": sum(1 for r in rows if r.get("split")), "rows": rows}


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("models", nargs="+")
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--samples", type=int, default=5)
  parser.add_argument("--min-depth", type=float, default=5e-4)
  parser.add_argument("--radius", type=float, default=3e-3)
  parser.add_argument("--options", default="{}", help="plugin Options as a JSON object")
  parser.add_argument("--json", default=None)
  parser.add_argument("--rows", action="store_true", help="print every missed point")
  args = parser.parse_args(argv)
  options = Options(**json.loads(args.options))
  reports = []
  for path in args.models:
    r = missed_points(path, args.steps, args.samples, args.min_depth, args.radius, options)
    reports.append(r)
    print(f"{os.path.basename(path)}: {r['missed']} of {r['deep_points']} deep points missed: {r['classes']}, "
          f"{r['on_split_faces']} on a flat face MuJoCo left split into coplanar polygons")
    if args.rows:
      for row in r["rows"]:
        print("  ", row)
  if args.json:
    with open(args.json, "w") as f:
      json.dump(reports, f, indent=1)


if __name__ == "__main__":
  sys.exit(main())
