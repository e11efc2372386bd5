"""The heightfield stage's per-pair terrain window and its jobs (device functions).

Each convex geom over a heightfield gets a window of grid cells under its extent
(``TerrainPair``, ``_window``); each cell gives jobs: its two triangle prisms and the terrain
features inside the geom (``_cell_jobs``), run by MPR (``_job_mpr``) or, for boxes and meshes,
MuJoCo Warp's GJK/EPA on the prism (``job_ccd``, rows of EPA memory in ``PrismCcd``); the plane
pass (``_plane_pass``) gives the geom's points under each triangle's plane. The functions that
ask support queries are built for one support mode by ``window_funcs``. heightfield.py's kernels
call these and own the launches and buffers; hfield_cells.py has the cells' geometry and the
``Heightfield`` struct they read a heightfield through.
"""

import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.collision_core import Geom
from mujoco_warp._src.collision_core import geom_collision_pair
from mujoco_warp._src.collision_gjk import ccd
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.box_prism import box_axes_part
from mjx_supportfield.geometry.box_prism import box_prism_contact
from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import MprSettings
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.geometry.sdf import primitive_sdf
from mjx_supportfield.geometry.shapes import posed_shape
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.stages.candidates import Candidates
from mjx_supportfield.stages.candidates import add_tagged
from mjx_supportfield.stages.candidates import TAG_DEEPEST
from mjx_supportfield.stages.candidates import TAG_PRISM
from mjx_supportfield.stages.candidates import TAG_VERTEX
from mjx_supportfield.stages.candidates import triangle_tag
from mjx_supportfield.stages.hfield_cells import Heightfield
from mjx_supportfield.stages.hfield_cells import capsule_end
from mjx_supportfield.stages.hfield_cells import cell_corners
from mjx_supportfield.stages.hfield_cells import cell_size
from mjx_supportfield.stages.hfield_cells import feature_point
from mjx_supportfield.stages.hfield_cells import fold_answer_kept
from mjx_supportfield.stages.hfield_cells import outside_walls_func
from mjx_supportfield.stages.hfield_cells import plane_depth
from mjx_supportfield.stages.hfield_cells import point_shape
from mjx_supportfield.stages.hfield_cells import prism_answer_kept
from mjx_supportfield.stages.hfield_cells import prism_geom
from mjx_supportfield.stages.hfield_cells import prism_shape
from mjx_supportfield.stages.hfield_cells import shape_point
from mjx_supportfield.stages.hfield_cells import shape_point_count
from mjx_supportfield.stages.hfield_cells import unit_axis
from mjx_supportfield.stages.routing import NGEOMTYPE
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import MODULE_OPTIONS


wp.set_module_options(MODULE_OPTIONS)

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
COUNT_BEYOND = COUNT_KIND + NKIND  # box and mesh prisms beyond the MPR queue (places asked for in the beyond queue)
COUNT_CCD_AS_MPR = COUNT_BEYOND + 1  # prisms that found the beyond queue full too and ran MPR instead
# rows of EPA memory (each a GJK/EPA run's scratch, about 5 kB at MuJoCo's default ccd_iterations):
# hfield_ccd's threads. GJK/EPA at its register cap fits 16 warps on a streaming multiprocessor:
# 65536 threads fill a GPU of over a hundred of them once (8192 left three quarters of each idle,
# each thread running dozens of prisms one after another), for about 330 MB
CCD_THREADS = 65536
# places in the beyond queue: box and mesh prisms that find the MPR queue full go there, for
# hfield_ccd, so that hfield_contacts runs no GJK/EPA (whose code would double its build time at
# first use); 36 bytes each, however small Options.hfield_mprs_per_pair makes the MPR queue
CCD_BEYOND = 65536


