"""Signed-distance fields of the convex geoms, for the SDF fallback of deep overlaps.

Mesh hulls are baked once on a regular grid (20 % padding around the hull, ``sdf_res`` cells
along its longest side) with Warp's winding-number mesh queries, and cached on disk keyed by
the hull's content and the bake's code (disk_cache.py). Primitives use closed forms.
"""

import functools
from types import SimpleNamespace

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry import disk_cache
from mjx_supportfield.geometry.hull_graph import hull_graph
from mjx_supportfield.geometry.support import GRID_DIRECTIONS
from mjx_supportfield.geometry.support import hull_point
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

PADDING = 0.2
# the distance of a point to a shape without an SDF, and the bake's search radius: past any
# depth a contact could have
NO_SDF = 1.0e6


@wp.struct
class MeshSdf:
  """Baked hull SDFs of all meshes, flattened with per-mesh offsets (res 0: none)."""

  adr: wp.array(dtype=int)
  res: wp.array(dtype=wp.vec3i)
  lo: wp.array(dtype=wp.vec3)  # grid origin, mesh frame
  cell: wp.array(dtype=float)  # cell size
  values: wp.array(dtype=float)


def hull_triangles(mjm: mujoco.MjModel, meshid: int) -> np.ndarray:
  """Triangles of MuJoCo's convex hull of a mesh (mesh vertex ids), or an empty array."""
  graph = hull_graph(mjm, meshid)
  return np.zeros((0, 3), np.int32) if graph is None else graph.faces


@wp.kernel
def _bake(mesh: wp.uint64, lo: wp.vec3, cell: float, res: wp.vec3i, out: wp.array(dtype=float)):
  i, j, k = wp.tid()
  p = lo + cell * wp.vec3(float(i), float(j), float(k))
  q = wp.mesh_query_point_sign_winding_number(mesh, p, NO_SDF)
  d = float(NO_SDF)
  if q.result:
    d = q.sign * wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
  out[(k * res[1] + j) * res[0] + i] = d


def bake_mesh(verts: np.ndarray, tris: np.ndarray, sdf_res: int, device=None):
  """(values flattened x-fastest, res, lo, cell) of one hull; from the disk cache when there."""
  vmin, vmax = verts.min(axis=0), verts.max(axis=0)
  ext = np.maximum(vmax - vmin, 1e-9)
  lo = vmin - PADDING * ext
  cell = float((ext * (1 + 2 * PADDING)).max() / sdf_res)
  res = np.maximum(np.ceil(ext * (1 + 2 * PADDING) / cell).astype(int) + 1, 2)
  digest = disk_cache.key(("sdf", verts.astype(np.float32), tris.astype(np.int32), sdf_res), code=(_bake.func,))
  cached = disk_cache.load("sdf", digest)
  if cached is not None and "values" in cached and cached["values"].shape == (int(np.prod(res)),):
    return cached["values"], res, lo, cell
  mesh = wp.Mesh(points=wp.array(verts.astype(np.float32), dtype=wp.vec3, device=device),
                 indices=wp.array(tris.ravel(), dtype=int, device=device), support_winding_number=True)
  out = wp.zeros(int(np.prod(res)), dtype=float, device=device)
  wp.launch(_bake, dim=tuple(int(x) for x in res), inputs=[mesh.id, wp.vec3(*lo), cell, wp.vec3i(*res)],
            outputs=[out], device=device)
  values = out.numpy()
  disk_cache.store("sdf", digest, {"values": values})
  return values, res, lo, cell


