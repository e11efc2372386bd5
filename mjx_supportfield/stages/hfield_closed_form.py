"""The heightfield stage's closed-form pass: spheres and capsules against terrain, with no MPR.

A leg's feet and shins are spheres and capsules (mjlab's Go1 and G1): against a terrain triangle
each has an exact answer, the ball's (a sphere, or a point of a capsule's axis) against the
triangle's point nearest to it. MuJoCo gives one contact a triangle prism; this pass gives one a
triangle the same way (less the prism's side walls, which lie inside the terrain), plus a
capsule's own ends over the triangle:

- inside the triangle, along its normal;
- on an edge or a corner of a ridge or a fold, from that point toward the ball;
- on an edge or a corner lying flat (the next triangle in the same plane), along the normal, as
  deep as the ball reaches below the plane there: MuJoCo's prism beside the one under a ball
  answers there too, but tilted toward the edge, which pushes a ball lying on a plane sideways.

A capsule's point for a triangle: where the part of its axis over the triangle (seen along z)
reaches the triangle's plane, the contact is the least overlap of the capsule and the triangle's
prism, along the normal or across one of the triangle's edges (_sunk_part), at that part's end
nearest the plane (the middle where the axis lies parallel to it) or at the axis point nearest
the edge; else the point of the whole axis nearest the triangle, tried from the part's point
nearest the plane first (so that a capsule lying parallel to a plane keeps a point over each
triangle): on a slope the axis point nearest a triangle can lie past its edge seen along z, and a
ridge or a steep triangle beside the capsule has no part under it at all.

One kernel, ``hfield_closed_form``, one thread a pair of hfield_jobs' list (which marks the pairs
by ``closed_form``), in a module of its own: the stage's other kernels (MPR, GJK/EPA) take
minutes to build, and this one is small. A pair reaching past the heightfield's outer edge keeps
the MPR path, whose prisms see the outer side walls. heightfield.py launches it; the pair list
and the window are hfield_window.py's.
"""

import warp as wp
from mujoco_warp._src.math import closest_segment_to_segment_points
from mujoco_warp._src.types import GeomType

from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.grid import HEAVY_REGISTERS
from mjx_supportfield.stages.candidates import NCANDIDATE
from mjx_supportfield.stages.candidates import Candidates
from mjx_supportfield.stages.candidates import add_candidate
from mjx_supportfield.stages.candidates import empty_with_room
from mjx_supportfield.stages.candidates import write_candidates
from mjx_supportfield.stages.hfield_cells import Heightfield
from mjx_supportfield.stages.hfield_cells import cell_corners
from mjx_supportfield.stages.hfield_cells import cell_size
from mjx_supportfield.stages.hfield_cells import grid_vertex
from mjx_supportfield.stages.hfield_cells import heightfield
from mjx_supportfield.stages.hfield_window import COUNT_PAIRS
from mjx_supportfield.stages.hfield_window import TerrainPair
from mjx_supportfield.stages.hfield_window import above_cell
from mjx_supportfield.stages.hfield_window import terrain_pair
from mjx_supportfield.stages.hfield_window import window_cell
from mjx_supportfield.types import FAR
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# where on a triangle its nearest point to a point lies (_closest_on_triangle): inside, on edge
# k = 0 (v0 v1), 1 (v1 v2), 2 (v2 v0), or at corner k (between edges k - 1 and k)
ON_FACE = wp.constant(0)
ON_EDGE = wp.constant(1)
ON_CORNER = wp.constant(2)
# a capsule's points a triangle (_ball_for): the part's point, then the capsule's two ends
NBALL = 3
# a capsule's part and the triangle are nearest in one of: a given point, the part's two ends, or
# the part against one of the triangle's three edges (_nearest_pair)
NPAIR = 6