@wp.struct
class PrismCcd:
  """What MuJoCo Warp's GJK/EPA (collision_gjk.ccd) needs to collide a terrain prism with a box
  or a mesh as MuJoCo C does: the meshes, the solver's options, and EPA memory, one row a thread."""

  mesh_vertadr: wp.array(dtype=int)
  mesh_vertnum: wp.array(dtype=int)
  mesh_graphadr: wp.array(dtype=int)
  mesh_vert: wp.array(dtype=wp.vec3)
  mesh_graph: wp.array(dtype=int)
  mesh_polynum: wp.array(dtype=int)
  mesh_polyadr: wp.array(dtype=int)
  mesh_polynormal: wp.array(dtype=wp.vec3)
  mesh_polyvertadr: wp.array(dtype=int)
  mesh_polyvertnum: wp.array(dtype=int)
  mesh_polyvert: wp.array(dtype=int)
  mesh_polymapadr: wp.array(dtype=int)
  mesh_polymapnum: wp.array(dtype=int)
  mesh_polymap: wp.array(dtype=int)
  tolerance: wp.array(dtype=float)  # per world: m.opt.ccd_tolerance
  iterations: int
  epa_iterations: int
  vert: wp.array2d(dtype=wp.vec3)
  vert_index: wp.array2d(dtype=int)
  face: wp.array2d(dtype=int)
  face_pr: wp.array2d(dtype=wp.vec3)
  face_norm2: wp.array2d(dtype=float)
  horizon: wp.array2d(dtype=int)


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
  beyond_start: int  # a box's or a mesh's prisms beyond the MPR queue: the first beyond_count of them,
  beyond_count: int  # in order, are places beyond_start ... of the beyond queue (hfield_ccd runs them)
  closed_form: int  # 1: a sphere or a capsule within the grid, hfield_closed_form's (no MPR job)


