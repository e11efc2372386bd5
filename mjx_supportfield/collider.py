"""The installed collision stage: model-time data, per-Data state and the step-time driver."""

import dataclasses
import weakref
from typing import Optional

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src import collision_driver
from mujoco_warp._src.collision_core import CollisionContext
from mujoco_warp._src.types import DeterminismType
from mujoco_warp._src.types import DisableBit
from mujoco_warp._src.types import EnableBit
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import OverflowType

from mjx_supportfield import broadphase
from mjx_supportfield import contact_quota
from mjx_supportfield import contact_sort
from mjx_supportfield import heightfield
from mjx_supportfield import nonconvex
from mjx_supportfield import narrowphase
from mjx_supportfield import warmstart
from mjx_supportfield.aabb import update_aabbs
from mjx_supportfield.options import NXN_MAX_PAIRS
from mjx_supportfield.options import Options
from mjx_supportfield.sdf import build_mesh_sdf
from mjx_supportfield.support_field import build_mesh_support
from mjx_supportfield.types import CONVEX_TYPES
from mjx_supportfield.types import STOCK_TYPES
from mjx_supportfield.types import SUPPORT_MODE_ID

_ATTR = "_mjx_supportfield_collider"
_STATE_ATTR = "_mjx_supportfield_state"
_GRID_THREADS = 1 << 20  # cap of the grid-stride narrow-phase launches
# multi-contact pairs per world left to the tilts (no face clipping) whose tilts run in parallel
# threads (narrowphase.tilt_kernel); pairs beyond run them in patch_kernel's thread: same
# result, only slower
_TILT_PAIRS_PER_WORLD = 32
# a sleeping step's second pass appends to the first pass's contacts, which the quota has packed
_SLEEP_QUOTA = ("mjx_supportfield: Options.contacts_per_world does not work with sleeping (the model enables"
                " mjtEnableBit.mjENBL_SLEEP); use contacts_per_world = 0 or disable sleeping")


@dataclasses.dataclass
class DataState:
  """Per-Data buffers: sizes depend on nworld, which install cannot know."""

  aabb_lo: wp.array
  aabb_hi: wp.array
  nonfinite: wp.array  # per world: 1 if a geom pose held NaN/inf this step
  sap_init: wp.array
  order: wp.array
  world_npair: wp.array
  npair: wp.array
  ndropped: wp.array
  nwarned: wp.array
  slot_pair: wp.array  # per-world slots written by the sweep (a placeholder with nxn)
  slot_pairid: wp.array
  world_count: wp.array
  world_start: wp.array
  pair: wp.array  # the compacted pair list, worlds back to back
  pairid: wp.array
  pair_worldid: wp.array
  stock_ctx: CollisionContext
  capacity: int
  warm: warmstart.WarmCache
  queue_count: wp.array  # pairs in each narrow-phase kernel's queue (narrowphase.queue_pair)
  queue_pair: wp.array  # (NQUEUE, capacity) the queues: indices into pair
  queues: narrowphase.PairQueues  # the two above, and what deciding a pair's queue needs
  patch_count: wp.array  # pairs queued for multi-contact (narrowphase.face_pair_kernel)
  patch_pair: wp.array
  patch_result: wp.array
  patch_pos: wp.array
  face_count: wp.array  # of those, the pairs touching face on feature (narrowphase.manifold_kernel)
  face_queue: wp.array  # their indices into patch_pair
  face_faces: wp.array  # their faces (multicontact.face_pair)
  tilt_pair_count: wp.array  # and the pairs left to the tilts (narrowphase.patch_kernel)
  tilt_pair: wp.array  # their indices into patch_pair
  tilt_result: wp.array  # (pairs left to the tilts, 8) the tilts' points, both attempts
  tilt_count: wp.array  # tilts queued for MPR (narrowphase.tilt_mpr_kernel)
  tilt_queue: wp.array  # their flat indices into tilt_result
  hfield_count: wp.array  # heightfield pairs, MPRs, those beyond the queue, per kind (heightfield.COUNT_*)
  hfield_pair: wp.array  # (pairs) heightfield.TerrainPair
  hfield_job: wp.array  # (MPRs) the MPR queue: (index into hfield_pair, cell * NJOB + job)
  hfield_kind_next: wp.array  # (heightfield.NKIND) next place of each kind of job in hfield_order
  hfield_order: wp.array  # (MPRs) the queue's jobs grouped by kind, the order hfield_mpr runs them in
  hfield_answer: wp.array  # (MPRs) each MPR's point and depth
  hfield_normal: wp.array  # (MPRs) and normal
  pair_outputs: broadphase.PairOutputs  # the arrays above (and d's overflow, ncollision) for the broad phase
  quota: contact_quota.QuotaBuffers  # each world's contact rows (Options.contacts_per_world)
  sort: Optional[contact_sort.SortBuffers] = None  # made on the first deterministic call