@wp.func
def closed_form(b: Shape, tp: TerrainPair, size: wp.vec4) -> bool:
  """Whether the pair takes the closed-form pass instead of the plane pass and MPR jobs: B is a
  sphere or a capsule and stays within the heightfield's outer edge (``size``: its x and y
  radii)."""
  if b.gtype != GeomType.SPHERE and b.gtype != GeomType.CAPSULE:
    return False
  return tp.lo[0] > -size[0] and tp.hi[0] < size[0] and tp.lo[1] > -size[1] and tp.hi[1] < size[1]


@wp.func
def _closest_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> tuple[wp.vec3, wp.vec2i]:
  """The point of triangle abc nearest to p and where it lies: (ON_FACE, 0), (ON_EDGE, edge) or
  (ON_CORNER, corner), by the triangle's Voronoi regions (Ericson, Real-Time Collision
  Detection, 5.1.5)."""
  ab = b - a
  ac = c - a
  ap = p - a
  d1 = wp.dot(ab, ap)
  d2 = wp.dot(ac, ap)
  if d1 <= 0.0 and d2 <= 0.0:
    return a, wp.vec2i(ON_CORNER, 0)
  bp = p - b
  d3 = wp.dot(ab, bp)
  d4 = wp.dot(ac, bp)
  if d3 >= 0.0 and d4 <= d3:
    return b, wp.vec2i(ON_CORNER, 1)
  vc = d1 * d4 - d3 * d2
  if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
    return a + (d1 / (d1 - d3)) * ab, wp.vec2i(ON_EDGE, 0)
  cp = p - c
  d5 = wp.dot(ab, cp)
  d6 = wp.dot(ac, cp)
  if d6 >= 0.0 and d5 <= d6:
    return c, wp.vec2i(ON_CORNER, 2)
  vb = d5 * d2 - d1 * d6
  if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
    return a + (d2 / (d2 - d6)) * ac, wp.vec2i(ON_EDGE, 2)
  va = d3 * d6 - d5 * d4
  if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b), wp.vec2i(ON_EDGE, 1)
  denom = 1.0 / (va + vb + vc)
  return a + (vb * denom) * ab + (vc * denom) * ac, wp.vec2i(ON_FACE, 0)


@wp.func
def _corner_of(k: int, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3) -> wp.vec3:
  return wp.where(k == 0, v0, wp.where(k == 1, v1, v2))


@wp.func
def _flat_edge(hfield: Heightfield, dx: float, dy: float, r: int, c: int, t: int, k: int, v0: wp.vec3, n: wp.vec3,
               eps: float) -> bool:
  """Whether edge k of triangle t of cell (r, c) (t = 0: p00 p10 p11, t = 1: p00 p11 p01) lies
  flat between its two triangles: the far corner of the triangle across it on this one's plane.
  The grid's outer edges are never flat."""
  fr = wp.where(t == 0, wp.where(k == 1, r + 2, r), wp.where(k == 2, r - 1, r + 1))
  fc = wp.where(t == 0, wp.where(k == 0, c - 1, c + 1), wp.where(k == 1, c + 2, c))
  if fr < 0 or fr >= hfield.nrow or fc < 0 or fc >= hfield.ncol:
    return False
  return wp.abs(wp.dot(n, grid_vertex(hfield, dx, dy, fr, fc) - v0)) <= eps


