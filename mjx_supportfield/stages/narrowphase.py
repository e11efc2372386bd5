"""Narrow phase: analytic pairs through MuJoCo Warp's routines, the rest by support-field MPR.

Its kernels walk the plugin's pair list (or their queue of it) with grid-stride loops, so their
launch sizes do not depend on the (host-unknown) number of pairs and they can be captured in a
CUDA graph.

This module owns the convex narrow phase's kernels (sift, analytic, MPR / GJK), the writer of
an MPR pair's contacts (``write_pair_contacts``), the per-Data buffers of the narrow phase and
of the multi-contact pass that follows it (``Buffers``: the MPR kernel fills the multi-contact
queues) and its stage class, ``NarrowPhase``. Which queue a pair goes to is
routing.py's; the multi-contact kernels are multicontact_pass.py's.
"""

import dataclasses
import functools

import warp as wp
from mujoco_warp._src.collision_core import contact_margin_gap
from mujoco_warp._src.collision_core import geom_collision_pair
from mujoco_warp._src.collision_primitive import _PRIMITIVE_COLLISIONS
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import vec5

from mjx_supportfield.geometry.gjk import gjk_funcs
from mjx_supportfield.geometry.mpr import BEHIND
from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import MprSettings
from mjx_supportfield.geometry.mpr import interior_point
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.geometry.mpr import settings_of
from mjx_supportfield.geometry.multicontact import NPERTURB
from mjx_supportfield.geometry.multicontact import TILT_GROWTH
from mjx_supportfield.geometry.multicontact import Patch
from mjx_supportfield.geometry.multicontact import keep_first
from mjx_supportfield.geometry.multicontact import patch_possible
from mjx_supportfield.geometry.sdf import MeshSdf
from mjx_supportfield.geometry.sdf import needs_sdf
from mjx_supportfield.geometry.sdf import sdf_funcs
from mjx_supportfield.geometry.shapes import posed_pair
from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import contact_mixing
from mjx_supportfield.launch.contact_quota import contact_outputs
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.contact_quota import rows
from mjx_supportfield.launch.contact_quota import write_row
from mjx_supportfield.launch.grid import GRID_THREADS
from mjx_supportfield.launch.grid import HEAVY_REGISTERS
from mjx_supportfield.options import Options
from mjx_supportfield.stages import warmstart
from mjx_supportfield.stages.routing import NQUEUE
from mjx_supportfield.stages.routing import QUEUE_ANALYTIC
from mjx_supportfield.stages.routing import QUEUE_CANDIDATE
from mjx_supportfield.stages.routing import QUEUE_GJK
from mjx_supportfield.stages.routing import QUEUE_MPR
from mjx_supportfield.stages.routing import PairQueues
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from mjx_supportfield.types import MODULE_OPTIONS
from mjx_supportfield.types import UNIQUE_MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


# multi-contact pairs per world left to the tilts (no face clipping) whose tilts run in parallel
# threads (tilt_kernel); pairs beyond run them in patch_kernel's thread: same result, only slower
TILT_PAIRS_PER_WORLD = 32
# MPR answers deeper than this x the smaller shape's bounding radius, on a pair with a face, go to
# deep_pairs.py's check: resting contacts sink a small fraction of that, and on a deep polytope
# pair MPR can settle on a face of A - B that is not the nearest
DEEP_GATE = 0.1
# a deep pair whose warm-started MPR answer stays within this cosine of the previous call's normal
# (the check's own answer when it ran) keeps the check's verdict instead of a new check: a robot
# whose link meshes overlap at rest would otherwise scan every hull face of them each call
DEEP_REUSE_COS = 0.999  # ~2.6 deg
# ... but no more than this many calls in a row: a pair sliding along a face that is no longer the
# nearest keeps MPR's answer near the old normal, and only a new check finds the other face.
# Read at each launch (a kernel input); 1 checks every deep pair every call.
DEEP_RECHECK_CALLS = 8
_PHASE_MIX = wp.constant(wp.uint32(2654435769))


