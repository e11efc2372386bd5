"""The installed collision stage: the driver that runs the stages in pipeline order.

Each stage module owns its kernels and a stage class (launch/stage.py's contract: model-time
facts, per-Data buffers, one ``launch``): broadphase, narrowphase, deep_pairs, multicontact_pass,
heightfield, nonconvex. This module builds the model-time data and the stages (``Collider``),
keeps the per-Data state (``DataState``) and runs the stages in order between the start
(stage_ends) and the contact rows' packing and sort (launch/); it launches no kernel of its own.
"""

import dataclasses
import weakref
from typing import Optional

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src import collision_driver
from mujoco_warp._src.types import DeterminismType
from mujoco_warp._src.types import DisableBit
from mujoco_warp._src.types import EnableBit
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import OverflowType

from mjx_supportfield.geometry.sdf import build_mesh_sdf
from mjx_supportfield.geometry.support_field import MAX_HULL
from mjx_supportfield.geometry.support_field import build_mesh_support
from mjx_supportfield.geometry.support_field import hull_vertex_count
from mjx_supportfield.geometry.support_field import too_large
from mjx_supportfield.launch import contact_quota
from mjx_supportfield.launch import contact_sort
from mjx_supportfield.launch import first_use
from mjx_supportfield.options import Options
from mjx_supportfield.stages import broadphase
from mjx_supportfield.stages import deep_pairs
from mjx_supportfield.stages import heightfield
from mjx_supportfield.stages import multicontact_pass
from mjx_supportfield.stages import narrowphase
from mjx_supportfield.stages import nonconvex
from mjx_supportfield.stages import routing
from mjx_supportfield.stages import stage_ends
from mjx_supportfield.stages import warmstart
from mjx_supportfield.types import CONVEX_TYPES
from mjx_supportfield.types import STOCK_TYPES
from mjx_supportfield.types import SupportMode

_STATE_ATTR = "_mjx_supportfield_state"
STOCK_COLLISION = collision_driver.collision  # MuJoCo Warp's own, taken before install() routes it here
# a sleeping step's second pass appends to the first pass's contacts, which the quota has packed
_SLEEP_QUOTA = ("mjx_supportfield: Options.contacts_per_world does not work with sleeping (the model enables"
                " mjtEnableBit.mjENBL_SLEEP); use contacts_per_world = 0 or disable sleeping")


@dataclasses.dataclass
class DataState:
  """Per-Data buffers, one set per stage under the stage's name (sizes depend on nworld, which
  install cannot know), and the call's ``awake_prev``: what a stage's launch reads."""

  warm: warmstart.WarmCache
  quota: contact_quota.QuotaBuffers  # each world's contact rows (Options.contacts_per_world)
  broad: Optional[broadphase.Buffers] = None  # boxes, pair list, the pairs left to MuJoCo Warp (stock_ctx)
  narrow: Optional[narrowphase.Buffers] = None  # narrow-phase and multi-contact queues
  deep: Optional[deep_pairs.Buffers] = None  # MPR's deep answers queued for their check
  multicontact: None = None  # the pass works in the narrow phase's buffers
  hfield: Optional[heightfield.Buffers] = None
  nonconvex: None = None
  awake_prev: Optional[wp.array] = None  # the collision call's (sleeping's incremental pass), else None
  sort: Optional[contact_sort.SortBuffers] = None  # made on the first deterministic call
  fields: Optional[tuple] = None  # contact_sort.fields_and_copy, made on first use: packing's and sorting's scratch


# Data fields and the MjModel size each has per world
_DATA_SIZES = (("geom_xpos", "ngeom"), ("qpos", "nq"), ("qvel", "nv"), ("xpos", "nbody"), ("xanchor", "njnt"),
               ("ctrl", "nu"), ("act", "na"), ("mocap_pos", "nmocap"), ("site_xpos", "nsite"), ("cam_xpos", "ncam"),
               ("light_xpos", "nlight"), ("ten_length", "ntendon"), ("sensordata", "nsensordata"),
               ("eq_active", "neq"))


