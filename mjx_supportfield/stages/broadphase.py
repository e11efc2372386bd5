"""Broad phase: the pairs of boxes that overlap, after MuJoCo's pair filters, dealt out to
the narrow-phase kernels' queues.

Two ways, chosen at install (``Options.broadphase``):

- nxn, for models with few pairs after the static filters (``m.nxn_geom_pair_filtered``):
  one thread per (world, pair) tests it and lists it; one launch.
- Sweep-and-prune, which scales with the geoms, not their pairs: each world keeps the order of
  its geoms along one axis from the previous step; insertion sort (one thread per world)
  restores it in near-linear time when little moved. The sweep runs one thread per (world,
  sorted box): it walks the boxes that start inside its own, tests the other two axes, then
  applies MuJoCo's pair filters (``m.nxn_pairid``: contype / conaffinity, parent-child, weld,
  exclude). Explicit ``<pair>``s and pairs watched by collision sensors are not swept: a small
  kernel tests them with their own margins, as MuJoCo does. Pairs land in per-world slots
  and are then compacted into one list, worlds back to back.

Both apply the sleep rules and MuJoCo Warp's own bounding filters (plane, sphere, AABB, OBB
per ``m.opt.broadphase_filter``). On a GPU, nxn's threads take a model's few pairs pair by pair
across the worlds (``pair_major_by_default``), so that the narrow phase's queues hold them in
that order.

This module owns the broad phase's kernels, its per-Data buffers (``Buffers``) and its stage
class, ``BroadPhase``, whose ``launch`` runs the geoms' boxes (aabb.py's kernel), then nxn or
the sweep, then the compacted pair list and the narrow-phase queues.
"""

import dataclasses
import functools

import numpy as np
import warp as wp
from mujoco_warp._src.collision_core import CollisionContext
from mujoco_warp._src.collision_driver import _broadphase_filter
from mujoco_warp._src.math import upper_tri_index
from mujoco_warp._src.types import EnableBit
from mujoco_warp._src.types import OverflowType
from mujoco_warp._src.types import SleepState

from mjx_supportfield.launch import first_use
from mjx_supportfield.options import NXN_MAX_PAIRS
from mjx_supportfield.stages.aabb import update_aabbs
from mjx_supportfield.stages.routing import NGEOMTYPE
from mjx_supportfield.stages.routing import PairQueues
from mjx_supportfield.stages.routing import queue_pair
from mjx_supportfield.types import MODULE_OPTIONS
from mjx_supportfield.types import UNIQUE_MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# the pair list's order (_world_and_item): None for pair_major_by_default's choice, True or False
# everywhere (benchmarks/pair_order.py times the two on a GPU; tests run pair by pair on the CPU)
PAIR_MAJOR = None
# nxn lists of at most this many pairs go pair by pair on a GPU (pair_major_by_default)
PAIR_MAJOR_MAX_PAIRS = 2048


@wp.struct
class PairOutputs:
  """Where the broad phase writes: the plugin's pair list (through per-world slots with
  sweep-and-prune, directly with nxn) and the list handed to stock MuJoCo Warp."""

  world_npair: wp.array(dtype=int)  # pairs found per world (kept or not)
  slot_pair: wp.array(dtype=wp.vec2i)  # world * max_pairs + k
  slot_pairid: wp.array(dtype=wp.vec2i)
  ndropped: wp.array(dtype=int)  # per world: pairs beyond max_pairs
  nwarned: wp.array(dtype=int)  # overflow warnings printed this step (one is enough)
  overflow: wp.array(dtype=int)  # d.overflow
  ncollision: wp.array(dtype=int)  # d.ncollision: pairs handed to stock MuJoCo Warp
  stock_pair: wp.array(dtype=wp.vec2i)
  stock_pairid: wp.array(dtype=wp.vec2i)
  stock_worldid: wp.array(dtype=int)
  npair: wp.array(dtype=int)  # the pair list the narrow phase walks
  pair: wp.array(dtype=wp.vec2i)
  pairid: wp.array(dtype=wp.vec2i)
  pair_worldid: wp.array(dtype=int)