@functools.lru_cache(maxsize=None)
def analytic_kernel(pair_types: tuple, per_world: bool = False):
  """Grid-stride kernel running MuJoCo Warp's analytic routine of each pair type present: a
  pair's contact parameters and poses are read once, then its type picks the routine.

  ``per_world`` (Options.contacts_per_world > 0): the routines write through views of each
  world's rows; without it, into the contact arrays themselves (contact_quota.rows)."""
  funcs = [_PRIMITIVE_COLLISIONS[t] for t in pair_types]

  @wp.kernel(module="unique", module_options=UNIQUE_MODULE_OPTIONS, enable_backward=False)
  def analytic_narrowphase(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
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
    contacts_out: ContactRows,
  ):
    tid = wp.tid()
    for i in range(tid, queue_count[QUEUE_ANALYTIC], nthread):
      cid = queue_pair[QUEUE_ANALYTIC, i]
      geoms = pair_in[cid]
      type1 = geom_type[geoms[0]]
      type2 = geom_type[geoms[1]]
      worldid = pair_worldid_in[cid]
      (limit, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
       rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type, rows_geomcollisionid,
       rows_adhesion, rows_nacon) = wp.static(rows(per_world))(
        quota, worldid, naconmax_in, contacts_out,
      )
      # the parameters and poses read once, before the routine's branch, as stock MuJoCo Warp's
      # kernel does: read inside each branch, a warp of mixed pair types ran them once per type
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(mixing, pair_in,
        pairid_in,
        cid,
        worldid)
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
      pairid = pairid_in[cid]
      for k in range(wp.static(len(funcs))):
        if type1 == wp.static(pair_types[k][0]) and type2 == wp.static(pair_types[k][1]):
          wp.static(funcs[k])(
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
            pairid,
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
  contacts_out: ContactRows,
  quota: ContactQuota,
):
  """Writes a pair's contacts: MPR's point (when kept, see keep_first), then the patch's points,
  all with MPR's normal; the margin band comes off depth and position."""
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
    write_row(
      quota, worldid, naconmax_in, k, band - depth, pos - 0.5 * band * res.normal, frame, margin, gap, condim,
      friction, solref, solreffriction, solimp, adhesion, geoms, pairid, contacts_out,
    )


@wp.func
def suspect_deep(type1: int, type2: int, depth: float, rbound1: float, rbound2: float) -> bool:
  """Whether MPR's answer of a pair (its depth, margin band off) goes to deep_pairs.py's check:
  deeper than DEEP_GATE x the smaller bounding radius, with a face on either shape (a mesh, a
  box or a cylinder) whose normal may be the nearer way out."""
  faces = (type1 == GeomType.MESH or type1 == GeomType.BOX or type1 == GeomType.CYLINDER
           or type2 == GeomType.MESH or type2 == GeomType.BOX or type2 == GeomType.CYLINDER)
  return faces and depth > DEEP_GATE * wp.min(rbound1, rbound2)


@wp.func
def deep_verdict_holds(last: wp.vec4, checked: int, normal: wp.vec3, now: int, key: int, period: int) -> bool:
  """Whether a deep pair skips the check this call and keeps MPR's answer ``normal``: its MPR
  was warm-started from ``last`` (the previous call's normal, corrected by the check when that
  ran) and stayed within DEEP_REUSE_COS of it, the check last ran (the world's call ``checked``)
  fewer than ``period`` calls ago, and this is not the pair's recheck call. Each pair rechecks
  every ``period`` of its world's calls (``now``, counted from the world's last reset) at a phase
  of its own (a hash of the geom pair), so that the checks of pairs that went deep together
  spread over the calls instead of all landing in one. The phase is not the world's: identical
  worlds must check in the same calls, wherever they sit in the batch."""
  if last[3] <= 0.0 or now - checked >= period:
    return False
  phase = int((wp.uint32(key) * _PHASE_MIX) >> wp.uint32(8)) % period
  if (now + phase) % period == 0:
    return False
  return wp.dot(normal, wp.vec3(last[0], last[1], last[2])) >= DEEP_REUSE_COS


@wp.func
def wants_patch(
  geom_type: wp.array(dtype=int), geoms: wp.vec2i, a: Shape, b: Shape, ms: MeshSupport, res: MprResult,
  max_contacts: int, mc_perturbation: float,
) -> bool:
  """Whether a pair's answer goes to the multi-contact pass: it may touch in more points than
  MPR's (not spheres and ellipsoids, where one point is the whole contact)."""
  one_point = (
    geom_type[geoms[0]] == GeomType.SPHERE
    or geom_type[geoms[0]] == GeomType.ELLIPSOID
    or geom_type[geoms[1]] == GeomType.SPHERE
    or geom_type[geoms[1]] == GeomType.ELLIPSOID
  )
  tilt = mc_perturbation * TILT_GROWTH  # the steepest tilt perturbed_contacts tries
  return max_contacts > 1 and not one_point and patch_possible(a, b, ms, res.normal, tilt, res.depth)