def _mesh_plan(mjm: mujoco.MjModel, m, pairs: np.ndarray) -> tuple[list[int], list[int], list[int]]:
  """The meshes the plugin collides, the mesh geoms that name them, and the mesh geoms it leaves
  to MuJoCo Warp's narrow phase.

  A mesh geom in no pair of the model (a visual mesh: contype = conaffinity = 0 and in no
  <pair>) collides nothing, so its meshes get no field, SDF or polygons. A geom whose hull (in
  any world: ``geom_dataid`` may differ per world) has more vertices than a field's cell can
  name is collided by MuJoCo Warp itself, with a note."""
  in_pairs = np.zeros(mjm.ngeom, bool)
  in_pairs[pairs.reshape(-1)] = True
  dataid = np.asarray(m.geom_dataid.numpy()).reshape(-1, mjm.ngeom)  # (worlds batched, ngeom)
  mesh_geoms = np.nonzero(in_pairs & (np.asarray(mjm.geom_type) == GeomType.MESH))[0]
  meshes_of = {int(g): {int(x) for x in dataid[:, g] if x >= 0} for g in mesh_geoms}
  large = set(too_large(mjm, set().union(*meshes_of.values())))
  stock_geoms = [g for g, ids in meshes_of.items() if ids & large]
  for g in stock_geoms:
    meshid = min(meshes_of[g] & large)
    first_use.logger.info(
      "geom '%s': the hull of mesh '%s' has %d vertices, more than a support field's %d; MuJoCo Warp's own narrow"
      " phase collides its pairs", _name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g), _name(mjm, mujoco.mjtObj.mjOBJ_MESH,
                                                                                     meshid),
      hull_vertex_count(mjm, meshid), MAX_HULL)
  plugin_geoms = [g for g in meshes_of if g not in stock_geoms]
  return sorted(set().union(*(meshes_of[g] for g in plugin_geoms))), plugin_geoms, stock_geoms


def _name(mjm: mujoco.MjModel, kind, i: int) -> str:
  return mujoco.mj_id2name(mjm, kind, i) or f"#{i}"


