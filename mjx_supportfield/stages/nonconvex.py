"""Non-convex meshes: contacts from signed-distance fields of the true mesh.

MuJoCo collides every mesh through its convex hull, so a bowl is a dome. Geoms marked
non-convex (``Options.nonconvex_geoms`` or the MJCF custom text ``mjx_supportfield.nonconvex``)
keep their triangles: the mesh's SDF is baked at install (sdf.py, winding-number sign, disk
cache), and a pair with such a geom collides in two passes, both directions:
- vertex pass: points of one geom in the other's SDF: a non-convex mesh's vertices, a convex
  mesh's hull vertices, a box's corners, the centre of a sphere and the nearest axis point of
  a capsule (with their radius), 26 support points of a cylinder or an ellipsoid;
- edge pass, only when the vertex pass found nothing: the point of each non-convex mesh edge
  (or box edge) deepest in the other's SDF, by sampling the edge at cell spacing and then
  bisecting (edge-edge contacts, e.g. a rim across a box edge).
The other geom's SDF is its true mesh's when non-convex, its hull's when a convex mesh, a
closed form for primitives. Depth is the SDF value (less the radius), the normal its
gradient; points merge and the deepest and farthest are written (candidates.py). Planes and
heightfields meet a non-convex mesh through its hull, which touches them at the same points.

This module owns the non-convex stage's install-time data (which geoms, their SDFs) and kernel,
and its stage class, ``NonConvex`` (no per-Data buffers: it walks the broad phase's pair list).
"""

import functools
import warnings
from types import SimpleNamespace

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.sdf import MeshSdf
from mjx_supportfield.geometry.sdf import sdf_funcs
from mjx_supportfield.geometry.sdf import shape_sdf
from mjx_supportfield.geometry.sdf import shape_sdf_grad
from mjx_supportfield.geometry.shapes import posed_shape
from mjx_supportfield.geometry.support import GRID_DIRECTIONS
from mjx_supportfield.geometry.support import box_corner
from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import contact_mixing
from mjx_supportfield.launch.contact_quota import contact_outputs
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.grid import GRID_THREADS
from mjx_supportfield.options import Options
from mjx_supportfield.stages.candidates import Candidates
from mjx_supportfield.stages.candidates import add_candidate
from mjx_supportfield.stages.candidates import empty
from mjx_supportfield.stages.candidates import write_candidates
from mjx_supportfield.types import FAR
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

MARKER = "mjx_supportfield.nonconvex"  # custom text listing non-convex geom names
EDGE_SAMPLES = 16  # most samples along one edge before bisecting
BISECTIONS = 8


def nonconvex_geom_ids(mjm: mujoco.MjModel, names) -> list[int]:
  """Geom ids marked non-convex by ``names`` and by the MJCF marker; ValueError naming a geom
  that does not exist or is not a mesh."""
  wanted = list(names)
  tid = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_TEXT, MARKER)
  if tid >= 0:
    adr, size = int(mjm.text_adr[tid]), int(mjm.text_size[tid])
    text = bytes(mjm.text_data[adr : adr + size]).split(b"\0")[0].decode()
    wanted += text.replace(",", " ").split()
  ids = []
  for name in dict.fromkeys(wanted):
    g = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name)
    if g < 0:
      raise ValueError(f"non-convex geoms: no geom named '{name}'")
    if mjm.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH:
      raise ValueError(f"non-convex geoms: geom '{name}' is a {mujoco.mjtGeom(mjm.geom_type[g]).name}, not a mesh")
    ids.append(g)
  return ids


def mesh_triangles(mjm: mujoco.MjModel, meshid: int) -> np.ndarray:
  """The mesh's own triangles (vertex ids within the mesh)."""
  adr, num = int(mjm.mesh_faceadr[meshid]), int(mjm.mesh_facenum[meshid])
  return np.asarray(mjm.mesh_face[adr : adr + num], dtype=np.int32).reshape(-1, 3)


def open_edges(tris: np.ndarray) -> int:
  """Edges not shared by exactly two triangles (0 for a closed, manifold surface)."""
  e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
  _, counts = np.unique(e, axis=0, return_counts=True)
  return int((counts != 2).sum())


def warn_open_meshes(mjm: mujoco.MjModel, geoms) -> None:
  """Warns, naming the geom, when a non-convex mesh is not watertight (its SDF's sign then
  comes from winding numbers, which still tell inside from outside for small holes)."""
  for g in geoms:
    meshid = int(mjm.geom_dataid[g])
    n = open_edges(mesh_triangles(mjm, meshid))
    if n:
      name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g)
      mesh = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_MESH, meshid)
      warnings.warn(f"mjx_supportfield: geom '{name}': mesh '{mesh}' is not watertight ({n} open edges); its SDF "
                    "takes the inside/outside sign from winding numbers", stacklevel=3)


