"""Narrow phase: analytic pairs through MuJoCo Warp's routines, the rest by support-field MPR.

Both kernels walk the plugin's pair list with a grid-stride loop, so their launch size does
not depend on the (host-unknown) number of pairs and they can be captured in a CUDA graph.

This module owns the convex narrow phase's kernels (sift, analytic, MPR / GJK) and the
multi-contact kernels that follow them (face pairs, manifolds, tilts, patches), their per-Data
buffers (``Buffers``, ``make_buffers``) and their host entries, ``launch`` and
``launch_multicontact``.
"""

import dataclasses
import functools

import numpy as np
import warp as wp
from mujoco_warp._src.collision_core import contact_margin_gap
from mujoco_warp._src.collision_core import contact_params
from mujoco_warp._src.collision_core import geom_collision_pair
from mujoco_warp._src.collision_core import write_contact
from mujoco_warp._src.collision_primitive import _PRIMITIVE_COLLISIONS
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import vec5

from mjx_supportfield import warmstart
from mjx_supportfield.contact_quota import ContactQuota
from mjx_supportfield.contact_quota import contact_outputs
from mjx_supportfield.contact_quota import world_rows
from mjx_supportfield.gjk import gjk_epa
from mjx_supportfield.mpr import BEHIND
from mjx_supportfield.mpr import MprResult
from mjx_supportfield.mpr import apart_along_centres
from mjx_supportfield.mpr import behind_origin
from mjx_supportfield.mpr import interior_point
from mjx_supportfield.mpr import mpr_refined_from
from mjx_supportfield.multicontact import NPERTURB
from mjx_supportfield.multicontact import TILTS
from mjx_supportfield.multicontact import TILT_GROWTH
from mjx_supportfield.multicontact import UNKNOWN
from mjx_supportfield.multicontact import Patch
from mjx_supportfield.multicontact import clip_faces
from mjx_supportfield.multicontact import face_pair
from mjx_supportfield.multicontact import keep_first
from mjx_supportfield.multicontact import manifold_dist
from mjx_supportfield.multicontact import manifold_pos
from mjx_supportfield.multicontact import patch_possible
from mjx_supportfield.multicontact import perturbed_contacts
from mjx_supportfield.multicontact import tilt_closed_form
from mjx_supportfield.multicontact import tilt_mpr
from mjx_supportfield.multicontact import tilt_rotation
from mjx_supportfield.sdf import MeshSdf
from mjx_supportfield.sdf import needs_sdf
from mjx_supportfield.sdf import sdf_contact
from mjx_supportfield.types import CONVEX_TYPES
from mjx_supportfield.types import SUPPORT_MODE_ID
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

# pairs MuJoCo Warp solves in closed form (plane-*, sphere/capsule pairs, box-box, plane-mesh)
ANALYTIC_PAIRS = tuple(_PRIMITIVE_COLLISIONS.keys())

NGEOMTYPE = len(GeomType)
# the narrow-phase kernels' pair queues (queue_pair)
QUEUE_ANALYTIC = wp.constant(0)
QUEUE_MPR = wp.constant(1)
QUEUE_GJK = wp.constant(2)
QUEUE_CANDIDATE = wp.constant(3)  # MPR pairs not yet tested for being apart (sift_mpr_pairs)
NQUEUE = 4
# register cap of the MPR, GJK and multi-contact kernels: uncapped they sit at 255 registers,
# which leaves 8 warps an SM to hide their memory latency; at 128 (16 warps) they spill a few
# hundred bytes to the stack and still run faster (measured caps: docs/performance.md, "Register cap")
HEAVY_REGISTERS = 128
GRID_THREADS = 1 << 20  # cap of the grid-stride narrow-phase launches
# multi-contact pairs per world left to the tilts (no face clipping) whose tilts run in parallel
# threads (tilt_kernel); pairs beyond run them in patch_kernel's thread: same result, only slower
TILT_PAIRS_PER_WORLD = 32