@wp.func
def _asleep_pair(s1: int, s2: int) -> bool:
  """MuJoCo Warp's rule: a pair is skipped when both are asleep, or one asleep and one static."""
  return (
    (s1 == SleepState.ASLEEP and s2 == SleepState.ASLEEP)
    or (s1 == SleepState.ASLEEP and s2 == SleepState.STATIC)
    or (s2 == SleepState.ASLEEP and s1 == SleepState.STATIC)
  )


@wp.func
def _overlap(lo1: wp.vec3, hi1: wp.vec3, lo2: wp.vec3, hi2: wp.vec3) -> bool:
  return (
    lo1[0] <= hi2[0] and lo2[0] <= hi1[0] and lo1[1] <= hi2[1] and lo2[1] <= hi1[1] and lo1[2] <= hi2[2] and lo2[2] <= hi1[2]
  )


@wp.func
def _empty(aabb_lo: wp.array2d(dtype=wp.vec3), aabb_hi: wp.array2d(dtype=wp.vec3), worldid: int, g: int) -> bool:
  """An empty box marks an absent mesh or a non-finite pose (aabb.update_aabbs)."""
  return aabb_lo[worldid, g][0] > aabb_hi[worldid, g][0]


@wp.func
def _ordered(g1: int, g2: int, type1: int, type2: int) -> wp.vec2i:
  """The pair with the lower geom type first, as the narrow-phase routines expect."""
  if type1 > type2:
    return wp.vec2i(g2, g1)
  return wp.vec2i(g1, g2)


@wp.func
def _to_stock(geom_type: wp.array(dtype=int), geom_stock: wp.array(dtype=int), type_stock: wp.array(dtype=int),
              g1: int, g2: int) -> bool:
  """Whether MuJoCo Warp's own narrow phase collides the pair: a geom it owns (``geom_stock``
  1: SDF geoms, meshes too large for a support field), else the pair's class where the options
  route it there (``type_stock``, routing.stock_type_table), unless a geom is the plugin's
  whatever its class (-1: non-convex meshes, of which MuJoCo Warp has only the hull)."""
  stock1 = geom_stock[g1]
  stock2 = geom_stock[g2]
  if stock1 > 0 or stock2 > 0:
    return True
  if stock1 < 0 or stock2 < 0:
    return False
  return type_stock[geom_type[g1] * wp.static(NGEOMTYPE) + geom_type[g2]] != 0


@wp.func
def _emit_stock(pair: wp.vec2i, pairid: wp.vec2i, worldid: int, naconmax: int, out: PairOutputs):
  """Appends a pair to the list handed to stock MuJoCo Warp, which flags ncollision > naconmax
  itself (d.overflow, BROADPHASE)."""
  cid = wp.atomic_add(out.ncollision, 0, 1)
  if cid < naconmax:
    out.stock_pair[cid] = pair
    out.stock_pairid[cid] = pairid
    out.stock_worldid[cid] = worldid


@wp.func
def _world_and_item(t0: int, t1: int, pair_major: bool):
  """The (world, item) of a thread of a (world, item) launch, or of an (item, world) launch
  where ``pair_major``: there consecutive threads take one item (a geom pair of the list, or a
  world's k-th slot) in consecutive worlds, so the pairs reach the narrow phase's queues in
  that order and each warp of its kernels runs one pair of geoms in 32 worlds, on one branch
  of its code, where a warp of one world's pairs runs the branch of each type of pair in turn."""
  if pair_major:
    return t1, t0
  return t0, t1


@wp.func
def _claim(worldid: int, max_pairs: int, warn: bool, out: PairOutputs) -> int:
  """The pair's place within its world's budget, or -1 past max_pairs (counted and flagged)."""
  k = wp.atomic_add(out.world_npair, worldid, 1)
  if k < max_pairs:
    return k
  wp.atomic_add(out.ndropped, worldid, 1)
  wp.atomic_or(out.overflow, worldid, int(OverflowType.BROADPHASE))
  if warn:
    if wp.atomic_add(out.nwarned, 0, 1) == 0:
      wp.printf(
        "mjx_supportfield: broadphase overflow - more than %d pairs in world %d; raise Options.max_collision_pairs\n"
        "To disable the print warning: m.opt.warn_overflow &= ~mjw.OverflowType.BROADPHASE (or = 0 for all)\n",
        max_pairs,
        worldid,
      )
  return -1


