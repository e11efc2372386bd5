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
  sideways through them, so those answers are dropped. A box or a mesh runs MuJoCo Warp's GJK/EPA
  (collision_gjk.ccd) on each prism instead, built as MuJoCo C builds it, and keeps each prism's
  answer unless it is a side wall's or a face lying flat on the triangle (whose corners the plane
  pass has): such a face on rough terrain overlaps many prisms, and MuJoCo C's contact of each
  lies where its EPA ends, spread over the face, where the deepest terrain points alone leave
  no contact;
- the point pass (terrain features in the geom): peaks (grid vertices above the mean of
  their neighbours), and the point of each ridge edge (a convex fold of the surface) nearest
  the geom's centre and its ends, that lie inside the geom; MPR of that point against the
  geom gives depth and normal (the geom's surface normal). This catches ridges and peaks
  poking into a geom, which no triangle's plane sees. A round geom (sphere, capsule,
  ellipsoid, cylinder) also gets the point of each valley edge (a concave fold) nearest its
  centre, kept where its normal leans away from one of the edge's triangles: lying over one
  triangle beside the fold, it touches the triangle across the fold only at that edge.
Four kernels: hfield_jobs finds each pair's cells and its prism and point MPRs that pass
cheap tests (B above the triangle's plane, outside a prism's side wall, a point outside B by
one support query; for a box, a point outside it, or a prism parted from it by one of the box's
axes or an edge pair's: geometry/box_prism.py) and queues them; hfield_mpr runs the queued MPRs,
one thread each, so that a warp's lanes all run MPRs side by side (one thread a pair ran its ten
or so one after another, beside lanes that had none), and hfield_ccd the queued GJK/EPA prisms of
boxes and meshes on CCD_THREADS threads, each with a row of EPA memory; hfield_contacts, one
thread a pair, adds the plane pass and the MPR answers in job order. MPRs that find the queue full
(``Options.hfield_mprs_per_pair``) run in hfield_contacts instead: the same contacts, slower; but
a box's or a mesh's prisms among them go to a second queue, the beyond queue (CCD_BEYOND places,
written by hfield_jobs), whose GJK/EPA hfield_ccd runs too, so that hfield_contacts has no GJK/EPA
to build (a prism that finds the beyond queue full as well runs MPR, counted in the heightfield
count buffer's COUNT_CCD_AS_MPR).

The kernels are built in parts of the stage's module (types.mode_module), which Warp builds side
by side at first use (first_use.py), so that the first collision waits for the largest part, not
for the sum: the light kernels, hfield_mpr, hfield_ccd (only for models with boxes or meshes on a
heightfield: GJK/EPA, the one part with MuJoCo Warp's collision_gjk) and hfield_contacts.

Candidates closer than a duplicate radius merge (the deeper wins); the deepest and then the
points farthest from those already chosen are written, up to ``max_contacts``, and after them
every other candidate that penetrates: each is a distinct terrain feature inside the geom (a
peak or ridge under a face, a corner in a triangle), as MuJoCo's one contact per triangle prism
is, and a geom lying on rough terrain rests on all of them, not on the few that spread widest
(``max_contacts`` = 1 still writes one). A box or a mesh gets one contact a triangle, as MuJoCo C
gets one a prism: the prism's GJK/EPA answer where it was kept (a box's gives way to the exact
answer where it cannot be right: hfield_window._box_prism_answer), else the deepest of the box's
corners or the mesh's hull vertices under that triangle and B's deepest point under its plane
(a face lying on a triangle is one contact, not one a corner). A geom over more than MAX_CELLS
cells keeps the cells nearest its centre and sets ``OverflowType.HFIELD`` (with a printed
warning unless ``m.opt.warn_overflow`` clears it).

This module owns the heightfield stage's kernels (built for one support mode by ``stage_kernels``),
its install-time check (``check_model``), its per-Data buffers (``Buffers``) and its stage class,
``Heightfield``.
Each pair's window of cells and its jobs (device functions) are hfield_window.py's; the cells'
geometry (vertices, prisms, features, the keep-or-drop tests) is hfield_cells.py's.
"""

import dataclasses
import functools
from types import SimpleNamespace

import mujoco
import numpy as np
import warp as wp
from mujoco_warp._src.collision_core import contact_margin_gap
from mujoco_warp._src.types import MJ_MAX_EPAFACES
from mujoco_warp._src.types import MJ_MAX_EPAHORIZON
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import OverflowType

from mjx_supportfield.geometry.mpr import MprSettings
from mjx_supportfield.geometry.mpr import settings_of
from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import contact_mixing
from mjx_supportfield.launch.contact_quota import contact_outputs
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.grid import GRID_THREADS
from mjx_supportfield.launch.grid import HEAVY_REGISTERS
from mjx_supportfield.options import Options
from mjx_supportfield.stages.candidates import NCANDIDATE
from mjx_supportfield.stages.candidates import empty_with_room
from mjx_supportfield.stages.candidates import write_candidates
from mjx_supportfield.stages.hfield_cells import heightfield
from mjx_supportfield.stages.hfield_closed_form import closed_form
from mjx_supportfield.stages.hfield_closed_form import hfield_closed_form
from mjx_supportfield.types import MODULE_OPTIONS
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from mjx_supportfield.stages.hfield_window import (
  MAX_CELLS,
  NJOB,
  KEPT_CELLS,
  vec_kept,
  NKIND,
  COUNT_PAIRS,
  COUNT_JOBS,
  COUNT_UNQUEUED,
  COUNT_KIND,
  COUNT_BEYOND,
  COUNT_CCD_AS_MPR,
  CCD_THREADS,
  CCD_BEYOND,
  PrismCcd,
  TerrainPair,
  terrain_pair,
  uses_ccd,
  ccd_geom,
  job_ccd,
  add_job_answer,
  set_bits,
  queue_cell,
  window_funcs,
)


# no contraction of multiply-adds into FMAs: GJK/EPA's answer for a face resting on a prism is
# ill-conditioned (where EPA ends on the face moves by millimetres with the last bit of the input),
# and a GPU compiler contracts the same code differently in each kernel that inlines it, so a
# prism run in hfield_ccd and the same prism run beyond the queue in hfield_contacts gave different
# contacts (an MPR queued or beyond the queue runs in two kernels still); without contraction every
# operation rounds as written, in each kernel and on the CPU (whose code this option leaves as it was)
wp.set_module_options({**MODULE_OPTIONS, "fuse_fp": False})


@functools.lru_cache(maxsize=None)
def stage_kernels(mode: int) -> SimpleNamespace:
  """The stage's kernels for support mode ``mode`` but hfield_contacts (contacts_kernel), in parts
  of that mode's module (types.mode_module) that compile side by side at first use: ``jobs``,
  ``kind_start`` and ``order`` in one, ``mpr`` and ``ccd`` in one each."""
  module = mode_module(__name__, mode)
  window = window_funcs(mode)
  _window = window._window
  _cell_jobs = window._cell_jobs
  _job_mpr = window._job_mpr
  _queue_beyond = window._queue_beyond

  @wp.kernel(module=module)
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
    beyond_job_out: wp.array(dtype=wp.vec2i),
  ):
    """First of the heightfield kernels: each heightfield - convex pair's window of cells, and its
    MPR jobs (prisms and terrain points that pass the cheap tests), queued in cell order so that
    hfield_mpr runs them on dense warps. hfield_count_out counts the pairs, the jobs asked for,
    and those that found the queue full (hfield_contacts runs them in the pair's thread, but a
    box's or a mesh's prisms, which go to the beyond queue for hfield_ccd)."""
    tid = wp.tid()
    for cid in range(tid, npair_in[0], nthread):
      geoms = pair_in[cid]
      if geom_type[geoms[0]] != GeomType.HFIELD or geom_type[geoms[1]] == GeomType.HFIELD or (
          geom_type[geoms[1]] == GeomType.PLANE):
        continue
      worldid = pair_worldid_in[cid]
      margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
      _, b, hf = terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms, worldid)
      hfield = heightfield(hfield_size, hfield_nrow, hfield_ncol, hfield_adr, hfield_data, hf)
      tp = _window(b, ms, wp.max(margin + gap, 0.0), hfield)
      if tp.window[0] > tp.window[1] or tp.window[2] > tp.window[3]:
        continue
      slot = wp.atomic_add(hfield_count_out, COUNT_PAIRS, 1)
      if slot >= hfield_pair_out.shape[0]:  # the slots are as many as a world's heightfield pairs can be
        wp.atomic_or(overflow_out, worldid, int(OverflowType.HFIELD))
        continue
      tp.cid = cid
      tp.closed_form = wp.where(closed_form(b, tp, hfield.size), 1, 0)
      ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
      # two sweeps over the cells (nsweep = 2, an argument so that the loop is not unrolled): the
      # first counts the jobs, keeping the first KEPT_CELLS cells' masks, the second queues the
      # jobs of the cells beyond those (only for pairs with more cells that have jobs)
      kept_cell = vec_kept()
      kept_mask = vec_kept()
      nkept = int(0)
      n = int(0)  # jobs counted (first sweep), then queued
      nprism = int(0)  # prisms counted
      # a sphere or a capsule within the grid has no MPR jobs: hfield_closed_form answers it
      for sweep in range(wp.where(tp.closed_form == 1, 0, nsweep)):
        cell = int(0)
        if sweep == 1:
          if nkept < KEPT_CELLS or n >= tp.job_count:
            break  # every cell with jobs was kept, or the pair's share of the queue is full
          cell = kept_cell[KEPT_CELLS - 1] + 1
        while cell < ncell:
          mask = _cell_jobs(hfield, b, ms, tp, cell)
          if mask != 0:
            if sweep == 1:
              n = queue_cell(hfield_job_out, slot, tp, cell, mask, n)
            elif nkept < KEPT_CELLS:
              kept_cell[nkept] = cell
              kept_mask[nkept] = mask
              nkept += 1
            else:
              n += set_bits(mask)
              nprism += set_bits(mask & 3)
          cell += 1
        if sweep == 0:
          for i in range(nkept):
            n += set_bits(kept_mask[i])
            nprism += set_bits(kept_mask[i] & 3)
          tp.job_total = n
          if n > 0:  # a pair without jobs asks for no place (atomics on one counter from every pair wait in line)
            tp.job_start = wp.atomic_add(hfield_count_out, COUNT_JOBS, n)
            tp.job_count = wp.max(0, wp.min(n, hfield_job_out.shape[0] - tp.job_start))
            if tp.job_count < n:  # no room in the queue: the rest run in hfield_contacts
              wp.atomic_add(hfield_count_out, COUNT_UNQUEUED, n - tp.job_count)
          n = int(0)
          for i in range(nkept):
            n = queue_cell(hfield_job_out, slot, tp, kept_cell[i], kept_mask[i], n)
      for j in range(tp.job_start, tp.job_start + tp.job_count):
        if hfield_job_out[j][1] % NJOB < 2:
          tp.nprism += 1
      if tp.job_count > 0:
        kind = COUNT_KIND + 2 * geom_type[geoms[1]]
        wp.atomic_add(hfield_count_out, kind, tp.nprism)
        wp.atomic_add(hfield_count_out, kind + 1, tp.job_count - tp.nprism)
      if nprism > tp.nprism and uses_ccd(b, 0):  # a box's or a mesh's prisms beyond the MPR queue
        tp.beyond_start = wp.atomic_add(hfield_count_out, COUNT_BEYOND, nprism - tp.nprism)
        tp.beyond_count = wp.max(0, wp.min(nprism - tp.nprism, beyond_job_out.shape[0] - tp.beyond_start))
        _queue_beyond(hfield, b, ms, tp, slot, hfield_job_out, beyond_job_out)
      hfield_pair_out[slot] = tp

  @wp.kernel(module=module)
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

  @wp.kernel(module=module)
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
      if tp.job_count == 0:
        continue  # nothing to place (a closed-form pair): no wait on its kind's counters
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

  @wp.kernel(module=mode_module(__name__, mode, "mpr"), cuda_max_registers=HEAVY_REGISTERS)
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
    mpr_options: MprSettings,
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
    depth (0: none) and the normal, for hfield_contacts (a box's or a mesh's prisms: hfield_ccd)."""
    tid = wp.tid()
    for i in range(tid, wp.min(hfield_count_in[COUNT_JOBS], hfield_job_in.shape[0]), nthread):
      j = order_in[i]
      job = hfield_job_in[j]
      tp = hfield_pair_in[job[0]]
      worldid = pair_worldid_in[tp.cid]
      _, b, hf = terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, pair_in[tp.cid],
                               worldid)
      if uses_ccd(b, job[1]):
        continue  # hfield_ccd's
      hfield = heightfield(hfield_size, hfield_nrow, hfield_ncol, hfield_adr, hfield_data, hf)
      answer, normal = _job_mpr(hfield, b, ms, tp, job[1], mpr_options)
      answer_out[j] = answer
      normal_out[j] = normal

  @wp.kernel(module=mode_module(__name__, mode, "ccd"), cuda_max_registers=HEAVY_REGISTERS)
  def hfield_ccd(
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
    pair_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    hfield_count_in: wp.array(dtype=int),
    hfield_pair_in: wp.array(dtype=TerrainPair),
    hfield_job_in: wp.array(dtype=wp.vec2i),
    kind_end_in: wp.array(dtype=int),
    order_in: wp.array(dtype=int),
    beyond_job_in: wp.array(dtype=wp.vec2i),
    ccd_in: PrismCcd,
    nthread: int,
    # Out:
    overflow_out: wp.array(dtype=int),
    answer_out: wp.array(dtype=wp.vec4),
    normal_out: wp.array(dtype=wp.vec3),
    beyond_answer_out: wp.array(dtype=wp.vec4),
    beyond_normal_out: wp.array(dtype=wp.vec3),
  ):
    """The prisms of boxes and meshes by GJK/EPA (job_ccd): the queued ones of those two kinds in
    hfield_order's order, then those of the beyond queue, one thread a job, each thread on its own
    row of EPA memory (nthread rows). One call of job_ccd: each call site is a copy of GJK/EPA."""
    tid = wp.tid()
    box = kind_end_in[2 * int(GeomType.BOX)] - kind_end_in[2 * int(GeomType.BOX) - 1]  # prisms queued
    queued = box + kind_end_in[2 * int(GeomType.MESH)] - kind_end_in[2 * int(GeomType.MESH) - 1]
    for i in range(tid, queued + wp.min(hfield_count_in[COUNT_BEYOND], beyond_job_in.shape[0]), nthread):
      j = i - queued  # a place in the beyond queue, or in the MPR queue:
      if i < box:
        j = order_in[kind_end_in[2 * int(GeomType.BOX) - 1] + i]
      elif i < queued:
        j = order_in[kind_end_in[2 * int(GeomType.MESH) - 1] + i - box]
      job = wp.vec2i()
      if i < queued:
        job = hfield_job_in[j]
      else:
        job = beyond_job_in[j]
      tp = hfield_pair_in[job[0]]
      worldid = pair_worldid_in[tp.cid]
      geoms = pair_in[tp.cid]
      hf = geom_dataid[worldid % geom_dataid.shape[0], geoms[0]]
      bgeom = ccd_geom(ccd_in, geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, geoms, worldid)
      hfield = heightfield(hfield_size, hfield_nrow, hfield_ncol, hfield_adr, hfield_data, hf)
      answer, normal = job_ccd(hfield, bgeom, geom_type[geoms[1]], tp, job[1], ccd_in, tid, worldid, overflow_out)
      if i < queued:
        answer_out[j] = answer
        normal_out[j] = normal
      else:
        beyond_answer_out[j] = answer
        beyond_normal_out[j] = normal

  return SimpleNamespace(jobs=hfield_jobs, kind_start=hfield_kind_start, order=hfield_order, mpr=hfield_mpr,
                         ccd=hfield_ccd)


