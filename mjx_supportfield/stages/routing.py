"""Queue routing: which narrow-phase kernel runs each pair the broad phase lists.

The broad phase deals its pairs into one queue per narrow-phase kernel (``queue_pair``, on the
device); the Collider builds, at install, the table that maps a pair's geom types to its queue
(``pair_types_present``, ``pair_queue_table``). A pair class the options route to MuJoCo Warp's
own narrow phase (``PairClass``, ``stock_types``) never reaches a queue: the broad phase lists
its pairs for MuJoCo Warp instead (``stock_type_table``). This module owns the queues' layout
(``PairQueues``, ``QUEUE_*``) and those functions; it launches nothing.
"""

import enum

import numpy as np
import warp as wp
from mujoco_warp._src.collision_primitive import _PRIMITIVE_COLLISIONS
from mujoco_warp._src.types import BroadphaseType
from mujoco_warp._src.types import GeomType

from mjx_supportfield.types import CONVEX_TYPES


# pairs MuJoCo Warp solves in closed form (plane-*, sphere/capsule pairs, box-box, plane-mesh)
ANALYTIC_PAIRS = tuple(_PRIMITIVE_COLLISIONS.keys())

NGEOMTYPE = len(GeomType)

# the narrow-phase kernels' pair queues (queue_pair)
QUEUE_ANALYTIC = wp.constant(0)
QUEUE_MPR = wp.constant(1)
QUEUE_GJK = wp.constant(2)
QUEUE_CANDIDATE = wp.constant(3)  # MPR pairs not yet tested for being apart (sift_mpr_pairs)
NQUEUE = 4


@wp.struct
class PairQueues:
  """Where the broad phase deals out the pairs it lists: one queue per narrow-phase kernel.

  ``pair_queue_type`` maps a pair's geom types (type1 * NGEOMTYPE + type2) to QUEUE_ANALYTIC,
  QUEUE_GJK or QUEUE_CANDIDATE (``pair_queue_table``, at install), else -1 (the heightfield and
  non-convex kernels, and stock MuJoCo Warp, walk the whole list)."""

  pair_queue_type: wp.array(dtype=int)
  geom_nonconvex: wp.array(dtype=int)
  count: wp.array(dtype=int)  # (NQUEUE,) pairs in each queue
  pair: wp.array2d(dtype=int)  # (NQUEUE, capacity): indices into the pair list


@wp.func
def queue_pair(geom_type: wp.array(dtype=int), geoms: wp.vec2i, cid: int, queues: PairQueues):
  """Queues pair ``cid`` of the list for its narrow-phase kernel, so the warps of each kernel
  run only pairs of their own kind (in one pair list, a pile's mesh-plane pairs sat idle in the
  MPR kernel's warps, between the mesh-mesh pairs).

  The queue of each type pair is decided at install (``pair_queue_table``); a convex pair with a
  non-convex mesh goes to nonconvex.py instead. Cheap on purpose: the broad-phase kernels that
  call it run a thread per (world, pair), and support queries here would make every one of
  those threads heavy.
  """
  type1 = geom_type[geoms[0]]
  type2 = geom_type[geoms[1]]
  queue = queues.pair_queue_type[type1 * wp.static(NGEOMTYPE) + type2]
  if queue == QUEUE_GJK or queue == QUEUE_CANDIDATE:
    if queues.geom_nonconvex[geoms[0]] or queues.geom_nonconvex[geoms[1]]:
      return
  if queue >= 0:
    slot = wp.atomic_add(queues.count, queue, 1)
    queues.pair[queue, slot] = cid


def pair_types_present(mjm, pairs) -> set:
  """Ordered (type1 <= type2) geom-type pairs that the model can produce."""
  types = set()
  gt = np.asarray(mjm.geom_type)
  for g1, g2 in pairs:
    t1, t2 = sorted((int(gt[g1]), int(gt[g2])))
    types.add((GeomType(t1), GeomType(t2)))
  return types


