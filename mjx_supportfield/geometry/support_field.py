"""Builds the support field of every mesh from MuJoCo's convex hulls.

A field is a lat-long grid of ``res x res`` directions per mesh; each cell stores the
14-bit local index of the hull vertex that is extreme in that direction (positions are
gathered from MuJoCo's ``mesh_vert``), so a cell costs 2 bytes.
The two top bits carry proofs made at build time about the cell's quad: CERTIFIED, its vertex
is the support for every direction between the quad's 4 corners (a query needs one read);
CORNERS_EXACT, the best of the 4 corner vertices is (a query needs no climb); WITH_EXTRAS, the
best of the corners and up to 3 listed vertices is (the quads of a fine hull where a vertex's
normal cone is smaller than a cell and no corner sees it; the lists cost 2 bytes a vertex).
Geoms that share a mesh share its field. Each mesh gets one resolution step above the
smallest (up to 64) at which the plain 4-cell lookup (``support_mode="field"``) returns the
exact support on a dense check set (4 directions inside every cell plus random ones), else
``Options.support_res``. The check set is not a proof: ``field`` mode stays approximate,
``refined`` is exact.
"""

import dataclasses
import logging
import sys
import time
from typing import Collection
from typing import Optional

import mujoco
import numpy as np
import warp as wp

from mjx_supportfield import types as mjx_types
from mjx_supportfield.geometry import disk_cache
from mjx_supportfield.geometry import support
from mjx_supportfield.geometry.hull_graph import hull_graph
from mjx_supportfield.geometry.support import CERTIFIED
from mjx_supportfield.geometry.support import CORNERS_EXACT
from mjx_supportfield.geometry.support import EXTRA_COUNT_SHIFT
from mjx_supportfield.geometry.support import GRID_DIRECTIONS
from mjx_supportfield.geometry.support import INDEX_MASK
from mjx_supportfield.geometry.support import MAX_EXTRAS
from mjx_supportfield.geometry.support import PROOF_MASK
from mjx_supportfield.geometry.support import WITH_EXTRAS
from mjx_supportfield.geometry.support import field_cell
from mjx_supportfield.geometry.support import field_lookup
from mjx_supportfield.geometry.support import hill_climb
from mjx_supportfield.geometry.support import hull_point
from mjx_supportfield.geometry.support import hull_scan
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# candidate resolutions, coarse to fine (the cap Options.support_res is always a candidate)
_RESOLUTIONS = (4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 180, 256, 360, 512, 1024, 2048, 4096)
_NCHECK_RANDOM = 1024  # random check directions per mesh, besides the in-cell samples
_NCHECK_SUB = 2  # in-cell samples per cell side
# coarser grids are tried up to this resolution; generic (non-polyhedral-grid) hulls never
# become exact at any finite resolution, since near each face normal three or more vertex
# cones meet inside one cell, so those meshes get the cap without paying for finer checks
_ADAPTIVE_MAX = 64
MAX_HULL = INDEX_MASK  # largest hull a cell's 14 index bits can address
# what install builds of the fields (and the disk cache keeps): MeshSupport's arrays and dtypes
_FIELD_DTYPES = {"field_res": int, "field_adr": int, "field": wp.uint16, "extra_adr": int, "extra": wp.uint16}
FIELD_ARRAYS = tuple(_FIELD_DTYPES)
logger = logging.getLogger("mjx_supportfield")


@dataclasses.dataclass
class HullData:
  """Host-side hull description of all meshes (local vertex ids, neighbour lists)."""

  hull_adr: np.ndarray
  hull_num: np.ndarray
  hull_vert: np.ndarray
  hull_center: np.ndarray
  nbr_adr: np.ndarray
  nbr_num: np.ndarray
  nbr: np.ndarray
  # hull face planes (outward unit normal, offset; mesh frame), per mesh; none: EPA serves instead
  plane_adr: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int32))
  plane_num: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int32))
  plane: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4), np.float32))
  # MuJoCo's hull polygons (see MeshSupport); none: no point is ever known to lie on a face
  polygons: dict = dataclasses.field(default_factory=dict)