@wp.struct
class SdfSet:
  """The SDFs a pair may need: true meshes of non-convex geoms, hulls of convex meshes."""

  true_mesh: MeshSdf
  hull: MeshSdf


@wp.func
def _field(nonconvex: int, sdfs: SdfSet) -> MeshSdf:
  """The baked SDFs a mesh geom answers from: its true mesh's when non-convex, else its hull's."""
  if nonconvex:
    return sdfs.true_mesh
  return sdfs.hull


@wp.func
def signed_distance(s: Shape, nonconvex: int, sdfs: SdfSet, p_world: wp.vec3) -> float:
  """Signed distance of a world point to a geom (its true mesh when non-convex)."""
  return shape_sdf(s, _field(nonconvex, sdfs), p_world)


@wp.func
def _step(s: Shape, nonconvex: int, sdfs: SdfSet) -> float:
  """Finite-difference step and sampling spacing for a geom's SDF: a quarter cell of a baked
  grid, 1e-4 of the size for closed forms."""
  if s.gtype == GeomType.MESH:
    return 0.25 * _field(nonconvex, sdfs).cell[s.mesh]
  return 1.0e-4 * wp.max(wp.length(s.size), 1.0e-6)


@wp.func
def _point(c: wp.ref[Candidates], dst: Shape, dst_nonconvex: int, sdfs: SdfSet, p: wp.vec3, radius: float,
           side: int, band: float, spacing: float):
  """Adds to ``c`` a point of the source geom (a ball of ``radius`` around p) in dst's SDF. side
  0: dst is geom 1 (the normal is dst's gradient), side 1: dst is geom 2 (its opposite)."""
  phi = signed_distance(dst, dst_nonconvex, sdfs, p) - radius
  if phi >= band:
    return
  grad = shape_sdf_grad(dst, _field(dst_nonconvex, sdfs), p, _step(dst, dst_nonconvex, sdfs))
  n = wp.where(side == 0, grad, -grad)
  # midpoint of the source's surface point (p - radius grad) and dst's nearest surface point
  # (p - (phi + radius) grad); stored grown by the band, as the writer expects
  mid = p - 0.5 * (phi + 2.0 * radius) * grad
  add_candidate(c, mid + 0.5 * band * n, n, band - phi, spacing)


@wp.func
def _segment_min(dst: Shape, dst_nonconvex: int, sdfs: SdfSet, p0: wp.vec3, p1: wp.vec3, spacing: float) -> wp.vec3:
  """The point of segment p0-p1 deepest in dst's SDF: samples, then bisection around the best."""
  n = wp.clamp(int(wp.length(p1 - p0) / wp.max(spacing, 1.0e-9)) + 2, 2, EDGE_SAMPLES)
  best_t = float(0.0)
  best = float(FAR)
  for k in range(n):
    t = float(k) / float(n - 1)
    v = signed_distance(dst, dst_nonconvex, sdfs, p0 + t * (p1 - p0))
    if v < best:
      best = v
      best_t = t
  half = 0.5 / float(n - 1)
  for _ in range(BISECTIONS):
    lo_t = wp.max(best_t - half, 0.0)
    hi_t = wp.min(best_t + half, 1.0)
    vlo = signed_distance(dst, dst_nonconvex, sdfs, p0 + lo_t * (p1 - p0))
    vhi = signed_distance(dst, dst_nonconvex, sdfs, p0 + hi_t * (p1 - p0))
    if vlo < best:
      best = vlo
      best_t = lo_t
    if vhi < best:
      best = vhi
      best_t = hi_t
    half = 0.5 * half
  return p0 + best_t * (p1 - p0)


@wp.func
def _samples(src: Shape, src_nonconvex: int, ms: MeshSupport, mesh_vertnum: wp.array(dtype=int),
             mesh_facenum: wp.array(dtype=int), edges: int) -> int:
  """How many samples of src a pass tries (see the module doc): edges = 0 the vertex pass, 1
  the edge pass (3 a triangle of a non-convex mesh, of which each edge's second copy is
  skipped)."""
  if edges:
    if src.gtype == GeomType.BOX:
      return 12
    if src.gtype == GeomType.MESH and src_nonconvex:
      return 3 * mesh_facenum[src.mesh]
    return 0
  if src.gtype == GeomType.SPHERE or src.gtype == GeomType.CAPSULE:
    return 1
  if src.gtype == GeomType.BOX:
    return 8
  if src.gtype == GeomType.MESH:
    if src_nonconvex:
      return mesh_vertnum[src.mesh]
    return ms.hull_num[src.mesh]
  return GRID_DIRECTIONS  # cylinder, ellipsoid: support points in the grid directions