@wp.func
def _clip_xy(p0: wp.vec3, p1: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec2:
  """The part of segment p0 p1 whose projection along z falls in triangle abc's: (t0, t1) along
  the segment, empty when t0 > t1."""
  t0 = float(0.0)
  t1 = float(1.0)
  area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
  for k in range(3):
    e0 = _corner_of(k, a, b, c)
    e1 = _corner_of((k + 1) % 3, a, b, c)
    # inside the edge's half plane where the signed area with the edge has the triangle's sign
    f0 = area * ((e1[0] - e0[0]) * (p0[1] - e0[1]) - (e1[1] - e0[1]) * (p0[0] - e0[0]))
    f1 = area * ((e1[0] - e0[0]) * (p1[1] - e0[1]) - (e1[1] - e0[1]) * (p1[0] - e0[0]))
    if f0 < 0.0 and f1 < 0.0:
      return wp.vec2(1.0, 0.0)
    if f0 < 0.0:
      t0 = wp.max(t0, f0 / (f0 - f1))
    elif f1 < 0.0:
      t1 = wp.min(t1, f0 / (f0 - f1))
  return wp.vec2(t0, t1)


@wp.func
def _nearest_pair(x0: wp.vec3, s0: wp.vec3, s1: wp.vec3, npair: int, v0: wp.vec3, v1: wp.vec3,
                  v2: wp.vec3) -> tuple[wp.vec3, wp.vec3, wp.vec2i]:
  """Of segment s0 s1 and triangle v0 v1 v2, the nearest pair of points: the segment's point,
  the triangle's, and where that lies (_closest_on_triangle). Tried in order, a nearer pair
  winning, the first ``npair`` of: x0 (a point of the segment), the segment's ends, the segment
  against each of the triangle's edges (npair = 1: x0 alone)."""
  best_x = x0
  best_q = x0
  best_at = wp.vec2i(ON_FACE, 0)
  best = float(FAR)
  for i in range(npair):
    x = wp.where(i == 1, s0, wp.where(i == 2, s1, x0))
    q = wp.vec3(0.0)
    at = wp.vec2i(ON_EDGE, i - 3)
    if i < 3:
      q, at = _closest_on_triangle(x, v0, v1, v2)
    else:
      x, q = closest_segment_to_segment_points(s0, s1, _corner_of(i - 3, v0, v1, v2),
                                                _corner_of((i - 2) % 3, v0, v1, v2))
    if wp.length(x - q) < best:
      best = wp.length(x - q)
      best_x = x
      best_q = q
      best_at = at
  return best_x, best_q, best_at


@wp.func
def _ball_for(b: Shape, k: int, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, n: wp.vec3) -> tuple[int, wp.vec3, wp.vec3,
                                                                                           wp.vec3]:
  """B's k-th ball against triangle v0 v1 v2 (normal n), as (_nearest_pair's npair, x0, s0, s1),
  npair 0 where there is none: a sphere's centre (k = 0); a capsule's point for the triangle
  (k = 0; module notes), its end k - 1 where the part over the triangle holds it. A capsule's
  k = 0 with npair 1 is the part over the triangle reaching its plane, s0 s1, for _sunk_part."""
  if b.gtype == GeomType.SPHERE:
    return wp.where(k == 0, 1, 0), b.pos, b.pos, b.pos
  axis = wp.vec3(b.rot[0, 2], b.rot[1, 2], b.rot[2, 2]) * b.size[1]
  p0 = b.pos - axis
  p1 = b.pos + axis
  span = _clip_xy(p0, p1, v0, v1, v2)
  if span[0] > span[1]:  # no part over the triangle: the whole axis against it
    return wp.where(k == 0, NPAIR, 0), p0, p0, p1
  s0 = p0 + span[0] * (p1 - p0)
  s1 = p0 + span[1] * (p1 - p0)
  h0 = wp.dot(n, s0 - v0)
  h1 = wp.dot(n, s1 - v0)
  deepest = wp.where(h0 <= h1, span[0], span[1])
  if wp.abs(h0 - h1) <= 1.0e-3 * b.size[0]:  # the axis parallel to the plane: the part's middle
    deepest = 0.5 * (span[0] + span[1])
  if k == 0:
    # reaching the plane over the triangle: the part (_sunk_part); above it, the whole axis against
    # the triangle, from the part's point nearest the plane
    if wp.min(h0, h1) <= 0.0:
      return 1, p0 + deepest * (p1 - p0), s0, s1
    return NPAIR, p0 + deepest * (p1 - p0), p0, p1
  end = float(k - 1)
  held = end >= span[0] and end <= span[1] and end != deepest
  x = p0 + end * (p1 - p0)
  return wp.where(held, 1, 0), x, x, x


@wp.func
def _answer(hfield: Heightfield, dx: float, dy: float, r: int, c: int, t: int, v0: wp.vec3, n: wp.vec3, x: wp.vec3,
            q: wp.vec3, at: wp.vec2i, rad: float, band: float) -> tuple[float, wp.vec3, wp.vec3]:
  """The contact of a ball of radius ``rad`` at x with q, the nearest point of triangle t of cell
  (r, c) (corner v0, normal n), which lies where ``at`` says: (depth, position, normal), the
  depth grown by band (<= 0: none; module notes)."""
  eps = 1.0e-6 * (dx + dy + hfield.size[2])
  height = wp.dot(n, x - v0)
  if at[0] == ON_FACE:
    depth = band + rad - height
    return depth, x - rad * n + 0.5 * depth * n, n
  w = x - q
  if wp.dot(w, n) <= 0.0:  # x below the triangle lies over another one
    return 0.0, q, n
  flat = _flat_edge(hfield, dx, dy, r, c, t, at[1], v0, n, eps)
  if at[0] == ON_CORNER:
    flat = flat and _flat_edge(hfield, dx, dy, r, c, t, (at[1] + 2) % 3, v0, n, eps)
  if flat:
    across = x - height * n - q
    reach = rad * rad - wp.dot(across, across)
    depth = band + wp.sqrt(wp.max(reach, 0.0)) - height
    return wp.where(reach > 0.0, depth, 0.0), q - 0.5 * depth * n + band * n, n
  length = wp.length(w)
  if length < 1.0e-9 * rad:
    return 0.0, q, n
  u = w / length
  depth = band + rad - length
  return depth, x - rad * u + 0.5 * depth * u, u


@wp.func
def _overlap_along(u: wp.vec3, s0: wp.vec3, s1: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, rad: float) -> float:
  """How far the capsule part s0 s1 (radius rad) must move along unit u to clear triangle v0 v1 v2
  (its prism's top, u pointing out of the terrain)."""
  top = wp.max(wp.dot(u, v0), wp.max(wp.dot(u, v1), wp.dot(u, v2)))
  return top - wp.min(wp.dot(u, s0), wp.dot(u, s1)) + rad


@wp.func
def _sunk_part(s0: wp.vec3, s1: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, n: wp.vec3, rad: float,
               band: float) -> tuple[float, wp.vec3, wp.vec3]:
  """The contact of a capsule whose axis part over triangle v0 v1 v2 (normal n) reaches below its
  plane: the least of the overlaps along n and along each cross of the axis with an edge of the
  triangle (a segment and a triangle's prism separate along one of those), as MuJoCo's
  penetration of the prism answers; (depth, position, normal), the depth grown by band. Along n
  alone, a foot sunk into a slope beside a ridge would be pushed out along the slope's normal
  where the ridge's edge holds it less."""
  best_u = n
  best = _overlap_along(n, s0, s1, v0, v1, v2, rad)
  best_edge = int(-1)
  axis = s1 - s0
  for k in range(3):
    edge = _corner_of((k + 1) % 3, v0, v1, v2) - _corner_of(k, v0, v1, v2)
    u = wp.cross(axis, edge)
    length = wp.length(u)
    if length <= 1.0e-6 * wp.length(axis) * wp.length(edge):
      continue  # the axis along the edge
    u = u / length
    if wp.dot(u, n) < 0.0:
      u = -u
    overlap = _overlap_along(u, s0, s1, v0, v1, v2, rad)
    if overlap < best:
      best = overlap
      best_u = u
      best_edge = k
  # across an edge the axis point nearest to that edge; along n the axis point deepest below the
  # plane (the middle where the axis lies parallel to it)
  x = 0.5 * (s0 + s1)
  if best_edge >= 0:
    x, _ = closest_segment_to_segment_points(s0, s1, _corner_of(best_edge, v0, v1, v2),
                                             _corner_of((best_edge + 1) % 3, v0, v1, v2))
  else:
    h0 = wp.dot(best_u, s0)
    h1 = wp.dot(best_u, s1)
    if wp.abs(h0 - h1) > 1.0e-3 * rad:
      x = wp.where(h0 < h1, s0, s1)
  depth = band + best
  return depth, x - rad * best_u + 0.5 * depth * best_u, best_u


@wp.func
def closed_form_pass(cands: wp.ref[Candidates], hfield: Heightfield, b: Shape, tp: TerrainPair, spacing: float,
                     nball: int):
  """Adds to ``cands`` a sphere's or a capsule's contact candidates against the terrain under it:
  each triangle's balls (_ball_for, ``nball`` of them) answered at their nearest points (module
  notes)."""
  dx, dy = cell_size(hfield)
  ncell = (tp.window[1] - tp.window[0] + 1) * (tp.window[3] - tp.window[2] + 1)
  for cell in range(ncell):
    r, c = window_cell(tp, cell)
    p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, r, c)
    if above_cell(tp, p00, p01, p10, p11):
      continue
    # one loop over the two triangles and their balls (a bound known at run time: not unrolled,
    # so that the answer is built once in the kernel's code)
    for item in range(2 * nball):
      t = item // nball
      v1 = wp.where(t == 0, p10, p11)
      v2 = wp.where(t == 0, p11, p01)
      n = wp.where(t == 0, na, nb)
      npair, x0, s0, s1 = _ball_for(b, item % nball, p00, v1, v2, n)
      if npair == 0:
        continue
      depth = float(0.0)
      pos = x0
      normal = n
      if b.gtype == GeomType.CAPSULE and item % nball == 0 and npair == 1:
        # the axis part over the triangle reaches its plane (_ball_for)
        depth, pos, normal = _sunk_part(s0, s1, p00, v1, v2, n, b.size[0], tp.band)
      else:
        x, q, at = _nearest_pair(x0, s0, s1, npair, p00, v1, v2)
        depth, pos, normal = _answer(hfield, dx, dy, r, c, t, p00, n, x, q, at, b.size[0], tp.band)
      if depth > 0.0:
        add_candidate(cands, pos, normal, depth, spacing)