def mesh_hull(mjm: mujoco.MjModel, meshid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Hull vertex ids (within the mesh), neighbour counts and flat neighbour lists of a mesh.

  From MuJoCo's convex-hull graph (see hull_graph). A mesh without one uses all its vertices
  and no neighbours (its queries then use the field or a scan).
  """
  graph = hull_graph(mjm, meshid)
  if graph is None:
    n = int(mjm.mesh_vertnum[meshid])
    return np.arange(n, dtype=np.int32), np.zeros(n, np.int32), np.zeros(0, np.int32)
  return graph.vert, graph.nbr_num, graph.nbr


def mesh_hull_planes(mjm: mujoco.MjModel, meshid: int) -> np.ndarray:
  """(nface, 4) supporting planes along the face normals of MuJoCo's convex hull of a mesh:
  outward unit normal n and offset max(n . v) over the hull vertices (n . x <= offset inside),
  mesh frame; none for a mesh without a hull graph.

  The offset is the hull's support along n rather than the face's own offset, so a sliver face
  with a poor float32 normal still gives a plane the whole hull lies behind (it can only make a
  point's depth, the smallest distance to the planes, too large, never too small).
  """
  graph = hull_graph(mjm, meshid)
  if graph is None:
    return np.zeros((0, 4), np.float32)
  faces = graph.faces
  vert = np.asarray(mjm.mesh_vert[mjm.mesh_vertadr[meshid] : mjm.mesh_vertadr[meshid] + mjm.mesh_vertnum[meshid]],
                    dtype=np.float64)
  hull = vert[np.unique(faces)]
  p0, p1, p2 = vert[faces[:, 0]], vert[faces[:, 1]], vert[faces[:, 2]]
  n = np.cross(p1 - p0, p2 - p0)
  length = np.linalg.norm(n, axis=1)
  n = n[length > 0] / length[length > 0, None]
  n[n @ hull.mean(axis=0) > np.einsum("ij,ij->i", n, p0[length > 0])] *= -1  # outward whatever the winding
  return np.concatenate([n, (hull @ n.T).max(axis=0)[:, None]], axis=1).astype(np.float32)


def _ranges(adr: np.ndarray, num: np.ndarray) -> np.ndarray:
  """The indices adr[i] .. adr[i] + num[i] - 1 of every i, back to back."""
  adr, num = np.asarray(adr, np.int64), np.asarray(num, np.int64)
  return np.repeat(adr - np.cumsum(num) + num, num) + np.arange(num.sum())


def hull_polygons(mjm: mujoco.MjModel, hull_adr: np.ndarray, hull_num: np.ndarray, hull_vert: np.ndarray) -> dict:
  """MuJoCo's hull polygons of the meshes that have hulls here (``hull_num`` > 0), re-indexed for
  MeshSupport: corners as global hull indices (``poly_hull``, which _set_polygons turns into
  positions), and per hull vertex (global hull index) the polygons around it (indices within the
  mesh, as MuJoCo's). The other meshes' polygons are left out. A polygon with a corner that is
  not a hull vertex gets no corners (never used)."""
  nmesh = len(hull_num)
  npoly = np.asarray(mjm.mesh_polynum, np.int64)[:nmesh] * (np.asarray(hull_num) > 0)
  if nmesh == 0 or npoly.sum() == 0:
    return {}
  vertadr = np.asarray(mjm.mesh_vertadr, np.int64)
  mesh_of_hull = np.repeat(np.arange(nmesh), hull_num)
  local = np.arange(len(hull_vert)) - np.asarray(hull_adr, np.int64)[mesh_of_hull]
  hull_index = np.full(mjm.nmeshvert, -1, np.int64)  # global mesh vertex -> local hull index
  hull_index[vertadr[mesh_of_hull] + hull_vert] = local
  polys = _ranges(np.asarray(mjm.mesh_polyadr, np.int64)[:nmesh], npoly)  # the kept polygons, by mesh
  vert_num = np.asarray(mjm.mesh_polyvertnum, np.int64)[polys]
  mesh_of_poly = np.repeat(np.arange(nmesh), npoly)
  corner_poly = np.repeat(np.arange(len(polys)), vert_num)
  corner = _ranges(np.asarray(mjm.mesh_polyvertadr, np.int64)[polys], vert_num)  # their corners, in order
  corners = hull_index[vertadr[mesh_of_poly[corner_poly]] + np.asarray(mjm.mesh_polyvert, np.int64)[corner]]
  bad = np.zeros(len(polys), bool)
  bad[corner_poly[corners < 0]] = True
  poly_hull = np.asarray(hull_adr, np.int64)[mesh_of_poly[corner_poly]] + np.maximum(corners, 0)
  around = vertadr[mesh_of_hull] + hull_vert  # each hull vertex as a global mesh vertex
  map_num = np.asarray(mjm.mesh_polymapnum, np.int64)[around]
  return {
    "poly_adr": (np.cumsum(npoly) - npoly).astype(np.int32),
    "poly_normal": np.asarray(mjm.mesh_polynormal, np.float32).reshape(-1, 3)[polys],
    "poly_vert_adr": (np.cumsum(vert_num) - vert_num).astype(np.int32),
    "poly_vert_num": np.where(bad | (vert_num < 3), 0, vert_num).astype(np.int32),
    "poly_hull": poly_hull.astype(np.int32) if len(poly_hull) else np.zeros(1, np.int32),
    "vert_poly_adr": (np.cumsum(map_num) - map_num).astype(np.int32),
    "vert_poly_num": map_num.astype(np.int32),
    "vert_poly": np.asarray(mjm.mesh_polymap, np.int32)[_ranges(np.asarray(mjm.mesh_polymapadr)[around], map_num)],
  }


def hull_vertex_count(mjm: mujoco.MjModel, meshid: int) -> int:
  """Vertices of a mesh's hull as MeshSupport holds it (all its vertices without a hull graph)."""
  adr = int(mjm.mesh_graphadr[meshid])
  return int(mjm.mesh_vertnum[meshid]) if adr < 0 else int(mjm.mesh_graph[adr])


def hull_data(mjm: mujoco.MjModel, meshes: Optional[Collection[int]] = None) -> HullData:
  """Flattens the hulls of a model's meshes: all of them, or only ``meshes`` (the others get
  empty hulls, no polygons and, in build_from_hulls, no field)."""
  keep = range(mjm.nmesh) if meshes is None else set(int(i) for i in meshes)
  empty = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int32))
  parts = [mesh_hull(mjm, i) if i in keep else empty for i in range(mjm.nmesh)]
  planes = [mesh_hull_planes(mjm, i) if i in keep else np.zeros((0, 4), np.float32) for i in range(mjm.nmesh)]
  plane_num = np.array([len(p) for p in planes], dtype=np.int32)
  hull_num = np.array([len(p[0]) for p in parts], dtype=np.int32)
  nbr_num = np.concatenate([p[1] for p in parts]).astype(np.int32) if parts else np.zeros(0, np.int32)
  centers = [
    mjm.mesh_vert[mjm.mesh_vertadr[i] + p[0]].mean(axis=0) if len(p[0]) else np.zeros(3) for i, p in enumerate(parts)
  ]
  hull_adr = np.concatenate([[0], np.cumsum(hull_num)[:-1]]).astype(np.int32) if parts else np.zeros(0, np.int32)
  hull_vert = np.concatenate([p[0] for p in parts]).astype(np.int32) if parts else np.zeros(0, np.int32)
  return HullData(
    hull_adr=hull_adr,
    hull_num=hull_num,
    hull_vert=hull_vert,
    hull_center=np.array(centers, dtype=np.float32).reshape(-1, 3),
    nbr_adr=np.concatenate([[0], np.cumsum(nbr_num)[:-1]]).astype(np.int32) if len(nbr_num) else np.zeros(0, np.int32),
    nbr_num=nbr_num,
    nbr=np.concatenate([p[2] for p in parts]).astype(np.int32) if parts else np.zeros(0, np.int32),
    plane_adr=np.concatenate([[0], np.cumsum(plane_num)[:-1]]).astype(np.int32) if parts else np.zeros(0, np.int32),
    plane_num=plane_num,
    plane=np.concatenate(planes).astype(np.float32) if parts else np.zeros((0, 4), np.float32),
    polygons=hull_polygons(mjm, hull_adr, hull_num, hull_vert),
  )


@wp.func
def cell_direction(u: float, v: float, res: int) -> wp.vec3:
  """Direction at continuous cell coordinates (u, v): theta = 2 pi u / res - pi, phi = pi v / (res - 1).

  Row v = 0 is the +z pole and row v = res - 1 the -z pole, so both poles are sampled.
  """
  theta = 2.0 * wp.pi * u / float(res) - wp.pi
  phi = wp.pi * wp.min(v, float(res - 1)) / float(res - 1)
  return wp.vec3(wp.sin(phi) * wp.cos(theta), wp.sin(phi) * wp.sin(theta), wp.cos(phi))


@wp.kernel
def _build_field(
  ms: MeshSupport, cell_mesh: wp.array(dtype=int), extremes: wp.array2d(dtype=int), field_out: wp.array(dtype=wp.uint16)
):
  """Support vertex of each cell's direction: hill-climb from the best of the mesh's extreme
  vertices (exact on a hull graph, and O(climb) instead of O(vertices)); scan without a graph."""
  cell = wp.tid()
  mesh = cell_mesh[cell]
  res = ms.field_res[mesh]
  local = cell - ms.field_adr[mesh]
  d = cell_direction(float(local % res), float(local // res), res)
  start = extremes[mesh, 0]
  start_dot = wp.dot(hull_point(ms, mesh, start), d)
  for k in range(1, GRID_DIRECTIONS):
    e = extremes[mesh, k]
    ed = wp.dot(hull_point(ms, mesh, e), d)
    if ed > start_dot:
      start = e
      start_dot = ed
  if ms.nbr_num[ms.hull_adr[mesh] + start] > 0:
    field_out[cell] = wp.uint16(hill_climb(ms, mesh, start, d))
  else:
    field_out[cell] = wp.uint16(hull_scan(ms, mesh, d))


@wp.kernel
def _check_field(
  ms: MeshSupport,
  check_mesh: wp.array(dtype=int),
  check_dir: wp.array(dtype=wp.vec3),
  mismatches_out: wp.array(dtype=int),
):
  """Counts, per mesh, check directions where the 4-cell lookup misses the exact support."""
  k = wp.tid()
  mesh = check_mesh[k]
  d = check_dir[k]
  found, _ = field_lookup(ms, mesh, d, False)
  # hill-climbing on the hull graph is exact and cheaper than a scan; without a graph, scan
  if ms.nbr_num[ms.hull_adr[mesh] + found] > 0:
    truth = hill_climb(ms, mesh, found, d)
  else:
    truth = hull_scan(ms, mesh, d)
  exact = wp.dot(hull_point(ms, mesh, truth), d)
  got = wp.dot(hull_point(ms, mesh, found), d)
  if got < exact - 1.0e-6 * wp.max(wp.abs(exact), 1.0e-12):
    wp.atomic_add(mismatches_out, mesh, 1)


def _check_directions(res: int, rng: np.random.Generator) -> np.ndarray:
  """_NCHECK_SUB^2 directions inside every cell of a res grid, plus random ones."""
  sub = (np.arange(_NCHECK_SUB) + 0.5) / _NCHECK_SUB
  u, v = np.meshgrid((np.arange(res)[:, None] + sub).ravel(), (np.arange(res - 1)[:, None] + sub).ravel())
  theta = 2 * np.pi * u.ravel() / res - np.pi
  phi = np.pi * v.ravel() / (res - 1)
  mids = np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)], axis=1)
  rand = rng.normal(size=(_NCHECK_RANDOM, 3))
  rand /= np.linalg.norm(rand, axis=1, keepdims=True)
  return np.concatenate([mids, rand]).astype(np.float32)