@functools.lru_cache(maxsize=None)
def analytic_kernel(pair_types: tuple):
  """Grid-stride kernel running MuJoCo Warp's analytic routine of each pair type present."""
  funcs = [_PRIMITIVE_COLLISIONS[t] for t in pair_types]

  @wp.kernel(module="unique", enable_backward=False)
  def analytic_narrowphase(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_condim: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_priority: wp.array(dtype=int),
    geom_solmix: wp.array2d(dtype=float),
    geom_solref: wp.array2d(dtype=wp.vec2),
    geom_solimp: wp.array2d(dtype=vec5),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_friction: wp.array2d(dtype=wp.vec3),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    geom_adhesion: wp.array2d(dtype=float),
    mesh_vertadr: wp.array(dtype=int),
    mesh_vertnum: wp.array(dtype=int),
    mesh_graphadr: wp.array(dtype=int),
    mesh_vert: wp.array(dtype=wp.vec3),
    mesh_graph: wp.array(dtype=int),
    mesh_polynum: wp.array(dtype=int),
    mesh_polyadr: wp.array(dtype=int),
    mesh_polynormal: wp.array(dtype=wp.vec3),
    mesh_polyvertadr: wp.array(dtype=int),
    mesh_polyvertnum: wp.array(dtype=int),
    mesh_polyvert: wp.array(dtype=int),
    mesh_polymapadr: wp.array(dtype=int),
    mesh_polymapnum: wp.array(dtype=int),
    mesh_polymap: wp.array(dtype=int),
    pair_dim: wp.array(dtype=int),
    pair_solref: wp.array2d(dtype=wp.vec2),
    pair_solreffriction: wp.array2d(dtype=wp.vec2),
    pair_solimp: wp.array2d(dtype=vec5),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    pair_adhesion: wp.array2d(dtype=float),
    pair_friction: wp.array2d(dtype=vec5),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    queue_count: wp.array(dtype=int),
    queue_pair: wp.array2d(dtype=int),
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    nthread: int,
    quota: ContactQuota,
    # Data out:
    contact_dist_out: wp.array(dtype=float),
    contact_pos_out: wp.array(dtype=wp.vec3),
    contact_frame_out: wp.array(dtype=wp.mat33),
    contact_includemargin_out: wp.array(dtype=float),
    contact_friction_out: wp.array(dtype=vec5),
    contact_solref_out: wp.array(dtype=wp.vec2),
    contact_solreffriction_out: wp.array(dtype=wp.vec2),
    contact_solimp_out: wp.array(dtype=vec5),
    contact_dim_out: wp.array(dtype=int),
    contact_geom_out: wp.array(dtype=wp.vec2i),
    contact_efc_address_out: wp.array2d(dtype=int),
    contact_worldid_out: wp.array(dtype=int),
    contact_type_out: wp.array(dtype=int),
    contact_geomcollisionid_out: wp.array(dtype=int),
    contact_adhesion_out: wp.array(dtype=float),
    nacon_out: wp.array(dtype=int),
  ):
    tid = wp.tid()
    for i in range(tid, queue_count[QUEUE_ANALYTIC], nthread):
      cid = queue_pair[QUEUE_ANALYTIC, i]
      geoms = pair_in[cid]
      type1 = geom_type[geoms[0]]
      type2 = geom_type[geoms[1]]
      worldid = pair_worldid_in[cid]
      (limit, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
       rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type, rows_geomcollisionid, rows_adhesion,
       rows_nacon) = world_rows(
        quota, worldid, naconmax_in, contact_dist_out, contact_pos_out, contact_frame_out, contact_includemargin_out,
        contact_friction_out, contact_solref_out, contact_solreffriction_out, contact_solimp_out, contact_dim_out,
        contact_geom_out, contact_efc_address_out, contact_worldid_out, contact_type_out, contact_geomcollisionid_out,
        contact_adhesion_out, nacon_out,
      )
      for i in range(wp.static(len(funcs))):
        if type1 == wp.static(pair_types[i][0]) and type2 == wp.static(pair_types[i][1]):
          _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = contact_params(
            geom_condim,
            geom_priority,
            geom_solmix,
            geom_solref,
            geom_solimp,
            geom_friction,
            geom_margin,
            geom_gap,
            geom_adhesion,
            pair_dim,
            pair_solref,
            pair_solreffriction,
            pair_solimp,
            pair_margin,
            pair_gap,
            pair_adhesion,
            pair_friction,
            pair_in,
            pairid_in,
            cid,
            worldid,
          )
          geom1, geom2 = geom_collision_pair(
            geom_type,
            geom_dataid,
            geom_size,
            mesh_vertadr,
            mesh_vertnum,
            mesh_graphadr,
            mesh_vert,
            mesh_graph,
            mesh_polynum,
            mesh_polyadr,
            mesh_polynormal,
            mesh_polyvertadr,
            mesh_polyvertnum,
            mesh_polyvert,
            mesh_polymapadr,
            mesh_polymapnum,
            mesh_polymap,
            geom_xpos_in,
            geom_xmat_in,
            geoms,
            worldid,
          )
          wp.static(funcs[i])(
            limit,
            geom1,
            geom2,
            worldid,
            margin,
            gap,
            condim,
            friction,
            solref,
            solreffriction,
            solimp,
            adhesion,
            geoms,
            pairid_in[cid],
            rows_dist,
            rows_pos,
            rows_frame,
            rows_includemargin,
            rows_friction,
            rows_solref,
            rows_solreffriction,
            rows_solimp,
            rows_dim,
            rows_geom,
            rows_efc_address,
            rows_worldid,
            rows_type,
            rows_geomcollisionid,
            rows_adhesion,
            rows_nacon,
          )

  return analytic_narrowphase


@wp.func
def posed_shape(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  geomid: int,
  worldid: int,
) -> Shape:
  """Geom ``geomid`` of world ``worldid`` as a Shape (world frame, no inflation)."""
  s = Shape()
  s.gtype = geom_type[geomid]
  s.pos = geom_xpos_in[worldid, geomid]
  s.rot = geom_xmat_in[worldid, geomid]
  s.size = geom_size[worldid % geom_size.shape[0], geomid]
  s.mesh = -1
  s.center = s.pos
  s.inflate = 0.0
  if s.gtype == GeomType.MESH:
    s.mesh = geom_dataid[worldid % geom_dataid.shape[0], geomid]
    s.center = s.pos + s.rot @ ms.hull_center[s.mesh]
  return s


@wp.func
def posed_pair(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  band: float,
  geoms: wp.vec2i,
  worldid: int,
):
  """A pair as the narrow phase collides it: A grown by the margin band, B, and the pair's scale
  (the sum of the bounding radii; thresholds are relative to it)."""
  a = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[0], worldid)
  b = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[1], worldid)
  a.inflate = band
  rb = worldid % geom_rbound.shape[0]
  return a, b, wp.max(geom_rbound[rb, geoms[0]] + geom_rbound[rb, geoms[1]], 1.0e-9)


@wp.func
def write_pair_contacts(
  res: MprResult,
  extra: Patch,
  min_spacing: float,
  tol_abs: float,
  max_contacts: int,
  band: float,
  naconmax_in: int,
  margin: float,
  gap: float,
  condim: int,
  friction: vec5,
  solref: wp.vec2,
  solreffriction: wp.vec2,
  solimp: vec5,
  adhesion: float,
  geoms: wp.vec2i,
  pairid: wp.vec2i,
  worldid: int,
  contact_dist_out: wp.array(dtype=float),
  contact_pos_out: wp.array(dtype=wp.vec3),
  contact_frame_out: wp.array(dtype=wp.mat33),
  contact_includemargin_out: wp.array(dtype=float),
  contact_friction_out: wp.array(dtype=vec5),
  contact_solref_out: wp.array(dtype=wp.vec2),
  contact_solreffriction_out: wp.array(dtype=wp.vec2),
  contact_solimp_out: wp.array(dtype=vec5),
  contact_dim_out: wp.array(dtype=int),
  contact_geom_out: wp.array(dtype=wp.vec2i),
  contact_efc_address_out: wp.array2d(dtype=int),
  contact_worldid_out: wp.array(dtype=int),
  contact_type_out: wp.array(dtype=int),
  contact_geomcollisionid_out: wp.array(dtype=int),
  contact_adhesion_out: wp.array(dtype=float),
  nacon_out: wp.array(dtype=int),
  quota: ContactQuota,
):
  """Writes a pair's contacts: MPR's point (when kept, see keep_first), then the patch's points,
  all with MPR's normal; the margin band comes off depth and position."""
  (limit, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
   rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type, rows_geomcollisionid, rows_adhesion,
   rows_nacon) = world_rows(
    quota, worldid, naconmax_in, contact_dist_out, contact_pos_out, contact_frame_out, contact_includemargin_out,
    contact_friction_out, contact_solref_out, contact_solreffriction_out, contact_solimp_out, contact_dim_out,
    contact_geom_out, contact_efc_address_out, contact_worldid_out, contact_type_out, contact_geomcollisionid_out,
    contact_adhesion_out, nacon_out,
  )
  first = wp.where(extra.n > 0, wp.where(keep_first(res, extra, min_spacing, tol_abs), -1, 0), -1)
  count = wp.min(wp.max(extra.n, 0) - first, max_contacts)
  frame = make_frame(res.normal)
  for k in range(count):
    j = first + k
    depth = res.depth
    pos = res.pos
    if j >= 0:
      depth = extra.depth[j]
      pos = wp.vec3(extra.pos[j, 0], extra.pos[j, 1], extra.pos[j, 2])
    write_contact(
      limit, k, band - depth, pos - 0.5 * band * res.normal, frame, margin, gap, condim, friction, solref,
      solreffriction, solimp, adhesion, geoms, pairid, worldid, rows_dist, rows_pos, rows_frame,
      rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
      rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid,
      rows_type, rows_geomcollisionid, rows_adhesion, rows_nacon,
    )