@functools.lru_cache(maxsize=None)
def sift_mpr_pairs(mode: int) -> wp.Kernel:
  """The sift of MPR's candidates for support mode ``mode``, in that mode's module
  (types.mode_module)."""
  apart_along_centres = mpr_funcs(mode).apart_along_centres

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
    geoms: wp.vec2i,
    pairid: int,
    worldid: int,
  ) -> bool:
    """apart_along_centres for a pair as convex_narrowphase poses it (A grown by the margin band)."""
    margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid, worldid)
    a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                             wp.max(margin + gap, 0.0), geoms, worldid)
    return apart_along_centres(a, b, ms, scale)

  @wp.kernel(module=mode_module(__name__, mode))
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
                    geom_xpos_in, geom_xmat_in, ms, pair_in[cid], pairid_in[cid][0], pair_worldid_in[cid]):
        slot = wp.atomic_add(queues.count, QUEUE_MPR, 1)
        queues.pair[QUEUE_MPR, slot] = cid

  return sift_mpr_pairs


@functools.lru_cache(maxsize=None)
def convex_kernel(use_gjk: bool, mode: int):
  """The narrow-phase kernel of the convex pairs that are not analytic: penetration by MPR
  (warm-started, refined), or, with ``use_gjk``, by GJK/EPA (gjk.py), on the support functions
  of support mode ``mode``.

  Each variant walks its own queue (queue_pair). Two kernels, not one branch: EPA's polytope
  takes about 10 KB of stack a thread, and inlined beside MPR it made every MPR pair slower on
  the GPU.
  """
  gjk_epa = gjk_funcs(mode).gjk_epa
  behind_origin = mpr_funcs(mode).behind_origin
  mpr_refined_from = mpr_funcs(mode).mpr_refined_from
  sdf_contact = sdf_funcs(mode).sdf_contact

  @wp.kernel(module="unique", module_options=UNIQUE_MODULE_OPTIONS, enable_backward=False, cuda_max_registers=HEAVY_REGISTERS)
  def convex_narrowphase(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    mpr_options: MprSettings,
    max_contacts: int,
    mc_perturbation: float,
    sdf: MeshSdf,
    sdf_ratio: float,
    warm_start: int,
    ws_stamp: wp.array(dtype=int),
    ws_slot_stamp: wp.array2d(dtype=int),
    ws_slot_key: wp.array2d(dtype=int),
    ws_slot_value: wp.array2d(dtype=wp.vec4),
    ws_slot_checked: wp.array2d(dtype=int),
    ws_misses: wp.array(dtype=int),
    deep_recheck: int,
    deep_per_world: int,
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
    deep_count: wp.array(dtype=int),
    deep_world_count: wp.array(dtype=int),
    deep_pair: wp.array(dtype=int),
    deep_result: wp.array(dtype=wp.vec4),
    deep_pos: wp.array(dtype=wp.vec3),
    # Data out:
    contacts_out: ContactRows,
  ):
    """Contacts of convex pairs by MPR (or GJK/EPA) on the shapes' support functions: the
    deepest point; a pair that may touch in more points (not spheres and ellipsoids, where one
    point is the whole contact) is queued for face_pair_kernel instead, and face clipping or the
    tilts write up to max_contacts. With warm_start, MPR starts from the pair's normal of the previous call and
    falls back to a cold start when that misses."""
    tid = wp.tid()
    queue = wp.static(QUEUE_GJK if use_gjk else QUEUE_MPR)
    for i in range(tid, queue_count[queue], nthread):
      cid = queue_pair[queue, i]
      geoms = pair_in[cid]
      g1 = geoms[0]
      g2 = geoms[1]
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(mixing, pair_in,
        pairid_in,
        cid,
        worldid)
      # contacts are wanted up to margin + gap apart: grow A by that band, shrink the answer back
      band = wp.max(margin + gap, 0.0)
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                               geoms, worldid)
      rb = worldid % geom_rbound.shape[0]
      key = g1 * geom_type.shape[0] + g2
      now = ws_stamp[worldid]
      res = MprResult()
      res.hit = 0
      last = wp.vec4(0.0)
      checked = int(warmstart.NEVER)
      if wp.static(use_gjk):
        res = gjk_epa(a, b, ms, scale, mpr_options.tolerance, mpr_options.iterations)
      else:
        if warm_start:
          last, checked = warmstart.lookup(ws_slot_stamp, ws_slot_key, ws_slot_value, ws_slot_checked, now, worldid,
                                           key)
        # one MPR call site, in a loop, keeps the kernel small: warm first when the pair has a
        # normal from the previous call, then cold if that found nothing
        for attempt in range(2):
          if attempt == 1 and (res.hit != 0 or last[3] <= 0.0):
            break
          if attempt == 1:
            wp.atomic_add(ws_misses, worldid, 1)
          q0 = interior_point(a, b, scale)
          if attempt == 0 and last[3] > 0.0:
            q0 = behind_origin(a, b, ms, wp.vec3(last[0], last[1], last[2]), last[3], scale, BEHIND)
          res = mpr_refined_from(a, b, ms, q0, scale, mpr_options.tolerance, mpr_options.iterations,
                                 mpr_options.refine, BEHIND)
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
        fallback = sdf_contact(bare, b, ms, sdf, 1.0e-4 * scale)
        if fallback.hit and fallback.depth + band < res.depth:
          res.depth = fallback.depth + band
          res.normal = fallback.normal
          res.pos = fallback.pos + 0.5 * band * fallback.normal
          extra.n = -1  # a fallback contact is not perturbed
      if warm_start and not wp.static(use_gjk):
        value = wp.vec4(res.normal[0], res.normal[1], res.normal[2], res.depth)
        stored = warmstart.insert(ws_slot_stamp, ws_slot_key, ws_slot_value, now, worldid, key, value)
        if stored >= 0:
          ws_slot_checked[worldid, stored] = checked
      # the SDFs' answer too (extra.n -1): its depth is the deepest point's, below the overlap
      # along its normal, so "shallower" there is no proof that its normal is the way out
      if not wp.static(use_gjk) and extra.n <= 0 and suspect_deep(
        geom_type[g1], geom_type[g2], res.depth - band, geom_rbound[rb, g1], geom_rbound[rb, g2]
      ):
        if warm_start and deep_verdict_holds(last, checked, res.normal, now, key, deep_recheck):
          wp.atomic_add(deep_count, 1, 1)  # counted apart from the queue: the pair goes on below
        elif wp.atomic_add(deep_world_count, worldid, 1) < deep_per_world:
          # checked by deep_pairs.py, which then queues or writes it as below; beyond its world's
          # rows it keeps MPR's answer (counted)
          slot = wp.atomic_add(deep_count, 0, 1)
          if slot < deep_pair.shape[0]:
            deep_pair[slot] = cid
            # an SDF answer's depth is queued negated: kept, it stays one contact, unperturbed
            deep_result[slot] = wp.vec4(res.normal[0], res.normal[1], res.normal[2],
                                        wp.where(extra.n < 0, -res.depth, res.depth))
            deep_pos[slot] = res.pos
            continue
      if extra.n == 0 and wants_patch(geom_type, geoms, a, b, ms, res, max_contacts, mc_perturbation):
        # queued for face_pair_kernel, which leaves the pairs without a face pair to the tilts
        slot = wp.atomic_add(patch_count, 0, 1)
        patch_pair[slot] = cid
        patch_result[slot] = wp.vec4(res.normal[0], res.normal[1], res.normal[2], res.depth)
        patch_pos[slot] = res.pos
        continue
      write_pair_contacts(
        res, extra, 0.0, 0.0, 1, band, naconmax_in, margin, gap, condim, friction, solref, solreffriction, solimp,
        adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
      )

  return convex_narrowphase


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
  face_faces: wp.array  # their faces (faceclip.face_pair)
  tilt_pair_count: wp.array  # and the pairs left to the tilts (patch_kernel)
  tilt_pair: wp.array  # their indices into patch_pair
  tilt_result: wp.array  # (pairs left to the tilts, 8) the tilts' points, both attempts
  tilt_count: wp.array  # tilts queued for MPR (tilt_mpr_kernel)
  tilt_queue: wp.array  # their flat indices into tilt_result