def _layout(ms: MeshSupport, field_res: np.ndarray, device) -> np.ndarray:
  """Sets field_res/field_adr/field for these resolutions; returns the owning mesh per cell."""
  ncells = field_res.astype(np.int64) ** 2
  adr = np.concatenate([[0], np.cumsum(ncells)])
  if adr[-1] >= 2**31:
    raise ValueError(f"support fields need {adr[-1]} cells, more than 2^31; lower Options.support_res")
  ms.field_res = wp.array(field_res.astype(np.int32), dtype=int, device=device)
  ms.field_adr = wp.array(adr[:-1].astype(np.int32), dtype=int, device=device)
  ms.field = wp.zeros(max(int(adr[-1]), 1), dtype=wp.uint16, device=device)
  ms.extra_adr = wp.zeros(len(field_res), dtype=int, device=device)  # no extras lists until _prove
  ms.extra = wp.zeros(1, dtype=wp.uint16, device=device)  # the end entry only
  return np.repeat(np.arange(len(field_res), dtype=np.int32), ncells)


@wp.func
def _min_on_meridian(a: wp.vec3, theta: float, ph0: float, ph1: float) -> float:
  """min of a . d over the arc theta = const, phi in [ph0, ph1]: R cos(phi - phi*)."""
  p = a[0] * wp.cos(theta) + a[1] * wp.sin(theta)
  f0 = p * wp.sin(ph0) + a[2] * wp.cos(ph0)
  f1 = p * wp.sin(ph1) + a[2] * wp.cos(ph1)
  m = wp.min(f0, f1)
  star = wp.atan2(p, a[2])
  for k in range(2):
    crit = star + wp.where(k == 0, wp.pi, -wp.pi)
    if crit >= ph0 and crit <= ph1:
      m = wp.min(m, -wp.sqrt(p * p + a[2] * a[2]))
  return m


