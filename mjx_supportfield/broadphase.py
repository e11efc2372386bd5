"""Sweep-and-prune broad phase with a warm-started per-world endpoint order.

Each world keeps the order of its geoms along one axis from the previous step; insertion
sort (one thread per world) restores it in near-linear time when little moved. The sweep
runs one thread per (world, sorted box): it walks the boxes that start inside its own,
tests the other two axes, then applies MuJoCo's pair filters (``m.nxn_pairid``: contype /
conaffinity, parent-child, weld, exclude), sleeping bodies and MuJoCo Warp's own bounding
filters (plane, sphere, AABB, OBB per ``m.opt.broadphase_filter``).

Explicit ``<pair>``s and pairs watched by collision sensors are not swept: a small kernel
tests them with their own margins, as MuJoCo does.
"""

import functools

import warp as wp
from mujoco_warp._src.collision_driver import _broadphase_filter
from mujoco_warp._src.math import upper_tri_index
from mujoco_warp._src.types import OverflowType
from mujoco_warp._src.types import SleepState


@wp.struct
class PairOutputs:
  """Where the broad phase writes: per-world pair slots for the plugin, a list for stock."""

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
  """Appends a pair to the plugin's list or to the list handed to stock MuJoCo Warp."""
  pair = wp.vec2i(g1, g2)
  if type1 > type2:
    pair = wp.vec2i(g2, g1)

  if to_stock:
    # stock MuJoCo Warp flags ncollision > naconmax itself (d.overflow, BROADPHASE)
    cid = wp.atomic_add(out.ncollision, 0, 1)
    if cid < naconmax:
      out.stock_pair[cid] = pair
      out.stock_pairid[cid] = pairid
      out.stock_worldid[cid] = worldid
    return

  k = wp.atomic_add(out.world_npair, worldid, 1)
  if k >= max_pairs:
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


_MODEL_INPUTS = (
  "geom_type",
  "geom_bodyid",
  "geom_aabb",
  "geom_rbound",
  "geom_margin",
  "geom_gap",
  "pair_margin",
  "pair_gap",
  "nxn_pairid",
)


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

  @wp.kernel(module="unique", enable_backward=False)
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
        continue  # filtered out, or an explicit/sensor pair (tested by explicit_pairs)
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
        geom_stock[g1] != 0 or geom_stock[g2] != 0,
        max_pairs,
        naconmax_in,
        warn,
        out,
      )

  return sweep


@functools.lru_cache(maxsize=None)
def explicit_kernel(static_key: tuple):
  """Explicit <pair>s and collision-sensor pairs, one thread per (world, pair)."""
  pair_test = _pair_test(*static_key)

  @wp.kernel(module="unique", enable_backward=False)
  def explicit_pairs(
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
    aabb_lo: wp.array2d(dtype=wp.vec3),
    aabb_hi: wp.array2d(dtype=wp.vec3),
    explicit_pair: wp.array(dtype=wp.vec2i),
    explicit_pairid: wp.array(dtype=wp.vec2i),
    max_pairs: int,
    warn: bool,
    # Out:
    out: PairOutputs,
  ):
    worldid, k = wp.tid()
    geoms = explicit_pair[k]
    g1 = geoms[0]
    g2 = geoms[1]
    # an empty box marks an absent mesh or a non-finite pose
    if aabb_lo[worldid, g1][0] > aabb_hi[worldid, g1][0] or aabb_lo[worldid, g2][0] > aabb_hi[worldid, g2][0]:
      return
    pairid = explicit_pairid[k]
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
    _emit(
      g1,
      g2,
      geom_type[g1],
      geom_type[g2],
      pairid,
      worldid,
      geom_stock[g1] != 0 or geom_stock[g2] != 0 or pairid[1] >= 0,
      max_pairs,
      naconmax_in,
      warn,
      out,
    )

  return explicit_pairs


@wp.kernel
def clamp_counts(max_pairs: int, world_npair: wp.array(dtype=int), world_count_out: wp.array(dtype=int)):
  """Pairs kept per world (the counter also counts the dropped ones)."""
  worldid = wp.tid()
  world_count_out[worldid] = wp.min(world_npair[worldid], max_pairs)


@wp.kernel
def compact_pairs(
  max_pairs: int,
  world_count: wp.array(dtype=int),
  world_start: wp.array(dtype=int),
  slot_pair: wp.array(dtype=wp.vec2i),
  slot_pairid: wp.array(dtype=wp.vec2i),
  # Out:
  npair_out: wp.array(dtype=int),
  pair_out: wp.array(dtype=wp.vec2i),
  pairid_out: wp.array(dtype=wp.vec2i),
  pair_worldid_out: wp.array(dtype=int),
):
  """Copies each world's slots to its range of the pair list (world_start: exclusive scan)."""
  worldid, k = wp.tid()
  n = world_count[worldid]
  if k == 0 and worldid == world_count.shape[0] - 1:
    npair_out[0] = world_start[worldid] + n
  if k >= n:
    return
  src = worldid * max_pairs + k
  dst = world_start[worldid] + k
  pair_out[dst] = slot_pair[src]
  pairid_out[dst] = slot_pairid[src]
  pair_worldid_out[dst] = worldid