@wp.func
def has_core(type1: int, type2: int) -> bool:
  """Whether a pair has a sphere or capsule (a point or segment core grown by a radius)."""
  return (type1 == GeomType.SPHERE or type1 == GeomType.CAPSULE or type2 == GeomType.SPHERE
          or type2 == GeomType.CAPSULE)


@wp.func
def _apart(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  support_mode: int,
  geoms: wp.vec2i,
  pairid: int,
  worldid: int,
) -> bool:
  """apart_along_centres for a pair as convex_narrowphase poses it (A grown by the margin band)."""
  margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid, worldid)
  a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                           wp.max(margin + gap, 0.0), geoms, worldid)
  return apart_along_centres(a, b, ms, support_mode, scale)


@wp.struct
class PairQueues:
  """Where the broad phase deals out the pairs it lists: one queue per narrow-phase kernel.

  ``pair_queue_type`` maps a pair's geom types (type1 * NGEOMTYPE + type2) to QUEUE_ANALYTIC or
  QUEUE_MPR, else -1 (the heightfield and non-convex kernels, and stock MuJoCo Warp, walk the
  whole list)."""

  pair_queue_type: wp.array(dtype=int)
  geom_nonconvex: wp.array(dtype=int)
  gjk_all: int  # narrowphase="gjk": every convex non-analytic pair to GJK/EPA
  count: wp.array(dtype=int)  # (NQUEUE,) pairs in each queue
  pair: wp.array2d(dtype=int)  # (NQUEUE, capacity): indices into the pair list


@wp.func
def queue_pair(geom_type: wp.array(dtype=int), geoms: wp.vec2i, cid: int, queues: PairQueues):
  """Queues pair ``cid`` of the list for its narrow-phase kernel, so the warps of each kernel
  run only pairs of their own kind (in one pair list, a pile's mesh-plane pairs sat idle in the
  MPR kernel's warps, between the mesh-mesh pairs).

  A convex pair with a sphere or capsule goes to GJK (a point or segment core grown by a
  radius: GJK gives the exact nearest points, where MPR's normal drifts for a small sphere sunk
  deep), as do all with ``gjk_all``; one with a non-convex mesh goes to nonconvex.py. The other
  MPR pairs wait in QUEUE_CANDIDATE for sift_mpr_pairs. Cheap on purpose: the broad-phase
  kernels that call it run a thread per (world, pair), and support queries here made those
  threads heavy (aloha_pot's nxn kernel: 2.8 ms at 8192 worlds).
  """
  type1 = geom_type[geoms[0]]
  type2 = geom_type[geoms[1]]
  queue = queues.pair_queue_type[type1 * wp.static(NGEOMTYPE) + type2]
  if queue == QUEUE_MPR:
    if queues.geom_nonconvex[geoms[0]] or queues.geom_nonconvex[geoms[1]]:
      return
    if queues.gjk_all != 0 or has_core(type1, type2):
      queue = QUEUE_GJK
    else:
      queue = QUEUE_CANDIDATE
  if queue >= 0:
    slot = wp.atomic_add(queues.count, queue, 1)
    queues.pair[queue, slot] = cid


@wp.kernel(enable_backward=False)
def sift_mpr_pairs(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  nthread: int,
  # Out:
  queues: PairQueues,
):
  """Moves the MPR pairs that MPR's first step does not prove apart (two support points,
  apart_along_centres) from QUEUE_CANDIDATE to QUEUE_MPR: in a pile most broad-phase pairs are
  such near misses, and in the MPR kernel's warps their lanes idled beside the pairs that touch."""
  tid = wp.tid()
  for i in range(tid, queues.count[QUEUE_CANDIDATE], nthread):
    cid = queues.pair[QUEUE_CANDIDATE, i]
    if not _apart(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap, pair_margin, pair_gap,
                  geom_xpos_in, geom_xmat_in, ms, support_mode, pair_in[cid], pairid_in[cid][0], pair_worldid_in[cid]):
      slot = wp.atomic_add(queues.count, QUEUE_MPR, 1)
      queues.pair[QUEUE_MPR, slot] = cid