@wp.func
def _min_on_parallel(a: wp.vec3, phi: float, th0: float, th1: float) -> float:
  """min of a . d over the arc phi = const, theta in [th0, th1]."""
  sp = wp.sin(phi)
  cp = wp.cos(phi)
  f0 = sp * (a[0] * wp.cos(th0) + a[1] * wp.sin(th0)) + a[2] * cp
  f1 = sp * (a[0] * wp.cos(th1) + a[1] * wp.sin(th1)) + a[2] * cp
  m = wp.min(f0, f1)
  crit = wp.atan2(a[1], a[0]) + wp.pi  # where cos(theta - theta*) = -1
  for k in range(3):
    t = crit + 2.0 * wp.pi * float(k - 1)
    if t >= th0 and t <= th1:
      m = wp.min(m, -sp * wp.sqrt(a[0] * a[0] + a[1] * a[1]) + a[2] * cp)
  return m


@wp.func
def min_on_quad(a: wp.vec3, th0: float, th1: float, ph0: float, ph1: float) -> float:
  """min of a . d over the directions with theta in [th0, th1] and phi in [ph0, ph1].

  A linear function on the sphere has one interior minimum, at -a/|a|; elsewhere the
  minimum lies on the quad's two meridian arcs or two parallel arcs.
  """
  m = wp.min(wp.min(_min_on_meridian(a, th0, ph0, ph1), _min_on_meridian(a, th1, ph0, ph1)),
             wp.min(_min_on_parallel(a, ph0, th0, th1), _min_on_parallel(a, ph1, th0, th1)))
  n = wp.length(a)
  if n > 0.0:
    t = wp.atan2(-a[1], -a[0])
    if t < th0:
      t += 2.0 * wp.pi
    f = wp.acos(wp.clamp(-a[2] / n, -1.0, 1.0))
    if t <= th1 and f >= ph0 and f <= ph1:
      m = wp.min(m, -n)
  return m


