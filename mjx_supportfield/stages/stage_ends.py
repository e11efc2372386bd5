"""The collision stage's first and last launches: the counters of every stage reset before the
broad phase; after the plugin's narrow phase, MuJoCo Warp's own on the pairs left to it, and the
contacts' surface velocities.

This module owns ``start_collision`` (one kernel for the counters that the broad phase, the
narrow phase, the deep-pair check, the heightfield stage and the warm-start cache own) and its host entry, ``start``,
``stock_narrowphase`` and ``surface_velocities`` (MuJoCo Warp's kernels, launched as its collision
driver does).
"""

from typing import Optional

import warp as wp
from mujoco_warp._src import collision_driver
from mujoco_warp._src.collision_convex import convex_narrowphase
from mujoco_warp._src.collision_primitive import primitive_narrowphase
from mujoco_warp._src.types import CollisionType
from mujoco_warp._src.types import DisableBit
from mujoco_warp._src.types import GeomType

from mjx_supportfield.stages import warmstart
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
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
  deep_count: wp.array(dtype=int),
  deep_world_count: wp.array(dtype=int),
  hfield_count: wp.array(dtype=int),
  warm_stamp: wp.array(dtype=int),
  warm_misses: wp.array(dtype=int),
):
  """Resets the collision stage's counters, one thread a world (one launch instead of ten
  memsets: on a few-geom scene those cost more than the collisions). The incremental pass of
  a sleeping step keeps the contacts, drop counts and flags of the first pass."""
  worldid = wp.tid()
  world_npair[worldid] = 0
  deep_world_count[worldid] = 0
  if warm_start:
    warmstart.advance_stamp(warm_stamp, warm_misses, worldid)
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
  deep_count[0] = 0
  deep_count[1] = 0
  for q in range(queue_count.shape[0]):
    queue_count[q] = 0
  for k in range(hfield_count.shape[0]):
    hfield_count[k] = 0
  if not incremental:
    nacon[0] = 0


def start(d, st, incremental: bool, warm_start: bool) -> None:
  """Resets the counters of every stage of ``st`` (the Collider's per-Data state) for a step."""
  broad, narrow = st.broad, st.narrow
  wp.launch(
    start_collision,
    dim=d.nworld,
    inputs=[incremental, warm_start],
    outputs=[d.ncollision, d.nacon, broad.ndropped, broad.nonfinite, broad.world_npair, broad.npair, broad.nwarned,
             narrow.queue_count, narrow.patch_count, narrow.face_count, narrow.tilt_pair_count, narrow.tilt_count,
             st.deep.count, st.deep.world_count, st.hfield.count, st.warm.stamp, st.warm.misses],
  )


def stock_narrowphase(m, d, ctx, types: Optional[frozenset]) -> None:
  """MuJoCo Warp's own narrow phase on the pairs the broad phase left to it (``ctx``): all its
  kernels (``types`` None: the model has SDF geoms, collision-sensor pairs or meshes too large for
  a field, whose pairs can be of any type), or only those of the ordered geom-type pairs
  ``types`` (the classes Options.stock_pair_classes routes there), each in the kernel MuJoCo
  Warp's collision table gives it, so no launch runs for a type pair it cannot be handed."""
  if types is None:
    collision_driver._narrowphase(m, d, ctx)
    return
  table = dict(collision_driver.MJ_COLLISION_TABLE)
  if m.opt.disableflags & DisableBit.NATIVECCD:  # MuJoCo Warp's own rule (collision_driver._narrowphase)
    table[(GeomType.BOX, GeomType.BOX)] = CollisionType.PRIMITIVE
  convex = [t for t, kind in table.items() if t in types and kind == CollisionType.CONVEX]
  primitive = [t for t, kind in table.items() if t in types and kind == CollisionType.PRIMITIVE]
  if convex:
    convex_narrowphase(m, d, ctx, convex)
  if primitive:
    primitive_narrowphase(m, d, ctx, primitive)


def surface_velocities(m, d) -> None:
  """The contacts' surface velocities (models with ``geom_surfacevel``), as MuJoCo Warp writes them."""
  wp.launch(
    collision_driver._contact_surfacevel,
    dim=d.naconmax,
    inputs=[m.geom_surfacevel, d.geom_xpos, d.geom_xmat, d.contact.pos, d.contact.frame, d.contact.geom,
            d.contact.worldid, d.naconmax, d.nacon],
    outputs=[d.contact.surfacevel],
  )