@wp.func
def terrain_pair(
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
def window_cell(tp: TerrainPair, cell: int) -> tuple[int, int]:
  """Grid row and column of the window's cell number ``cell`` (numbered along its rows)."""
  ncols = tp.window[3] - tp.window[2] + 1
  return tp.window[0] + cell // ncols, tp.window[2] + cell % ncols


@wp.func
def above_cell(tp: TerrainPair, p00: wp.vec3, p01: wp.vec3, p10: wp.vec3, p11: wp.vec3) -> bool:
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
def _job_shape(hfield: Heightfield, b: Shape, tp: TerrainPair, code: int) -> Shape:
  """The terrain part of MPR job ``code`` (cell * NJOB + job): a triangle's prism or a point."""
  dx, dy = cell_size(hfield)
  eps = 1.0e-6 * (dx + dy + hfield.size[2])
  job = code % NJOB
  r, c = window_cell(tp, code // NJOB)
  p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
  if job >= 2:
    q, convex = feature_point(hfield, dx, dy, r, c, tp.window[1], tp.window[3], job, p00, p01,
                          p10, p11, b.center, eps, False)
    return point_shape(q, tp.band)
  return prism_shape(p00, wp.where(job == 0, p10, p11), wp.where(job == 0, p11, p01), -hfield.size[3], tp.band)


@wp.func
def uses_ccd(b: Shape, code: int) -> bool:
  """Whether job ``code`` is a prism against a box or a mesh: those run MuJoCo Warp's GJK/EPA, as
  MuJoCo C collides each prism. A face of such a geom lying on rough terrain overlaps many prisms,
  and C's one contact per prism lies where its EPA ends, spread over the face: MPR's answer (the
  deepest terrain point, often one grid vertex shared by the prisms around it) leaves those
  places without a contact."""
  return code % NJOB < 2 and (b.gtype == GeomType.BOX or b.gtype == GeomType.MESH)


@wp.func
def ccd_geom(ccd_in: PrismCcd, geom_type: wp.array(dtype=int), geom_dataid: wp.array2d(dtype=int),
              geom_size: wp.array2d(dtype=wp.vec3), geom_xpos_in: wp.array2d(dtype=wp.vec3),
              geom_xmat_in: wp.array2d(dtype=wp.mat33), geoms: wp.vec2i, worldid: int) -> Geom:
  """Geom B of the pair as MuJoCo Warp's GJK/EPA takes it, posed in the terrain's frame."""
  _, g = geom_collision_pair(
    geom_type, geom_dataid, geom_size, ccd_in.mesh_vertadr, ccd_in.mesh_vertnum, ccd_in.mesh_graphadr,
    ccd_in.mesh_vert, ccd_in.mesh_graph, ccd_in.mesh_polynum, ccd_in.mesh_polyadr, ccd_in.mesh_polynormal,
    ccd_in.mesh_polyvertadr, ccd_in.mesh_polyvertnum, ccd_in.mesh_polyvert, ccd_in.mesh_polymapadr,
    ccd_in.mesh_polymapnum, ccd_in.mesh_polymap, geom_xpos_in, geom_xmat_in, geoms, worldid,
  )
  rt = wp.transpose(geom_xmat_in[worldid, geoms[0]])
  g.pos = rt @ (g.pos - geom_xpos_in[worldid, geoms[0]])
  g.rot = rt @ g.rot
  return g


# how much deeper than a box's exact penetration of a prism (times the pair's length scale) a
# GJK/EPA answer may be (float32 rounding) before the exact answer replaces it (_box_prism_answer)
EXACT_SLACK = 1.0e-4
# how close (times the same scale) two corners' depths along the exact normal must be to count as
# one feature of the box or the prism (a face, an edge) for the exact answer's point
EXACT_FEATURE = 1.0e-5


@wp.func
def job_ccd(hfield: Heightfield, bgeom: Geom, btype: int, tp: TerrainPair, code: int, ccd_in: PrismCcd, row: int,
             worldid: int, overflow_out: wp.array(dtype=int)) -> tuple[wp.vec4, wp.vec3]:
  """Prism job ``code``'s answer by MuJoCo Warp's GJK/EPA on EPA memory ``row``, the prism built
  as collision_convex's heightfield kernel builds it (MuJoCo's vertex order, GJK started from its
  centre): the midpoint of the witness points and the depth with the band (0 when apart), and the
  normal from the terrain to B."""
  dx, dy = cell_size(hfield)
  r, c = window_cell(tp, code // NJOB)
  p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
  first = code % NJOB == 0  # MuJoCo's first triangle (p10, p00, p11), then (p00, p11, p01)
  prism = prism_geom(wp.where(first, p10, p00), wp.where(first, p00, p11), wp.where(first, p11, p01), -hfield.size[3])
  centre = wp.vec3(0.0)
  for i in range(6):
    centre += prism.polyvert[i]
  dist, ncontact, w1, w2, _ = ccd(
    ccd_in.tolerance[worldid % ccd_in.tolerance.shape[0]], tp.band, ccd_in.iterations, ccd_in.epa_iterations, prism,
    bgeom, int(GeomType.HFIELD), btype, centre / 6.0, bgeom.pos, ccd_in.vert[row], ccd_in.vert_index[row],
    ccd_in.face[row], ccd_in.face_pr[row], ccd_in.face_norm2[row], ccd_in.horizon[row], False, worldid, overflow_out,
  )
  direction = wp.where(dist < 0.0, w1 - w2, w2 - w1)  # w1 on the prism, w2 on B
  if ncontact == 0 or dist >= tp.band or wp.length(direction) == 0.0:
    return wp.vec4(0.0), wp.vec3(0.0)
  pos = 0.5 * (w1 + w2)
  return wp.vec4(pos[0], pos[1], pos[2], tp.band - dist), wp.normalize(direction)


@wp.func
def _box_prism_answer(hfield: Heightfield, b: Shape, tp: TerrainPair, job: int, p00: wp.vec3, p01: wp.vec3,
                      p10: wp.vec3, p11: wp.vec3, scale: float, answer: wp.vec4, normal: wp.vec3
                      ) -> tuple[wp.vec4, wp.vec3]:
  """A box prism's GJK/EPA answer, or the exact one (box_prism_contact) where GJK/EPA's cannot be
  right: none where the two penetrate, one deeper than their exact penetration, or a normal into
  the terrain. MuJoCo Warp's float32 GJK/EPA on a prism a box's face rests on is ill-conditioned
  (the last bits of the input move its answer by millimetres) and returns such answers, a normal
  straight up or down with a wrong depth among them. An answer only short of the exact depth is
  kept: MuJoCo C's EPA stops short on many of the same prisms, at the same places, and the exact
  answer there would move the contact off C's. ``scale``: the pair's length scale (_scale)."""
  exact, n = box_prism_contact(p00, wp.where(job == 0, p10, p11), wp.where(job == 0, p11, p01), -hfield.size[3], b,
                               EXACT_FEATURE * scale)
  if exact[3] <= 0.0:
    return answer, normal
  if answer[3] > tp.band and answer[3] - tp.band <= exact[3] + EXACT_SLACK * scale and normal[2] >= 0.0:
    return answer, normal
  return wp.vec4(exact[0], exact[1], exact[2], exact[3] + tp.band), n


@wp.func
def _through_border(hfield: Heightfield, r: int, c: int, normal: wp.vec3) -> bool:
  """Whether a prism's answer leaves through the heightfield's outer side wall (a cell of its
  first or last row or column, the normal within 60° of that wall's outward direction). The
  walls between cells lie inside the terrain and their answers are dropped; the outer walls
  bound it: a body sunk across the edge (a robot toppled off a tile) is pushed out through
  them, as MuJoCo C's prisms push it."""
  out_x = wp.where(c == 0, -1.0, wp.where(c == hfield.ncol - 2, 1.0, 0.0))
  out_y = wp.where(r == 0, -1.0, wp.where(r == hfield.nrow - 2, 1.0, 0.0))
  return out_x * normal[0] >= 0.5 or out_y * normal[1] >= 0.5


@wp.func
def _tag(hfield: Heightfield, b: Shape, r: int, c: int, t: int, source: int) -> int:
  """Candidates.tag of B's candidate of triangle t of cell (r, c) from ``source``: a box's or a
  mesh's, whose prisms run GJK/EPA as MuJoCo C's do and which get one contact a triangle as C's
  get one a prism (a face on a triangle gives the triangle's contact, not one a corner); 0 for
  other geoms."""
  if uses_ccd(b, 0):
    return triangle_tag(2 * (r * (hfield.ncol - 1) + c) + t, source)
  return 0


@wp.func
def add_job_answer(hfield: Heightfield, tp: TerrainPair, b: Shape, cands: wp.ref[Candidates], code: int,
                    answer: wp.vec4, normal: wp.vec3, spacing: float, tol: float):
  """Adds MPR job ``code``'s answer (position, depth; depth 0 when it found nothing) to ``cands``
  (a box prism's GJK/EPA answer checked against the exact one, _box_prism_answer),
  unless it is a prism's answer through a side wall or one the face contacts
  already hold (prism_answer_kept), or a point's with a normal into the terrain or between
  two faces that hold B's contacts (fold_answer_kept)."""
  box_prism = code % NJOB < 2 and uses_ccd(b, code) and b.gtype == GeomType.BOX
  if answer[3] <= 0.0 and not box_prism:
    return
  dx, dy = cell_size(hfield)
  job = code % NJOB
  r, c = window_cell(tp, code // NJOB)
  p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
  scale = _scale(tp, dx, dy)
  if box_prism:
    answer, normal = _box_prism_answer(hfield, b, tp, job, p00, p01, p10, p11, scale, answer, normal)
    if answer[3] <= 0.0:
      return
  res = MprResult()
  res.hit = 1
  res.depth = answer[3]
  res.pos = wp.vec3(answer[0], answer[1], answer[2])
  res.normal = normal
  if job < 2:
    if not (_through_border(hfield, r, c, normal)
            or prism_answer_kept(cands, res, wp.where(job == 0, na, nb), p00, dx, dy, job, scale, tol,
                                 uses_ccd(b, code))):
      return
  elif wp.dot(normal, na + nb) <= 0.0:
    return  # B's surface normal must point away from the terrain
  elif not fold_answer_kept(hfield, dx, dy, r, c, job, p00, p01, p10, p11, normal,
                             1.0e-6 * (dx + dy + hfield.size[2])):
    return
  add_tagged(cands, res.pos, normal, res.depth, spacing, wp.where(job < 2, _tag(hfield, b, r, c, job, TAG_PRISM), 0))


@wp.func
def set_bits(mask: int) -> int:
  """How many bits of mask are set."""
  n = int(0)
  m = mask
  while m != 0:
    m = m & (m - 1)
    n += 1
  return n


@wp.func
def queue_cell(job_out: wp.array(dtype=wp.vec2i), slot: int, tp: TerrainPair, cell: int, mask: int, n: int) -> int:
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


@functools.lru_cache(maxsize=None)
def window_funcs(mode: int) -> SimpleNamespace:
  """The window's and the jobs' device functions on the support functions of support mode
  ``mode`` (support_funcs, mpr_funcs): ``_window``, ``_cell_jobs``, ``_job_mpr``, ``_queue_beyond``
  and ``_plane_pass``."""
  support_world = support_funcs(mode).support_world
  mpr_refined = mpr_funcs(mode).mpr_refined
  _outside_walls = outside_walls_func(mode)

  @wp.func
  def _window(b: Shape, ms: MeshSupport, band: float, hfield: Heightfield) -> TerrainPair:
    """The cells under B (its bounds grown by band), at most MAX_CELLS around its centre; an
    empty window (r0 > r1) when B is off the terrain or above or below it."""
    tp = TerrainPair()
    tp.band = band
    tp.cut = 0
    tp.job_total = 0
    tp.job_start = 0
    tp.job_count = 0
    tp.nprism = 0
    tp.beyond_start = 0
    tp.beyond_count = 0
    tp.closed_form = 0
    for k in range(3):
      tp.hi[k] = support_world(b, ms, unit_axis(k))[k] + band
      tp.lo[k] = support_world(b, ms, -unit_axis(k))[k] - band
    dx, dy = cell_size(hfield)
    c0 = wp.max(0, int(wp.floor((tp.lo[0] + hfield.size[0]) / dx)))
    c1 = wp.min(hfield.ncol - 2, int(wp.floor((tp.hi[0] + hfield.size[0]) / dx)))
    r0 = wp.max(0, int(wp.floor((tp.lo[1] + hfield.size[1]) / dy)))
    r1 = wp.min(hfield.nrow - 2, int(wp.floor((tp.hi[1] + hfield.size[1]) / dy)))
    if tp.lo[2] > hfield.size[2] or tp.hi[2] < -hfield.size[3]:
      r1 = r0 - 1
    if c0 <= c1 and r0 <= r1 and (c1 - c0 + 1) * (r1 - r0 + 1) > MAX_CELLS:
      tp.cut = 1
      half = wp.static(int(MAX_CELLS**0.5) // 2)
      cc = int(wp.floor((b.center[0] + hfield.size[0]) / dx))
      rc = int(wp.floor((b.center[1] + hfield.size[1]) / dy))
      c0 = wp.max(c0, cc - half)
      c1 = wp.min(c1, cc + half - 1)
      r0 = wp.max(r0, rc - half)
      r1 = wp.min(r1, rc + half - 1)
    tp.window = wp.vec4i(r0, r1, c0, c1)
    return tp

  @wp.func
  def _cell_jobs(hfield: Heightfield, b: Shape, ms: MeshSupport, tp: TerrainPair, cell: int) -> int:
    """The MPR jobs of a window cell that pass the cheap tests, as a bit mask over its NJOB jobs:
    0, 1 the prisms of its two triangles, 2 + 3 k + end feature k's points (feature_point)."""
    dx, dy = cell_size(hfield)
    eps = 1.0e-6 * (dx + dy + hfield.size[2])
    band = tp.band
    r, c = window_cell(tp, cell)
    p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
    if above_cell(tp, p00, p01, p10, p11):
      return 0
    # B's deepest point under each triangle's plane: where B stays above a plane (by more than the
    # band), that triangle, its prism and the terrain features on it touch nothing
    below_a = wp.dot(na, p00 - support_world(b, ms, -na)) + band > 0.0
    below_b = wp.dot(nb, p00 - support_world(b, ms, -nb)) + band > 0.0
    mask = int(0)
    job = int(0)
    while job < NJOB and (below_a or below_b):
      wanted = bool(False)
      if (job == 0 and below_a) or (job == 1 and below_b):
        v1 = wp.where(job == 0, p10, p11)
        v2 = wp.where(job == 0, p11, p01)
        wanted = not _outside_walls(b, ms, p00, v1, v2, band, 3)
        if wanted and b.gtype == GeomType.BOX:  # most of a box's remaining prisms are apart (box_prism.py)
          wanted = not box_axes_part(p00, v1, v2, -hfield.size[3], b, band)
      elif job >= 2:
        k = (job - 2) // 3
        on_a = k == 0 or k == 2 or k == 3 or k == 5 or k == 7 or k == 8  # see _feature
        on_b = k == 0 or k == 1 or k == 3 or k == 4 or k == 6 or k == 8
        if (below_a or not on_a) and (below_b or not on_b):
          q, wanted = feature_point(hfield, dx, dy, r, c, tp.window[1], tp.window[3], job,
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
            wanted = wp.dot(q - support_world(b, ms, out), out) <= band
          if wanted and b.gtype == GeomType.BOX:  # a point's MPR on a box finds what its distance says
            wanted = primitive_sdf(GeomType.BOX, b.size, wp.transpose(b.rot) @ (q - b.pos)) <= band
      if wanted:
        mask = mask | (1 << job)
      job += 1
    return mask

  @wp.func
  def _job_mpr(hfield: Heightfield, b: Shape, ms: MeshSupport, tp: TerrainPair, code: int,
               mpr_options: MprSettings) -> tuple[wp.vec4, wp.vec3]:
    """MPR job ``code``'s answer: the contact point and depth (0 when it found none), and the normal."""
    a = _job_shape(hfield, b, tp, code)
    dx, dy = cell_size(hfield)
    scale = _scale(tp, dx, dy)
    res = mpr_refined(a, b, ms, scale, mpr_options.tolerance, mpr_options.iterations, mpr_options.refine,
                      RESTART_BEHIND)
    depth = wp.where(res.hit != 0 and res.depth > 0.0, res.depth, 0.0)
    pos = res.pos
    if code % NJOB >= 2:
      # a terrain point's contact lies on the normal through the point, its witness on the terrain:
      # MPR's point slides along a tie of B's (a capsule lying across the point), as far as B's
      # centre, cells away and off the terrain's surface
      pos = a.pos + wp.dot(res.pos - a.pos, res.normal) * res.normal
    return wp.vec4(pos[0], pos[1], pos[2], depth), res.normal

  @wp.func
  def _queue_beyond(hfield: Heightfield, b: Shape, ms: MeshSupport, tp: TerrainPair, slot: int,
                    job_in: wp.array(dtype=wp.vec2i), beyond_out: wp.array(dtype=wp.vec2i)):
    """Queues the first tp.beyond_count prisms of the pair (in slot) beyond the MPR queue, in order,
    as places tp.beyond_start ... of the beyond queue: the prisms hfield_contacts meets, in the same
    order, when it walks the jobs the MPR queue had no room for."""
    code = int(0)  # after the pair's last queued job (the queue holds its first job_count jobs, in order)
    if tp.job_count > 0:
      code = job_in[tp.job_start + tp.job_count - 1][1] + 1
    ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
    k = int(0)
    while k < tp.beyond_count and code < ncell * NJOB:
      cell = code // NJOB
      mask = _cell_jobs(hfield, b, ms, tp, cell)
      mask = (mask >> (code % NJOB)) << (code % NJOB)  # the cell's jobs from code on
      for job in range(2):  # its prisms
        if ((mask >> job) & 1) == 1 and k < tp.beyond_count:
          beyond_out[tp.beyond_start + k] = wp.vec2i(slot, cell * NJOB + job)
          k += 1
      code = (cell + 1) * NJOB

  @wp.func
  def _plane_pass(cands: wp.ref[Candidates], hfield: Heightfield, b: Shape, ms: MeshSupport, tp: TerrainPair,
                  spacing: float):
    """Adds to ``cands`` the face contacts: B's corners against the triangle under each, then each
    cell's triangles against B's deepest points (and a capsule's ends)."""
    band = tp.band
    r0 = tp.window[0]
    r1 = tp.window[1]
    c0 = tp.window[2]
    c1 = tp.window[3]
    dx, dy = cell_size(hfield)
    ncell = (r1 - r0 + 1) * (c1 - c0 + 1)
    ncorner = shape_point_count(b, ms)
    nlow = wp.where(b.gtype == GeomType.CAPSULE, 3, 1)  # plane jobs a triangle: B's deepest point, a capsule's ends
    for item in range(ncorner + ncell):
      corner = wp.vec3(0.0)
      r, c = window_cell(tp, item - ncorner)
      if item < ncorner:
        corner = shape_point(b, ms, item)
        c = int(wp.floor((corner[0] + hfield.size[0]) / dx))
        r = int(wp.floor((corner[1] + hfield.size[1]) / dy))
        if c < c0 or c > c1 or r < r0 or r > r1:
          continue
      p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
      if above_cell(tp, p00, p01, p10, p11):
        continue
      njob = wp.where(item < ncorner, 1, 2 * nlow)
      for job in range(njob):
        t = job // nlow  # the triangle: (p00, p10, p11) or (p00, p11, p01)
        p = corner
        if item < ncorner:
          t = wp.where((corner[1] - p00[1]) / dy >= (corner[0] - p00[0]) / dx, 0, 1)  # above the diagonal: the first
        n = wp.where(t == 0, na, nb)
        if item >= ncorner and job % nlow == 0:
          p = support_world(b, ms, -n)
        elif item >= ncorner:
          p = capsule_end(b, job % nlow - 1, n)
        depth = plane_depth(p, p00, wp.where(t == 0, p10, p11), wp.where(t == 0, p11, p01), n, band)
        if depth > 0.0:
          tag = _tag(hfield, b, r, c, t, wp.where(item < ncorner, TAG_VERTEX, TAG_DEEPEST))
          add_tagged(cands, p + 0.5 * depth * n, n, depth, spacing, tag)

  return SimpleNamespace(_window=_window, _cell_jobs=_cell_jobs, _job_mpr=_job_mpr, _queue_beyond=_queue_beyond,
                         _plane_pass=_plane_pass)