_PROOF_SPLITS = 8  # a quad the candidates do not cover as a whole is retried in 2x2, 4x4, 8x8 parts
_QUAD_CORNERS = 4  # a quad's corner cells: the candidates a proof starts from
_MAX_CANDIDATES = _QUAD_CORNERS + MAX_EXTRAS
# a quad's proof code (_certify): 0 unproven, and _PROOF_CORNERS + k for the corners and k extras
_UNPROVEN = 0
_PROOF_CERTIFIED = 1
_PROOF_CORNERS = 2
# _unbeaten_neighbour's answers besides a vertex
_ALL_BEATEN = -1
_NO_GRAPH = -2
_candidates = wp.types.vector(length=_MAX_CANDIDATES, dtype=int)


@wp.func
def _beaten_on_part(ms: MeshSupport, mesh: int, cand: _candidates, ncand: int, pn: wp.vec3, th0: float, th1: float,
                    ph0: float, ph1: float) -> bool:
  """Whether one candidate vertex beats the point pn for every direction of the quad part."""
  for c in range(ncand):
    if min_on_quad(hull_point(ms, mesh, cand[c]) - pn, th0, th1, ph0, ph1) >= 0.0:
      return True
  return False


@wp.func
def _beaten_on_quad(ms: MeshSupport, mesh: int, cand: _candidates, ncand: int, n: int, th0: float, th1: float,
                    ph0: float, ph1: float) -> bool:
  """Whether, for every direction of the quad, some candidate vertex beats vertex n.

  Proven part by part: the quad as a whole, else split into 2x2, 4x4 and 8x8 parts, each of
  which must have one candidate that beats n all over it.
  """
  for c in range(ncand):
    if cand[c] == n:
      return True
  pn = hull_point(ms, mesh, n)
  splits = int(1)
  while splits <= _PROOF_SPLITS:
    dth = (th1 - th0) / float(splits)
    dph = (ph1 - ph0) / float(splits)
    proven = bool(True)
    for k in range(splits * splits):
      a = th0 + dth * float(k % splits)
      b = ph0 + dph * float(k // splits)
      if not _beaten_on_part(ms, mesh, cand, ncand, pn, a, a + dth, b, b + dph):
        proven = False
        break
    if proven:
      return True
    splits *= 2
  return False


@wp.func
def _unbeaten_neighbour(ms: MeshSupport, mesh: int, cand: _candidates, ncand: int, th0: float, th1: float,
                        ph0: float, ph1: float) -> int:
  """A hull neighbour of a candidate that no candidate is proven to beat over the quad,
  _ALL_BEATEN when there is none, _NO_GRAPH when a candidate has no hull graph to prove anything
  with."""
  for c in range(ncand):
    g = ms.hull_adr[mesh] + cand[c]
    if ms.nbr_num[g] == 0:
      return _NO_GRAPH
    for k in range(ms.nbr_num[g]):
      n = ms.nbr[ms.nbr_adr[g] + k]
      if not _beaten_on_quad(ms, mesh, cand, ncand, n, th0, th1, ph0, ph1):
        return n
  return _ALL_BEATEN


@wp.kernel
def _certify(ms: MeshSupport, cell_mesh: wp.array(dtype=int), proof_out: wp.array(dtype=int),
             extras_out: wp.array2d(dtype=int)):
  """Proves, per quad, which vertices its lookup must weigh to be exact.

  Let w be the best of a candidate set S for a direction d. If every hull neighbour of every
  vertex of S is beaten, over the whole quad, by some vertex of S, then w beats all its own
  neighbours at d, and on a convex hull a vertex that no neighbour beats is the support. S
  starts as the quad's 4 corner vertices; a neighbour that cannot be proven beaten joins S (it
  is usually a vertex whose normal cone lies inside the quad, seen by no corner), up to
  MAX_EXTRAS of them. proof_out: 0 unproven, 1 CERTIFIED (the corners agree and suffice),
  2 CORNERS_EXACT, 2 + k the corners and the k vertices in extras_out suffice.
  """
  cell = wp.tid()
  proof_out[cell] = _UNPROVEN
  mesh = cell_mesh[cell]
  res = ms.field_res[mesh]
  local = cell - ms.field_adr[mesh]
  i = local % res
  j = local // res
  if j >= res - 1:
    return
  i1 = (i + 1) % res
  cand = _candidates()
  cand[0] = field_cell(ms, mesh, i, j)
  cand[1] = field_cell(ms, mesh, i1, j)
  cand[2] = field_cell(ms, mesh, i, j + 1)
  cand[3] = field_cell(ms, mesh, i1, j + 1)
  th0 = 2.0 * wp.pi * float(i) / float(res) - wp.pi
  th1 = th0 + 2.0 * wp.pi / float(res)
  ph0 = wp.pi * float(j) / float(res - 1)
  ph1 = wp.pi * float(j + 1) / float(res - 1)
  ncand = int(_QUAD_CORNERS)
  while ncand <= _MAX_CANDIDATES:
    n = _unbeaten_neighbour(ms, mesh, cand, ncand, th0, th1, ph0, ph1)
    if n == _NO_GRAPH:
      return
    if n == _ALL_BEATEN:
      break
    if ncand == _MAX_CANDIDATES:
      return
    cand[ncand] = n
    ncand += 1
  if ncand > _QUAD_CORNERS:
    proof_out[cell] = _PROOF_CORNERS + ncand - _QUAD_CORNERS
    for k in range(ncand - _QUAD_CORNERS):
      extras_out[cell, k] = cand[_QUAD_CORNERS + k]
  elif cand[1] == cand[0] and cand[2] == cand[0] and cand[3] == cand[0]:
    proof_out[cell] = _PROOF_CERTIFIED
  else:
    proof_out[cell] = _PROOF_CORNERS


@wp.kernel
def _extras_size(proof: wp.array(dtype=int), size_out: wp.array(dtype=int)):
  """Entries a quad's extras list takes: its own vertex and its k extras."""
  cell = wp.tid()
  size_out[cell] = wp.where(proof[cell] > _PROOF_CORNERS, proof[cell] - _PROOF_CORNERS + 1, 0)


@wp.kernel
def _write_proofs(ms: MeshSupport, cell_mesh: wp.array(dtype=int), proof: wp.array(dtype=int),
                  extras: wp.array2d(dtype=int), offset: wp.array(dtype=int), field_out: wp.array(dtype=wp.uint16),
                  extra_out: wp.array(dtype=wp.uint16)):
  """Writes each quad's proof code into its cell word and its extras list into ``extra``."""
  cell = wp.tid()
  code = proof[cell]
  v = int(field_out[cell])
  if code == _PROOF_CERTIFIED:
    field_out[cell] = wp.uint16(v | CERTIFIED)
  elif code == _PROOF_CORNERS:
    field_out[cell] = wp.uint16(v | CORNERS_EXACT)
  elif code > _PROOF_CORNERS:
    mesh = cell_mesh[cell]
    start = offset[cell]
    pointer = start - offset[ms.field_adr[mesh]]
    if pointer > INDEX_MASK:
      return  # the mesh's lists outgrew 14-bit pointers: this quad stays unproven (it climbs)
    extra_out[start] = wp.uint16(v | ((code - _PROOF_CORNERS) << EXTRA_COUNT_SHIFT))
    for k in range(code - _PROOF_CORNERS):
      extra_out[start + 1 + k] = wp.uint16(extras[cell, k])
    field_out[cell] = wp.uint16(pointer | WITH_EXTRAS)


@wp.kernel
def _mesh_extra_adr(field_adr: wp.array(dtype=int), offset: wp.array(dtype=int), total: int,
                    extra_adr_out: wp.array(dtype=int)):
  """Every mesh's lists start at the list offset of its first cell."""
  mesh = wp.tid()
  first = field_adr[mesh]
  extra_adr_out[mesh] = wp.where(first < offset.shape[0], offset[wp.min(first, offset.shape[0] - 1)], total)


def _prove(ms: MeshSupport, cells: wp.array, device):
  """Runs _certify and packs its proofs into the field words and the extras lists."""
  n = cells.shape[0]
  proof = wp.empty(n, dtype=int, device=device)
  extras = wp.zeros((n, MAX_EXTRAS), dtype=int, device=device)
  wp.launch(_certify, dim=n, inputs=[ms, cells], outputs=[proof, extras], device=device)
  size = wp.empty(n, dtype=int, device=device)
  wp.launch(_extras_size, dim=n, inputs=[proof], outputs=[size], device=device)
  offset = wp.empty(n, dtype=int, device=device)
  wp.utils.array_scan(size, offset, inclusive=False)
  total = int(offset[n - 1 :].numpy()[0] + size[n - 1 :].numpy()[0])
  ms.extra = wp.zeros(total + 1, dtype=wp.uint16, device=device)  # + an unused end entry: never empty
  wp.launch(_mesh_extra_adr, dim=ms.field_adr.shape[0], inputs=[ms.field_adr, offset, total], outputs=[ms.extra_adr],
            device=device)
  wp.launch(_write_proofs, dim=n, inputs=[ms, cells, proof, extras, offset], outputs=[ms.field, ms.extra],
            device=device)


def extreme_vertices(hd: HullData, vert: np.ndarray, vertadr: np.ndarray) -> np.ndarray:
  """Per mesh, the local hull indices of the extreme vertices in the GRID_DIRECTIONS."""
  dirs = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)], float)
  out = np.zeros((len(hd.hull_num), GRID_DIRECTIONS), np.int32)
  for mesh, (adr, num) in enumerate(zip(hd.hull_adr, hd.hull_num)):
    if num:
      pts = vert[vertadr[mesh] + hd.hull_vert[adr : adr + num]]
      out[mesh] = np.argmax(pts @ dirs.T, axis=0)
  return out