# at the heavy kernels' register cap (16 warps an SM instead of 10) it spills a few hundred bytes and
# runs over twice as fast: one thread walks a pair's cells, its time is latency
@wp.kernel(module="mjx_supportfield.stages.hfield_closed_form", cuda_max_registers=HEAVY_REGISTERS)
def hfield_closed_form(
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
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  naconmax_in: int,
  # In:
  ms: MeshSupport,
  max_contacts: int,
  mc_tolerance: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  hfield_count_in: wp.array(dtype=int),
  hfield_pair_in: wp.array(dtype=TerrainPair),
  nthread: int,
  quota: ContactQuota,
  # Data out:
  contacts_out: ContactRows,
):
  """The pairs of hfield_jobs' list that take the closed-form pass (marked there by closed_form),
  one thread a pair: their candidates merged (candidates.py) and written (heightfield first, as
  MuJoCo orders the pair); the stage's other kernels leave them alone."""
  tid = wp.tid()
  for slot in range(tid, wp.min(hfield_count_in[COUNT_PAIRS], hfield_pair_in.shape[0]), nthread):
    tp = hfield_pair_in[slot]
    if tp.closed_form == 0:
      continue  # hfield_contacts'
    cid = tp.cid
    geoms = pair_in[cid]
    worldid = pair_worldid_in[cid]
    terrain, b, hf = terrain_pair(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms, worldid)
    hfield = heightfield(hfield_size, hfield_nrow, hfield_ncol, hfield_adr, hfield_data, hf)
    spacing = mc_tolerance * 2.0 * wp.length(geom_aabb[worldid % geom_aabb.shape[0], geoms[1], 1])
    cands = empty_with_room(NCANDIDATE)
    closed_form_pass(cands, hfield, b, tp, spacing, wp.where(b.gtype == GeomType.CAPSULE, NBALL, 1))
    if max_contacts > 1:
      cands.keep = tp.band  # the penetrating ones (depths include the band)
    _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
      mixing, pair_in, pairid_in, cid, worldid)
    write_candidates(
      cands, max_contacts, terrain.rot, terrain.pos, tp.band, naconmax_in, margin, gap, condim, friction, solref,
      solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
    )