class Collider:
  """Everything the plugin built for one MuJoCo Warp model (see ``install``)."""

  def __init__(self, mjm: mujoco.MjModel, m, options: Options):
    heightfield.check_model(mjm)
    if options.contacts_per_world and m.opt.enableflags & EnableBit.SLEEP:
      raise ValueError(_SLEEP_QUOTA)
    self.options, self.ngeom = options, mjm.ngeom
    self.support_mode = SupportMode.of(options.support_mode)  # the kernels' factories' key
    # every model-sized array of a Data: a Data made for another model differs in one of them
    self.data_sizes = {field: int(getattr(mjm, size)) for field, size in _DATA_SIZES}
    self.device = device = m.geom_type.device
    with wp.ScopedDevice(device):
      pairs = np.asarray(m.nxn_geom_pair_filtered.numpy()).reshape(-1, 2)
      pairids = np.asarray(m.nxn_pairid_filtered.numpy()).reshape(-1, 2)
      self.collided_meshes, plugin_geoms, large = _mesh_plan(mjm, m, pairs)
      # for a m.geom_dataid replaced after install (_check_geom_dataid)
      self._plugin_mesh_geoms = {_name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g): g for g in plugin_geoms}
      self._geom_dataid = m.geom_dataid
      self.mesh_support = build_mesh_support(mjm, m.mesh_vert, options.support_res, device,
                                             meshes=self.collided_meshes)
      # non-convex meshes: their own triangles' SDFs
      ncgeoms = nonconvex.nonconvex_geom_ids(mjm, options.nonconvex_geoms)
      nonconvex.warn_open_meshes(mjm, ncgeoms)
      flags = np.isin(np.arange(mjm.ngeom), ncgeoms).astype(np.int32)
      geom_nonconvex = wp.array(flags, dtype=int)
      has_nonconvex_pairs = bool(len(ncgeoms)) and bool(flags[pairs].any()) if len(pairs) else False
      stock = np.isin(np.asarray(mjm.geom_type), [int(t) for t in STOCK_TYPES])
      stock[large] = True
      # per geom: 1 MuJoCo Warp's, -1 the plugin's whatever the pair's class, 0 by the class
      self.geom_stock = wp.array(np.where(stock, 1, -flags).astype(np.int32), dtype=int)

      explicit = (pairids[:, 0] >= 0) | (pairids[:, 1] >= 0)
      sensor = pairids[:, 1] >= 0
      # no world can have more pairs than the model allows after its static filters
      max_pairs = max(1, min(options.max_collision_pairs, len(pairs)))
      nxn = options.broadphase == "nxn" or (options.broadphase == "auto"
                                            and len(pairs) <= broadphase.nxn_pair_limit(mjm, pairs))
      t1, t2 = np.sort(np.asarray(mjm.geom_type)[pairs], axis=1).T if len(pairs) else (np.zeros(0, int),) * 2
      # the pair classes routed to MuJoCo Warp's narrow phase (Options.stock_pair_classes), by the
      # table the broad phase routes them with
      type_stock = routing.stock_type_table(routing.stock_types(
        routing.pair_types_present(mjm, pairs), {routing.PairClass.named(c) for c in options.stock_pair_classes}))
      routed = (type_stock[t1 * routing.NGEOMTYPE + t2] != 0) & ~flags[pairs].any(axis=1)
      self.has_stock_pairs = bool((stock[pairs].any(axis=1) | sensor | routed).any())
      # MuJoCo Warp's kernels for the routed types only, unless pairs of any type can reach it
      self.stock_types = None if bool(stock.any()) or bool(sensor.any()) else frozenset(
        (GeomType(a), GeomType(b)) for a, b in zip(t1[routed], t2[routed]))
      self.broad = broadphase.BroadPhase(
        mjm.ngeom, nxn, max_pairs, len(pairs), wp.array(pairs[explicit].astype(np.int32), dtype=wp.vec2i),
        wp.array(pairids[explicit].astype(np.int32), dtype=wp.vec2i), self.geom_stock,
        wp.array(type_stock, dtype=int), options.sap_axis)

      kept = ~routed  # the pairs not routed away by class (those of MuJoCo Warp's own geoms count, as bounds)
      present = routing.pair_types_present(mjm, pairs[kept])
      analytic_types, mpr_types, queue_table = routing.pair_queue_table(present, options.narrowphase == "gjk")
      has_hfield_pairs = any(t1 == GeomType.HFIELD and t2 in CONVEX_TYPES for t1, t2 in present)
      queues = queue_table[t1[kept] * routing.NGEOMTYPE + t2[kept]]
      nmpr = int(((queues == routing.QUEUE_GJK) | (queues == routing.QUEUE_CANDIDATE)).sum())
      self.warm_slots = warmstart.slots_per_world(min(nmpr, max_pairs))
      # bounds its kernels' pairs; boxes and meshes collide prisms by GJK/EPA
      on_hfield = (t1 == GeomType.HFIELD) & kept
      convex_on_hfield = on_hfield & np.isin(t2, list(map(int, CONVEX_TYPES)))
      # spheres and capsules on terrain: the closed-form kernel (hfield_closed_form.py)
      round_on_hfield = on_hfield & np.isin(t2, [int(GeomType.SPHERE), int(GeomType.CAPSULE)])
      self.hfield = heightfield.Heightfield(
        options, self.support_mode, self.mesh_support, has_hfield_pairs, min(int(convex_on_hfield.sum()), max_pairs),
        heightfield.job_pairs(int((convex_on_hfield & ~round_on_hfield).sum()), int(round_on_hfield.sum()), max_pairs),
        bool((on_hfield & np.isin(t2, [int(GeomType.BOX), int(GeomType.MESH)])).any()),
        bool(round_on_hfield.any()),
        int(mjm.opt.ccd_iterations))
      ncmeshes = {int(mjm.geom_dataid[g]) for g in ncgeoms}
      sdfs = nonconvex.SdfSet()
      sdfs.true_mesh = build_mesh_sdf(mjm, options.nonconvex_sdf_res, ncmeshes, device, nonconvex.mesh_triangles)
      # hull SDFs: for the fallback of meshes that meet another shape through MPR, and for the
      # convex meshes a non-convex one may touch
      mesh_ids = set(self.collided_meshes)
      meshes = set()
      if options.mpr_to_sdf_overlap_ratio > 0 and any(GeomType.MESH in t for t in mpr_types):
        meshes = set(mesh_ids)
      if has_nonconvex_pairs:
        meshes |= mesh_ids
      self.mesh_sdf = build_mesh_sdf(mjm, options.sdf_res, meshes, device)
      sdfs.hull = self.mesh_sdf
      self.narrow = narrowphase.NarrowPhase(options, self.support_mode, self.mesh_support, self.mesh_sdf,
                                            analytic_types, mpr_types, wp.array(queue_table, dtype=int), geom_nonconvex)
      self.deep = deep_pairs.DeepPairs(options, self.support_mode, self.mesh_support, mpr_types)
      self.multicontact = multicontact_pass.MultiContactPass(options, self.support_mode, self.mesh_support, mpr_types)
      self.nonconvex = nonconvex.NonConvex(
        options, self.support_mode, self.mesh_support, has_nonconvex_pairs, geom_nonconvex,
        wp.array(np.asarray(mjm.mesh_faceadr, np.int32).reshape(-1), dtype=int),
        wp.array(np.asarray(mjm.mesh_facenum, np.int32).reshape(-1), dtype=int), sdfs)
    self.mpr_types = mpr_types
    # the pipeline's stages in launch order, each under its name in DataState (the stage contract)
    self.stages = {"broad": self.broad, "narrow": self.narrow, "deep": self.deep, "multicontact": self.multicontact,
                   "hfield": self.hfield, "nonconvex": self.nonconvex}
    self.stock_path = routing.gives_plugin_nothing(options, nxn, bool(mpr_types or has_hfield_pairs
                                                                      or has_nonconvex_pairs), m)

  # --- per-Data state -------------------------------------------------------------------

  @staticmethod
  def _states(d) -> weakref.WeakKeyDictionary:
    """The per-Collider states kept on ``d``: a DataState, or None for the stock path's checked Data."""
    states = getattr(d, _STATE_ATTR, None)
    if states is None:
      states = weakref.WeakKeyDictionary()  # a Collider that is gone takes its state along
      object.__setattr__(d, _STATE_ATTR, states)
    return states

  def state(self, m, d) -> DataState:
    """State kept on ``d`` (created on its first collision): one buffer set per stage."""
    states = self._states(d)
    st = states.get(self)
    if st is None:
      self._check_data(d)
      with wp.ScopedDevice(self.device):
        st = DataState(warm=warmstart.make_cache(d.nworld, self.warm_slots if self.options.warm_start else 1),
                       quota=contact_quota.make_buffers(d.nworld, self.options.contacts_per_world))
        for name, stage in self.stages.items():
          setattr(st, name, stage.make_buffers(d, st))
      states[self] = st
    return st

  def _check_data(self, d):
    for field, want in self.data_sizes.items():
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
    for field in contact_quota.WRITTEN_CONTACT_FIELDS:
      if not getattr(d.contact, field).is_contiguous:
        raise ValueError(f"mjx_supportfield: Data.contact.{field} is not contiguous; make the Data with"
                         " mjw.make_data or mjw.put_data")
    if self.options.contacts_per_world:
      contact_quota.check_fits(self.options.contacts_per_world, d.nworld, d.naconmax)

  @staticmethod
  def reset_worlds(d, reset: Optional[wp.array] = None) -> None:
    """Drops every installed model's history on ``d`` of the worlds ``reset`` marks (all when
    None): warm-start normals and sweep-and-prune order, so a reset world repeats its run bit for bit."""
    states = Collider._states(d)
    if reset is not None and reset.dtype != wp.bool:
      mask = wp.empty(d.nworld, dtype=bool, device=reset.device)
      wp.utils.array_cast(reset, mask)
      reset = mask
    for st in [st for st in states.values() if st is not None]:  # the stock path keeps no history
      warmstart.forget(st.warm, st.broad.sap_init, reset)

  def _check_geom_dataid(self, m):
    """Accepts a ``m.geom_dataid`` replaced after install (per-world mesh variants) whose meshes
    install built support for; raises naming the geom, world and mesh otherwise."""
    if m.geom_dataid.device.is_capturing:
      raise ValueError("mjx_supportfield: m.geom_dataid was replaced after install and is first seen while a CUDA"
                       " graph is captured; run one step (or collision) uncaptured first, so the plugin can check it")
    dataid = np.asarray(m.geom_dataid.numpy()).reshape(-1, self.ngeom)
    built = set(self.collided_meshes)
    for name, g in self._plugin_mesh_geoms.items():
      for w, meshid in enumerate(dataid[:, g]):
        if meshid >= 0 and int(meshid) not in built:
          raise ValueError(
            f"mjx_supportfield: m.geom_dataid was replaced after install: geom '{name}' names mesh {int(meshid)} in"
            f" world {w}, for which install built no support field (it builds them for the meshes m.geom_dataid"
            " names then); set per-world meshes before install, or uninstall(m) and install again")
    self._geom_dataid = m.geom_dataid

  # --- the collision stage ---------------------------------------------------------------

  def collision(self, m, d, awake_prev: Optional[wp.array] = None):
    """AABBs -> sweep-and-prune -> narrow phase, writing into ``d.contact`` / ``d.nacon``.

    Runs on the model's device whatever the current device is, so models on several GPUs can
    be stepped from one thread."""
    with wp.ScopedDevice(self.device):
      self._collision(m, d, awake_prev)

  def _collision(self, m, d, awake_prev: Optional[wp.array]):
    if self.stock_path:
      states = self._states(d)
      if self not in states:  # checked once per Data, as the plugin path's state is made once
        self._check_data(d)
        states[self] = None
      STOCK_COLLISION(m, d, awake_prev)
      return
    if d.naconmax == 0 or m.opt.disableflags & (DisableBit.CONSTRAINT | DisableBit.CONTACT):
      d.nacon.zero_()
      return
    if m.geom_dataid is not self._geom_dataid:
      self._check_geom_dataid(m)
    per_world = self.options.contacts_per_world
    if per_world and (awake_prev is not None or m.opt.enableflags & EnableBit.SLEEP):  # enabled after install
      raise ValueError(_SLEEP_QUOTA)
    st = self.state(m, d)
    incremental = awake_prev is not None
    stage_ends.start(d, st, incremental, bool(self.mpr_types) and self.options.warm_start)
    if per_world:
      contact_quota.start(d, st.quota, per_world)
    st.awake_prev = awake_prev
    # in order; the deep-pair check before the multi-contact pass: a checked pair joins its queue
    # with the corrected normal
    for stage in self.stages.values():
      stage.launch(m, d, st)
    if self.has_stock_pairs:  # routed classes, SDF geoms, collision-sensor pairs: MuJoCo Warp's own narrow phase
      stage_ends.stock_narrowphase(m, d, st.broad.stock_ctx, self.stock_types)
    if m.nflex > 0 and not incremental:
      collision_driver.flex_collision(m, d, st.broad.stock_ctx)
    sort = m.opt.deterministic & DeterminismType.CONTACTS
    if (per_world or sort) and st.fields is None:
      st.fields = contact_sort.fields_and_copy(d)
    if per_world:
      contact_quota.pack(d, st.quota, st.fields, bool(int(m.opt.warn_overflow) & int(OverflowType.NARROWPHASE)))
    # the packed rows keep each world's writers' order, which atomics make vary on a GPU: the sort still runs
    if sort:
      if st.sort is None:
        st.sort = contact_sort.make_buffers(d, self.ngeom, st.fields)
      contact_sort.sort_contacts(d, st.sort, self.ngeom)
    if m.flg_surfacevel:
      stage_ends.surface_velocities(m, d)
    if m.callback.contactfilter:
      m.callback.contactfilter(m, d)

  # --- diagnostics --------------------------------------------------------------------

  def model_bytes(self) -> int:
    """Device bytes of the model-time data install built (hulls, polygons, support fields, SDFs,
    pair tables); MuJoCo Warp's arrays that the plugin reads in place (mesh vertices) not counted."""
    shared = {id(self.mesh_support.vert)}
    seen, total = set(), 0
    for holder in (self, *self.stages.values(), self.mesh_support, self.mesh_sdf, self.nonconvex.sdfs.true_mesh):
      for value in vars(holder).values():
        if isinstance(value, wp.array) and id(value) not in shared | seen:
          seen.add(id(value))
          total += value.capacity
    return total

  def stats(self, d) -> dict:
    """Host-side counters of the last collision on ``d`` (reads the device: not for graphs): a
    ``CollisionStats``, a dict of counters (per-world lists included; its docstring names them)
    that prints as a summary."""
    from mjx_supportfield import stats

    states = getattr(d, _STATE_ATTR, None)
    return stats.collect(self, d, states.get(self) if states is not None else None)