@functools.lru_cache(maxsize=None)
def convex_kernel(use_gjk: bool):
  """The narrow-phase kernel of the convex pairs that are not analytic: penetration by MPR
  (warm-started, refined), or, with ``use_gjk``, by GJK/EPA (gjk.py).

  Each variant walks its own queue (queue_pair). Two kernels, not one branch: EPA's polytope
  takes about 10 KB of stack a thread, and inlined beside MPR it made every MPR pair slower on
  the GPU.
  """

  @wp.kernel(module="unique", enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
  def convex_narrowphase(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_condim: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_priority: wp.array(dtype=int),
    geom_solmix: wp.array2d(dtype=float),
    geom_solref: wp.array2d(dtype=wp.vec2),
    geom_solimp: wp.array2d(dtype=vec5),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_friction: wp.array2d(dtype=wp.vec3),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    geom_adhesion: wp.array2d(dtype=float),
    pair_dim: wp.array(dtype=int),
    pair_solref: wp.array2d(dtype=wp.vec2),
    pair_solreffriction: wp.array2d(dtype=wp.vec2),
    pair_solimp: wp.array2d(dtype=vec5),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    pair_adhesion: wp.array2d(dtype=float),
    pair_friction: wp.array2d(dtype=vec5),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    support_mode: int,
    tolerance: float,
    iterations: int,
    refine: int,
    max_contacts: int,
    mc_perturbation: float,
    sdf: MeshSdf,
    sdf_ratio: float,
    warm_start: int,
    ws_stamp: wp.array(dtype=int),
    ws_slot_stamp: wp.array2d(dtype=int),
    ws_slot_key: wp.array2d(dtype=int),
    ws_slot_value: wp.array2d(dtype=wp.vec4),
    ws_misses: wp.array(dtype=int),
    queue_count: wp.array(dtype=int),
    queue_pair: wp.array2d(dtype=int),
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    nthread: int,
    quota: ContactQuota,
    # Out:
    patch_count: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    # Data out:
    contact_dist_out: wp.array(dtype=float),
    contact_pos_out: wp.array(dtype=wp.vec3),
    contact_frame_out: wp.array(dtype=wp.mat33),
    contact_includemargin_out: wp.array(dtype=float),
    contact_friction_out: wp.array(dtype=vec5),
    contact_solref_out: wp.array(dtype=wp.vec2),
    contact_solreffriction_out: wp.array(dtype=wp.vec2),
    contact_solimp_out: wp.array(dtype=vec5),
    contact_dim_out: wp.array(dtype=int),
    contact_geom_out: wp.array(dtype=wp.vec2i),
    contact_efc_address_out: wp.array2d(dtype=int),
    contact_worldid_out: wp.array(dtype=int),
    contact_type_out: wp.array(dtype=int),
    contact_geomcollisionid_out: wp.array(dtype=int),
    contact_adhesion_out: wp.array(dtype=float),
    nacon_out: wp.array(dtype=int),
  ):
    """Contacts of convex pairs by MPR (or GJK/EPA) on the shapes' support functions: the
    deepest point; a pair that may touch in more points (not spheres and ellipsoids, where one
    point is the whole contact) is queued for face_pair_kernel instead, and face clipping or the
    tilts write up to max_contacts. With warm_start, MPR starts from the pair's normal of the previous call and
    falls back to a cold start when that misses."""
    tid = wp.tid()
    now = ws_stamp[0]
    queue = wp.static(QUEUE_GJK if use_gjk else QUEUE_MPR)
    for i in range(tid, queue_count[queue], nthread):
      cid = queue_pair[queue, i]
      geoms = pair_in[cid]
      g1 = geoms[0]
      g2 = geoms[1]
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = contact_params(
        geom_condim,
        geom_priority,
        geom_solmix,
        geom_solref,
        geom_solimp,
        geom_friction,
        geom_margin,
        geom_gap,
        geom_adhesion,
        pair_dim,
        pair_solref,
        pair_solreffriction,
        pair_solimp,
        pair_margin,
        pair_gap,
        pair_adhesion,
        pair_friction,
        pair_in,
        pairid_in,
        cid,
        worldid,
      )
      # contacts are wanted up to margin + gap apart: grow A by that band, shrink the answer back
      band = wp.max(margin + gap, 0.0)
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                               geoms, worldid)
      rb = worldid % geom_rbound.shape[0]
      key = g1 * geom_type.shape[0] + g2
      res = MprResult()
      res.hit = 0
      if wp.static(use_gjk):
        res = gjk_epa(a, b, ms, support_mode, scale, tolerance, iterations)
      else:
        last = wp.vec4(0.0)
        if warm_start:
          last = warmstart.lookup(ws_slot_stamp, ws_slot_key, ws_slot_value, now, worldid, key)
        # one MPR call site, in a loop, keeps the kernel small: warm first when the pair has a
        # normal from the previous call, then cold if that found nothing
        for attempt in range(2):
          if attempt == 1 and (res.hit != 0 or last[3] <= 0.0):
            break
          if attempt == 1:
            wp.atomic_add(ws_misses, 0, 1)
          q0 = interior_point(a, b, scale)
          if attempt == 0 and last[3] > 0.0:
            q0 = behind_origin(a, b, ms, support_mode, wp.vec3(last[0], last[1], last[2]), last[3], scale, BEHIND)
          res = mpr_refined_from(a, b, ms, support_mode, q0, scale, tolerance, iterations, refine, BEHIND)
      if res.hit == 0:
        continue
      extra = Patch()
      extra.n = 0
      # one shape largely inside the other (deeper than sdf_ratio x the smaller one's bounding
      # diameter): MPR's portal face need not be the nearest; the SDFs know the nearest surface
      # (EPA's depth is exact: the fallback only serves MPR)
      if not wp.static(use_gjk) and needs_sdf(res.depth - band, geom_rbound[rb, g1], geom_rbound[rb, g2], sdf_ratio):
        bare = a  # the SDFs measure the true surfaces; A keeps its margin band for multi-contact
        bare.inflate = 0.0
        fallback = sdf_contact(bare, b, ms, sdf, support_mode, 1.0e-4 * scale)
        if fallback.hit and fallback.depth + band < res.depth:
          res.depth = fallback.depth + band
          res.normal = fallback.normal
          res.pos = fallback.pos + 0.5 * band * fallback.normal
          extra.n = -1  # a fallback contact is not perturbed
      if warm_start and not wp.static(use_gjk):
        value = wp.vec4(res.normal[0], res.normal[1], res.normal[2], res.depth)
        warmstart.insert(ws_slot_stamp, ws_slot_key, ws_slot_value, now, worldid, key, value)
      one_point = (
        geom_type[g1] == GeomType.SPHERE
        or geom_type[g1] == GeomType.ELLIPSOID
        or geom_type[g2] == GeomType.SPHERE
        or geom_type[g2] == GeomType.ELLIPSOID
      )
      tilt = mc_perturbation * TILT_GROWTH  # the steepest tilt perturbed_contacts tries
      if max_contacts > 1 and not one_point and extra.n == 0 and patch_possible(a, b, ms, res.normal, tilt, res.depth):
        # queued for face_pair_kernel, which leaves the pairs without a face pair to the tilts
        slot = wp.atomic_add(patch_count, 0, 1)
        patch_pair[slot] = cid
        patch_result[slot] = wp.vec4(res.normal[0], res.normal[1], res.normal[2], res.depth)
        patch_pos[slot] = res.pos
        continue
      write_pair_contacts(
        res, extra, 0.0, 0.0, 1, band, naconmax_in, margin, gap, condim, friction, solref, solreffriction, solimp,
        adhesion, geoms, pairid_in[cid], worldid, contact_dist_out, contact_pos_out, contact_frame_out,
        contact_includemargin_out, contact_friction_out, contact_solref_out, contact_solreffriction_out,
        contact_solimp_out, contact_dim_out, contact_geom_out, contact_efc_address_out, contact_worldid_out,
        contact_type_out, contact_geomcollisionid_out, contact_adhesion_out, nacon_out, quota,
      )

  return convex_narrowphase