@functools.lru_cache(maxsize=None)
def contacts_kernel(mode: int) -> wp.Kernel:
  """hfield_contacts for support mode ``mode``, in a module of its own, without GJK/EPA (whose code
  would double the module's build time at first use): a box's or a mesh's prisms beyond the MPR
  queue take hfield_ccd's answers from the beyond queue."""
  window = window_funcs(mode)
  _cell_jobs = window._cell_jobs
  _job_mpr = window._job_mpr
  _plane_pass = window._plane_pass

  @wp.kernel(module=mode_module(__name__, mode, "contacts"))
  def hfield_contacts(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    hfield_size: wp.array(dtype=wp.vec4),
    hfield_nrow: wp.array(dtype=int),
    hfield_ncol: wp.array(dtype=int),
    hfield_adr: wp.array(dtype=int),
    hfield_data: wp.array(dtype=float),
    opt_warn_hfield: int,
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    mpr_options: MprSettings,
    max_contacts: int,
    mc_tolerance: float,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    hfield_pair_in: wp.array(dtype=TerrainPair),
    hfield_job_in: wp.array(dtype=wp.vec2i),
    answer_in: wp.array(dtype=wp.vec4),
    normal_in: wp.array(dtype=wp.vec3),
    beyond_answer_in: wp.array(dtype=wp.vec4),
    beyond_normal_in: wp.array(dtype=wp.vec3),
    nthread: int,
    quota: ContactQuota,
    # Data out:
    overflow_out: wp.array(dtype=int),
    # Out:
    hfield_count_out: wp.array(dtype=int),
    # Data out:
    contacts_out: ContactRows,
  ):
    """One thread a pair of hfield_jobs, except those hfield_closed_form answers: the face
    contacts and its MPR answers in job order (running those the queue had no room for), merged
    (candidates.py) and written (heightfield first, as MuJoCo orders the pair)."""
    tid = wp.tid()
    for slot in range(tid, wp.min(hfield_count_out[COUNT_PAIRS], hfield_pair_in.shape[0]), nthread):
      tp = hfield_pair_in[slot]
      cid = tp.cid
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      if tp.cut:
        wp.atomic_or(overflow_out, worldid, int(OverflowType.HFIELD))
        if opt_warn_hfield:
          wp.printf("mjx_supportfield: heightfield overflow - geom %d covers more than %d cells in world %d; only the "
                    "cells around its centre are used\n", geoms[1], MAX_CELLS, worldid)
      if tp.closed_form == 1:
        continue  # hfield_closed_form's
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      terrain, b, hf = terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms, worldid)
      hfield = heightfield(hfield_size, hfield_nrow, hfield_ncol, hfield_adr, hfield_data, hf)
      spacing = mc_tolerance * 2.0 * wp.length(geom_aabb[worldid % geom_aabb.shape[0], geoms[1], 1])
      cands = empty_with_room(NCANDIDATE)  # a face on rough terrain rests on many prisms (uses_ccd)
      _plane_pass(cands, hfield, b, ms, tp, spacing)
      for j in range(tp.job_start, tp.job_start + tp.job_count):
        add_job_answer(hfield, tp, b, cands, hfield_job_in[j][1], answer_in[j], normal_in[j], spacing,
                       mpr_options.tolerance)
      # the jobs the queue had no room for, in order after the queued ones
      code = int(0)
      if tp.job_count > 0:
        code = hfield_job_in[tp.job_start + tp.job_count - 1][1] + 1
      left = tp.job_total - tp.job_count
      beyond = int(0)  # the pair's prisms met so far that hfield_ccd ran from the beyond queue
      ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
      while left > 0 and code < ncell * NJOB:
        cell = code // NJOB
        mask = _cell_jobs(hfield, b, ms, tp, cell)
        mask = (mask >> (code % NJOB)) << (code % NJOB)  # the cell's jobs from code on
        job = int(0)
        while mask != 0:
          if (mask & 1) == 1:
            answer, normal = wp.vec4(), wp.vec3()
            mpr = bool(True)
            if uses_ccd(b, cell * NJOB + job):
              if beyond < tp.beyond_count:
                answer = beyond_answer_in[tp.beyond_start + beyond]
                normal = beyond_normal_in[tp.beyond_start + beyond]
                mpr = False
              else:  # the beyond queue was full too
                wp.atomic_add(hfield_count_out, COUNT_CCD_AS_MPR, 1)
              beyond += 1
            if mpr:  # one call: each call site is a copy of MPR
              answer, normal = _job_mpr(hfield, b, ms, tp, cell * NJOB + job, mpr_options)
            add_job_answer(hfield, tp, b, cands, cell * NJOB + job, answer, normal, spacing, mpr_options.tolerance)
            left -= 1
          mask = mask >> 1
          job += 1
        code = (cell + 1) * NJOB
      if max_contacts > 1:
        cands.keep = tp.band  # the penetrating ones (depths include the band)
      write_candidates(
        cands, max_contacts, terrain.rot, terrain.pos, tp.band, naconmax_in, margin, gap, condim, friction, solref,
        solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
      )

  return hfield_contacts


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

  count: wp.array  # heightfield pairs, MPRs, those beyond the queue, per kind, prisms beyond it, ... (COUNT_*)
  pair: wp.array  # (pairs) TerrainPair
  job: wp.array  # (MPRs) the MPR queue: (index into pair, cell * NJOB + job)
  kind_next: wp.array  # (NKIND) next place of each kind of job in order
  order: wp.array  # (MPRs) the queue's jobs grouped by kind, the order hfield_mpr runs them in
  answer: wp.array  # (MPRs) each MPR's point and depth
  normal: wp.array  # (MPRs) and normal
  beyond_job: wp.array  # (CCD_BEYOND, 1 without GJK/EPA) the beyond queue: box and mesh prisms beyond the MPR queue
  beyond_answer: wp.array  # their point and depth (hfield_ccd's)
  beyond_normal: wp.array  # and normal
  ccd_rows: int  # rows of EPA memory (PrismCcd): hfield_ccd's threads (1 without GJK/EPA)
  epa: tuple  # (vert, vert_index, face, face_pr, face_norm2, horizon), ccd_rows rows each





