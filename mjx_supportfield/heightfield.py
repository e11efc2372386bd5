"""Heightfield terrain against convex geoms.

MuJoCo's heightfield: ``nrow x ncol`` elevations (scaled to [0, 1]) times ``size[2]`` over the
rectangle ``[-size[0], size[0]] x [-size[1], size[1]]`` of the geom's frame (columns along x,
rows along y), solid down to ``-size[3]``. Each grid cell is split into two triangles along
the diagonal from (row, col) to (row + 1, col + 1), as MuJoCo does.

The cells under the geom's extent (support queries in the terrain frame) are visited, and
give contact candidates in three passes:
- the plane pass (geom points in terrain faces), first: B's deepest point under each
  triangle's plane (and a capsule's two ends), and each of a box's corners and a mesh's hull
  vertices against the triangle under it, kept when below the plane and over the triangle. On
  flat terrain this gives the contacts of a plane;
- the prism pass (a geom edge dipping into a face): MPR of the triangle's prism (triangle and
  base, as MuJoCo collides) against the geom, kept only when the prism's witness point lies
  on the top triangle and no plane-pass candidate with that normal is as deep. A prism's
  side walls lie inside the terrain: an exact penetration solver would push geoms out
  sideways through them, so those answers are dropped;
- the point pass (terrain features in the geom): peaks (grid vertices above the mean of
  their neighbours), and the point of each ridge edge (a convex fold of the surface) nearest
  the geom's centre and its ends, that lie inside the geom; MPR of that point against the
  geom gives depth and normal (the geom's surface normal). This catches ridges and peaks
  poking into a geom, which no triangle's plane sees. A round geom (sphere, capsule,
  ellipsoid, cylinder) also gets the point of each valley edge (a concave fold) nearest its
  centre, kept where its normal leans away from one of the edge's triangles: lying over one
  triangle beside the fold, it touches the triangle across the fold only at that edge.
Three kernels: hfield_jobs finds each pair's cells and its prism and point MPRs that pass
cheap tests (B above the triangle's plane, outside a prism's side wall, a point outside B by
one support query) and queues them; hfield_mpr runs the queued MPRs, one thread each, so that a
warp's lanes all run MPRs side by side (one thread a pair ran its ten or so one after another,
beside lanes that had none); hfield_contacts, one thread a pair, adds the plane pass and the
MPR answers in job order. MPRs that find the queue full (``Options.hfield_mprs_per_pair``) run
in hfield_contacts instead: the same contacts, slower.

Candidates closer than a duplicate radius merge (the deeper wins); the deepest and then the
points farthest from those already chosen are written, up to ``max_contacts``, and after them
every other candidate that penetrates: each is a distinct terrain feature inside the geom (a
peak or ridge under a face, a corner in a triangle), as MuJoCo's one contact per triangle prism
is, and a geom lying on rough terrain rests on all of them, not on the few that spread widest
(``max_contacts`` = 1 still writes one). A geom over
more than MAX_CELLS cells keeps the cells nearest its centre and sets ``OverflowType.HFIELD``
(with a printed warning unless ``m.opt.warn_overflow`` clears it).

This module owns the heightfield stage's kernels, its install-time check (``check_model``), its
per-Data buffers (``Buffers``, ``make_buffers``) and its host entry, ``launch``.
The cells' geometry (vertices, prisms, features, the keep-or-drop tests) is hfield_cells.py's.
"""

import dataclasses

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src.collision_core import contact_margin_gap
from mujoco_warp._src.collision_core import contact_params
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import OverflowType
from mujoco_warp._src.types import vec5

from mjx_supportfield.candidates import Candidates
from mjx_supportfield.candidates import add_candidate
from mjx_supportfield.candidates import empty
from mjx_supportfield.candidates import write_candidates
from mjx_supportfield.contact_quota import ContactQuota
from mjx_supportfield.hfield_cells import _axis
from mjx_supportfield.hfield_cells import _capsule_end
from mjx_supportfield.hfield_cells import _cell
from mjx_supportfield.hfield_cells import _cell_size
from mjx_supportfield.hfield_cells import _corner
from mjx_supportfield.hfield_cells import _corners
from mjx_supportfield.hfield_cells import _feature_point
from mjx_supportfield.hfield_cells import _fold_answer_kept
from mjx_supportfield.hfield_cells import _outside_walls
from mjx_supportfield.hfield_cells import _plane_depth
from mjx_supportfield.hfield_cells import _point_shape
from mjx_supportfield.hfield_cells import _prism_answer_kept
from mjx_supportfield.hfield_cells import _prism_shape
from mjx_supportfield.mpr import MprResult
from mjx_supportfield.mpr import mpr_refined
from mjx_supportfield.contact_quota import contact_outputs
from mjx_supportfield.narrowphase import GRID_THREADS
from mjx_supportfield.narrowphase import HEAVY_REGISTERS
from mjx_supportfield.routing import NGEOMTYPE
from mjx_supportfield.shapes import posed_shape
from mjx_supportfield.support import support_world
from mjx_supportfield.types import SUPPORT_MODE_ID
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