def _check_heightfields(mjm: mujoco.MjModel) -> None:
  """Heightfields need a grid of at least 2 x 2 samples and positive sizes (the cell size divides)."""
  for g in np.nonzero(np.asarray(mjm.geom_type) == GeomType.HFIELD)[0]:
    hf = int(mjm.geom_dataid[g])
    nrow, ncol, size = int(mjm.hfield_nrow[hf]), int(mjm.hfield_ncol[hf]), np.asarray(mjm.hfield_size[hf])
    name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, int(g)) or f"geom {g}"
    if nrow < 2 or ncol < 2:
      raise ValueError(f"install: geom '{name}': heightfield {hf} has {nrow} rows and {ncol} columns; at least 2 of each"
                       " are needed")
    if not (np.all(np.isfinite(size)) and size[0] > 0 and size[1] > 0 and size[2] >= 0 and size[3] >= 0):
      raise ValueError(f"install: geom '{name}': heightfield {hf} has size {size.tolist()}; x and y radii must be"
                       " positive, elevation and base non-negative")


@wp.kernel(enable_backward=False)
def start_collision(
  # In:
  incremental: bool,
  warm_start: bool,
  # Out:
  ncollision: wp.array(dtype=int),
  nacon: wp.array(dtype=int),
  ndropped: wp.array(dtype=int),
  nonfinite: wp.array(dtype=int),
  world_npair: wp.array(dtype=int),
  npair: wp.array(dtype=int),
  nwarned: wp.array(dtype=int),
  queue_count: wp.array(dtype=int),
  patch_count: wp.array(dtype=int),
  face_count: wp.array(dtype=int),
  tilt_pair_count: wp.array(dtype=int),
  tilt_count: wp.array(dtype=int),
  hfield_count: wp.array(dtype=int),
  warm_stamp: wp.array(dtype=int),
  warm_misses: wp.array(dtype=int),
):
  """Resets the collision stage's counters, one thread a world (one launch instead of ten
  memsets: on a few-geom scene those cost more than the collisions). The incremental pass of
  a sleeping step keeps the contacts, drop counts and flags of the first pass."""
  worldid = wp.tid()
  world_npair[worldid] = 0
  if not incremental:
    ndropped[worldid] = 0
    nonfinite[worldid] = 0
  if worldid != 0:
    return
  ncollision[0] = 0
  npair[0] = 0
  nwarned[0] = 0
  patch_count[0] = 0
  face_count[0] = 0
  tilt_pair_count[0] = 0
  tilt_count[0] = 0
  for q in range(queue_count.shape[0]):
    queue_count[q] = 0
  for k in range(hfield_count.shape[0]):
    hfield_count[k] = 0
  if not incremental:
    nacon[0] = 0
  if warm_start:
    warmstart.advance_stamp(warm_stamp, warm_misses)


# the contact fields the plugin's writers take (Collider._contact_outputs, in that order)
_WRITTEN_CONTACT_FIELDS = (
  "dist", "pos", "frame", "includemargin", "friction", "solref", "solreffriction", "solimp", "dim", "geom",
  "efc_address", "worldid", "type", "geomcollisionid", "adhesion",
)  # fmt: skip