def pair_queue_table(present, gjk_all: bool) -> tuple:
  """The analytic and the MPR geom-type pairs among ``present`` (ordered pairs the model can
  produce), and the table that maps a pair's types to its queue (see PairQueues).

  An MPR pair with a sphere or capsule goes to GJK (a point or segment core grown by a radius:
  GJK gives the exact nearest points, where MPR's normal drifts for a small sphere sunk deep), as
  do all with ``gjk_all`` (narrowphase="gjk"); the others wait in QUEUE_CANDIDATE for
  sift_mpr_pairs, which passes those not proven apart on to QUEUE_MPR."""
  analytic_types = tuple(t for t in ANALYTIC_PAIRS if t in present)
  queue_table = np.full(NGEOMTYPE**2, -1, dtype=np.int32)
  for t1, t2 in analytic_types:
    queue_table[int(t1) * NGEOMTYPE + int(t2)] = QUEUE_ANALYTIC
  mpr_types = []
  core = (GeomType.SPHERE, GeomType.CAPSULE)
  for t1, t2 in present:
    if (t1, t2) not in ANALYTIC_PAIRS and t1 in CONVEX_TYPES and t2 in CONVEX_TYPES:
      gjk = gjk_all or t1 in core or t2 in core
      queue_table[int(t1) * NGEOMTYPE + int(t2)] = QUEUE_GJK if gjk else QUEUE_CANDIDATE
      mpr_types.append((t1, t2))
  return analytic_types, mpr_types, queue_table


class PairClass(enum.IntEnum):
  """Pair classes by the plugin's kernels that collide them: what ``Options.stock_pair_classes``
  routes to MuJoCo Warp's own narrow phase instead (docs/performance.md's cost model per class)."""

  ANALYTIC = 0  # MuJoCo Warp's closed forms (plane-*, sphere and capsule pairs, box-box, plane-mesh)
  PRIMITIVE = 1  # other pairs of convex primitives (cylinders, ellipsoids): MPR and multi-contact
  MESH = 2  # a convex mesh against a primitive
  MESH_MESH = 3  # two convex meshes
  HFIELD_ROUND = 4  # a sphere or capsule on a heightfield: the closed-form pass (hfield_closed_form.py)
  HFIELD_PRISM = 5  # another convex geom on a heightfield: its triangle prisms by MPR (heightfield.py)

  @classmethod
  def of(cls, type1: GeomType, type2: GeomType) -> "PairClass":
    """The class of an ordered (type1 <= type2) geom-type pair the plugin collides."""
    if (type1, type2) in ANALYTIC_PAIRS:
      return cls.ANALYTIC
    if type1 == GeomType.HFIELD:
      return cls.HFIELD_ROUND if type2 in (GeomType.SPHERE, GeomType.CAPSULE) else cls.HFIELD_PRISM
    if type1 == GeomType.MESH:  # both meshes: types are ordered
      return cls.MESH_MESH
    return cls.MESH if type2 == GeomType.MESH else cls.PRIMITIVE

  @classmethod
  def named(cls, name: str) -> "PairClass":
    """The class of an Options.stock_pair_classes name ("analytic", "primitive", ...)."""
    return cls[name.upper()]


def stock_types(present, classes) -> set:
  """The ordered geom-type pairs among ``present`` whose class is one of ``classes``: those
  MuJoCo Warp's own narrow phase collides. Non-convex meshes stay the plugin's whatever their
  class (MuJoCo Warp has only their hulls)."""
  return {(t1, t2) for t1, t2 in present if PairClass.of(t1, t2) in classes}


def stock_type_table(types) -> np.ndarray:
  """Per geom-type pair (type1 * NGEOMTYPE + type2, either order): 1 where the pair goes to
  MuJoCo Warp's own narrow phase (``types``, from ``stock_types``), else 0."""
  table = np.zeros(NGEOMTYPE**2, dtype=np.int32)
  for t1, t2 in types:
    table[int(t1) * NGEOMTYPE + int(t2)] = table[int(t2) * NGEOMTYPE + int(t1)] = 1
  return table


def gives_plugin_nothing(options, nxn: bool, plugin_pairs: bool, m) -> bool:
  """Whether MuJoCo Warp's own collision stage computes model ``m``'s contacts, bit for bit, with
  less work than the plugin's: analytic pairs only, which both run through MuJoCo Warp's routines,
  and pairs of classes routed to MuJoCo Warp (Options.stock_pair_classes), whose contacts are its
  own either way (``plugin_pairs``: a pair left to the plugin's MPR, heightfield or non-convex
  kernels), on an nxn broad phase in both (Options.stock_for_analytic_models)."""
  return (options.stock_for_analytic_models and options.broadphase == "auto" and nxn
          and not options.contacts_per_world and not plugin_pairs and m.opt.broadphase == BroadphaseType.NXN)