def _build(ms: MeshSupport, field_res: np.ndarray, extremes: wp.array, device, certify: bool = False):
  cell_mesh = _layout(ms, field_res, device)
  if len(cell_mesh):
    cells = wp.array(cell_mesh, dtype=int, device=device)
    wp.launch(_build_field, dim=len(cell_mesh), inputs=[ms, cells, extremes], outputs=[ms.field], device=device)
    if certify:
      _prove(ms, cells, device)


def choose_resolutions(ms: MeshSupport, hull_num: np.ndarray, cap: int, extremes: wp.array, device) -> np.ndarray:
  """Per mesh, one step above the smallest resolution whose lookup is exact on the check set."""
  nmesh = len(hull_num)
  chosen = np.where(hull_num > 0, cap, 0).astype(np.int32)
  open_ = hull_num > 0
  rng = np.random.default_rng(0)
  levels = [r for r in _RESOLUTIONS if r < cap] + [cap]
  for level, res in enumerate(levels[:-1]):
    if res > _ADAPTIVE_MAX:
      break
    if not open_.any():
      break
    _build(ms, np.where(open_, res, 0).astype(np.int32), extremes, device)
    dirs = _check_directions(res, rng)
    meshes = np.nonzero(open_)[0].astype(np.int32)
    check_mesh = np.repeat(meshes, len(dirs))
    check_dir = np.tile(dirs, (len(meshes), 1))
    mismatches = wp.zeros(nmesh, dtype=int, device=device)
    wp.launch(_check_field, dim=len(check_mesh),
              inputs=[ms, wp.array(check_mesh, dtype=int, device=device), wp.array(check_dir, dtype=wp.vec3, device=device)],
              outputs=[mismatches], device=device)
    exact = open_ & (mismatches.numpy() == 0)
    chosen[exact] = levels[level + 1]  # one step of margin: the check set is finite
    open_ &= ~exact
  return chosen