wp.set_module_options({"enable_backward": False})

MAX_CELLS = 4096  # cells visited per pair (a 64 x 64 window)
# the passes' MPR reruns start half their depth behind the origin, not mpr.BEHIND x scale: from
# farther back they converge onto a triangle prism's rim, where the normal leans toward a side
# wall (a sphere on a sloping plane got a second contact 18° off at the edge between two
# triangles), and rejecting rim answers outright left bodies sliding on the terrain
RESTART_BEHIND = 0.0


NFEATURE = 9  # terrain features a cell owns for the point pass (see _feature)
NJOB = 2 + 3 * NFEATURE  # a cell's MPR jobs: two prisms, then up to three points per feature
KEPT_CELLS = 16  # cells with jobs whose job masks hfield_jobs keeps from its counting sweep
vec_kept = wp.types.vector(length=KEPT_CELLS, dtype=int)
# hfield_mpr runs the queued jobs grouped by kind: geom B's type, and prism or point, so that a
# warp's lanes take the same branches of the support functions
NKIND = 2 * NGEOMTYPE
COUNT_PAIRS, COUNT_JOBS, COUNT_UNQUEUED, COUNT_KIND = 0, 1, 2, 3  # hfield_count: then NKIND counts


@wp.struct
class TerrainPair:
  """A heightfield - convex pair with cells under the geom, as hfield_jobs leaves it for the MPR
  and contact kernels."""

  cid: int  # index into the pair list
  window: wp.vec4i  # the cells visited: rows r0 ... r1, columns c0 ... c1
  lo: wp.vec3  # B's bounds in the terrain frame, grown by band
  hi: wp.vec3
  band: float  # margin + gap
  cut: int  # 1 when B covers more than MAX_CELLS cells (only those around its centre are visited)
  job_total: int  # the pair's MPR jobs (those that pass the cheap tests)
  job_start: int  # the first job_count of them, in order, are jobs job_start ... of the MPR queue
  job_count: int
  nprism: int  # how many of those are prisms (hfield_order groups them apart from the points)


@wp.func
def _terrain_pair(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  geoms: wp.vec2i,
  worldid: int,
) -> tuple[Shape, Shape, int]:
  """The terrain (world frame), geom B posed in the terrain's frame, and the heightfield's id."""
  terrain = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[0], worldid)
  b = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[1], worldid)
  rt = wp.transpose(terrain.rot)
  b.pos = rt @ (b.pos - terrain.pos)
  b.center = rt @ (b.center - terrain.pos)
  b.rot = rt @ b.rot
  return terrain, b, geom_dataid[worldid % geom_dataid.shape[0], geoms[0]]