class NarrowPhase:
  """The convex narrow phase: the pair types install found and the model-time data its kernels
  read, the per-Data buffers (its queues and the multi-contact queues), and the step's launches
  (the stage contract: docs/architecture.md)."""

  def __init__(self, options: Options, support_mode: SupportMode, mesh_support: MeshSupport, mesh_sdf: MeshSdf,
               analytic_types: tuple, mpr_types: tuple, pair_queue_type: wp.array, geom_nonconvex: wp.array):
    self.options, self.support_mode = options, support_mode
    self.mesh_support, self.mesh_sdf = mesh_support, mesh_sdf
    self.analytic_types, self.mpr_types = analytic_types, mpr_types  # the model's pair types, by kernel
    self.pair_queue_type = pair_queue_type  # per pair of geom types: its queue (routing.pair_queue_table)
    self.geom_nonconvex = geom_nonconvex  # per geom: 1 for a mesh collided through its triangles
    # pairs with a sphere or a capsule take GJK on their core in a kernel of their own
    self.has_core_pairs = any(t in (GeomType.SPHERE, GeomType.CAPSULE) for pair in mpr_types for t in pair)

  def make_buffers(self, d, st) -> Buffers:
    """The narrow phase's buffers for Data ``d`` (as many pairs as the broad phase lists)."""
    nworld, capacity = d.nworld, st.broad.capacity
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
    q.pair_queue_type, q.geom_nonconvex = self.pair_queue_type, self.geom_nonconvex
    q.count, q.pair = b.queue_count, b.queue_pair
    return b

  def launch(self, m, d, st) -> None:
    """The convex pairs of one step: MPR's candidates sifted, the analytic pairs, then MPR's and
    GJK's pairs; MPR's suspicious answers go to the deep-pair queue."""
    pairs, b, warm, quota, deep = st.broad, st.narrow, st.warm, st.quota.quota, st.deep
    nthread = max(1, min(pairs.capacity, GRID_THREADS))
    queue_inputs = [b.queue_count, b.queue_pair, pairs.pair, pairs.pairid, pairs.pair_worldid]  # + the launch's threads
    # analytic pairs are cheap: as many threads as contacts fit, as stock MuJoCo Warp launches them
    nthread_analytic = max(1, min(nthread, d.naconmax))
    opt = self.options
    mode = self.support_mode
    gjk_all = opt.narrowphase == "gjk"
    if self.mpr_types and not gjk_all:
      wp.launch(
        sift_mpr_pairs(mode),
        dim=nthread,
        inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, pairs.pair, pairs.pairid, pairs.pair_worldid,
                nthread],
        outputs=[b.queues],
      )
    if self.analytic_types:
      wp.launch(
        analytic_kernel(self.analytic_types, bool(opt.contacts_per_world)),
        dim=nthread_analytic,
        inputs=[
          m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.mesh_vertadr, m.mesh_vertnum,
          m.mesh_graphadr, m.mesh_vert, m.mesh_graph, m.mesh_polynum, m.mesh_polyadr, m.mesh_polynormal,
          m.mesh_polyvertadr, m.mesh_polyvertnum, m.mesh_polyvert, m.mesh_polymapadr, m.mesh_polymapnum,
          m.mesh_polymap, d.geom_xpos, d.geom_xmat, d.naconmax,
        ] + queue_inputs + [nthread_analytic, quota],
        outputs=contact_outputs(d),
      )
    if not self.mpr_types:
      return
    # MPR's pairs, then GJK's (all with narrowphase="gjk", else those with a sphere or capsule)
    for use_gjk in (False, True):
      if (use_gjk and not (gjk_all or self.has_core_pairs)) or (not use_gjk and gjk_all):
        continue
      wp.launch(
        convex_kernel(use_gjk, mode),
        dim=nthread,
        inputs=[
          m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_rbound, d.geom_xpos, d.geom_xmat,
          d.naconmax, self.mesh_support, settings_of(opt), opt.mpr_pair_contacts, opt.mc_perturbation,
          self.mesh_sdf, opt.mpr_to_sdf_overlap_ratio, opt.warm_start,
          warm.stamp, warm.slot_stamp, warm.slot_key, warm.slot_value, warm.slot_checked, warm.misses,
          DEEP_RECHECK_CALLS, deep.per_world,
        ] + queue_inputs + [nthread, quota],
        outputs=[b.patch_count, b.patch_pair, b.patch_result, b.patch_pos, deep.count, deep.world_count, deep.pair,
                 deep.result, deep.pos] + contact_outputs(d),
      )