def build_mesh_support(mjm: mujoco.MjModel, mesh_vert: wp.array, res: int, device=None, adaptive: bool = True,
                       meshes: Optional[Collection[int]] = None) -> MeshSupport:
  """Builds MeshSupport (hulls, neighbour lists and one field per mesh) on the device.

  Args:
    mjm: the host model (MuJoCo's hulls are read from it).
    mesh_vert: MuJoCo Warp's device copy of the mesh vertices (shared, not copied).
    res: the resolution cap (``Options.support_res``).
    device: Warp device.
    adaptive: pick the smallest exact resolution per mesh; False uses ``res`` for all.
    meshes: the meshes the plugin collides (None: all); the others get nothing.

  Raises:
    ValueError: a hull too large for 16-bit cells, naming the mesh (``too_large`` finds them
      first, so that their geoms can go to MuJoCo Warp's own narrow phase).
  """
  hd = hull_data(mjm, meshes)
  big = np.nonzero(hd.hull_num > MAX_HULL)[0]
  if len(big):
    name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_MESH, int(big[0])) or f"mesh {big[0]}"
    raise ValueError(f"mesh '{name}': its convex hull has {hd.hull_num[big[0]]} vertices, more than {MAX_HULL}"
                     " (set maxhullvert on the mesh)")
  return build_from_hulls(hd, mesh_vert, np.asarray(mjm.mesh_vertadr, dtype=np.int32), res, device, adaptive)


def too_large(mjm: mujoco.MjModel, meshes: Collection[int]) -> list[int]:
  """Those of ``meshes`` whose hull has more vertices than a field's cell can name."""
  return [int(i) for i in meshes if hull_vertex_count(mjm, int(i)) > MAX_HULL]


def build_from_hulls(hd: HullData, vert: wp.array, vertadr: np.ndarray, res: int, device=None, adaptive: bool = True
                     ) -> MeshSupport:
  """Builds MeshSupport from flattened hulls (``build_mesh_support`` without MuJoCo)."""
  ms = MeshSupport()

  def arr(x, dtype=int):
    return wp.array(x, dtype=dtype, device=device)

  ms.vert = vert
  ms.vertadr = arr(vertadr)
  ms.hull_adr = arr(hd.hull_adr)
  ms.hull_num = arr(hd.hull_num)
  ms.hull_center = arr(hd.hull_center, wp.vec3)
  ms.hull_vert = arr(hd.hull_vert)
  host_vert = vert.numpy()
  mesh_of_hull = np.repeat(np.arange(len(hd.hull_num)), hd.hull_num)
  hull_pos = host_vert[vertadr[mesh_of_hull] + hd.hull_vert].reshape(-1, 3)
  ms.hull_pos = arr(hull_pos, wp.vec3)
  ms.nbr_adr = arr(hd.nbr_adr)
  ms.nbr_num = arr(hd.nbr_num)
  ms.nbr = arr(hd.nbr)
  nmesh = len(hd.hull_num)
  has_planes = len(hd.plane_num) == nmesh and len(hd.plane) > 0
  ms.plane_adr = arr(hd.plane_adr if has_planes else np.zeros(nmesh, np.int32))
  ms.plane_num = arr(hd.plane_num if has_planes else np.zeros(nmesh, np.int32))
  ms.plane = arr(hd.plane if has_planes else np.zeros((1, 4), np.float32), wp.vec4)
  _set_polygons(ms, hd, hull_pos, arr)
  extremes_host = extreme_vertices(hd, host_vert, vertadr)
  digest = disk_cache.key(
    ("fields", wp.get_device(device).is_cuda, res, adaptive, hd.hull_adr, hd.hull_num, hd.hull_vert, hd.nbr_adr,
     hd.nbr_num, hd.nbr, hull_pos.astype(np.float32), extremes_host),
    code=(sys.modules[__name__], support, mjx_types))
  cached = disk_cache.load("fields", digest)
  if cached is not None and set(cached) == set(FIELD_ARRAYS):
    for name in FIELD_ARRAYS:
      setattr(ms, name, wp.array(cached[name], dtype=_FIELD_DTYPES[name], device=device))
    logger.info("support fields of %d meshes: from the cache (%s)", int((hd.hull_num > 0).sum()), disk_cache.root())
    return ms
  start = time.perf_counter()
  logger.info("support fields of %d meshes: building and proving them (not in the cache at %s yet)",
              int((hd.hull_num > 0).sum()), disk_cache.root())
  extremes = wp.array(extremes_host, dtype=int, device=device)
  if adaptive:
    field_res = choose_resolutions(ms, hd.hull_num, res, extremes, device)
  else:
    field_res = np.where(hd.hull_num > 0, res, 0)
  field_res = np.asarray(field_res, dtype=np.int32)
  _build(ms, field_res, extremes, device, certify=True)
  if adaptive:
    _fit_budget(ms, field_res, 2 * res * res, extremes, device)
  disk_cache.store("fields", digest, {name: getattr(ms, name).numpy() for name in FIELD_ARRAYS})
  logger.info("support fields built in %.1f s; later installs of these meshes read them from the cache",
              time.perf_counter() - start)
  return ms