@functools.lru_cache(maxsize=None)
def candidate_funcs(mode: int) -> SimpleNamespace:
  """The candidates' device functions on the support functions of support mode ``mode``
  (sdf_funcs: a convex shape's samples are support points): ``pair_candidates``."""
  sample_point = sdf_funcs(mode).sample_point

  @wp.func
  def _sample(src: Shape, src_nonconvex: int, ms: MeshSupport, mesh_face: wp.array(dtype=wp.vec3i),
              mesh_faceadr: wp.array(dtype=int), edges: int,
              k: int) -> tuple[wp.vec3, wp.vec3, float, bool]:
    """Sample k of src for a pass (see _samples): a segment p0-p1 (its point deepest in the other
    geom's SDF counts; p0 = p1 for a point), the radius around it, and whether it is one."""
    if edges == 0:
      if src.gtype == GeomType.SPHERE:
        return src.pos, src.pos, src.size[0], True
      if src.gtype == GeomType.CAPSULE:
        axis = wp.vec3(src.rot[0, 2], src.rot[1, 2], src.rot[2, 2])
        return src.pos - src.size[1] * axis, src.pos + src.size[1] * axis, src.size[0], True
      p = wp.vec3(0.0)
      if src.gtype == GeomType.BOX:
        p = box_corner(src, k)
      elif src.gtype == GeomType.MESH and src_nonconvex:
        p = src.pos + src.rot @ ms.vert[ms.vertadr[src.mesh] + k]
      else:
        p = sample_point(src, ms, k)  # a convex mesh's hull vertices, 26 support points
      return p, p, 0.0, True
    if src.gtype == GeomType.BOX:
      along = k // 4  # edges along x, y, z: 4 each
      j = k % 4
      bits0 = wp.where(along == 0, (j & 1) * 2 + (j & 2) * 2, wp.where(along == 1, (j & 1) + (j & 2) * 2, (j & 1) + (j & 2)))
      bits1 = bits0 + wp.where(along == 0, 1, wp.where(along == 1, 2, 4))
      return box_corner(src, bits0), box_corner(src, bits1), 0.0, True
    tri = mesh_face[mesh_faceadr[src.mesh] + k // 3]
    i0 = tri[k % 3]
    i1 = tri[(k + 1) % 3]
    adr = ms.vertadr[src.mesh]
    p0 = src.pos + src.rot @ ms.vert[adr + i0]
    p1 = src.pos + src.rot @ ms.vert[adr + i1]
    return p0, p1, 0.0, i0 < i1  # each edge of a closed mesh belongs to two triangles: take it once

  @wp.func
  def pair_candidates(cands: wp.ref[Candidates], a: Shape, nc1: int, b: Shape, nc2: int, sdfs: SdfSet,
                      ms: MeshSupport, mesh_vertnum: wp.array(dtype=int), mesh_face: wp.array(dtype=wp.vec3i),
                      mesh_faceadr: wp.array(dtype=int), mesh_facenum: wp.array(dtype=int), band: float,
                      spacing: float):
    """Adds to ``cands`` the contact candidates of a pair with a non-convex mesh: the vertex pass both ways (B's
    samples in A's SDF, then A's in B's), then, when it found nothing, the edge pass both ways.

    One loop with runtime bounds and one call site for the SDF point and the edge search:
    unrolled (a box's 8 corners and 12 edges, 26 samples, four passes) the CUDA build of this
    module ran for over 45 minutes."""
    stage = int(0)  # 2 x edges + side
    k = int(0)
    while stage < 4:
      side = stage % 2
      edges = stage // 2
      src = b
      src_nc = nc2
      dst = a
      dst_nc = nc1
      if side == 1:
        src = a
        src_nc = nc1
        dst = b
        dst_nc = nc2
      if stage == 2 and k == 0 and cands.n > 0:
        break  # the vertex pass found contacts: no edge pass
      if k >= _samples(src, src_nc, ms, mesh_vertnum, mesh_facenum, edges):
        stage += 1
        k = 0
        continue
      p0, p1, radius, valid = _sample(src, src_nc, ms, mesh_face, mesh_faceadr, edges, k)
      k += 1
      if not valid:
        continue
      q = p0
      if wp.length(p1 - p0) > 0.0:
        q = _segment_min(dst, dst_nc, sdfs, p0, p1, _step(dst, dst_nc, sdfs) * 4.0)
      _point(cands, dst, dst_nc, sdfs, q, radius, side, band, spacing)

  return SimpleNamespace(pair_candidates=pair_candidates)


@functools.lru_cache(maxsize=None)
def nonconvex_narrowphase(mode: int) -> wp.Kernel:
  """The non-convex pairs' kernel for support mode ``mode``, in that mode's module
  (types.mode_module)."""
  pair_candidates = candidate_funcs(mode).pair_candidates

  @wp.kernel(module=mode_module(__name__, mode))
  def nonconvex_narrowphase(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    mesh_vertnum: wp.array(dtype=int),
    mesh_faceadr: wp.array(dtype=int),
    mesh_facenum: wp.array(dtype=int),
    mesh_face: wp.array(dtype=wp.vec3i),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    geom_nonconvex: wp.array(dtype=int),
    sdfs: SdfSet,
    max_contacts: int,
    mc_tolerance: float,
    npair_in: wp.array(dtype=int),
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    nthread: int,
    quota: ContactQuota,
    # Data out:
    contacts_out: ContactRows,
  ):
    """Contacts of pairs with a non-convex mesh (and neither a plane nor a heightfield)."""
    tid = wp.tid()
    for cid in range(tid, npair_in[0], nthread):
      geoms = pair_in[cid]
      g1 = geoms[0]
      g2 = geoms[1]
      nc1 = geom_nonconvex[g1]
      nc2 = geom_nonconvex[g2]
      if nc1 == 0 and nc2 == 0:
        continue
      t1 = geom_type[g1]
      if t1 == GeomType.PLANE or t1 == GeomType.HFIELD:
        continue
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      a = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, g1, worldid)
      b = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, g2, worldid)
      band = wp.max(margin + gap, 0.0)
      ab = worldid % geom_aabb.shape[0]
      spacing = mc_tolerance * 2.0 * wp.min(wp.length(geom_aabb[ab, g1, 1]), wp.length(geom_aabb[ab, g2, 1]))
      cands = empty()
      pair_candidates(cands, a, nc1, b, nc2, sdfs, ms, mesh_vertnum, mesh_face, mesh_faceadr, mesh_facenum, band,
                      spacing)
      write_candidates(
        cands, max_contacts, wp.identity(n=3, dtype=float), wp.vec3(0.0), band, naconmax_in, margin, gap, condim,
        friction, solref, solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
      )

  return nonconvex_narrowphase