@wp.func
def _queued_patch(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  band: float,
  geoms: wp.vec2i,
  worldid: int,
  result: wp.vec4,
  pos: wp.vec3,
):
  """A queued multi-contact pair: its shapes (A grown by the margin band), scale, and the first contact."""
  a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                           geoms, worldid)
  res = MprResult()
  res.hit = 1
  res.normal = wp.vec3(result[0], result[1], result[2])
  res.depth = result[3]
  res.pos = pos
  return a, b, scale, res


@wp.func
def _queued_first(result: wp.vec4, pos: wp.vec3) -> MprResult:
  """A queued multi-contact pair's first contact."""
  res = MprResult()
  res.hit = 1
  res.normal = wp.vec3(result[0], result[1], result[2])
  res.depth = result[3]
  res.pos = pos
  return res


@wp.func
def _queued_tilt(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  mc_perturbation: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  i: int,
  j: int,
):
  """Attempt j // NPERTURB of tilt j % NPERTURB of queued multi-contact pair i: its shapes,
  scale, first contact and rotation."""
  cid = patch_pair[i]
  geoms = pair_in[cid]
  worldid = pair_worldid_in[cid]
  margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
  a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                                   wp.max(margin + gap, 0.0), geoms, worldid, patch_result[i], patch_pos[i])
  return a, b, scale, res, tilt_rotation(res.normal, mc_perturbation, j % NPERTURB, j // NPERTURB)


@wp.kernel(enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
def face_pair_kernel(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  patch_count: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  nthread: int,
  # Out:
  face_count: wp.array(dtype=int),
  face_queue: wp.array(dtype=int),
  face_faces: wp.array(dtype=wp.vec3i),
  tilt_pair_count: wp.array(dtype=int),
  tilt_pair: wp.array(dtype=int),
):
  """The pairs convex_narrowphase queued for multi-contact, one thread a pair: those touching
  face on feature along the normal (multicontact.face_pair) are queued, with their faces, for
  manifold_kernel; the rest (edge on edge, curved surfaces, polygons over budget), by their
  index in the multi-contact queue, for the tilts (tilt_kernel, tilt_mpr_kernel, patch_kernel).
  Apart from the clipping, so that the support queries here and the clipping's loops there do
  not share one kernel's registers, and the clipping runs on dense warps of face pairs."""
  tid = wp.tid()
  for i in range(tid, patch_count[0], nthread):
    cid = patch_pair[i]
    geoms = pair_in[cid]
    worldid = pair_worldid_in[cid]
    margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
    a, b, _ = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                         wp.max(margin + gap, 0.0), geoms, worldid)
    result = patch_result[i]
    faces = face_pair(a, b, ms, support_mode, wp.vec3(result[0], result[1], result[2]))
    if faces[0] < 0:
      tilt_pair[wp.atomic_add(tilt_pair_count, 0, 1)] = i
    else:
      slot = wp.atomic_add(face_count, 0, 1)
      face_queue[slot] = i
      face_faces[slot] = faces


@wp.kernel(enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
def manifold_kernel(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_condim: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_priority: wp.array(dtype=int),
  geom_solmix: wp.array2d(dtype=float),
  geom_solref: wp.array2d(dtype=wp.vec2),
  geom_solimp: wp.array2d(dtype=vec5),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_friction: wp.array2d(dtype=wp.vec3),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  geom_adhesion: wp.array2d(dtype=float),
  geom_aabb: wp.array3d(dtype=wp.vec3),
  pair_dim: wp.array(dtype=int),
  pair_solref: wp.array2d(dtype=wp.vec2),
  pair_solreffriction: wp.array2d(dtype=wp.vec2),
  pair_solimp: wp.array2d(dtype=vec5),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  pair_adhesion: wp.array2d(dtype=float),
  pair_friction: wp.array2d(dtype=vec5),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  naconmax_in: int,
  # In:
  ms: MeshSupport,
  max_contacts: int,
  mc_tolerance: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  face_count: wp.array(dtype=int),
  face_queue: wp.array(dtype=int),
  face_faces: wp.array(dtype=wp.vec3i),
  nthread: int,
  quota: ContactQuota,
  # Out:
  tilt_pair_count: wp.array(dtype=int),
  tilt_pair: wp.array(dtype=int),
  # Data out:
  contact_dist_out: wp.array(dtype=float),
  contact_pos_out: wp.array(dtype=wp.vec3),
  contact_frame_out: wp.array(dtype=wp.mat33),
  contact_includemargin_out: wp.array(dtype=float),
  contact_friction_out: wp.array(dtype=vec5),
  contact_solref_out: wp.array(dtype=wp.vec2),
  contact_solreffriction_out: wp.array(dtype=wp.vec2),
  contact_solimp_out: wp.array(dtype=vec5),
  contact_dim_out: wp.array(dtype=int),
  contact_geom_out: wp.array(dtype=wp.vec2i),
  contact_efc_address_out: wp.array2d(dtype=int),
  contact_worldid_out: wp.array(dtype=int),
  contact_type_out: wp.array(dtype=int),
  contact_geomcollisionid_out: wp.array(dtype=int),
  contact_adhesion_out: wp.array(dtype=float),
  nacon_out: wp.array(dtype=int),
):
  """The pairs face_pair_kernel queued for face clipping, one thread a pair: the faces it found
  clipped (multicontact.clip_faces) give the contacts; a pair whose corners all lie above the
  band goes on to the tilts after all."""
  tid = wp.tid()
  for s in range(tid, face_count[0], nthread):
    i = face_queue[s]
    cid = patch_pair[i]
    geoms = pair_in[cid]
    worldid = pair_worldid_in[cid]
    # the contact parameters are read once the clipping is done: held through it, they took
    # registers it needed
    margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
    band = wp.max(margin + gap, 0.0)
    a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                                     geoms, worldid, patch_result[i], patch_pos[i])
    # duplicates: closer than mc_tolerance x the smaller geom's box size (as patch_kernel's)
    ab = worldid % geom_aabb.shape[0]
    size = 2.0 * wp.min(wp.length(geom_aabb[ab, geoms[0], 1]), wp.length(geom_aabb[ab, geoms[1], 1]))
    found = clip_faces(a, b, ms, res, scale, max_contacts, mc_tolerance * size, face_faces[s])
    # the pair read again, not held through the clipping
    i = face_queue[s]
    if found.status == TILTS:
      tilt_pair[wp.atomic_add(tilt_pair_count, 0, 1)] = i
      continue
    cid = patch_pair[i]
    geoms = pair_in[cid]
    worldid = pair_worldid_in[cid]
    _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = contact_params(
      geom_condim, geom_priority, geom_solmix, geom_solref, geom_solimp, geom_friction, geom_margin, geom_gap,
      geom_adhesion, pair_dim, pair_solref, pair_solreffriction, pair_solimp, pair_margin, pair_gap, pair_adhesion,
      pair_friction, pair_in, pairid_in, cid, worldid,
    )
    band = wp.max(margin + gap, 0.0)
    res = _queued_first(patch_result[i], patch_pos[i])
    frame = make_frame(res.normal)
    # the clipped corners lie in the reference shape's frame: its pose read again here, not held
    # through the clipping
    ref_geom = geoms[wp.where(found.ref_is_b, 1, 0)]
    rot = geom_xmat_in[worldid, ref_geom]
    shift = geom_xpos_in[worldid, ref_geom]
    # the world's contact rows (Options.contacts_per_world), made once the clipping is done
    (limit, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
     rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type, rows_geomcollisionid, rows_adhesion,
     rows_nacon) = world_rows(
      quota, worldid, naconmax_in, contact_dist_out, contact_pos_out, contact_frame_out, contact_includemargin_out,
      contact_friction_out, contact_solref_out, contact_solreffriction_out, contact_solimp_out, contact_dim_out,
      contact_geom_out, contact_efc_address_out, contact_worldid_out, contact_type_out, contact_geomcollisionid_out,
      contact_adhesion_out, nacon_out,
    )
    for k in range(found.n):
      pos = rot @ manifold_pos(found, k) + shift
      if k == found.first:
        pos = res.pos - 0.5 * band * res.normal
      write_contact(
        limit, k, manifold_dist(found, k), pos, frame, margin, gap,
        condim, friction, solref, solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, rows_dist,
        rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref,
        rows_solreffriction, rows_solimp, rows_dim, rows_geom, rows_efc_address,
        rows_worldid, rows_type, rows_geomcollisionid, rows_adhesion, rows_nacon,
      )


@wp.kernel(enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
def tilt_kernel(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  mc_perturbation: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  tilt_pair_count: wp.array(dtype=int),
  tilt_pair: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  nthread: int,
  # Out:
  tilt_result: wp.array2d(dtype=wp.vec4),
  tilt_count: wp.array(dtype=int),
  tilt_queue: wp.array(dtype=int),
):
  """Both attempts of each of the four tilts of the pairs left to the tilts by face_pair_kernel
  and manifold_kernel (row q of tilt_result: the q-th of them), one thread an attempt, in closed form
  (multicontact.tilt_closed_form); the attempts it cannot answer are queued for tilt_mpr_kernel,
  so the tilted MPRs run on dense warps. The steeper attempt is computed whether or not
  patch_kernel's replay needs it: on the pile and on aloha_pot 84 % of the first attempts land
  back on the first contact and need it."""
  tid = wp.tid()
  nattempt = 2 * NPERTURB
  for j in range(tid, wp.min(tilt_pair_count[0], tilt_result.shape[0]) * nattempt, nthread):
    q = j // nattempt
    i = tilt_pair[q]
    a, b, scale, res, rot = _queued_tilt(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap,
                                         pair_margin, pair_gap, geom_xpos_in, geom_xmat_in, ms, mc_perturbation,
                                         pair_in, pairid_in, pair_worldid_in, patch_pair, patch_result, patch_pos, i,
                                         j % nattempt)
    answer = tilt_closed_form(a, b, ms, support_mode, res, scale, rot)
    tilt_result[q, j % nattempt] = answer
    if answer[3] == UNKNOWN:
      tilt_queue[wp.atomic_add(tilt_count, 0, 1)] = j


@wp.kernel(enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
def tilt_mpr_kernel(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  tolerance: float,
  iterations: int,
  mc_perturbation: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  tilt_pair: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  tilt_count: wp.array(dtype=int),
  tilt_queue: wp.array(dtype=int),
  nthread: int,
  # Out:
  tilt_result: wp.array2d(dtype=wp.vec4),
):
  """The tilted MPRs of the attempts tilt_kernel queued (edge against edge, or a foot beside
  the face), one thread an attempt."""
  tid = wp.tid()
  nattempt = 2 * NPERTURB
  for s in range(tid, tilt_count[0], nthread):
    j = tilt_queue[s]
    q = j // nattempt
    i = tilt_pair[q]
    a, b, scale, res, rot = _queued_tilt(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap,
                                         pair_margin, pair_gap, geom_xpos_in, geom_xmat_in, ms, mc_perturbation,
                                         pair_in, pairid_in, pair_worldid_in, patch_pair, patch_result, patch_pos, i,
                                         j % nattempt)
    tilt_result[q, j % nattempt] = tilt_mpr(a, b, ms, support_mode, res, scale, tolerance, iterations, rot)


@wp.kernel(enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
def patch_kernel(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_condim: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_priority: wp.array(dtype=int),
  geom_solmix: wp.array2d(dtype=float),
  geom_solref: wp.array2d(dtype=wp.vec2),
  geom_solimp: wp.array2d(dtype=vec5),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_friction: wp.array2d(dtype=wp.vec3),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  geom_adhesion: wp.array2d(dtype=float),
  geom_aabb: wp.array3d(dtype=wp.vec3),
  pair_dim: wp.array(dtype=int),
  pair_solref: wp.array2d(dtype=wp.vec2),
  pair_solreffriction: wp.array2d(dtype=wp.vec2),
  pair_solimp: wp.array2d(dtype=vec5),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  pair_adhesion: wp.array2d(dtype=float),
  pair_friction: wp.array2d(dtype=vec5),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  naconmax_in: int,
  # In:
  ms: MeshSupport,
  support_mode: int,
  tolerance: float,
  iterations: int,
  max_contacts: int,
  mc_perturbation: float,
  mc_tolerance: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  tilt_pair_count: wp.array(dtype=int),
  tilt_pair: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  tilt_result: wp.array2d(dtype=wp.vec4),
  nthread: int,
  quota: ContactQuota,
  # Data out:
  contact_dist_out: wp.array(dtype=float),
  contact_pos_out: wp.array(dtype=wp.vec3),
  contact_frame_out: wp.array(dtype=wp.mat33),
  contact_includemargin_out: wp.array(dtype=float),
  contact_friction_out: wp.array(dtype=vec5),
  contact_solref_out: wp.array(dtype=wp.vec2),
  contact_solreffriction_out: wp.array(dtype=wp.vec2),
  contact_solimp_out: wp.array(dtype=vec5),
  contact_dim_out: wp.array(dtype=int),
  contact_geom_out: wp.array(dtype=wp.vec2i),
  contact_efc_address_out: wp.array2d(dtype=int),
  contact_worldid_out: wp.array(dtype=int),
  contact_type_out: wp.array(dtype=int),
  contact_geomcollisionid_out: wp.array(dtype=int),
  contact_adhesion_out: wp.array(dtype=float),
  nacon_out: wp.array(dtype=int),
):
  """The pairs left to the tilts (face_pair_kernel, manifold_kernel): the tilts, then all their
  contacts.

  A separate kernel so that warps run only pairs that need the tilts: in the convex kernel one
  such pair held its whole warp (8x the cost on a GPU). The tilts come from tilt_kernel and
  tilt_mpr_kernel for the first ``len(tilt_result)`` queued pairs; this kernel replays the tilt
  logic with them, and computes the tilts itself for any pair beyond.
  """
  tid = wp.tid()
  for q in range(tid, tilt_pair_count[0], nthread):
    i = tilt_pair[q]
    cid = patch_pair[i]
    geoms = pair_in[cid]
    g1 = geoms[0]
    g2 = geoms[1]
    worldid = pair_worldid_in[cid]
    _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = contact_params(
      geom_condim, geom_priority, geom_solmix, geom_solref, geom_solimp, geom_friction, geom_margin, geom_gap,
      geom_adhesion, pair_dim, pair_solref, pair_solreffriction, pair_solimp, pair_margin, pair_gap, pair_adhesion,
      pair_friction, pair_in, pairid_in, cid, worldid,
    )
    band = wp.max(margin + gap, 0.0)
    a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                                     geoms, worldid, patch_result[i], patch_pos[i])
    # duplicates: closer than mc_tolerance x the smaller geom's box size
    ab = worldid % geom_aabb.shape[0]
    size = 2.0 * wp.min(wp.length(geom_aabb[ab, g1, 1]), wp.length(geom_aabb[ab, g2, 1]))
    extra = perturbed_contacts(a, b, ms, support_mode, res, scale, tolerance, iterations, mc_perturbation,
                               mc_tolerance * size, tilt_result, wp.where(q < tilt_result.shape[0], q, -1))
    write_pair_contacts(
      res, extra, mc_tolerance * size, tolerance * scale, max_contacts, band, naconmax_in, margin, gap, condim,
      friction, solref, solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contact_dist_out,
      contact_pos_out, contact_frame_out, contact_includemargin_out, contact_friction_out, contact_solref_out,
      contact_solreffriction_out, contact_solimp_out, contact_dim_out, contact_geom_out, contact_efc_address_out,
      contact_worldid_out, contact_type_out, contact_geomcollisionid_out, contact_adhesion_out, nacon_out, quota,
    )


def pair_types_present(mjm, pairs) -> set:
  """Ordered (type1 <= type2) geom-type pairs that the model can produce."""
  types = set()
  gt = np.asarray(mjm.geom_type)
  for g1, g2 in pairs:
    t1, t2 = sorted((int(gt[g1]), int(gt[g2])))
    types.add((GeomType(t1), GeomType(t2)))
  return types


def pair_queue_table(present) -> tuple:
  """The analytic and the MPR geom-type pairs among ``present`` (ordered pairs the model can
  produce), and the table that maps a pair's types to its queue (see PairQueues)."""
  analytic_types = tuple(t for t in ANALYTIC_PAIRS if t in present)
  queue_table = np.full(NGEOMTYPE**2, -1, dtype=np.int32)
  for t1, t2 in analytic_types:
    queue_table[int(t1) * NGEOMTYPE + int(t2)] = QUEUE_ANALYTIC
  mpr_types = []
  for t1, t2 in present:
    if (t1, t2) not in ANALYTIC_PAIRS and t1 in CONVEX_TYPES and t2 in CONVEX_TYPES:
      queue_table[int(t1) * NGEOMTYPE + int(t2)] = QUEUE_MPR
      mpr_types.append((t1, t2))
  return analytic_types, mpr_types, queue_table


@dataclasses.dataclass
class Buffers:
  """The narrow phase's per-Data buffers: its queues and the multi-contact queues."""

  queue_count: wp.array  # pairs in each narrow-phase kernel's queue (queue_pair)
  queue_pair: wp.array  # (NQUEUE, capacity) the queues: indices into the pair list
  queues: PairQueues  # the two above, and what deciding a pair's queue needs
  patch_count: wp.array  # pairs queued for multi-contact (face_pair_kernel)
  patch_pair: wp.array
  patch_result: wp.array
  patch_pos: wp.array
  face_count: wp.array  # of those, the pairs touching face on feature (manifold_kernel)
  face_queue: wp.array  # their indices into patch_pair
  face_faces: wp.array  # their faces (multicontact.face_pair)
  tilt_pair_count: wp.array  # and the pairs left to the tilts (patch_kernel)
  tilt_pair: wp.array  # their indices into patch_pair
  tilt_result: wp.array  # (pairs left to the tilts, 8) the tilts' points, both attempts
  tilt_count: wp.array  # tilts queued for MPR (tilt_mpr_kernel)
  tilt_queue: wp.array  # their flat indices into tilt_result


def make_buffers(c, nworld: int, capacity: int) -> Buffers:
  """The narrow phase's buffers for ``nworld`` worlds of ``capacity`` pairs in all (``c``: the Collider)."""
  ntilt_pair = min(capacity, nworld * TILT_PAIRS_PER_WORLD)
  b = Buffers(
    queue_count=wp.zeros(NQUEUE, dtype=int),
    queue_pair=wp.zeros((NQUEUE, capacity), dtype=int),
    queues=PairQueues(),
    patch_count=wp.zeros(1, dtype=int),
    patch_pair=wp.zeros(capacity, dtype=int),
    patch_result=wp.zeros(capacity, dtype=wp.vec4),
    patch_pos=wp.zeros(capacity, dtype=wp.vec3),
    face_count=wp.zeros(1, dtype=int),
    face_queue=wp.zeros(capacity, dtype=int),
    face_faces=wp.zeros(capacity, dtype=wp.vec3i),
    tilt_pair_count=wp.zeros(1, dtype=int),
    tilt_pair=wp.zeros(capacity, dtype=int),
    tilt_result=wp.zeros((ntilt_pair, 2 * NPERTURB), dtype=wp.vec4),
    tilt_count=wp.zeros(1, dtype=int),
    tilt_queue=wp.zeros(ntilt_pair * 2 * NPERTURB, dtype=int),
  )
  q = b.queues
  q.pair_queue_type, q.geom_nonconvex = c.pair_queue_type, c.geom_nonconvex
  q.gjk_all = int(c.options.narrowphase == "gjk")
  q.count, q.pair = b.queue_count, b.queue_pair
  return b


def launch(c, m, d, pairs, b: Buffers, warm: warmstart.WarmCache, quota: ContactQuota):
  """The convex pairs of one step: MPR's candidates sifted, the analytic pairs, then MPR's and
  GJK's pairs (``c``: the Collider; ``pairs``: the broad phase's buffers)."""
  nthread = max(1, min(pairs.capacity, GRID_THREADS))
  queue_inputs = [b.queue_count, b.queue_pair, pairs.pair, pairs.pairid, pairs.pair_worldid]  # + the launch's threads
  # analytic pairs are cheap: as many threads as contacts fit, as stock MuJoCo Warp launches them
  nthread_analytic = max(1, min(nthread, d.naconmax))
  opt = c.options
  gjk_all = opt.narrowphase == "gjk"
  if c.mpr_types and not gjk_all:
    wp.launch(
      sift_mpr_pairs,
      dim=nthread,
      inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
              m.pair_gap, d.geom_xpos, d.geom_xmat, c.mesh_support, SUPPORT_MODE_ID[opt.support_mode],
              pairs.pair, pairs.pairid, pairs.pair_worldid, nthread],
      outputs=[b.queues],
    )
  if c.analytic_types:
    wp.launch(
      analytic_kernel(c.analytic_types),
      dim=nthread_analytic,
      inputs=[
        m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
        m.geom_size, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.mesh_vertadr, m.mesh_vertnum,
        m.mesh_graphadr, m.mesh_vert, m.mesh_graph, m.mesh_polynum, m.mesh_polyadr, m.mesh_polynormal,
        m.mesh_polyvertadr, m.mesh_polyvertnum, m.mesh_polyvert, m.mesh_polymapadr, m.mesh_polymapnum,
        m.mesh_polymap, m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin,
        m.pair_gap, m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax,
      ] + queue_inputs + [nthread_analytic, quota],
      outputs=contact_outputs(d),
    )
  if not c.mpr_types:
    return
  # MPR's pairs, then GJK's (all with narrowphase="gjk", else those with a sphere or capsule)
  for use_gjk in (False, True):
    if (use_gjk and not (gjk_all or c.has_core_pairs)) or (not use_gjk and gjk_all):
      continue
    wp.launch(
      convex_kernel(use_gjk),
      dim=nthread,
      inputs=[
        m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref,
        m.geom_solimp, m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion,
        m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
        m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, c.mesh_support,
        SUPPORT_MODE_ID[opt.support_mode], opt.mpr_tolerance, opt.mpr_iterations, opt.mpr_refine,
        opt.max_contacts_per_pair if opt.multi_contact else 1, opt.mc_perturbation,
        c.mesh_sdf, opt.mpr_to_sdf_overlap_ratio, opt.warm_start,
        warm.stamp, warm.slot_stamp, warm.slot_key, warm.slot_value, warm.misses,
      ] + queue_inputs + [nthread, quota],
      outputs=[b.patch_count, b.patch_pair, b.patch_result, b.patch_pos] + contact_outputs(d),
    )


def launch_multicontact(c, m, d, pairs, b: Buffers, quota: ContactQuota):
  """The multi-contact pass over the pairs the MPR kernel queued: face pairs, face clipping, the
  tilts and their MPRs, then each tilted pair's contacts (``c``: the Collider; ``pairs``: the
  broad phase's buffers)."""
  if not c.mpr_types:
    return
  opt = c.options
  mode = SUPPORT_MODE_ID[opt.support_mode]
  nthread = max(1, min(pairs.capacity, GRID_THREADS))
  nthread_tilt = max(1, min(b.tilt_result.shape[0] * b.tilt_result.shape[1], GRID_THREADS))
  pair, pairid, pair_worldid = pairs.pair, pairs.pairid, pairs.pair_worldid
  wp.launch(
    face_pair_kernel,
    dim=nthread,
    inputs=[
      m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
      m.pair_gap, d.geom_xpos, d.geom_xmat, c.mesh_support, mode,
      pair, pairid, pair_worldid, b.patch_count, b.patch_pair, b.patch_result, nthread,
    ],
    outputs=[b.face_count, b.face_queue, b.face_faces, b.tilt_pair_count, b.tilt_pair],
  )
  wp.launch(
    manifold_kernel,
    dim=nthread,
    inputs=[
      m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
      m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb,
      m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
      m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, c.mesh_support,
      opt.max_contacts_per_pair, opt.mc_tolerance, pair, pairid, pair_worldid,
      b.patch_pair, b.patch_result, b.patch_pos, b.face_count, b.face_queue, b.face_faces, nthread,
      quota,
    ],
    outputs=[b.tilt_pair_count, b.tilt_pair] + contact_outputs(d),
  )
  tilt_model = [m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                m.pair_gap, d.geom_xpos, d.geom_xmat, c.mesh_support, mode]
  wp.launch(
    tilt_kernel,
    dim=nthread_tilt,
    inputs=tilt_model + [opt.mc_perturbation, pair, pairid, pair_worldid, b.tilt_pair_count,
                         b.tilt_pair, b.patch_pair, b.patch_result, b.patch_pos, nthread_tilt],
    outputs=[b.tilt_result, b.tilt_count, b.tilt_queue],
  )
  wp.launch(
    tilt_mpr_kernel,
    dim=nthread_tilt,
    inputs=tilt_model + [opt.mpr_tolerance, opt.mpr_iterations, opt.mc_perturbation,
                         pair, pairid, pair_worldid, b.tilt_pair, b.patch_pair, b.patch_result,
                         b.patch_pos, b.tilt_count, b.tilt_queue, nthread_tilt],
    outputs=[b.tilt_result],
  )
  wp.launch(
    patch_kernel,
    dim=nthread,
    inputs=[
      m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
      m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb,
      m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
      m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, c.mesh_support,
      mode, opt.mpr_tolerance, opt.mpr_iterations,
      opt.max_contacts_per_pair, opt.mc_perturbation, opt.mc_tolerance, pair,
      pairid, pair_worldid, b.tilt_pair_count, b.tilt_pair, b.patch_pair, b.patch_result, b.patch_pos,
      b.tilt_result, nthread, quota,
    ],
    outputs=contact_outputs(d),
  )