@wp.func
def _emit(
  g1: int,
  g2: int,
  type1: int,
  type2: int,
  pairid: wp.vec2i,
  worldid: int,
  to_stock: bool,
  max_pairs: int,
  naconmax: int,
  warn: bool,
  # Out:
  out: PairOutputs,
):
  """Sweep-and-prune: appends a pair to its world's slots (compact_pairs lists them) or to the
  list handed to stock MuJoCo Warp."""
  pair = _ordered(g1, g2, type1, type2)
  if to_stock:
    _emit_stock(pair, pairid, worldid, naconmax, out)
    return
  k = _claim(worldid, max_pairs, warn, out)
  if k < 0:
    return
  # per-world slots: compact_pairs later lays the worlds out back to back, in world order,
  # so narrow-phase warps see pairs of one world (similar shapes) together
  slot = worldid * max_pairs + k
  out.slot_pair[slot] = pair
  out.slot_pairid[slot] = pairid


@functools.lru_cache(maxsize=None)
def _pair_test(
  broadphase_filter: int,
  ngeom_aabb: int,
  ngeom_rbound: int,
  ngeom_margin: int,
  ngeom_gap: int,
  npair_margin: int,
  npair_gap: int,
  enable_sleep: bool,
  incremental: bool,
):
  """Sleep rules and bounding filters shared by the sweep and the explicit-pair kernel."""
  bound_filter = _broadphase_filter(broadphase_filter, ngeom_aabb, ngeom_rbound, ngeom_margin, ngeom_gap, npair_margin, npair_gap)

  @wp.func
  def pair_test(
    geom_bodyid: wp.array(dtype=int),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    body_awake_in: wp.array2d(dtype=int),
    awake_prev_in: wp.array2d(dtype=int),
    g1: int,
    g2: int,
    pairid: wp.vec2i,
    worldid: int,
  ) -> bool:
    if wp.static(enable_sleep):
      b1 = geom_bodyid[g1]
      b2 = geom_bodyid[g2]
      if _asleep_pair(body_awake_in[worldid, b1], body_awake_in[worldid, b2]):
        return False
      if wp.static(incremental):
        # second (incremental) pass: only pairs the first pass skipped because they slept
        if not _asleep_pair(awake_prev_in[worldid, b1], awake_prev_in[worldid, b2]):
          return False
    if pairid[1] >= 0:
      return True  # collision sensors see every pair they watch
    return wp.static(bound_filter)(
      geom_aabb, geom_rbound, geom_margin, geom_gap, pair_margin, pair_gap, geom_xpos_in, geom_xmat_in, g1, g2, pairid[0], worldid
    )

  return pair_test


@wp.kernel
def sort_endpoints(
  ngeom: int,
  axis: int,
  aabb_lo: wp.array2d(dtype=wp.vec3),
  sap_init: wp.array(dtype=int),
  order: wp.array2d(dtype=int),
):
  """Per world: insertion sort of the geoms by lower bound, from last step's order."""
  worldid = wp.tid()
  if sap_init[worldid] == 0:
    for k in range(ngeom):
      order[worldid, k] = k
    sap_init[worldid] = 1
  for k in range(1, ngeom):
    g = order[worldid, k]
    key = aabb_lo[worldid, g][axis]
    j = k
    while j > 0 and aabb_lo[worldid, order[worldid, j - 1]][axis] > key:
      order[worldid, j] = order[worldid, j - 1]
      j -= 1
    order[worldid, j] = g


