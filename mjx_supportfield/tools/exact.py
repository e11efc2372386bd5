"""Exact geometry of MuJoCo's collision shapes in float64 numpy, on the host (no Warp).

The yardstick ``compare`` judges contacts with: support functions, the overlap of two convex
shapes along a normal, and the distance of a point outside a shape. Poses are a geom's world
position ``xpos`` (3,) and rotation ``xmat`` (3, 3) as MuJoCo C's ``MjData.geom_xpos`` /
``geom_xmat`` give them (a mesh's offset already included, so mesh vertices are in the geom
frame; MuJoCo stores them in float32, which bounds how exact a mesh's answers are). A mesh is its convex hull, as MuJoCo C collides it (``mesh_graph``), unless asked for
its true triangles. A plane is the half-space below it (its local z <= 0). A heightfield is the
union of MuJoCo's triangular prisms (two per grid cell, down to ``-size[3]``): not convex, so
it has a distance but no support function.
"""

import math
import weakref
from typing import Optional

import mujoco
import numpy as np

from mjx_supportfield.geometry.hull_graph import hull_graph

PLANE_NORMAL_COS = 1.0 - 1e-8  # a direction within ~1.4e-4 rad of a plane's normal is taken as it
ELLIPSOID_BISECTIONS = 200  # halvings of the Lagrange multiplier's bracket: float64 converges long before
ON_FACE = 1e-9  # a point this close to a polytope's face (relative to its size) is on it
DEGENERATE_AREA = 1e-12  # hull triangles with area below this times the hull's size squared are dropped

_GEOM = mujoco.mjtGeom


class NotConvexError(ValueError):
  """Raised for a geom without a support function (a heightfield): callers skip such pairs."""


def geom_poses(mjm: mujoco.MjModel, qpos: np.ndarray, mjd: mujoco.MjData = None) -> tuple[np.ndarray, np.ndarray]:
  """Every geom's float64 world pose at ``qpos`` (mj_kinematics): xpos (ngeom, 3), xmat (ngeom, 3, 3)."""
  mjd = mjd or mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_kinematics(mjm, mjd)
  return mjd.geom_xpos.copy(), mjd.geom_xmat.reshape(-1, 3, 3).copy()


# ---------------------------------------------------------------------------------------------
# mesh hulls and triangles, cached per model and mesh