def build_mesh_sdf(mjm: mujoco.MjModel, sdf_res: int, meshes, device=None, triangles=hull_triangles) -> MeshSdf:
  """Bakes the SDF of each mesh id in ``meshes`` (the others get none): of its hull, or of the
  surface ``triangles(mjm, meshid)`` gives."""
  adr, res, lo, cell, values = [], [], [], [], []
  total = 0
  for meshid in range(mjm.nmesh):
    tris = triangles(mjm, meshid) if meshid in meshes else np.zeros((0, 3), np.int32)
    if len(tris) == 0:
      adr.append(0)
      res.append((0, 0, 0))
      lo.append((0.0, 0.0, 0.0))
      cell.append(1.0)
      continue
    v0, nv = mjm.mesh_vertadr[meshid], mjm.mesh_vertnum[meshid]
    vals, r, l, c = bake_mesh(np.asarray(mjm.mesh_vert[v0 : v0 + nv]), tris, sdf_res, device)
    adr.append(total)
    res.append(tuple(int(x) for x in r))
    lo.append(tuple(float(x) for x in l))
    cell.append(c)
    values.append(vals)
    total += len(vals)
  out = MeshSdf()
  out.adr = wp.array(np.array(adr, np.int32), dtype=int, device=device)
  out.res = wp.array(np.array(res, np.int32).reshape(-1, 3), dtype=wp.vec3i, device=device)
  out.lo = wp.array(np.array(lo, np.float32).reshape(-1, 3), dtype=wp.vec3, device=device)
  out.cell = wp.array(np.array(cell, np.float32), dtype=float, device=device)
  out.values = wp.array(np.concatenate(values) if values else np.zeros(1, np.float32), dtype=float, device=device)
  return out


@wp.func
def _grid(sdf: MeshSdf, mesh: int, i: int, j: int, k: int) -> float:
  r = sdf.res[mesh]
  return sdf.values[sdf.adr[mesh] + (k * r[1] + j) * r[0] + i]


@wp.func
def mesh_sdf_value(sdf: MeshSdf, mesh: int, p: wp.vec3) -> float:
  """Trilinear hull SDF at p (mesh frame); outside the grid, plus the distance to the grid."""
  r = sdf.res[mesh]
  g = (p - sdf.lo[mesh]) / sdf.cell[mesh]
  gc = wp.vec3(
    wp.clamp(g[0], 0.0, float(r[0] - 1)), wp.clamp(g[1], 0.0, float(r[1] - 1)), wp.clamp(g[2], 0.0, float(r[2] - 1))
  )
  outside = wp.length(g - gc) * sdf.cell[mesh]
  i = wp.min(int(gc[0]), r[0] - 2)
  j = wp.min(int(gc[1]), r[1] - 2)
  k = wp.min(int(gc[2]), r[2] - 2)
  fx = gc[0] - float(i)
  fy = gc[1] - float(j)
  fz = gc[2] - float(k)
  c00 = _grid(sdf, mesh, i, j, k) * (1.0 - fx) + _grid(sdf, mesh, i + 1, j, k) * fx
  c10 = _grid(sdf, mesh, i, j + 1, k) * (1.0 - fx) + _grid(sdf, mesh, i + 1, j + 1, k) * fx
  c01 = _grid(sdf, mesh, i, j, k + 1) * (1.0 - fx) + _grid(sdf, mesh, i + 1, j, k + 1) * fx
  c11 = _grid(sdf, mesh, i, j + 1, k + 1) * (1.0 - fx) + _grid(sdf, mesh, i + 1, j + 1, k + 1) * fx
  return (c00 * (1.0 - fy) + c10 * fy) * (1.0 - fz) + (c01 * (1.0 - fy) + c11 * fy) * fz + outside


@wp.func
def primitive_sdf(gtype: int, size: wp.vec3, p: wp.vec3) -> float:
  """Closed-form signed distance in the geom frame (ellipsoid: a first-order estimate)."""
  if gtype == GeomType.SPHERE:
    return wp.length(p) - size[0]
  if gtype == GeomType.CAPSULE:
    return wp.length(wp.vec3(p[0], p[1], p[2] - wp.clamp(p[2], -size[1], size[1]))) - size[0]
  if gtype == GeomType.CYLINDER:
    dr = wp.sqrt(p[0] * p[0] + p[1] * p[1]) - size[0]
    dz = wp.abs(p[2]) - size[1]
    return wp.min(wp.max(dr, dz), 0.0) + wp.length(wp.vec2(wp.max(dr, 0.0), wp.max(dz, 0.0)))
  if gtype == GeomType.BOX:
    q = wp.vec3(wp.abs(p[0]) - size[0], wp.abs(p[1]) - size[1], wp.abs(p[2]) - size[2])
    out = wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0))
    return wp.length(out) + wp.min(wp.max(q[0], wp.max(q[1], q[2])), 0.0)
  if gtype == GeomType.ELLIPSOID:
    k0 = wp.length(wp.cw_div(p, size))
    k1 = wp.length(wp.cw_div(p, wp.cw_mul(size, size)))
    return k0 * (k0 - 1.0) / wp.max(k1, 1.0e-12)
  return NO_SDF