@functools.lru_cache(maxsize=None)
def sweep_kernel(static_key: tuple, axis: int):
  """Sweep from each sorted box over the boxes that start inside it; one thread per (world, box).

  static_key = the _pair_test parameters.
  """
  pair_test = _pair_test(*static_key)

  @wp.kernel(module="unique", module_options=UNIQUE_MODULE_OPTIONS, enable_backward=False)
  def sweep(
    # Model:
    ngeom: int,
    geom_type: wp.array(dtype=int),
    geom_bodyid: wp.array(dtype=int),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    nxn_pairid: wp.array(dtype=wp.vec2i),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    body_awake_in: wp.array2d(dtype=int),
    naconmax_in: int,
    # In:
    awake_prev_in: wp.array2d(dtype=int),
    geom_stock: wp.array(dtype=int),
    type_stock: wp.array(dtype=int),
    aabb_lo: wp.array2d(dtype=wp.vec3),
    aabb_hi: wp.array2d(dtype=wp.vec3),
    max_pairs: int,
    warn: bool,
    order: wp.array2d(dtype=int),
    # Out:
    out: PairOutputs,
  ):
    worldid, a = wp.tid()
    ga = order[worldid, a]
    lo_a = aabb_lo[worldid, ga]
    hi_a = aabb_hi[worldid, ga]
    if lo_a[axis] > hi_a[axis]:
      return  # empty box: absent mesh or non-finite pose
    for b in range(a + 1, ngeom):
      gb = order[worldid, b]
      lo_b = aabb_lo[worldid, gb]
      if lo_b[axis] > hi_a[axis]:
        break  # every later box starts beyond this one
      hi_b = aabb_hi[worldid, gb]
      if lo_b[axis] > hi_b[axis] or not _overlap(lo_a, hi_a, lo_b, hi_b):
        continue
      g1 = wp.min(ga, gb)
      g2 = wp.max(ga, gb)
      pairid = nxn_pairid[upper_tri_index(ngeom, g1, g2)]
      if pairid[0] == -2 or pairid[0] >= 0 or pairid[1] >= 0:
        continue  # filtered out, or an explicit/sensor pair (tested by listed_pairs)
      if not pair_test(
        geom_bodyid,
        geom_aabb,
        geom_rbound,
        geom_margin,
        geom_gap,
        pair_margin,
        pair_gap,
        geom_xpos_in,
        geom_xmat_in,
        body_awake_in,
        awake_prev_in,
        g1,
        g2,
        pairid,
        worldid,
      ):
        continue
      _emit(
        g1,
        g2,
        geom_type[g1],
        geom_type[g2],
        pairid,
        worldid,
        _to_stock(geom_type, geom_stock, type_stock, g1, g2),
        max_pairs,
        naconmax_in,
        warn,
        out,
      )

  return sweep


@wp.kernel
def clamp_counts(max_pairs: int, world_npair: wp.array(dtype=int), world_count_out: wp.array(dtype=int)):
  """Pairs kept per world (the counter also counts the dropped ones)."""
  worldid = wp.tid()
  world_count_out[worldid] = wp.min(world_npair[worldid], max_pairs)