# of the spheres' and capsules' pairs with a heightfield (closed-form within the grid, MPR only
# where they reach past its outer edge: a foot at a seam between tiles), one in this many counts
# toward the MPR queue's room
ROUND_PAIRS_PER_JOB_PAIR = 8


def job_pairs(other_pairs: int, round_pairs: int, max_pairs: int) -> int:
  """How many of a world's heightfield pairs its room in the MPR queue is counted in
  (``hfield_mprs_per_pair`` each), at most ``max_pairs``: those of geoms other than spheres and
  capsules, and one in ROUND_PAIRS_PER_JOB_PAIR of the spheres' and capsules' (``round_pairs``)."""
  return min(other_pairs + -(-round_pairs // ROUND_PAIRS_PER_JOB_PAIR), max_pairs)


class Heightfield:
  """The heightfield stage: what install found of the model's terrain pairs, the per-Data buffers,
  and the step's launches (the stage contract: docs/architecture.md)."""

  def __init__(self, options: Options, support_mode: SupportMode, mesh_support: MeshSupport, has_pairs: bool,
               pairs_per_world: int, job_pairs_per_world: int, ccd: bool, closed_form: bool, ccd_iterations: int):
    self.options, self.support_mode, self.mesh_support = options, support_mode, mesh_support
    self.has_pairs = has_pairs  # a heightfield - convex pair in the model
    self.pairs_per_world = pairs_per_world  # bounds the stage's pair slots
    self.job_pairs_per_world = job_pairs_per_world  # the MPR queue's room is hfield_mprs_per_pair times these (job_pairs)
    self.ccd = ccd  # boxes or meshes on a heightfield: their prisms by GJK/EPA (hfield_ccd)
    self.closed_form = closed_form  # spheres or capsules on a heightfield: hfield_closed_form
    self.ccd_iterations = ccd_iterations  # MuJoCo C's ccd_iterations, for GJK and EPA

  def make_buffers(self, d, st) -> Buffers:
    """The stage's buffers for Data ``d``."""
    nworld = d.nworld
    npair = max(1, nworld * self.pairs_per_world)
    nmpr = max(1, nworld * self.job_pairs_per_world * self.options.hfield_mprs_per_pair)
    rows = min(max(nmpr, npair), CCD_THREADS) if self.has_pairs and self.ccd else 1
    nbeyond = CCD_BEYOND if self.has_pairs and self.ccd else 1
    # sized as MuJoCo Warp's collision_convex sizes its EPA memory
    nvert = 10 + 2 * self.ccd_iterations
    nface = 6 + MJ_MAX_EPAFACES * self.ccd_iterations
    return Buffers(
      ccd_rows=rows,
      epa=(wp.empty((rows, nvert), dtype=wp.vec3), wp.empty((rows, nvert), dtype=int),
           wp.empty((rows, nface), dtype=int), wp.empty((rows, nface), dtype=wp.vec3),
           wp.empty((rows, nface), dtype=float), wp.empty((rows, MJ_MAX_EPAHORIZON), dtype=int)),
      count=wp.zeros(COUNT_CCD_AS_MPR + 1, dtype=int),
      kind_next=wp.zeros(NKIND, dtype=int),
      order=wp.zeros(nmpr, dtype=int),
      pair=wp.zeros(npair, dtype=TerrainPair),
      job=wp.zeros(nmpr, dtype=wp.vec2i),
      answer=wp.zeros(nmpr, dtype=wp.vec4),
      normal=wp.zeros(nmpr, dtype=wp.vec3),
      beyond_job=wp.zeros(nbeyond, dtype=wp.vec2i),
      beyond_answer=wp.zeros(nbeyond, dtype=wp.vec4),
      beyond_normal=wp.zeros(nbeyond, dtype=wp.vec3),
    )

  def prism_ccd(self, m, b: Buffers) -> PrismCcd:
    """The model's meshes, MuJoCo's GJK/EPA options (MuJoCo C's ccd_iterations for GJK and EPA, as
    MuJoCo Warp's heightfield kernel runs them) and the EPA memory of ``b``, for the kernels."""
    ccd_in = PrismCcd()
    for field in ("vertadr", "vertnum", "graphadr", "vert", "graph", "polynum", "polyadr", "polynormal", "polyvertadr",
                  "polyvertnum", "polyvert", "polymapadr", "polymapnum", "polymap"):
      setattr(ccd_in, "mesh_" + field, getattr(m, "mesh_" + field))
    ccd_in.tolerance = m.opt.ccd_tolerance
    ccd_in.iterations = self.ccd_iterations
    ccd_in.epa_iterations = self.ccd_iterations
    ccd_in.vert, ccd_in.vert_index, ccd_in.face, ccd_in.face_pr, ccd_in.face_norm2, ccd_in.horizon = b.epa
    return ccd_in

  def launch(self, m, d, st) -> None:
    """Heightfield - convex pairs of one step: windows and MPR queue, the queue grouped by kind,
    the queued MPRs, then the contacts."""
    pairs, b, quota = st.broad, st.hfield, st.quota.quota
    if not self.has_pairs:
      return
    opt = self.options
    nthread = max(1, min(pairs.capacity, GRID_THREADS))
    kernels = stage_kernels(self.support_mode)
    warn = int(bool(int(m.opt.warn_overflow) & int(OverflowType.HFIELD)))
    hfield = [m.hfield_size, m.hfield_nrow, m.hfield_ncol, m.hfield_adr, m.hfield_data]
    wp.launch(
      kernels.jobs,
      dim=nthread,
      inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_margin, m.geom_gap] + hfield
      + [m.pair_margin, m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support, pairs.npair, pairs.pair,
         pairs.pairid, pairs.pair_worldid, 2, nthread],
      outputs=[d.overflow, b.count, b.pair, b.job, b.beyond_job],
    )
    nthread_pair = max(1, min(b.pair.shape[0], GRID_THREADS))
    wp.launch(kernels.kind_start, dim=1, inputs=[b.count], outputs=[b.kind_next])
    wp.launch(
      kernels.order,
      dim=nthread_pair,
      inputs=[m.geom_type, pairs.pair, b.count, b.pair, b.job, nthread_pair],
      outputs=[b.kind_next, b.order],
    )
    ccd_in = self.prism_ccd(m, b)
    nthread_mpr = max(1, min(b.job.shape[0], GRID_THREADS))
    wp.launch(
      kernels.mpr,
      dim=nthread_mpr,
      inputs=[m.geom_type, m.geom_dataid, m.geom_size] + hfield
      + [d.geom_xpos, d.geom_xmat, self.mesh_support, settings_of(opt), pairs.pair, pairs.pair_worldid, b.count,
         b.pair, b.job, b.order, nthread_mpr],
      outputs=[b.answer, b.normal],
    )
    if self.ccd:
      wp.launch(
        kernels.ccd,
        dim=b.ccd_rows,
        inputs=[m.geom_type, m.geom_dataid, m.geom_size] + hfield
        + [d.geom_xpos, d.geom_xmat, pairs.pair, pairs.pair_worldid, b.count, b.pair, b.job, b.kind_next, b.order,
           b.beyond_job, ccd_in, b.ccd_rows],
        outputs=[d.overflow, b.answer, b.normal, b.beyond_answer, b.beyond_normal],
      )
    wp.launch(
      contacts_kernel(self.support_mode),
      dim=nthread_pair,
      inputs=[
        m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_aabb] + hfield + [
        warn, d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support, settings_of(opt),
        opt.max_contacts_per_pair, opt.mc_tolerance, pairs.pair, pairs.pairid, pairs.pair_worldid, b.pair, b.job,
        b.answer, b.normal, b.beyond_answer, b.beyond_normal, nthread_pair, quota,
      ],
      outputs=[d.overflow, b.count] + contact_outputs(d),
    )
    if self.closed_form:
      wp.launch(
        hfield_closed_form,
        dim=nthread_pair,
        inputs=[
          m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_aabb] + hfield + [
          d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support, opt.max_contacts_per_pair,
          opt.mc_tolerance, pairs.pair, pairs.pairid, pairs.pair_worldid, b.count, b.pair, nthread_pair, quota,
        ],
        outputs=contact_outputs(d),
      )