@wp.func
def shape_sdf(s: Shape, sdf: MeshSdf, p_world: wp.vec3) -> float:
  """Signed distance of a world point to a posed shape (NO_SDF for a mesh without a baked SDF)."""
  p = wp.transpose(s.rot) @ (p_world - s.pos)
  if s.gtype == GeomType.MESH:
    if sdf.res[s.mesh][0] == 0:
      return NO_SDF
    return mesh_sdf_value(sdf, s.mesh, p)
  return primitive_sdf(s.gtype, s.size, p)


@wp.func
def shape_sdf_grad(s: Shape, sdf: MeshSdf, p: wp.vec3, h: float) -> wp.vec3:
  """Normalized central-difference gradient of shape_sdf (world frame)."""
  g = wp.vec3(0.0)
  for a in range(3):
    e = wp.vec3(0.0)
    e[a] = h
    g[a] = shape_sdf(s, sdf, p + e) - shape_sdf(s, sdf, p - e)
  return wp.normalize(g)


@wp.func
def needs_sdf(depth: float, rbound1: float, rbound2: float, ratio: float) -> bool:
  """The fallback's trigger: MPR's depth beyond ratio x the smaller geom's bounding diameter."""
  return ratio > 0.0 and depth > ratio * 2.0 * wp.min(rbound1, rbound2)


@wp.struct
class SdfContact:
  hit: int
  depth: float
  normal: wp.vec3  # from A to B
  pos: wp.vec3


@functools.lru_cache(maxsize=None)
def sdf_funcs(mode: int) -> SimpleNamespace:
  """The SDF fallback's device functions on the support functions of support mode ``mode``
  (support_funcs): ``sample_point`` and ``sdf_contact``."""
  support_world = support_funcs(mode).support_world

  @wp.func
  def sample_point(s: Shape, ms: MeshSupport, n: int) -> wp.vec3:
    """Sample n of a shape: its hull vertices (meshes), else support points in the GRID_DIRECTIONS;
    the last sample is the interior point (world frame)."""
    if s.gtype == GeomType.MESH:
      if n < ms.hull_num[s.mesh]:
        return s.pos + s.rot @ hull_point(ms, s.mesh, n)
      return s.center
    if n == GRID_DIRECTIONS:
      return s.center
    m = wp.where(n >= 13, n + 1, n)  # skip the grid's centre
    d = wp.vec3(float(m % 3 - 1), float((m // 3) % 3 - 1), float(m // 9 - 1))
    return support_world(s, ms, d)

  @wp.func
  def sdf_contact(a: Shape, b: Shape, ms: MeshSupport, sdf: MeshSdf, h: float) -> SdfContact:
    """Deepest sample of A in B's SDF, or of B in A's; the normal is that SDF's gradient there."""
    best = SdfContact()
    best.hit = 0
    best.depth = 0.0
    for side in range(2):
      src = a
      dst = b
      if side == 1:
        src = b
        dst = a
      nsample = GRID_DIRECTIONS + 1
      if src.gtype == GeomType.MESH:
        nsample = ms.hull_num[src.mesh] + 1
      for n in range(nsample):
        p = sample_point(src, ms, n)
        depth = -shape_sdf(dst, sdf, p)
        if depth > best.depth:
          grad = shape_sdf_grad(dst, sdf, p, h)
          best.hit = 1
          best.depth = depth
          # A's point out of B: B moves along -grad_B; B's point out of A: B moves along +grad_A
          best.normal = wp.where(side == 0, -grad, grad)
          # midpoint between p and the other surface, depth away along the normal
          best.pos = p + wp.where(side == 0, -0.5, 0.5) * depth * best.normal
    return best

  return SimpleNamespace(sample_point=sample_point, sdf_contact=sdf_contact)