@functools.lru_cache(maxsize=None)
def listed_pairs_kernel(static_key: tuple, direct: bool):
  """Pairs given as a list, one thread per (world, pair): boxes (not for explicit ``<pair>``s and
  sensor pairs, which bring their own margins to the bounding filter), sleep rules and bounding
  filters as in the sweep.

  ``direct`` (nxn): the list is every pair MuJoCo's static filters keep
  (``m.nxn_geom_pair_filtered``), and a kept pair goes straight to the pair list and its
  narrow-phase queue; for a model with few pairs this one launch replaces the sort, the sweep,
  the count, the scan and the compaction. Otherwise the list holds the explicit and sensor pairs
  the sweep leaves out, and they go to the per-world slots, as the sweep's do.

  static_key = the _pair_test parameters.
  """
  pair_test = _pair_test(*static_key)

  @wp.kernel(module="unique", module_options=UNIQUE_MODULE_OPTIONS, enable_backward=False)
  def listed_pairs(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_bodyid: wp.array(dtype=int),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    body_awake_in: wp.array2d(dtype=int),
    naconmax_in: int,
    # In:
    awake_prev_in: wp.array2d(dtype=int),
    geom_stock: wp.array(dtype=int),
    type_stock: wp.array(dtype=int),
    aabb_lo: wp.array2d(dtype=wp.vec3),
    aabb_hi: wp.array2d(dtype=wp.vec3),
    listed_pair: wp.array(dtype=wp.vec2i),
    listed_pairid: wp.array(dtype=wp.vec2i),
    max_pairs: int,
    warn: bool,
    pair_major: bool,
    # Out:
    out: PairOutputs,
    queues: PairQueues,
  ):
    t0, t1 = wp.tid()
    worldid, k = _world_and_item(t0, t1, pair_major)
    geoms = listed_pair[k]
    g1 = geoms[0]
    g2 = geoms[1]
    if _empty(aabb_lo, aabb_hi, worldid, g1) or _empty(aabb_lo, aabb_hi, worldid, g2):
      return
    pairid = listed_pairid[k]
    swept = pairid[0] < 0 and pairid[1] < 0
    if swept and not _overlap(aabb_lo[worldid, g1], aabb_hi[worldid, g1], aabb_lo[worldid, g2], aabb_hi[worldid, g2]):
      return
    if not pair_test(
      geom_bodyid,
      geom_aabb,
      geom_rbound,
      geom_margin,
      geom_gap,
      pair_margin,
      pair_gap,
      geom_xpos_in,
      geom_xmat_in,
      body_awake_in,
      awake_prev_in,
      g1,
      g2,
      pairid,
      worldid,
    ):
      return
    to_stock = pairid[1] >= 0 or _to_stock(geom_type, geom_stock, type_stock, g1, g2)
    if not wp.static(direct):
      _emit(g1, g2, geom_type[g1], geom_type[g2], pairid, worldid, to_stock, max_pairs, naconmax_in, warn, out)
      return
    pair = _ordered(g1, g2, geom_type[g1], geom_type[g2])
    if to_stock:
      _emit_stock(pair, pairid, worldid, naconmax_in, out)
      return
    if _claim(worldid, max_pairs, warn, out) < 0:
      return
    cid = wp.atomic_add(out.npair, 0, 1)
    out.pair[cid] = pair
    out.pairid[cid] = pairid
    out.pair_worldid[cid] = worldid
    queue_pair(geom_type, pair, cid, queues)

  return listed_pairs


@wp.kernel
def compact_pairs(
  # Model:
  geom_type: wp.array(dtype=int),
  # In:
  max_pairs: int,
  world_count: wp.array(dtype=int),
  world_start: wp.array(dtype=int),
  pair_major: bool,
  # Out:
  out: PairOutputs,
  queues: PairQueues,
):
  """Copies each world's slots to its range of the pair list (world_start: exclusive scan) and
  queues each pair for its narrow-phase kernel (in the order of _world_and_item)."""
  t0, t1 = wp.tid()
  worldid, k = _world_and_item(t0, t1, pair_major)
  n = world_count[worldid]
  if k == 0 and worldid == world_count.shape[0] - 1:
    out.npair[0] = world_start[worldid] + n
  if k >= n:
    return
  src = worldid * max_pairs + k
  cid = world_start[worldid] + k
  pair = out.slot_pair[src]
  pairid = out.slot_pairid[src]
  out.pair[cid] = pair
  out.pairid[cid] = pairid
  out.pair_worldid[cid] = worldid
  queue_pair(geom_type, pair, cid, queues)


@dataclasses.dataclass
class Buffers:
  """The broad phase's per-Data buffers: sizes depend on nworld, which install cannot know."""

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
  pair: wp.array  # the pair list: worlds back to back, or with nxn on a GPU, pair by pair (_world_and_item)
  pairid: wp.array
  pair_worldid: wp.array
  stock_ctx: CollisionContext  # the pairs left to MuJoCo Warp's own narrow phase
  capacity: int
  outputs: PairOutputs  # the arrays above (and d's overflow, ncollision) for the kernels