class Collider:
  """Everything the plugin built for one MuJoCo Warp model (see ``install``)."""

  def __init__(self, mjm: mujoco.MjModel, m, options: Options):
    _check_heightfields(mjm)
    if options.contacts_per_world and m.opt.enableflags & EnableBit.SLEEP:
      raise ValueError(_SLEEP_QUOTA)
    self.options = options
    self.ngeom, self.nq, self.nbody = mjm.ngeom, mjm.nq, mjm.nbody
    device = m.geom_type.device
    self.device = device
    with wp.ScopedDevice(device):
      self.mesh_support = build_mesh_support(mjm, m.mesh_vert, options.support_res, device)
      stock = np.isin(np.asarray(mjm.geom_type), [int(t) for t in STOCK_TYPES])
      self.geom_stock = wp.array(stock.astype(np.int32), dtype=int)

      pairs = np.asarray(m.nxn_geom_pair_filtered.numpy()).reshape(-1, 2)
      pairids = np.asarray(m.nxn_pairid_filtered.numpy()).reshape(-1, 2)
      explicit = (pairids[:, 0] >= 0) | (pairids[:, 1] >= 0)
      self.nexplicit = int(explicit.sum())
      self.explicit_pair = wp.array(pairs[explicit].astype(np.int32), dtype=wp.vec2i)
      self.explicit_pairid = wp.array(pairids[explicit].astype(np.int32), dtype=wp.vec2i)
      # no world can have more pairs than the model allows after its static filters
      self.max_pairs = max(1, min(options.max_collision_pairs, len(pairs)))
      self.npair_filtered = len(pairs)
      self.nxn = options.broadphase == "nxn" or (options.broadphase == "auto" and len(pairs) <= NXN_MAX_PAIRS)
      self.has_stock_pairs = bool(stock.any()) or bool((pairids[:, 1] >= 0).any())

      present = self._pair_types_present(mjm, pairs)
      self.analytic_types = tuple(t for t in narrowphase.ANALYTIC_PAIRS if t in present)
      queue_table = np.full(narrowphase.NGEOMTYPE**2, -1, dtype=np.int32)  # see narrowphase.PairQueues
      for t1, t2 in self.analytic_types:
        queue_table[int(t1) * narrowphase.NGEOMTYPE + int(t2)] = narrowphase.QUEUE_ANALYTIC
      self.mpr_types = []
      for t1, t2 in present:
        if (t1, t2) not in narrowphase.ANALYTIC_PAIRS and t1 in CONVEX_TYPES and t2 in CONVEX_TYPES:
          queue_table[int(t1) * narrowphase.NGEOMTYPE + int(t2)] = narrowphase.QUEUE_MPR
          self.mpr_types.append((t1, t2))
      self.pair_queue_type = wp.array(queue_table, dtype=int)
      core = (GeomType.SPHERE, GeomType.CAPSULE)
      self.has_core_pairs = any(t1 in core or t2 in core for t1, t2 in self.mpr_types)
      self.has_hfield_pairs = any(t1 == GeomType.HFIELD and t2 in CONVEX_TYPES for t1, t2 in present)
      t1, t2 = np.sort(np.asarray(mjm.geom_type)[pairs], axis=1).T if len(pairs) else (np.zeros(0, int),) * 2
      nmpr = int((queue_table[t1 * narrowphase.NGEOMTYPE + t2] == narrowphase.QUEUE_MPR).sum())
      self.warm_slots = warmstart.slots_per_world(min(nmpr, self.max_pairs))
      nhfield = int(((t1 == GeomType.HFIELD) & np.isin(t2, [int(t) for t in CONVEX_TYPES])).sum())
      self.hfield_pairs_per_world = min(nhfield, self.max_pairs)  # bounds the heightfield kernels' pairs
      # non-convex meshes: their own triangles' SDFs
      ncgeoms = nonconvex.nonconvex_geom_ids(mjm, options.nonconvex_geoms)
      nonconvex.warn_open_meshes(mjm, ncgeoms)
      flags = np.zeros(mjm.ngeom, np.int32)
      flags[ncgeoms] = 1
      self.geom_nonconvex = wp.array(flags, dtype=int)
      self.has_nonconvex_pairs = bool(len(ncgeoms)) and bool(flags[pairs].any()) if len(pairs) else False
      ncmeshes = {int(mjm.geom_dataid[g]) for g in ncgeoms}
      self.mesh_faceadr = wp.array(np.asarray(mjm.mesh_faceadr, np.int32).reshape(-1), dtype=int)
      self.mesh_facenum = wp.array(np.asarray(mjm.mesh_facenum, np.int32).reshape(-1), dtype=int)
      self.sdfs = nonconvex.SdfSet()
      self.sdfs.true_mesh = build_mesh_sdf(mjm, options.nonconvex_sdf_res, ncmeshes, device, nonconvex.mesh_triangles)
      # hull SDFs: for the fallback of meshes that meet another shape through MPR, and for the
      # convex meshes a non-convex one may touch
      mesh_ids = {int(x) for x in np.asarray(mjm.geom_dataid)[np.asarray(mjm.geom_type) == GeomType.MESH] if x >= 0}
      meshes = set()
      if options.mpr_to_sdf_overlap_ratio > 0 and any(GeomType.MESH in t for t in self.mpr_types):
        meshes = set(mesh_ids)
      if self.has_nonconvex_pairs:
        meshes |= mesh_ids
      self.mesh_sdf = build_mesh_sdf(mjm, options.sdf_res, meshes, device)
      self.sdfs.hull = self.mesh_sdf

  @staticmethod
  def _pair_types_present(mjm, pairs):
    """Ordered (type1 <= type2) geom-type pairs that the model can produce."""
    types = set()
    gt = np.asarray(mjm.geom_type)
    for g1, g2 in pairs:
      t1, t2 = sorted((int(gt[g1]), int(gt[g2])))
      types.add((GeomType(t1), GeomType(t2)))
    return types

  # --- per-Data state -------------------------------------------------------------------

  def state(self, m, d) -> DataState:
    """State kept on ``d`` (created on its first collision): SAP order, pair buffers."""
    states = getattr(d, _STATE_ATTR, None)
    if states is None:
      states = weakref.WeakKeyDictionary()  # a Collider that is gone takes its state along
      object.__setattr__(d, _STATE_ATTR, states)
    st = states.get(self)
    if st is None:
      self._check_data(d)
      st = self._make_state(d)
      states[self] = st
    return st

  def _check_data(self, d):
    for field, want in (("geom_xpos", self.ngeom), ("qpos", self.nq), ("xpos", self.nbody)):
      shape = getattr(d, field).shape
      if len(shape) != 2 or shape[1] != want:
        raise ValueError(
          f"mjx_supportfield: Data.{field} has shape {tuple(shape)} but the model needs (nworld, {want});"
          " was this Data made for another model?"
        )
    if d.qpos.device != self.device:
      raise ValueError(f"mjx_supportfield: Data is on {d.qpos.device} but the model it steps with was installed on"
                       f" {self.device}; make both on one device (wp.ScopedDevice)")
    # the contact writers address rows through pointers (contact_quota.world_rows)
    for field in _WRITTEN_CONTACT_FIELDS:
      if not getattr(d.contact, field).is_contiguous:
        raise ValueError(f"mjx_supportfield: Data.contact.{field} is not contiguous; make the Data with"
                         " mjw.make_data or mjw.put_data")

  def _make_state(self, d) -> DataState:
    nworld = d.nworld
    capacity = nworld * self.max_pairs
    # the sweep's per-world slots; nxn lists pairs directly (aloha_pot: 2 x 268 MB saved at 8192 worlds)
    nslot = 1 if self.nxn else capacity
    ntilt_pair = min(capacity, nworld * _TILT_PAIRS_PER_WORLD)
    nhfield_pair = max(1, nworld * self.hfield_pairs_per_world)
    nhfield_mpr = nhfield_pair * self.options.hfield_mprs_per_pair if self.hfield_pairs_per_world else 1
    with wp.ScopedDevice(self.device):
      st = DataState(
        aabb_lo=wp.zeros((nworld, self.ngeom), dtype=wp.vec3),
        aabb_hi=wp.zeros((nworld, self.ngeom), dtype=wp.vec3),
        nonfinite=wp.zeros(nworld, dtype=int),
        sap_init=wp.zeros(nworld, dtype=int),
        order=wp.zeros((nworld, max(self.ngeom, 1)), dtype=int),
        world_npair=wp.zeros(nworld, dtype=int),
        npair=wp.zeros(1, dtype=int),
        ndropped=wp.zeros(nworld, dtype=int),
        nwarned=wp.zeros(1, dtype=int),
        slot_pair=wp.zeros(nslot, dtype=wp.vec2i),
        slot_pairid=wp.zeros(nslot, dtype=wp.vec2i),
        world_count=wp.zeros(nworld, dtype=int),
        world_start=wp.zeros(nworld, dtype=int),
        pair=wp.zeros(capacity, dtype=wp.vec2i),
        pairid=wp.zeros(capacity, dtype=wp.vec2i),
        pair_worldid=wp.zeros(capacity, dtype=int),
        stock_ctx=CollisionContext(
          collision_pair=wp.zeros(d.naconmax, dtype=wp.vec2i),
          collision_pairid=wp.zeros(d.naconmax, dtype=wp.vec2i),
          collision_worldid=wp.zeros(d.naconmax, dtype=int),
        ),
        capacity=capacity,
        warm=warmstart.make_cache(nworld, self.warm_slots if self.options.warm_start else 1),
        queue_count=wp.zeros(narrowphase.NQUEUE, dtype=int),
        queue_pair=wp.zeros((narrowphase.NQUEUE, capacity), dtype=int),
        patch_count=wp.zeros(1, dtype=int),
        patch_pair=wp.zeros(capacity, dtype=int),
        patch_result=wp.zeros(capacity, dtype=wp.vec4),
        patch_pos=wp.zeros(capacity, dtype=wp.vec3),
        face_count=wp.zeros(1, dtype=int),
        face_queue=wp.zeros(capacity, dtype=int),
        face_faces=wp.zeros(capacity, dtype=wp.vec3i),
        tilt_pair_count=wp.zeros(1, dtype=int),
        tilt_pair=wp.zeros(capacity, dtype=int),
        tilt_result=wp.zeros((ntilt_pair, 2 * narrowphase.NPERTURB), dtype=wp.vec4),
        tilt_count=wp.zeros(1, dtype=int),
        tilt_queue=wp.zeros(ntilt_pair * 2 * narrowphase.NPERTURB, dtype=int),
        hfield_count=wp.zeros(heightfield.COUNT_KIND + heightfield.NKIND, dtype=int),
        hfield_kind_next=wp.zeros(heightfield.NKIND, dtype=int),
        hfield_order=wp.zeros(nhfield_mpr, dtype=int),
        hfield_pair=wp.zeros(nhfield_pair, dtype=heightfield.TerrainPair),
        hfield_job=wp.zeros(nhfield_mpr, dtype=wp.vec2i),
        hfield_answer=wp.zeros(nhfield_mpr, dtype=wp.vec4),
        hfield_normal=wp.zeros(nhfield_mpr, dtype=wp.vec3),
        pair_outputs=broadphase.PairOutputs(),
        queues=narrowphase.PairQueues(),
        quota=contact_quota.make_buffers(nworld, self.options.contacts_per_world),
      )
    out = st.pair_outputs
    out.world_npair, out.slot_pair, out.slot_pairid = st.world_npair, st.slot_pair, st.slot_pairid
    out.ndropped, out.nwarned, out.overflow, out.ncollision = st.ndropped, st.nwarned, d.overflow, d.ncollision
    out.stock_pair = st.stock_ctx.collision_pair
    out.stock_pairid = st.stock_ctx.collision_pairid
    out.stock_worldid = st.stock_ctx.collision_worldid
    out.npair, out.pair, out.pairid, out.pair_worldid = st.npair, st.pair, st.pairid, st.pair_worldid
    q = st.queues
    q.pair_queue_type, q.geom_nonconvex = self.pair_queue_type, self.geom_nonconvex
    q.gjk_all = int(self.options.narrowphase == "gjk")
    q.count, q.pair = st.queue_count, st.queue_pair
    return st

  # --- the collision stage ---------------------------------------------------------------

  def collision(self, m, d, awake_prev: Optional[wp.array] = None):
    """AABBs -> sweep-and-prune -> narrow phase, writing into ``d.contact`` / ``d.nacon``.

    Runs on the model's device whatever the current device is, so models on several GPUs can
    be stepped from one thread."""
    with wp.ScopedDevice(self.device):
      self._collision(m, d, awake_prev)

  def _collision(self, m, d, awake_prev: Optional[wp.array]):
    if d.naconmax == 0 or m.opt.disableflags & (DisableBit.CONSTRAINT | DisableBit.CONTACT):
      d.nacon.zero_()
      return
    per_world = self.options.contacts_per_world
    if per_world:
      contact_quota.check_fits(per_world, d.nworld, d.naconmax)
      if awake_prev is not None or m.opt.enableflags & EnableBit.SLEEP:  # enabled after install
        raise ValueError(_SLEEP_QUOTA)
    st = self.state(m, d)
    incremental = awake_prev is not None
    warm = bool(self.mpr_types) and self.options.warm_start
    wp.launch(
      start_collision,
      dim=d.nworld,
      inputs=[incremental, warm],
      outputs=[d.ncollision, d.nacon, st.ndropped, st.nonfinite, st.world_npair, st.npair, st.nwarned, st.queue_count,
               st.patch_count, st.face_count, st.tilt_pair_count, st.tilt_count, st.hfield_count, st.warm.stamp, st.warm.misses],
    )
    q = st.quota
    if per_world:
      wp.launch(contact_quota.start_worlds, dim=d.nworld, inputs=[per_world],
                outputs=[d.nacon, q.quota.world_ncon, q.stock_dropped, q.nwarned])

    self._broadphase(m, d, st, awake_prev)
    self._narrowphase(m, d, st)

    if m.nflex > 0 and not incremental:
      collision_driver.flex_collision(m, d, st.stock_ctx)
    if per_world:
      contact_quota.pack(d, q, bool(int(m.opt.warn_overflow) & int(OverflowType.NARROWPHASE)))
    # the packed rows keep each world's writers' order, which atomics make vary on a GPU: the sort still runs
    if m.opt.deterministic & DeterminismType.CONTACTS:
      if st.sort is None:
        st.sort = contact_sort.make_buffers(d, self.ngeom)
      contact_sort.sort_contacts(d, st.sort, self.ngeom)
    if m.flg_surfacevel:
      wp.launch(
        collision_driver._contact_surfacevel,
        dim=d.naconmax,
        inputs=[m.geom_surfacevel, d.geom_xpos, d.geom_xmat, d.contact.pos, d.contact.frame, d.contact.geom,
                d.contact.worldid, d.naconmax, d.nacon],
        outputs=[d.contact.surfacevel],
      )
    if m.callback.contactfilter:
      m.callback.contactfilter(m, d)

  def _broadphase(self, m, d, st: DataState, awake_prev):
    wp.launch(
      update_aabbs,
      dim=(d.nworld, self.ngeom),
      inputs=[m.geom_type, m.geom_dataid, m.geom_aabb, m.geom_margin, m.geom_gap, d.geom_xpos, d.geom_xmat],
      outputs=[st.aabb_lo, st.aabb_hi, st.nonfinite],
    )
    enable_sleep = bool(m.opt.enableflags & EnableBit.SLEEP)
    incremental = awake_prev is not None
    key = (
      int(m.opt.broadphase_filter),
      m.geom_aabb.shape[0],
      m.geom_rbound.shape[0],
      m.geom_margin.shape[0],
      m.geom_gap.shape[0],
      m.pair_margin.shape[0],
      m.pair_gap.shape[0],
      enable_sleep,
      incremental,
    )
    awake_prev_in = awake_prev if incremental else d.body_awake
    warn = bool(int(m.opt.warn_overflow) & int(OverflowType.BROADPHASE))
    common_model = [m.geom_type, m.geom_bodyid, m.geom_aabb, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                    m.pair_gap]
    common_data = [d.geom_xpos, d.geom_xmat, d.body_awake, d.naconmax, awake_prev_in, self.geom_stock, st.aabb_lo,
                   st.aabb_hi]

    def listed(direct: bool, pairs: wp.array, pairids: wp.array, npair: int):
      wp.launch(
        broadphase.listed_pairs_kernel(key, direct),
        dim=(d.nworld, npair),
        inputs=common_model + common_data + [pairs, pairids, self.max_pairs, warn],
        outputs=[st.pair_outputs, st.queues],
      )

    if self.nxn:
      listed(True, m.nxn_geom_pair_filtered, m.nxn_pairid_filtered, self.npair_filtered)
      return
    if self.ngeom > 1:
      wp.launch(broadphase.sort_endpoints, dim=d.nworld, inputs=[self.ngeom, self.options.sap_axis, st.aabb_lo],
                outputs=[st.sap_init, st.order])
      wp.launch(
        broadphase.sweep_kernel(key, self.options.sap_axis),
        dim=(d.nworld, self.ngeom),
        inputs=[self.ngeom] + common_model + [m.nxn_pairid] + common_data + [self.max_pairs, warn, st.order],
        outputs=[st.pair_outputs],
      )
    if self.nexplicit:
      listed(False, self.explicit_pair, self.explicit_pairid, self.nexplicit)
    wp.launch(broadphase.clamp_counts, dim=d.nworld, inputs=[self.max_pairs, st.world_npair], outputs=[st.world_count])
    wp.utils.array_scan(st.world_count, st.world_start, inclusive=False)
    wp.launch(
      broadphase.compact_pairs,
      dim=(d.nworld, self.max_pairs),
      inputs=[m.geom_type, self.max_pairs, st.world_count, st.world_start],
      outputs=[st.pair_outputs, st.queues],
    )

  def _contact_outputs(self, d):
    return [getattr(d.contact, f) for f in _WRITTEN_CONTACT_FIELDS] + [d.nacon]

  def _narrowphase(self, m, d, st: DataState):
    quota = st.quota.quota
    nthread = max(1, min(st.capacity, _GRID_THREADS))
    pair_inputs = [st.npair, st.pair, st.pairid, st.pair_worldid, nthread]
    queue_inputs = [st.queue_count, st.queue_pair, st.pair, st.pairid, st.pair_worldid]  # + the launch's threads
    # analytic pairs are cheap: as many threads as contacts fit, as stock MuJoCo Warp launches them
    nthread_analytic = max(1, min(nthread, d.naconmax))
    nthread_tilt = max(1, min(st.tilt_result.shape[0] * st.tilt_result.shape[1], _GRID_THREADS))
    gjk_all = self.options.narrowphase == "gjk"
    if self.mpr_types and not gjk_all:
      wp.launch(
        narrowphase.sift_mpr_pairs,
        dim=nthread,
        inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, SUPPORT_MODE_ID[self.options.support_mode],
                st.pair, st.pairid, st.pair_worldid, nthread],
        outputs=[st.queues],
      )
    if self.analytic_types:
      wp.launch(
        narrowphase.analytic_kernel(self.analytic_types),
        dim=nthread_analytic,
        inputs=[
          m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
          m.geom_size, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.mesh_vertadr, m.mesh_vertnum,
          m.mesh_graphadr, m.mesh_vert, m.mesh_graph, m.mesh_polynum, m.mesh_polyadr, m.mesh_polynormal,
          m.mesh_polyvertadr, m.mesh_polyvertnum, m.mesh_polyvert, m.mesh_polymapadr, m.mesh_polymapnum,
          m.mesh_polymap, m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin,
          m.pair_gap, m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax,
        ] + queue_inputs + [nthread_analytic, quota],
        outputs=self._contact_outputs(d),
      )
    if self.mpr_types:
      warm = st.warm
      # MPR's pairs, then GJK's (all with narrowphase="gjk", else those with a sphere or capsule)
      for use_gjk in (False, True):
        if (use_gjk and not (gjk_all or self.has_core_pairs)) or (not use_gjk and gjk_all):
          continue
        wp.launch(
          narrowphase.convex_kernel(use_gjk),
          dim=nthread,
          inputs=[
            m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref,
            m.geom_solimp, m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion,
            m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
            m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support,
            SUPPORT_MODE_ID[self.options.support_mode], self.options.mpr_tolerance,
            self.options.mpr_iterations, self.options.mpr_refine,
            self.options.max_contacts_per_pair if self.options.multi_contact else 1, self.options.mc_perturbation,
            self.mesh_sdf, self.options.mpr_to_sdf_overlap_ratio, self.options.warm_start,
            warm.stamp, warm.slot_stamp, warm.slot_key, warm.slot_value, warm.misses,
          ] + queue_inputs + [nthread, quota],
          outputs=[st.patch_count, st.patch_pair, st.patch_result, st.patch_pos] + self._contact_outputs(d),
        )
      wp.launch(
        narrowphase.face_pair_kernel,
        dim=nthread,
        inputs=[
          m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
          m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, SUPPORT_MODE_ID[self.options.support_mode],
          st.pair, st.pairid, st.pair_worldid, st.patch_count, st.patch_pair, st.patch_result, nthread,
        ],
        outputs=[st.face_count, st.face_queue, st.face_faces, st.tilt_pair_count, st.tilt_pair],
      )
      wp.launch(
        narrowphase.manifold_kernel,
        dim=nthread,
        inputs=[
          m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
          m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb,
          m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
          m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support,
          self.options.max_contacts_per_pair, self.options.mc_tolerance, st.pair, st.pairid, st.pair_worldid,
          st.patch_pair, st.patch_result, st.patch_pos, st.face_count, st.face_queue, st.face_faces, nthread,
          quota,
        ],
        outputs=[st.tilt_pair_count, st.tilt_pair] + self._contact_outputs(d),
      )
      tilt_model = [m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                    m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, SUPPORT_MODE_ID[self.options.support_mode]]
      wp.launch(
        narrowphase.tilt_kernel,
        dim=nthread_tilt,
        inputs=tilt_model + [self.options.mc_perturbation, st.pair, st.pairid, st.pair_worldid, st.tilt_pair_count,
                             st.tilt_pair, st.patch_pair, st.patch_result, st.patch_pos, nthread_tilt],
        outputs=[st.tilt_result, st.tilt_count, st.tilt_queue],
      )
      wp.launch(
        narrowphase.tilt_mpr_kernel,
        dim=nthread_tilt,
        inputs=tilt_model + [self.options.mpr_tolerance, self.options.mpr_iterations, self.options.mc_perturbation,
                             st.pair, st.pairid, st.pair_worldid, st.tilt_pair, st.patch_pair, st.patch_result,
                             st.patch_pos, st.tilt_count, st.tilt_queue, nthread_tilt],
        outputs=[st.tilt_result],
      )
      wp.launch(
        narrowphase.patch_kernel,
        dim=nthread,
        inputs=[
          m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
          m.geom_size, m.geom_rbound, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb,
          m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap,
          m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support,
          SUPPORT_MODE_ID[self.options.support_mode], self.options.mpr_tolerance, self.options.mpr_iterations,
          self.options.max_contacts_per_pair, self.options.mc_perturbation, self.options.mc_tolerance, st.pair,
          st.pairid, st.pair_worldid, st.tilt_pair_count, st.tilt_pair, st.patch_pair, st.patch_result, st.patch_pos,
          st.tilt_result, nthread, quota,
        ],
        outputs=self._contact_outputs(d),
      )
    if self.has_hfield_pairs:
      self._heightfield(m, d, st, nthread)
    if self.has_nonconvex_pairs:
      wp.launch(
        nonconvex.nonconvex_narrowphase,
        dim=nthread,
        inputs=[
          m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
          m.geom_size, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb, m.mesh_vertnum,
          self.mesh_faceadr, self.mesh_facenum, m.mesh_face, m.pair_dim, m.pair_solref, m.pair_solreffriction,
          m.pair_solimp, m.pair_margin, m.pair_gap, m.pair_adhesion, m.pair_friction, d.geom_xpos, d.geom_xmat,
          d.naconmax, self.mesh_support, self.geom_nonconvex, self.sdfs, SUPPORT_MODE_ID[self.options.support_mode],
          self.options.max_contacts_per_pair, self.options.mc_tolerance,
        ] + pair_inputs + [quota],
        outputs=self._contact_outputs(d),
      )
    if self.has_stock_pairs:
      # SDF geoms and collision-sensor pairs: MuJoCo Warp's own narrow phase
      collision_driver._narrowphase(m, d, st.stock_ctx)

  def _heightfield(self, m, d, st: DataState, nthread: int):
    """Heightfield - convex pairs: windows and MPR queue, the queue grouped by kind, the queued
    MPRs, then the contacts."""
    mode = SUPPORT_MODE_ID[self.options.support_mode]
    warn = int(bool(int(m.opt.warn_overflow) & int(OverflowType.HFIELD)))
    hfield = [m.hfield_size, m.hfield_nrow, m.hfield_ncol, m.hfield_adr, m.hfield_data]
    wp.launch(
      heightfield.hfield_jobs,
      dim=nthread,
      inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_margin, m.geom_gap] + hfield
      + [m.pair_margin, m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, mode, st.npair, st.pair,
         st.pairid, st.pair_worldid, 2, nthread],
      outputs=[d.overflow, st.hfield_count, st.hfield_pair, st.hfield_job],
    )
    nthread_pair = max(1, min(st.hfield_pair.shape[0], _GRID_THREADS))
    wp.launch(heightfield.hfield_kind_start, dim=1, inputs=[st.hfield_count], outputs=[st.hfield_kind_next])
    wp.launch(
      heightfield.hfield_order,
      dim=nthread_pair,
      inputs=[m.geom_type, st.pair, st.hfield_count, st.hfield_pair, st.hfield_job, nthread_pair],
      outputs=[st.hfield_kind_next, st.hfield_order],
    )
    nthread_mpr = max(1, min(st.hfield_job.shape[0], _GRID_THREADS))
    wp.launch(
      heightfield.hfield_mpr,
      dim=nthread_mpr,
      inputs=[m.geom_type, m.geom_dataid, m.geom_size] + hfield
      + [d.geom_xpos, d.geom_xmat, self.mesh_support, mode, self.options.mpr_tolerance, self.options.mpr_iterations,
         self.options.mpr_refine, st.pair, st.pair_worldid, st.hfield_count, st.hfield_pair, st.hfield_job,
         st.hfield_order, nthread_mpr],
      outputs=[st.hfield_answer, st.hfield_normal],
    )
    wp.launch(
      heightfield.hfield_contacts,
      dim=nthread_pair,
      inputs=[
        m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
        m.geom_size, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb] + hfield + [
        m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap, m.pair_adhesion,
        m.pair_friction, warn, d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support, mode,
        self.options.mpr_tolerance, self.options.mpr_iterations, self.options.mpr_refine,
        self.options.max_contacts_per_pair, self.options.mc_tolerance, st.pair, st.pairid,
        st.pair_worldid, st.hfield_count, st.hfield_pair, st.hfield_job, st.hfield_answer, st.hfield_normal,
        nthread_pair, st.quota.quota,
      ],
      outputs=[d.overflow] + self._contact_outputs(d),
    )

  # --- diagnostics --------------------------------------------------------------------

  def stats(self, d) -> "CollisionStats":
    """Host-side counters of the last collision on ``d`` (reads the device: not for graphs).

    A ``CollisionStats``: a dict of the counters below (per-world lists included) that prints as a
    summary (totals and the worlds with the most pairs or drops; ``summary()``).

    With sleeping enabled, the pair counts are those of the step's second (incremental) pass.
    ``dropped_contacts`` counts the contacts beyond ``d.naconmax`` (all worlds together), and with
    ``Options.contacts_per_world`` also those beyond each world's rows; ``dropped_contacts_per_world``
    has those of each world (all 0 without contacts_per_world: the shared buffer does not know whose
    contacts it dropped).
    ``warm_start_misses`` counts the pairs whose warm-started MPR missed and ran again cold.
    ``hfield_mprs_unqueued`` counts the terrain MPRs the heightfield queue had no room for: they
    ran one after another in their pair's thread (the same contacts, slower; see
    ``Options.hfield_mprs_per_pair``).
    """
    from mjx_supportfield.stats import CollisionStats

    states = getattr(d, _STATE_ATTR, None)
    st = states.get(self) if states is not None else None
    if st is None:
      return CollisionStats({"pairs": 0, "pairs_per_world": [], "dropped_pairs_per_world": [], "nonfinite_worlds": [],
                             "dropped_contacts": 0, "dropped_contacts_per_world": [], "warm_start_misses": 0,
                             "hfield_mprs_unqueued": 0})
    return CollisionStats({
      "pairs": int(st.npair.numpy()[0]),
      "pairs_per_world": np.minimum(st.world_npair.numpy(), self.max_pairs).tolist(),
      "dropped_pairs_per_world": st.ndropped.numpy().tolist(),
      "nonfinite_worlds": np.nonzero(st.nonfinite.numpy())[0].tolist(),
      **self._dropped_contacts(d, st),
      "warm_start_misses": int(st.warm.misses.numpy()[0]) if self.options.warm_start else 0,
      # terrain MPRs that found the heightfield queue full and ran in their pair's thread
      "hfield_mprs_unqueued": int(st.hfield_count.numpy()[heightfield.COUNT_UNQUEUED]),
    })

  def _dropped_contacts(self, d, st: DataState) -> dict:
    """Contacts found but not stored: beyond naconmax (mjw.step flags OverflowType.NARROWPHASE) or,
    with contacts_per_world, beyond a world's rows (flagged in that world)."""
    per_world = self.options.contacts_per_world
    if not per_world:
      return {"dropped_contacts": max(0, int(d.nacon.numpy()[0]) - d.naconmax),
              "dropped_contacts_per_world": [0] * d.nworld}
    q = st.quota
    per_world_dropped = np.maximum(q.quota.world_ncon.numpy() - per_world, 0)
    return {"dropped_contacts": int(per_world_dropped.sum()) + int(q.stock_dropped.numpy()[0]),
            "dropped_contacts_per_world": per_world_dropped.tolist()}