@wp.func
def _window(b: Shape, ms: MeshSupport, mode: int, band: float, nrow: int, ncol: int, size: wp.vec4) -> TerrainPair:
  """The cells under B (its bounds grown by band), at most MAX_CELLS around its centre; an
  empty window (r0 > r1) when B is off the terrain or above or below it."""
  tp = TerrainPair()
  tp.band = band
  tp.cut = 0
  tp.job_total = 0
  tp.job_start = 0
  tp.job_count = 0
  tp.nprism = 0
  for k in range(3):
    tp.hi[k] = support_world(b, ms, _axis(k), mode)[k] + band
    tp.lo[k] = support_world(b, ms, -_axis(k), mode)[k] - band
  dx, dy = _cell_size(size, nrow, ncol)
  c0 = wp.max(0, int(wp.floor((tp.lo[0] + size[0]) / dx)))
  c1 = wp.min(ncol - 2, int(wp.floor((tp.hi[0] + size[0]) / dx)))
  r0 = wp.max(0, int(wp.floor((tp.lo[1] + size[1]) / dy)))
  r1 = wp.min(nrow - 2, int(wp.floor((tp.hi[1] + size[1]) / dy)))
  if tp.lo[2] > size[2] or tp.hi[2] < -size[3]:
    r1 = r0 - 1
  if c0 <= c1 and r0 <= r1 and (c1 - c0 + 1) * (r1 - r0 + 1) > MAX_CELLS:
    tp.cut = 1
    half = wp.static(int(MAX_CELLS**0.5) // 2)
    cc = int(wp.floor((b.center[0] + size[0]) / dx))
    rc = int(wp.floor((b.center[1] + size[1]) / dy))
    c0 = wp.max(c0, cc - half)
    c1 = wp.min(c1, cc + half - 1)
    r0 = wp.max(r0, rc - half)
    r1 = wp.min(r1, rc + half - 1)
  tp.window = wp.vec4i(r0, r1, c0, c1)
  return tp


@wp.func
def _window_cell(tp: TerrainPair, cell: int) -> tuple[int, int]:
  """Grid row and column of the window's cell number ``cell`` (numbered along its rows)."""
  ncols = tp.window[3] - tp.window[2] + 1
  return tp.window[0] + cell // ncols, tp.window[2] + cell % ncols


@wp.func
def _above_cell(tp: TerrainPair, p00: wp.vec3, p01: wp.vec3, p10: wp.vec3, p11: wp.vec3) -> bool:
  """Whether B (grown by the band) stays above the cell's highest corner: nothing there to touch."""
  return wp.max(wp.max(p00[2], p01[2]), wp.max(p10[2], p11[2])) + tp.band < tp.lo[2]


@wp.func
def _scale(tp: TerrainPair, dx: float, dy: float) -> float:
  """The pair's length scale (MPR's tolerances are relative to it)."""
  return wp.length(tp.hi - tp.lo) + dx + dy


@wp.func
def _round(b: Shape) -> bool:
  """Whether B's surface is curved, so that it can touch a concave terrain edge from the side
  (a box's or a mesh's faces meet such an edge only where they already meet a face or a
  ridge)."""
  return b.gtype == GeomType.SPHERE or b.gtype == GeomType.CAPSULE or b.gtype == GeomType.ELLIPSOID or (
    b.gtype == GeomType.CYLINDER)


@wp.func
def _cell_jobs(hfield_data: wp.array(dtype=float), adr: int, nrow: int, ncol: int, size: wp.vec4, b: Shape,
               ms: MeshSupport, mode: int, tp: TerrainPair, cell: int) -> int:
  """The MPR jobs of a window cell that pass the cheap tests, as a bit mask over its NJOB jobs:
  0, 1 the prisms of its two triangles, 2 + 3 k + end feature k's points (_feature_point)."""
  dx, dy = _cell_size(size, nrow, ncol)
  eps = 1.0e-6 * (dx + dy + size[2])
  band = tp.band
  r, c = _window_cell(tp, cell)
  p00, p01, p10, p11, na, nb = _cell(hfield_data, adr, ncol, size, dx, dy, r, c)
  if _above_cell(tp, p00, p01, p10, p11):
    return 0
  # B's deepest point under each triangle's plane: where B stays above a plane (by more than the
  # band), that triangle, its prism and the terrain features on it touch nothing
  below_a = wp.dot(na, p00 - support_world(b, ms, -na, mode)) + band > 0.0
  below_b = wp.dot(nb, p00 - support_world(b, ms, -nb, mode)) + band > 0.0
  mask = int(0)
  job = int(0)
  while job < NJOB and (below_a or below_b):
    wanted = bool(False)
    if (job == 0 and below_a) or (job == 1 and below_b):
      wanted = not _outside_walls(b, ms, mode, p00, wp.where(job == 0, p10, p11), wp.where(job == 0, p11, p01), band,
                                  3)
    elif job >= 2:
      k = (job - 2) // 3
      on_a = k == 0 or k == 2 or k == 3 or k == 5 or k == 7 or k == 8  # see _feature
      on_b = k == 0 or k == 1 or k == 3 or k == 4 or k == 6 or k == 8
      if (below_a or not on_a) and (below_b or not on_b):
        q, wanted = _feature_point(hfield_data, adr, nrow, ncol, size, dx, dy, r, c, tp.window[1], tp.window[3], job,
                                   p00, p01, p10, p11, b.center, eps, _round(b))
        lo = tp.lo
        hi = tp.hi
        if q[0] < lo[0] or q[1] < lo[1] or q[2] < lo[2] or q[0] > hi[0] or q[1] > hi[1] or q[2] > hi[2]:
          wanted = False
        # most such points lie outside B: B's support toward the point, from its centre, shows
        # that with one query instead of an MPR
        out = q - b.center
        if wanted and wp.length(out) > 0.0:
          out = wp.normalize(out)
          wanted = wp.dot(q - support_world(b, ms, out, mode), out) <= band
    if wanted:
      mask = mask | (1 << job)
    job += 1
  return mask


@wp.func
def _job_shape(hfield_data: wp.array(dtype=float), adr: int, nrow: int, ncol: int, size: wp.vec4, b: Shape,
               tp: TerrainPair, code: int) -> Shape:
  """The terrain part of MPR job ``code`` (cell * NJOB + job): a triangle's prism or a point."""
  dx, dy = _cell_size(size, nrow, ncol)
  eps = 1.0e-6 * (dx + dy + size[2])
  job = code % NJOB
  r, c = _window_cell(tp, code // NJOB)
  p00, p01, p10, p11, na, nb = _cell(hfield_data, adr, ncol, size, dx, dy, r, c)
  if job >= 2:
    q, convex = _feature_point(hfield_data, adr, nrow, ncol, size, dx, dy, r, c, tp.window[1], tp.window[3], job, p00, p01,
                          p10, p11, b.center, eps, False)
    return _point_shape(q, tp.band)
  return _prism_shape(p00, wp.where(job == 0, p10, p11), wp.where(job == 0, p11, p01), -size[3], tp.band)


@wp.func
def _job_mpr(hfield_data: wp.array(dtype=float), adr: int, nrow: int, ncol: int, size: wp.vec4, b: Shape,
             ms: MeshSupport, mode: int, tp: TerrainPair, code: int, tolerance: float, iterations: int,
             refine: int) -> tuple[wp.vec4, wp.vec3]:
  """MPR job ``code``'s answer: the contact point and depth (0 when it found none), and the normal."""
  a = _job_shape(hfield_data, adr, nrow, ncol, size, b, tp, code)
  dx, dy = _cell_size(size, nrow, ncol)
  scale = _scale(tp, dx, dy)
  res = mpr_refined(a, b, ms, mode, scale, tolerance, iterations, refine, RESTART_BEHIND)
  depth = wp.where(res.hit != 0 and res.depth > 0.0, res.depth, 0.0)
  return wp.vec4(res.pos[0], res.pos[1], res.pos[2], depth), res.normal


@wp.func
def _plane_pass(hfield_data: wp.array(dtype=float), adr: int, nrow: int, ncol: int, size: wp.vec4, b: Shape,
                ms: MeshSupport, mode: int, tp: TerrainPair, spacing: float) -> Candidates:
  """The face contacts: B's corners against the triangle under each, then each cell's
  triangles against B's deepest points (and a capsule's ends)."""
  cands = empty()
  band = tp.band
  r0 = tp.window[0]
  r1 = tp.window[1]
  c0 = tp.window[2]
  c1 = tp.window[3]
  dx, dy = _cell_size(size, nrow, ncol)
  ncell = (r1 - r0 + 1) * (c1 - c0 + 1)
  ncorner = _corners(b, ms)
  nlow = wp.where(b.gtype == GeomType.CAPSULE, 3, 1)  # plane jobs a triangle: B's deepest point, a capsule's ends
  for item in range(ncorner + ncell):
    corner = wp.vec3(0.0)
    r, c = _window_cell(tp, item - ncorner)
    if item < ncorner:
      corner = _corner(b, ms, item)
      c = int(wp.floor((corner[0] + size[0]) / dx))
      r = int(wp.floor((corner[1] + size[1]) / dy))
      if c < c0 or c > c1 or r < r0 or r > r1:
        continue
    p00, p01, p10, p11, na, nb = _cell(hfield_data, adr, ncol, size, dx, dy, r, c)
    if _above_cell(tp, p00, p01, p10, p11):
      continue
    njob = wp.where(item < ncorner, 1, 2 * nlow)
    for job in range(njob):
      t = job // nlow  # the triangle: (p00, p10, p11) or (p00, p11, p01)
      p = corner
      if item < ncorner:
        t = wp.where((corner[1] - p00[1]) / dy >= (corner[0] - p00[0]) / dx, 0, 1)  # above the diagonal: the first
      n = wp.where(t == 0, na, nb)
      if item >= ncorner and job % nlow == 0:
        p = support_world(b, ms, -n, mode)
      elif item >= ncorner:
        p = _capsule_end(b, job % nlow - 1, n)
      depth = _plane_depth(p, p00, wp.where(t == 0, p10, p11), wp.where(t == 0, p11, p01), n, band)
      if depth > 0.0:
        cands = add_candidate(cands, p + 0.5 * depth * n, n, depth, spacing)
  return cands


@wp.func
def _add_job_answer(hfield_data: wp.array(dtype=float), adr: int, nrow: int, ncol: int, size: wp.vec4,
                    tp: TerrainPair, cands: Candidates, code: int, answer: wp.vec4, normal: wp.vec3, spacing: float,
                    tol: float) -> Candidates:
  """Adds MPR job ``code``'s answer (position, depth; depth 0 when it found nothing) to the
  candidates, unless it is a prism's answer through a side wall or one the face contacts
  already hold (_prism_answer_kept), or a point's with a normal into the terrain or between
  two faces that hold B's contacts (_fold_answer_kept)."""
  if answer[3] <= 0.0:
    return cands
  dx, dy = _cell_size(size, nrow, ncol)
  job = code % NJOB
  r, c = _window_cell(tp, code // NJOB)
  p00, p01, p10, p11, na, nb = _cell(hfield_data, adr, ncol, size, dx, dy, r, c)
  res = MprResult()
  res.hit = 1
  res.depth = answer[3]
  res.pos = wp.vec3(answer[0], answer[1], answer[2])
  res.normal = normal
  if job < 2:
    if not _prism_answer_kept(cands, res, wp.where(job == 0, na, nb), p00, _scale(tp, dx, dy), tol):
      return cands
  elif wp.dot(normal, na + nb) <= 0.0:
    return cands  # B's surface normal must point away from the terrain
  elif not _fold_answer_kept(hfield_data, adr, nrow, ncol, size, dx, dy, r, c, job, p00, p01, p10, p11, normal,
                             1.0e-6 * (dx + dy + size[2])):
    return cands
  return add_candidate(cands, res.pos, normal, res.depth, spacing)


@wp.func
def _bits(mask: int) -> int:
  """How many bits of mask are set."""
  n = int(0)
  m = mask
  while m != 0:
    m = m & (m - 1)
    n += 1
  return n


@wp.func
def _queue_cell(job_out: wp.array(dtype=wp.vec2i), slot: int, tp: TerrainPair, cell: int, mask: int, n: int) -> int:
  """Queues the jobs in a cell's mask as the pair's jobs n, n + 1, ... (those that fit in its
  share of the queue); returns the next n."""
  out = n
  job = int(0)
  while job < NJOB:
    if ((mask >> job) & 1) == 1:
      if out < tp.job_count:
        job_out[tp.job_start + out] = wp.vec2i(slot, cell * NJOB + job)
      out += 1
    job += 1
  return out


@wp.kernel
def hfield_jobs(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  hfield_size: wp.array(dtype=wp.vec4),
  hfield_nrow: wp.array(dtype=int),
  hfield_ncol: wp.array(dtype=int),
  hfield_adr: wp.array(dtype=int),
  hfield_data: wp.array(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  npair_in: wp.array(dtype=int),
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  nsweep: int,
  nthread: int,
  # Out:
  overflow_out: wp.array(dtype=int),
  hfield_count_out: wp.array(dtype=int),
  hfield_pair_out: wp.array(dtype=TerrainPair),
  hfield_job_out: wp.array(dtype=wp.vec2i),
):
  """First of the heightfield kernels: each heightfield - convex pair's window of cells, and its
  MPR jobs (prisms and terrain points that pass the cheap tests), queued in cell order so that
  hfield_mpr runs them on dense warps. hfield_count_out counts the pairs, the jobs asked for,
  and those that found the queue full (hfield_contacts runs them in the pair's thread)."""
  tid = wp.tid()
  for cid in range(tid, npair_in[0], nthread):
    geoms = pair_in[cid]
    if geom_type[geoms[0]] != GeomType.HFIELD or geom_type[geoms[1]] == GeomType.HFIELD or (
        geom_type[geoms[1]] == GeomType.PLANE):
      continue
    worldid = pair_worldid_in[cid]
    margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
    _, b, hf = _terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms, worldid)
    nrow = hfield_nrow[hf]
    ncol = hfield_ncol[hf]
    size = hfield_size[hf]
    adr = hfield_adr[hf]
    tp = _window(b, ms, support_mode, wp.max(margin + gap, 0.0), nrow, ncol, size)
    if tp.window[0] > tp.window[1] or tp.window[2] > tp.window[3]:
      continue
    slot = wp.atomic_add(hfield_count_out, COUNT_PAIRS, 1)
    if slot >= hfield_pair_out.shape[0]:  # the slots are as many as a world's heightfield pairs can be
      wp.atomic_or(overflow_out, worldid, int(OverflowType.HFIELD))
      continue
    tp.cid = cid
    ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
    # two sweeps over the cells (nsweep = 2, an argument so that the loop is not unrolled): the
    # first counts the jobs, keeping the first KEPT_CELLS cells' masks, the second queues the
    # jobs of the cells beyond those (only for pairs with more cells that have jobs)
    kept_cell = vec_kept()
    kept_mask = vec_kept()
    nkept = int(0)
    n = int(0)  # jobs counted (first sweep), then queued
    for sweep in range(nsweep):
      cell = int(0)
      if sweep == 1:
        if nkept < KEPT_CELLS or n >= tp.job_count:
          break  # every cell with jobs was kept, or the pair's share of the queue is full
        cell = kept_cell[KEPT_CELLS - 1] + 1
      while cell < ncell:
        mask = _cell_jobs(hfield_data, adr, nrow, ncol, size, b, ms, support_mode, tp, cell)
        if mask != 0:
          if sweep == 1:
            n = _queue_cell(hfield_job_out, slot, tp, cell, mask, n)
          elif nkept < KEPT_CELLS:
            kept_cell[nkept] = cell
            kept_mask[nkept] = mask
            nkept += 1
          else:
            n += _bits(mask)
        cell += 1
      if sweep == 0:
        for i in range(nkept):
          n += _bits(kept_mask[i])
        tp.job_total = n
        tp.job_start = wp.atomic_add(hfield_count_out, COUNT_JOBS, n)
        tp.job_count = wp.max(0, wp.min(n, hfield_job_out.shape[0] - tp.job_start))
        if tp.job_count < n:  # no room in the queue: the rest run in hfield_contacts
          wp.atomic_add(hfield_count_out, COUNT_UNQUEUED, n - tp.job_count)
        n = int(0)
        for i in range(nkept):
          n = _queue_cell(hfield_job_out, slot, tp, kept_cell[i], kept_mask[i], n)
    for j in range(tp.job_start, tp.job_start + tp.job_count):
      if hfield_job_out[j][1] % NJOB < 2:
        tp.nprism += 1
    kind = COUNT_KIND + 2 * geom_type[geoms[1]]
    wp.atomic_add(hfield_count_out, kind, tp.nprism)
    wp.atomic_add(hfield_count_out, kind + 1, tp.job_count - tp.nprism)
    hfield_pair_out[slot] = tp


@wp.kernel
def hfield_kind_start(
  # In:
  hfield_count_in: wp.array(dtype=int),
  # Out:
  kind_next_out: wp.array(dtype=int),
):
  """Where each kind of job starts in hfield_order (one thread): the counts' running sum."""
  start = int(0)
  for kind in range(NKIND):
    kind_next_out[kind] = start
    start += hfield_count_in[COUNT_KIND + kind]


@wp.kernel
def hfield_order(
  # Model:
  geom_type: wp.array(dtype=int),
  # In:
  pair_in: wp.array(dtype=wp.vec2i),
  hfield_count_in: wp.array(dtype=int),
  hfield_pair_in: wp.array(dtype=TerrainPair),
  hfield_job_in: wp.array(dtype=wp.vec2i),
  nthread: int,
  # Out:
  kind_next_out: wp.array(dtype=int),
  order_out: wp.array(dtype=int),
):
  """The queued jobs grouped by kind (one thread a pair): each pair's prisms, then its points,
  go to the next places of their kinds in order_out, so hfield_mpr's warps run jobs of one kind."""
  tid = wp.tid()
  for slot in range(tid, wp.min(hfield_count_in[COUNT_PAIRS], hfield_pair_in.shape[0]), nthread):
    tp = hfield_pair_in[slot]
    kind = 2 * geom_type[pair_in[tp.cid][1]]
    prism = wp.atomic_add(kind_next_out, kind, tp.nprism)
    point = wp.atomic_add(kind_next_out, kind + 1, tp.job_count - tp.nprism)
    for j in range(tp.job_start, tp.job_start + tp.job_count):
      if hfield_job_in[j][1] % NJOB < 2:
        order_out[prism] = j
        prism += 1
      else:
        order_out[point] = j
        point += 1


@wp.kernel(cuda_max_registers=HEAVY_REGISTERS)
def hfield_mpr(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  hfield_size: wp.array(dtype=wp.vec4),
  hfield_nrow: wp.array(dtype=int),
  hfield_ncol: wp.array(dtype=int),
  hfield_adr: wp.array(dtype=int),
  hfield_data: wp.array(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # In:
  ms: MeshSupport,
  support_mode: int,
  tolerance: float,
  iterations: int,
  refine: int,
  pair_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  hfield_count_in: wp.array(dtype=int),
  hfield_pair_in: wp.array(dtype=TerrainPair),
  hfield_job_in: wp.array(dtype=wp.vec2i),
  order_in: wp.array(dtype=int),
  nthread: int,
  # Out:
  answer_out: wp.array(dtype=wp.vec4),
  normal_out: wp.array(dtype=wp.vec3),
):
  """The queued terrain MPRs, one thread a job in hfield_order's order: the contact point and
  depth (0: none) and the normal, for hfield_contacts."""
  tid = wp.tid()
  for i in range(tid, wp.min(hfield_count_in[COUNT_JOBS], hfield_job_in.shape[0]), nthread):
    j = order_in[i]
    job = hfield_job_in[j]
    tp = hfield_pair_in[job[0]]
    worldid = pair_worldid_in[tp.cid]
    _, b, hf = _terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, pair_in[tp.cid],
                             worldid)
    answer, normal = _job_mpr(hfield_data, hfield_adr[hf], hfield_nrow[hf], hfield_ncol[hf], hfield_size[hf], b, ms,
                              support_mode, tp, job[1], tolerance, iterations, refine)
    answer_out[j] = answer
    normal_out[j] = normal


@wp.kernel
def hfield_contacts(
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
  geom_aabb: wp.array3d(dtype=wp.vec3),
  hfield_size: wp.array(dtype=wp.vec4),
  hfield_nrow: wp.array(dtype=int),
  hfield_ncol: wp.array(dtype=int),
  hfield_adr: wp.array(dtype=int),
  hfield_data: wp.array(dtype=float),
  pair_dim: wp.array(dtype=int),
  pair_solref: wp.array2d(dtype=wp.vec2),
  pair_solreffriction: wp.array2d(dtype=wp.vec2),
  pair_solimp: wp.array2d(dtype=vec5),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  pair_adhesion: wp.array2d(dtype=float),
  pair_friction: wp.array2d(dtype=vec5),
  opt_warn_hfield: int,
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
  mc_tolerance: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  hfield_count_in: wp.array(dtype=int),
  hfield_pair_in: wp.array(dtype=TerrainPair),
  hfield_job_in: wp.array(dtype=wp.vec2i),
  answer_in: wp.array(dtype=wp.vec4),
  normal_in: wp.array(dtype=wp.vec3),
  nthread: int,
  quota: ContactQuota,
  # Data out:
  overflow_out: wp.array(dtype=int),
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
  """Last of the heightfield kernels, one thread a pair of hfield_jobs: the face contacts and
  its MPR answers in job order (running those the queue had no room for), merged
  (candidates.py) and written (heightfield first, as MuJoCo orders the pair)."""
  tid = wp.tid()
  for slot in range(tid, wp.min(hfield_count_in[COUNT_PAIRS], hfield_pair_in.shape[0]), nthread):
    tp = hfield_pair_in[slot]
    cid = tp.cid
    geoms = pair_in[cid]
    worldid = pair_worldid_in[cid]
    _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = contact_params(
      geom_condim, geom_priority, geom_solmix, geom_solref, geom_solimp, geom_friction, geom_margin, geom_gap,
      geom_adhesion, pair_dim, pair_solref, pair_solreffriction, pair_solimp, pair_margin, pair_gap, pair_adhesion,
      pair_friction, pair_in, pairid_in, cid, worldid,
    )
    terrain, b, hf = _terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms, worldid)
    nrow = hfield_nrow[hf]
    ncol = hfield_ncol[hf]
    size = hfield_size[hf]
    adr = hfield_adr[hf]
    spacing = mc_tolerance * 2.0 * wp.length(geom_aabb[worldid % geom_aabb.shape[0], geoms[1], 1])
    cands = _plane_pass(hfield_data, adr, nrow, ncol, size, b, ms, support_mode, tp, spacing)
    for j in range(tp.job_start, tp.job_start + tp.job_count):
      cands = _add_job_answer(hfield_data, adr, nrow, ncol, size, tp, cands, hfield_job_in[j][1], answer_in[j],
                              normal_in[j], spacing, tolerance)
    # the jobs the queue had no room for, in order after the queued ones
    code = int(0)
    if tp.job_count > 0:
      code = hfield_job_in[tp.job_start + tp.job_count - 1][1] + 1
    left = tp.job_total - tp.job_count
    ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
    while left > 0 and code < ncell * NJOB:
      cell = code // NJOB
      mask = _cell_jobs(hfield_data, adr, nrow, ncol, size, b, ms, support_mode, tp, cell)
      mask = (mask >> (code % NJOB)) << (code % NJOB)  # the cell's jobs from code on
      job = int(0)
      while mask != 0:
        if (mask & 1) == 1:
          answer, normal = _job_mpr(hfield_data, adr, nrow, ncol, size, b, ms, support_mode, tp, cell * NJOB + job,
                                    tolerance, iterations, refine)
          cands = _add_job_answer(hfield_data, adr, nrow, ncol, size, tp, cands, cell * NJOB + job, answer, normal,
                                  spacing, tolerance)
          left -= 1
        mask = mask >> 1
        job += 1
      code = (cell + 1) * NJOB
    if tp.cut:
      wp.atomic_or(overflow_out, worldid, int(OverflowType.HFIELD))
      if opt_warn_hfield:
        wp.printf("mjx_supportfield: heightfield overflow - geom %d covers more than %d cells in world %d; only the "
                  "cells around its centre are used\n", geoms[1], MAX_CELLS, worldid)
    if max_contacts > 1:
      cands.keep = tp.band  # the penetrating ones (depths include the band)
    write_candidates(
      cands, max_contacts, terrain.rot, terrain.pos, tp.band, naconmax_in, margin, gap, condim, friction, solref,
      solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contact_dist_out, contact_pos_out,
      contact_frame_out, contact_includemargin_out, contact_friction_out, contact_solref_out,
      contact_solreffriction_out, contact_solimp_out, contact_dim_out, contact_geom_out, contact_efc_address_out,
      contact_worldid_out, contact_type_out, contact_geomcollisionid_out, contact_adhesion_out, nacon_out, quota,
    )


def check_model(mjm: mujoco.MjModel) -> None:
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


@dataclasses.dataclass
class Buffers:
  """The heightfield stage's per-Data buffers."""

  count: wp.array  # heightfield pairs, MPRs, those beyond the queue, per kind (COUNT_*)
  pair: wp.array  # (pairs) TerrainPair
  job: wp.array  # (MPRs) the MPR queue: (index into pair, cell * NJOB + job)
  kind_next: wp.array  # (NKIND) next place of each kind of job in order
  order: wp.array  # (MPRs) the queue's jobs grouped by kind, the order hfield_mpr runs them in
  answer: wp.array  # (MPRs) each MPR's point and depth
  normal: wp.array  # (MPRs) and normal


def make_buffers(c, nworld: int) -> Buffers:
  """The heightfield stage's buffers for ``nworld`` worlds (``c``: the Collider)."""
  npair = max(1, nworld * c.hfield_pairs_per_world)
  nmpr = npair * c.options.hfield_mprs_per_pair if c.hfield_pairs_per_world else 1
  return Buffers(
    count=wp.zeros(COUNT_KIND + NKIND, dtype=int),
    kind_next=wp.zeros(NKIND, dtype=int),
    order=wp.zeros(nmpr, dtype=int),
    pair=wp.zeros(npair, dtype=TerrainPair),
    job=wp.zeros(nmpr, dtype=wp.vec2i),
    answer=wp.zeros(nmpr, dtype=wp.vec4),
    normal=wp.zeros(nmpr, dtype=wp.vec3),
  )


def launch(c, m, d, pairs, b: Buffers, quota: ContactQuota):
  """Heightfield - convex pairs of one step: windows and MPR queue, the queue grouped by kind,
  the queued MPRs, then the contacts (``c``: the Collider; ``pairs``: the broad phase's buffers)."""
  if not c.has_hfield_pairs:
    return
  opt = c.options
  nthread = max(1, min(pairs.capacity, GRID_THREADS))
  mode = SUPPORT_MODE_ID[opt.support_mode]
  warn = int(bool(int(m.opt.warn_overflow) & int(OverflowType.HFIELD)))
  hfield = [m.hfield_size, m.hfield_nrow, m.hfield_ncol, m.hfield_adr, m.hfield_data]
  wp.launch(
    hfield_jobs,
    dim=nthread,
    inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_margin, m.geom_gap] + hfield
    + [m.pair_margin, m.pair_gap, d.geom_xpos, d.geom_xmat, c.mesh_support, mode, pairs.npair, pairs.pair,
       pairs.pairid, pairs.pair_worldid, 2, nthread],
    outputs=[d.overflow, b.count, b.pair, b.job],
  )
  nthread_pair = max(1, min(b.pair.shape[0], GRID_THREADS))
  wp.launch(hfield_kind_start, dim=1, inputs=[b.count], outputs=[b.kind_next])
  wp.launch(
    hfield_order,
    dim=nthread_pair,
    inputs=[m.geom_type, pairs.pair, b.count, b.pair, b.job, nthread_pair],
    outputs=[b.kind_next, b.order],
  )
  nthread_mpr = max(1, min(b.job.shape[0], GRID_THREADS))
  wp.launch(
    hfield_mpr,
    dim=nthread_mpr,
    inputs=[m.geom_type, m.geom_dataid, m.geom_size] + hfield
    + [d.geom_xpos, d.geom_xmat, c.mesh_support, mode, opt.mpr_tolerance, opt.mpr_iterations,
       opt.mpr_refine, pairs.pair, pairs.pair_worldid, b.count, b.pair, b.job, b.order, nthread_mpr],
    outputs=[b.answer, b.normal],
  )
  wp.launch(
    hfield_contacts,
    dim=nthread_pair,
    inputs=[
      m.geom_type, m.geom_condim, m.geom_dataid, m.geom_priority, m.geom_solmix, m.geom_solref, m.geom_solimp,
      m.geom_size, m.geom_friction, m.geom_margin, m.geom_gap, m.geom_adhesion, m.geom_aabb] + hfield + [
      m.pair_dim, m.pair_solref, m.pair_solreffriction, m.pair_solimp, m.pair_margin, m.pair_gap, m.pair_adhesion,
      m.pair_friction, warn, d.geom_xpos, d.geom_xmat, d.naconmax, c.mesh_support, mode,
      opt.mpr_tolerance, opt.mpr_iterations, opt.mpr_refine,
      opt.max_contacts_per_pair, opt.mc_tolerance, pairs.pair, pairs.pairid,
      pairs.pair_worldid, b.count, b.pair, b.job, b.answer, b.normal,
      nthread_pair, quota,
    ],
    outputs=[d.overflow] + contact_outputs(d),
  )