def _grid_of(kernel, m, d) -> dict:
  """A one-thread-a-pair kernel's launch on a GPU as stock MuJoCo Warp launches its nxn: its
  block size, and blocks capped at a few times what fills the GPU, each thread looping over
  several (world, pair) items (a robot's thousand pairs in 8192 worlds would otherwise start
  millions of threads that mostly test one box each and exit)."""
  if not d.geom_xpos.device.is_cuda or first_use.planning():
    return {}  # a plan's launches are skipped: the occupancy query would load the module
  block_dim = m.block_dim.nxn_broadphase
  return {"block_dim": block_dim, "max_blocks": max(1, 8 * _filling_threads(kernel, d.geom_xpos.device) // block_dim)}


_FILLING_THREADS = {}  # (kernel, device alias): threads; Warp's Device is not hashable


def _filling_threads(kernel, device) -> int:
  """Threads that fill the GPU with ``kernel`` (CUDA's occupancy suggestion), asked once per
  kernel and device: the query is a driver call, and the launch is made every step."""
  key = (kernel, device.alias)
  if key not in _FILLING_THREADS:
    block, grid = wp.get_suggested_block_size(kernel, device)
    _FILLING_THREADS[key] = block * grid
  return _FILLING_THREADS[key]


def nxn_pair_limit(mjm, pairs: np.ndarray) -> int:
  """How many pairs left by MuJoCo's static filters (``pairs``, (npair, 2) geom ids) ``auto``
  takes nxn up to: NXN_MAX_PAIRS, times the ratio of the geoms in those pairs to those of them
  that move. The sweep sorts and walks every geom each step, the static ones too, which pair with
  nothing static (a terrain's tiles and stair boxes: mjlab's rough tasks have 554 of them beside
  one robot's 30 geoms); nxn's work is the pairs alone, and the static filters have left the
  static-static ones out already."""
  geoms = np.unique(pairs)
  if len(geoms) == 0:
    return NXN_MAX_PAIRS
  static = np.asarray(mjm.body_weldid)[np.asarray(mjm.geom_bodyid)[geoms]] == 0  # welded to the world
  return int(NXN_MAX_PAIRS * len(geoms) / max(1, int((~static).sum())))


def pair_major_by_default(cuda: bool, nxn: bool, npair: int) -> bool:
  """Whether the broad phase lists its pairs pair by pair across the worlds (_world_and_item):
  on a GPU, for an nxn list of at most PAIR_MAJOR_MAX_PAIRS pairs. There a warp of the narrow
  phase's kernels runs one pair of geoms in 32 worlds; the price is nxn's reads of the boxes,
  each lane's from another world's row of ``aabb_lo`` (uncoalesced), paid by every listed pair in
  every world, which a robot's thousands of listed pairs, few of them touching, do not win back.
  The sweep's per-world slots hold other pairs in each world at the same place, so it stays world
  by world; so does the CPU, whose threads run in that order (the contacts keep it)."""
  return cuda and nxn and npair <= PAIR_MAJOR_MAX_PAIRS


class BroadPhase:
  """The broad phase: the model's pair facts install found, per-Data buffers, and the step's
  launches (the stage contract: docs/architecture.md)."""

  def __init__(self, ngeom: int, nxn: bool, max_pairs: int, npair_filtered: int, explicit_pair: wp.array,
               explicit_pairid: wp.array, geom_stock: wp.array, type_stock: wp.array, sap_axis: int):
    self.ngeom = ngeom
    self.nxn = nxn  # nxn's one launch, else sweep-and-prune
    self.max_pairs = max_pairs  # pairs a world can have after MuJoCo's static filters (and the option's cap)
    self.npair_filtered = npair_filtered
    self.explicit_pair, self.explicit_pairid = explicit_pair, explicit_pairid  # <pair>s and sensor pairs
    self.nexplicit = explicit_pair.shape[0]
    self.geom_stock = geom_stock  # per geom: 1 when MuJoCo Warp's own narrow phase collides its pairs (-1: never)
    self.type_stock = type_stock  # per geom-type pair: 1 when its class is routed there (Options.stock_pair_classes)
    self.sap_axis = sap_axis
    self.pair_major = PAIR_MAJOR  # the pair list's order (pair_major_by_default where None)

  def make_buffers(self, d, st) -> Buffers:
    """The broad phase's buffers for Data ``d``."""
    nworld = d.nworld
    capacity = nworld * self.max_pairs
    # the sweep's per-world slots; nxn lists pairs directly, so it needs none (two large arrays saved)
    nslot = 1 if self.nxn else capacity
    b = Buffers(
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
      outputs=PairOutputs(),
    )
    out = b.outputs
    out.world_npair, out.slot_pair, out.slot_pairid = b.world_npair, b.slot_pair, b.slot_pairid
    out.ndropped, out.nwarned, out.overflow, out.ncollision = b.ndropped, b.nwarned, d.overflow, d.ncollision
    out.stock_pair = b.stock_ctx.collision_pair
    out.stock_pairid = b.stock_ctx.collision_pairid
    out.stock_worldid = b.stock_ctx.collision_worldid
    out.npair, out.pair, out.pairid, out.pair_worldid = b.npair, b.pair, b.pairid, b.pair_worldid
    return b

  def launch(self, m, d, st) -> None:
    """The broad phase of one step: boxes, then nxn or the sweep (and the listed pairs), then the
    compacted pair list, its pairs dealt out to the narrow phase's queues."""
    b, queues, awake_prev = st.broad, st.narrow.queues, st.awake_prev
    wp.launch(
      update_aabbs,
      dim=(d.nworld, self.ngeom),
      inputs=[m.geom_type, m.geom_dataid, m.geom_aabb, m.geom_margin, m.geom_gap, d.geom_xpos, d.geom_xmat],
      outputs=[b.aabb_lo, b.aabb_hi, b.nonfinite],
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
    common_data = [d.geom_xpos, d.geom_xmat, d.body_awake, d.naconmax, awake_prev_in, self.geom_stock, self.type_stock,
                   b.aabb_lo, b.aabb_hi]

    pair_major = self.pair_major
    if pair_major is None:
      pair_major = pair_major_by_default(d.geom_xpos.device.is_cuda, self.nxn, self.npair_filtered)

    def grid(nitem: int) -> tuple:
      return (nitem, d.nworld) if pair_major else (d.nworld, nitem)

    def listed(direct: bool, pairs: wp.array, pairids: wp.array, npair: int):
      kernel = listed_pairs_kernel(key, direct)
      wp.launch(
        kernel,
        dim=grid(npair),
        inputs=common_model + common_data + [pairs, pairids, self.max_pairs, warn, pair_major],
        outputs=[b.outputs, queues],
        **_grid_of(kernel, m, d),
      )

    if self.nxn:
      listed(True, m.nxn_geom_pair_filtered, m.nxn_pairid_filtered, self.npair_filtered)
      return
    if self.ngeom > 1:
      wp.launch(sort_endpoints, dim=d.nworld, inputs=[self.ngeom, self.sap_axis, b.aabb_lo],
                outputs=[b.sap_init, b.order])
      wp.launch(
        sweep_kernel(key, self.sap_axis),
        dim=(d.nworld, self.ngeom),
        inputs=[self.ngeom] + common_model + [m.nxn_pairid] + common_data + [self.max_pairs, warn, b.order],
        outputs=[b.outputs],
      )
    if self.nexplicit:
      listed(False, self.explicit_pair, self.explicit_pairid, self.nexplicit)
    wp.launch(clamp_counts, dim=d.nworld, inputs=[self.max_pairs, b.world_npair], outputs=[b.world_count])
    wp.utils.array_scan(b.world_count, b.world_start, inclusive=False)
    wp.launch(
      compact_pairs,
      dim=grid(self.max_pairs),
      inputs=[m.geom_type, self.max_pairs, b.world_count, b.world_start, pair_major],
      outputs=[b.outputs, queues],
    )