class NonConvex:
  """Non-convex meshes through their triangles' SDFs: what install built for them, and the step's
  launch (the stage contract: docs/architecture.md)."""

  def __init__(self, options: Options, support_mode: SupportMode, mesh_support: MeshSupport, has_pairs: bool,
               geom_nonconvex: wp.array, mesh_faceadr: wp.array, mesh_facenum: wp.array, sdfs: SdfSet):
    self.options, self.support_mode, self.mesh_support = options, support_mode, mesh_support
    self.has_pairs = has_pairs  # a pair of the model has a mesh marked non-convex
    self.geom_nonconvex = geom_nonconvex  # per geom: 1 for a mesh collided through its triangles
    self.mesh_faceadr, self.mesh_facenum = mesh_faceadr, mesh_facenum
    self.sdfs = sdfs  # the marked meshes' true SDFs and the hull SDFs

  def make_buffers(self, d, st) -> None:
    """None: one kernel, no buffers of its own."""
    return None

  def launch(self, m, d, st) -> None:
    """The non-convex pairs of one step."""
    pairs, quota = st.broad, st.quota.quota
    if not self.has_pairs:
      return
    opt = self.options
    nthread = max(1, min(pairs.capacity, GRID_THREADS))
    pair_inputs = [pairs.npair, pairs.pair, pairs.pairid, pairs.pair_worldid, nthread]
    wp.launch(
      nonconvex_narrowphase(self.support_mode),
      dim=nthread,
      inputs=[
        m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_aabb, m.mesh_vertnum,
        self.mesh_faceadr, self.mesh_facenum, m.mesh_face, d.geom_xpos, d.geom_xmat,
        d.naconmax, self.mesh_support, self.geom_nonconvex, self.sdfs,
        opt.max_contacts_per_pair, opt.mc_tolerance,
      ] + pair_inputs + [quota],
      outputs=contact_outputs(d),
    )