def _set_polygons(ms: MeshSupport, hd: HullData, hull_pos: np.ndarray, arr) -> None:
  """MeshSupport's polygon arrays from ``hd.polygons`` (empty: no mesh has polygons), the
  corners' positions copied out of ``hull_pos`` (ms.hull_pos's values, on the host)."""
  poly = dict(hd.polygons)
  nmesh, nhull = len(hd.hull_num), len(hd.hull_vert)
  if not poly:  # one unused entry where an array would be empty; no vertex lists a polygon
    poly = {"poly_adr": np.zeros(nmesh, np.int32), "poly_normal": np.zeros((1, 3), np.float32),
            "poly_vert_adr": np.zeros(1, np.int32), "poly_vert_num": np.zeros(1, np.int32),
            "poly_hull": np.zeros(1, np.int32), "vert_poly_adr": np.zeros(nhull, np.int32),
            "vert_poly_num": np.zeros(nhull, np.int32), "vert_poly": np.zeros(1, np.int32)}
  poly_hull = poly.pop("poly_hull")
  ms.poly_pos = arr(hull_pos[poly_hull] if len(hull_pos) else np.zeros((len(poly_hull), 3), np.float32), wp.vec3)
  for name, values in poly.items():
    setattr(ms, name, arr(values, wp.vec3 if name == "poly_normal" else int))


_BUDGET_ROUNDS = 4


def _fit_budget(ms: MeshSupport, field_res: np.ndarray, budget: int, extremes: wp.array, device):
  """Lowers the resolution of meshes whose cells and extras lists exceed ``budget`` bytes.

  Fine hulls need extras lists on many quads; a slightly coarser grid pays for them, so no
  field outgrows 2 bytes x support_res^2 (1/8 of the seed's 16 bytes a cell).
  """
  for _ in range(_BUDGET_ROUNDS):
    nbytes = field_bytes(ms)
    over = nbytes > budget
    if not over.any():
      return
    lists = nbytes - 2 * field_res.astype(np.int64) ** 2
    # the lists barely shrink with the grid: leave them 10 % more room than they take now
    fit = np.floor(np.sqrt(np.maximum(budget - 1.1 * lists, 2 * 16) / 2)).astype(np.int32)
    field_res[over] = np.minimum(field_res[over] - 1, fit[over])
    _build(ms, field_res, extremes, device, certify=True)


def decode_field(ms: MeshSupport) -> tuple[np.ndarray, np.ndarray]:
  """Host copy of every cell's support vertex (local hull index) and its quad's proof code
  (0, CERTIFIED, CORNERS_EXACT or WITH_EXTRAS)."""
  mesh = np.repeat(np.arange(ms.field_res.shape[0]), ms.field_res.numpy().astype(np.int64) ** 2)
  word = ms.field.numpy().astype(np.int64)[: len(mesh)]  # a model without fields keeps one unused cell
  proof = word & PROOF_MASK
  listed = proof == WITH_EXTRAS
  word[listed] = ms.extra.numpy()[ms.extra_adr.numpy()[mesh[listed]] + (word[listed] & INDEX_MASK)]
  return word & INDEX_MASK, proof


def field_bytes(ms: MeshSupport) -> np.ndarray:
  """Bytes of support field per mesh: its cells and its extras lists (2 bytes each)."""
  res = ms.field_res.numpy().astype(np.int64)
  lists = np.diff(np.append(ms.extra_adr.numpy().astype(np.int64), ms.extra.shape[0] - 1))  # less the end entry
  return (res * res + lists) * wp.types.type_size_in_bytes(ms.field.dtype)