class Polytope:
  """A convex polytope in its own frame: vertices, triangles and their outward planes."""

  def __init__(self, verts: np.ndarray, tris: np.ndarray):
    self.verts = np.asarray(verts, dtype=np.float64)
    scale = max(float(np.ptp(self.verts, axis=0).max()), 1e-30)
    a, b, c = (self.verts[tris[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    area2 = np.linalg.norm(normal, axis=1)
    keep = area2 > 2.0 * DEGENERATE_AREA * scale * scale
    normal = normal[keep] / area2[keep, None]
    a, b, c = a[keep], b[keep], c[keep]
    # outward: the centroid of a convex polytope's vertices lies inside it
    inward = np.einsum("ij,ij->i", normal, self.verts.mean(axis=0) - a) > 0
    normal[inward] *= -1.0
    self.tri = np.stack([a, b, c], axis=1)  # (nface, 3 corners, xyz)
    self.normal = normal
    self.offset = np.einsum("ij,ij->i", normal, a)
    self.on_face = ON_FACE * scale

  def distance(self, p: np.ndarray) -> float:
    """Distance of point p (own frame) outside the polytope; 0 inside (to within ON_FACE of
    its size: a point on a face is inside whatever the rounding). Outside, the nearest of all
    its triangles: picking only the faces p is above would drop the right triangle of a face
    split into coplanar triangles when rounding puts p under that triangle's plane."""
    if float((self.normal @ p - self.offset).max()) <= self.on_face:
      return 0.0
    t = self.tri
    return float(np.sqrt(_point_triangle_dist2(p, t[:, 0], t[:, 1], t[:, 2]).min()))


class TriangleMesh:
  """A closed triangle mesh in its own frame (not necessarily convex)."""

  def __init__(self, verts: np.ndarray, tris: np.ndarray):
    self.tri = np.asarray(verts, dtype=np.float64)[tris]  # (nface, 3, 3)

  def distance(self, p: np.ndarray) -> float:
    """Distance of point p outside the mesh; 0 inside (winding number > 1/2)."""
    if abs(_winding_number(p, self.tri)) > 0.5:  # either orientation
      return 0.0
    t = self.tri
    return float(np.sqrt(_point_triangle_dist2(p, t[:, 0], t[:, 1], t[:, 2]).min()))


_CACHE = weakref.WeakKeyDictionary()  # model -> {("hull" | "mesh", meshid): shape}


def _cached(mjm: mujoco.MjModel, key, build):
  per_model = _CACHE.setdefault(mjm, {})
  if key not in per_model:
    per_model[key] = build()
  return per_model[key]


def mesh_vertices(mjm: mujoco.MjModel, meshid: int) -> np.ndarray:
  """All of a mesh's vertices (mesh frame = geom frame), float64 (nvert, 3)."""
  adr, num = int(mjm.mesh_vertadr[meshid]), int(mjm.mesh_vertnum[meshid])
  return np.asarray(mjm.mesh_vert[adr : adr + num], dtype=np.float64)


def hull_faces(mjm: mujoco.MjModel, meshid: int) -> tuple[np.ndarray, np.ndarray]:
  """MuJoCo's convex hull of a mesh: (hull vertex ids, triangles as mesh vertex ids (nface, 3)).

  From ``mesh_graph`` (see hull_graph); a mesh without a graph gets its hull from scipy.
  """
  graph = hull_graph(mjm, meshid)
  if graph is None:
    from scipy.spatial import ConvexHull  # only for meshes MuJoCo built no hull for

    hull = ConvexHull(mesh_vertices(mjm, meshid))
    return np.asarray(hull.vertices), np.asarray(hull.simplices)
  return graph.vert, graph.faces


def mesh_hull(mjm: mujoco.MjModel, meshid: int) -> Polytope:
  """The mesh's convex hull as MuJoCo C collides it (cached per model)."""

  def build():
    _, faces = hull_faces(mjm, meshid)
    return Polytope(mesh_vertices(mjm, meshid), faces)

  return _cached(mjm, ("hull", meshid), build)


def mesh_surface(mjm: mujoco.MjModel, meshid: int) -> TriangleMesh:
  """The mesh's own triangles (cached per model)."""

  def build():
    adr, num = int(mjm.mesh_faceadr[meshid]), int(mjm.mesh_facenum[meshid])
    tris = np.asarray(mjm.mesh_face[adr : adr + num]).reshape(-1, 3)
    return TriangleMesh(mesh_vertices(mjm, meshid), tris)

  return _cached(mjm, ("mesh", meshid), build)


def _hull_vertices(mjm: mujoco.MjModel, meshid: int) -> np.ndarray:
  return _cached(mjm, ("hullvert", meshid), lambda: mesh_vertices(mjm, meshid)[hull_faces(mjm, meshid)[0]])


# ---------------------------------------------------------------------------------------------
# support and overlap


def _check_geom(mjm: mujoco.MjModel, g: int) -> int:
  if not 0 <= g < mjm.ngeom:
    raise ValueError(f"geom id {g} out of range (the model has {mjm.ngeom} geoms)")
  return int(mjm.geom_type[g])


def support(mjm: mujoco.MjModel, g: int, xpos, xmat, direction) -> float:
  """h(d) = max over geom g's convex shape of x.d (d need not be unit), exact, float64.

  A plane's half-space gives +inf unless d points along its normal. NotConvexError for a
  heightfield.
  """
  gtype = _check_geom(mjm, g)
  d = np.asarray(direction, dtype=np.float64)
  xpos, xmat = np.asarray(xpos, dtype=np.float64), np.asarray(xmat, dtype=np.float64).reshape(3, 3)
  local = xmat.T @ d
  size = mjm.geom_size[g].astype(np.float64)
  centre = float(xpos @ d)
  norm = float(np.linalg.norm(d))
  if gtype == _GEOM.mjGEOM_SPHERE:
    return centre + size[0] * norm
  if gtype == _GEOM.mjGEOM_CAPSULE:
    return centre + size[1] * abs(local[2]) + size[0] * norm
  if gtype == _GEOM.mjGEOM_ELLIPSOID:
    return centre + float(np.linalg.norm(size * local))
  if gtype == _GEOM.mjGEOM_CYLINDER:
    return centre + size[0] * math.hypot(local[0], local[1]) + size[1] * abs(local[2])
  if gtype == _GEOM.mjGEOM_BOX:
    return centre + float(np.abs(size * local).sum())
  if gtype == _GEOM.mjGEOM_MESH:
    return centre + float((_hull_vertices(mjm, int(mjm.geom_dataid[g])) @ local).max())
  if gtype == _GEOM.mjGEOM_PLANE:
    # sup of x.d over {x: (x - xpos).n <= 0} is xpos.d when d = s n, s >= 0, else unbounded
    if norm == 0.0 or local[2] >= PLANE_NORMAL_COS * norm:
      return centre
    return math.inf
  if gtype == _GEOM.mjGEOM_HFIELD:
    raise NotConvexError(f"geom {g} is a heightfield: not convex, it has no support function")
  raise ValueError(f"geom {g}: no support function for geom type {gtype}")


def overlap_along(mjm: mujoco.MjModel, g1: int, g2: int, xpos, xmat, normal) -> float:
  """Exact overlap of geoms g1 and g2 along ``normal``: h1(n) + h2(-n), n unit, pointing from g1
  to g2 (MuJoCo's contact frame[0]: from geom[0] to geom[1]).

  The overlap is the depth the pair would need to separate along n: of two candidate normals
  the smaller overlap is the better separating direction (negative: separated along n by that
  much). xpos (ngeom, 3) and xmat (ngeom, 3, 3) or (ngeom, 9) are every geom's pose. A plane
  only has its own normal (from the plane into the other geom); any other direction gives
  +inf. NotConvexError when either geom is a heightfield.
  """
  n = np.asarray(normal, dtype=np.float64)
  norm = float(np.linalg.norm(n))
  if not math.isfinite(norm) or norm == 0.0:
    raise ValueError(f"overlap_along: normal {normal} is not a nonzero finite vector")
  n = n / norm
  xpos, xmat = np.asarray(xpos, dtype=np.float64), np.asarray(xmat, dtype=np.float64).reshape(-1, 3, 3)
  return support(mjm, g1, xpos[g1], xmat[g1], n) + support(mjm, g2, xpos[g2], xmat[g2], -n)


# ---------------------------------------------------------------------------------------------
# distance of a point outside a shape


def distance_outside(mjm: mujoco.MjModel, g: int, xpos, xmat, point, hull: bool = True):
  """Euclidean distance of ``point`` (3,) outside geom g (0 inside), exact, float64; (N, 3)
  points give an (N,) array.

  Meshes: their convex hull (``hull=True``, as MuJoCo C collides them) or their true
  triangles (``hull=False``, inside by winding number). Planes: the height above the plane.
  Heightfields: the distance to the union of MuJoCo's cell prisms.
  """
  p = np.asarray(point, dtype=np.float64)
  if p.ndim == 2:
    return np.array([distance_outside(mjm, g, xpos, xmat, q, hull) for q in p])
  gtype = _check_geom(mjm, g)
  xmat = np.asarray(xmat, dtype=np.float64).reshape(3, 3)
  local = xmat.T @ (p - np.asarray(xpos, dtype=np.float64))
  size = mjm.geom_size[g].astype(np.float64)
  if gtype == _GEOM.mjGEOM_SPHERE:
    return max(float(np.linalg.norm(local)) - size[0], 0.0)
  if gtype == _GEOM.mjGEOM_CAPSULE:
    axis = np.array([0.0, 0.0, min(max(local[2], -size[1]), size[1])])
    return max(float(np.linalg.norm(local - axis)) - size[0], 0.0)
  if gtype == _GEOM.mjGEOM_ELLIPSOID:
    return ellipsoid_distance(size, local)
  if gtype == _GEOM.mjGEOM_CYLINDER:
    radial = max(math.hypot(local[0], local[1]) - size[0], 0.0)
    axial = max(abs(local[2]) - size[1], 0.0)
    return math.hypot(radial, axial)
  if gtype == _GEOM.mjGEOM_BOX:
    return float(np.linalg.norm(np.maximum(np.abs(local) - size, 0.0)))
  if gtype == _GEOM.mjGEOM_MESH:
    meshid = int(mjm.geom_dataid[g])
    return (mesh_hull(mjm, meshid) if hull else mesh_surface(mjm, meshid)).distance(local)
  if gtype == _GEOM.mjGEOM_PLANE:
    return max(float(local[2]), 0.0)
  if gtype == _GEOM.mjGEOM_HFIELD:
    return hfield_distance(mjm, int(mjm.geom_dataid[g]), local)
  raise ValueError(f"geom {g}: no distance for geom type {gtype}")


def ellipsoid_distance(radii: np.ndarray, p: np.ndarray) -> float:
  """Distance of p outside the axis-aligned ellipsoid with semi-axes ``radii``; 0 inside.

  The nearest point is x_i = r_i^2 p_i / (r_i^2 + t) with t > 0 the root of
  sum (r_i p_i / (r_i^2 + t))^2 = 1, a decreasing function of t: bisection in [0, max r |p|].
  """
  r2 = radii * radii
  if float(((p / radii) ** 2).sum()) <= 1.0:
    return 0.0
  lo, hi = 0.0, float(radii.max() * np.linalg.norm(p))
  for _ in range(ELLIPSOID_BISECTIONS):
    mid = 0.5 * (lo + hi)
    if mid in (lo, hi):
      break
    if float(((radii * p / (r2 + mid)) ** 2).sum()) > 1.0:
      lo = mid
    else:
      hi = mid
  nearest = r2 * p / (r2 + 0.5 * (lo + hi))
  return float(np.linalg.norm(p - nearest))


def hfield_elevations(mjm: mujoco.MjModel, hid: int) -> np.ndarray:
  """Heightfield hid's elevation data in [0, 1], (nrow, ncol), row r at y = -size[1] + r dy."""
  nrow, ncol, adr = int(mjm.hfield_nrow[hid]), int(mjm.hfield_ncol[hid]), int(mjm.hfield_adr[hid])
  return np.asarray(mjm.hfield_data[adr : adr + nrow * ncol], dtype=np.float64).reshape(nrow, ncol)


def hfield_prisms(mjm: mujoco.MjModel, hid: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
  """The prisms of cells rows r0..r1-1, columns c0..c1-1 of heightfield hid: (nprism, 6, 3),
  top triangle then its base, in the geom frame.

  MuJoCo C (mjc_ConvexHField) splits cell (r, c) along the diagonal from (r, c) to
  (r + 1, c + 1): triangles {(r, c), (r + 1, c), (r + 1, c + 1)} and {(r, c), (r + 1, c + 1),
  (r, c + 1)}; x along columns, y along rows, z = data * size[2], base at z = -size[3].
  """
  size = mjm.hfield_size[hid].astype(np.float64)
  nrow, ncol = int(mjm.hfield_nrow[hid]), int(mjm.hfield_ncol[hid])
  data = _cached(mjm, ("hfield", hid), lambda: hfield_elevations(mjm, hid))
  dx, dy = 2.0 * size[0] / (ncol - 1), 2.0 * size[1] / (nrow - 1)
  r, c = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
  r, c = r.ravel(), c.ravel()

  def vertex(rr, cc):
    return np.stack([dx * cc - size[0], dy * rr - size[1], data[rr, cc] * size[2]], axis=-1)

  v00, v10, v01, v11 = vertex(r, c), vertex(r + 1, c), vertex(r, c + 1), vertex(r + 1, c + 1)
  tops = np.concatenate([np.stack([v00, v10, v11], axis=1), np.stack([v00, v11, v01], axis=1)])
  bases = tops.copy()
  bases[..., 2] = -size[3]
  return np.concatenate([tops, bases], axis=1)


# a prism's 8 boundary triangles as corner ids: top, base, and two per side wall
_PRISM_TRIS = np.array([[0, 1, 2], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])


def _prism_distances(prisms: np.ndarray, p: np.ndarray) -> np.ndarray:
  """Distance of p outside each prism (0 inside): inside when over the top triangle (in xy),
  above the base and below the top's plane; else the nearest of its 8 boundary triangles."""
  tri = prisms[:, _PRISM_TRIS]  # (n, 8, 3, 3)
  flat = tri.reshape(-1, 3, 3)
  d = np.sqrt(_point_triangle_dist2(p, flat[:, 0], flat[:, 1], flat[:, 2]).reshape(-1, 8).min(axis=1))
  a, b, c = prisms[:, 0], prisms[:, 1], prisms[:, 2]
  n = np.cross(b - a, c - a)
  n *= np.sign(n[:, 2:3])  # upward
  below_top = np.einsum("ij,ij->i", n, p - a) <= 0.0
  above_base = p[2] >= prisms[:, 3, 2]
  inside = below_top & above_base & _in_triangle_xy(p, a, b, c)
  return np.where(inside, 0.0, d)


def _in_triangle_xy(p, a, b, c) -> np.ndarray:
  """Whether point p lies over each triangle (a[i], b[i], c[i]) seen along z (edges included)."""
  def edge(u, v):
    return (v[:, 0] - u[:, 0]) * (p[1] - u[:, 1]) - (v[:, 1] - u[:, 1]) * (p[0] - u[:, 0])

  e0, e1, e2 = edge(a, b), edge(b, c), edge(c, a)
  return ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))


def hfield_triangle_at(mjm: mujoco.MjModel, hid: int, p: np.ndarray) -> Optional[tuple[int, int, int]]:
  """The triangle of heightfield hid over point p (geom frame), as (row, col, t): cell (row, col)
  and its triangle t in hfield_prisms' order (0: {(r, c), (r + 1, c), (r + 1, c + 1)}); None
  where p lies off the grid."""
  size = mjm.hfield_size[hid].astype(np.float64)
  nrow, ncol = int(mjm.hfield_nrow[hid]), int(mjm.hfield_ncol[hid])
  col = math.floor((p[0] + size[0]) / (2.0 * size[0] / (ncol - 1)))
  row = math.floor((p[1] + size[1]) / (2.0 * size[1] / (nrow - 1)))
  if not (0 <= row < nrow - 1 and 0 <= col < ncol - 1):
    return None
  tops = hfield_prisms(mjm, hid, row, row + 1, col, col + 1)[:, :3]
  return row, col, int(np.argmax(_in_triangle_xy(p, tops[:, 0], tops[:, 1], tops[:, 2])))


def hfield_distance(mjm: mujoco.MjModel, hid: int, p: np.ndarray) -> float:
  """Distance of p (geom frame) outside heightfield hid's union of prisms; 0 inside one.

  The prisms of the cell under p (clamped to the grid) bound the distance; the nearest point
  then lies within that bound of p, so only the cells that close are searched.
  """
  size = mjm.hfield_size[hid].astype(np.float64)
  nrow, ncol = int(mjm.hfield_nrow[hid]), int(mjm.hfield_ncol[hid])
  dx, dy = 2.0 * size[0] / (ncol - 1), 2.0 * size[1] / (nrow - 1)

  def cells(x, y, reach):
    c0 = int(np.clip(math.floor((x - reach + size[0]) / dx), 0, ncol - 2))
    c1 = int(np.clip(math.floor((x + reach + size[0]) / dx), 0, ncol - 2)) + 1
    r0 = int(np.clip(math.floor((y - reach + size[1]) / dy), 0, nrow - 2))
    r1 = int(np.clip(math.floor((y + reach + size[1]) / dy), 0, nrow - 2)) + 1
    return r0, r1, c0, c1

  bound = float(_prism_distances(hfield_prisms(mjm, hid, *cells(p[0], p[1], 0.0)), p).min())
  if bound == 0.0:
    return 0.0
  return float(_prism_distances(hfield_prisms(mjm, hid, *cells(p[0], p[1], bound)), p).min())


# ---------------------------------------------------------------------------------------------
# vectorised primitives


def _point_triangle_dist2(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
  """Squared distance of point p (3,) to each triangle (a[i], b[i], c[i]) (Voronoi regions of
  the corners, edges and face; Ericson, Real-Time Collision Detection, 5.1.5)."""
  ab, ac, ap = b - a, c - a, p - a
  d1, d2 = _dot(ab, ap), _dot(ac, ap)
  bp = p - b
  d3, d4 = _dot(ab, bp), _dot(ac, bp)
  cp = p - c
  d5, d6 = _dot(ab, cp), _dot(ac, cp)
  va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
  with np.errstate(divide="ignore", invalid="ignore"):
    denom = va + vb + vc
    v = np.where(denom != 0, vb / denom, 0.0)
    w = np.where(denom != 0, vc / denom, 0.0)
    q = a + ab * v[:, None] + ac * w[:, None]  # inside the face
    t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    q = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + (c - b) * t_bc[:, None], q)
    q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * (d2 / (d2 - d6))[:, None], q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * (d1 / (d1 - d3))[:, None], q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
  diff = p - q
  return _dot(diff, diff)


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
  return np.einsum("ij,ij->i", u, v) if u.ndim == 2 and v.ndim == 2 else (u * v).sum(axis=-1)


def _winding_number(p: np.ndarray, tri: np.ndarray) -> float:
  """Generalised winding number of closed triangles (n, 3, 3) around p (Van Oosterom-Strackee
  solid angles): 1 inside, 0 outside."""
  a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p
  la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
  num = _dot(a, np.cross(b, c))
  den = la * lb * lc + _dot(a, b) * lc + _dot(b, c) * la + _dot(c, a) * lb
  return float(np.arctan2(num, den).sum() / (2.0 * math.pi))
