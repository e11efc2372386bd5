"""Heightfield geometry: the device functions heightfield.py's kernels build their jobs from.

A cell's vertices and triangles, their prisms as Shapes, the terrain features a cell owns for
the point pass (peaks, ridges, valleys) and the cheap tests that keep or drop a candidate or an
MPR answer (a point over a triangle, outside a prism's side walls). This module owns those
device functions for the heightfield stage (heightfield.py); it launches nothing.
"""

import functools

import warp as wp
from mujoco_warp._src.collision_core import Geom
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import mat63

from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.support import box_corner
from mjx_supportfield.geometry.support import hull_point
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.stages.candidates import Candidates
from mjx_supportfield.stages.candidates import depth_at
from mjx_supportfield.stages.candidates import normal_at
from mjx_supportfield.stages.candidates import pos_at
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


@wp.struct
class Heightfield:
  """One heightfield as the device functions read it, one argument instead of five: MuJoCo's
  elevations (all heightfields) and where this one's start, its grid and its size."""

  data: wp.array(dtype=float)  # MuJoCo's hfield_data: elevations scaled to [0, 1], all heightfields
  adr: int  # this heightfield's first sample in data
  nrow: int  # rows of samples (along y)
  ncol: int  # columns of samples (along x)
  size: wp.vec4  # x and y radii, elevation scale, base depth


@wp.func
def heightfield(hfield_size: wp.array(dtype=wp.vec4), hfield_nrow: wp.array(dtype=int),
                hfield_ncol: wp.array(dtype=int), hfield_adr: wp.array(dtype=int), hfield_data: wp.array(dtype=float),
                hf: int) -> Heightfield:
  """Heightfield ``hf`` of the model's arrays."""
  out = Heightfield()
  out.data = hfield_data
  out.adr = hfield_adr[hf]
  out.nrow = hfield_nrow[hf]
  out.ncol = hfield_ncol[hf]
  out.size = hfield_size[hf]
  return out


@wp.func
def _in_triangle_xy(p: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3) -> bool:
  """Whether p's projection along z falls in the triangle's (edges included)."""
  e1 = wp.vec2(v1[0] - v0[0], v1[1] - v0[1])
  e2 = wp.vec2(v2[0] - v0[0], v2[1] - v0[1])
  r = wp.vec2(p[0] - v0[0], p[1] - v0[1])
  det = e1[0] * e2[1] - e1[1] * e2[0]
  a = (r[0] * e2[1] - r[1] * e2[0]) / det
  b = (e1[0] * r[1] - e1[1] * r[0]) / det
  eps = 1.0e-6
  return a >= -eps and b >= -eps and a + b <= 1.0 + eps


@wp.func
def plane_depth(p: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, n: wp.vec3, band: float) -> float:
  """How far a geom point p lies below the triangle's plane (grown by band), where p lies over
  the triangle; 0 elsewhere."""
  depth = wp.dot(n, v0 - p) + band
  if depth <= 0.0 or not _in_triangle_xy(p, v0, v1, v2):
    return 0.0
  return depth


@wp.func
def shape_point_count(b: Shape, ms: MeshSupport) -> int:
  """How many of B's points, besides the deepest under each triangle, the plane pass tries: a
  box's corners or a mesh's hull vertices (each against the triangle under it)."""
  if b.gtype == GeomType.BOX:
    return 8
  if b.gtype == GeomType.MESH:
    return ms.hull_num[b.mesh]
  return 0


@wp.func
def shape_point(b: Shape, ms: MeshSupport, k: int) -> wp.vec3:
  """B's point k of those shape_point_count counts."""
  if b.gtype == GeomType.BOX:
    return box_corner(b, k)
  return b.pos + b.rot @ hull_point(ms, b.mesh, k)


@wp.func
def capsule_end(b: Shape, k: int, n: wp.vec3) -> wp.vec3:
  """The lowest point, against a plane with upward normal n, of a capsule's end k (0, 1)."""
  axis = wp.vec3(b.rot[0, 2], b.rot[1, 2], b.rot[2, 2])
  return b.pos + wp.where(k == 0, 1.0, -1.0) * b.size[1] * axis - b.size[0] * n


@wp.func
def prism_shape(v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, bottom: float, band: float) -> Shape:
  """The prism under triangle (v0, v1, v2) down to z = bottom, as a Shape (see support_world)."""
  s = Shape()
  s.gtype = GeomType.HFIELD
  s.pos = wp.vec3(0.0)
  s.rot = wp.mat33(v0[0], v0[1], v0[2], v1[0], v1[1], v1[2], v2[0], v2[1], v2[2])
  s.size = wp.vec3(bottom, 0.0, 0.0)
  s.mesh = -1
  top = (v0 + v1 + v2) / 3.0
  s.center = wp.vec3(top[0], top[1], 0.5 * (top[2] + bottom))
  s.inflate = band
  return s


@wp.func
def prism_geom(v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, bottom: float) -> Geom:
  """The prism under triangle (v0, v1, v2) down to z = bottom as MuJoCo Warp's GJK/EPA takes it
  (collision_convex's heightfield kernel): rows 0-2 the base, 3-5 the top, at the frame's origin."""
  g = Geom()
  g.pos = wp.vec3(0.0)
  g.rot = wp.identity(n=3, dtype=float)
  prism = mat63()
  for i in range(3):
    v = wp.where(i == 0, v0, wp.where(i == 1, v1, v2))
    prism[i] = wp.vec3(v[0], v[1], bottom)
    prism[i + 3] = v
  g.polyvert = prism
  g.index = -1
  return g


@functools.lru_cache(maxsize=None)
def outside_walls_func(mode: int) -> wp.Function:
  """``_outside_walls`` on the support functions of support mode ``mode`` (support_funcs)."""
  support_world = support_funcs(mode).support_world

  @wp.func
  def _outside_walls(b: Shape, ms: MeshSupport, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, band: float, nwall: int
                     ) -> bool:
    """Whether B (grown by band) lies wholly outside one of the prism's nwall = 3 vertical side
    walls (through the triangle's edges): then the prism's MPR can find nothing. nwall comes in
    as an argument so the loop is not unrolled (one support call site)."""
    for i in range(nwall):
      e0 = wp.where(i == 0, v0, wp.where(i == 1, v1, v2))
      e1 = wp.where(i == 0, v1, wp.where(i == 1, v2, v0))
      other = wp.where(i == 0, v2, wp.where(i == 1, v0, v1))
      out = wp.vec3(e1[1] - e0[1], e0[0] - e1[0], 0.0)
      out = wp.where(wp.dot(out, other - e0) > 0.0, -out, out)
      length = wp.length(out)
      if length > 0.0:
        out = out / length
        if wp.dot(support_world(b, ms, -out) - e0, out) > band:
          return True
    return False

  return _outside_walls


# how far below the top plane, as a fraction of its depth, a prism answer's witness may lie (float32
# rounding of MPR's and GJK/EPA's points grows with the depth) and still be the top face's
WITNESS_ROUNDING = 0.01
# how far outside a triangle (a fraction of the cell's size) a point still counts as over it
OVER_SLACK = 1.0e-4


@wp.func
def prism_answer_kept(c: wp.ref[Candidates], res: MprResult, n: wp.vec3, v0: wp.vec3, dx: float, dy: float, t: int,
                      scale: float, tol: float, one_per_prism: bool) -> bool:
  """Whether a prism's MPR answer is an edge of B dipping into the top face (normal n; v0 the
  cell's corner (r, c), t the triangle): the prism's witness point lies on the top triangle
  (answers through the side walls, which are inside the terrain, are dropped; the witness may
  sit below the plane by float32 rounding, which grows with the depth) and no plane-pass
  candidate over the same triangle with its normal is as deep (one over a neighbouring triangle
  as steep is another place of B's). With ``one_per_prism`` (GJK/EPA's answers for a box or a
  mesh, whose points MuJoCo C keeps one a prism) one such candidate is allowed: it is B's single
  deepest point under the triangle's plane, and EPA's point lies elsewhere on the part of B
  resting there; two or more are corners of a face lying flat on the plane, which they already
  span. Such an answer may also tilt more than 60 degrees from the triangle's normal where it
  still points up by 60 degrees or less (B's edge across the triangle's top edge), as C keeps
  it."""
  if wp.dot(res.normal, n) < 0.5 and (not one_per_prism or res.normal[2] < 0.5):
    return False
  witness = res.pos + 0.5 * res.depth * res.normal
  if wp.dot(n, witness - v0) < -(1.0e-6 * scale + WITNESS_ROUNDING * res.depth):
    return False
  allowed = wp.where(one_per_prism, 1, 0)
  for k in range(c.n):
    if wp.dot(normal_at(c, k), res.normal) > 0.9999 and depth_at(c, k) >= res.depth - tol * scale:
      if one_per_prism or over_triangle(pos_at(c, k), v0, dx, dy, t):
        allowed -= 1
        if allowed < 0:
          return False
  return True


@wp.func
def over_triangle(p: wp.vec3, v0: wp.vec3, dx: float, dy: float, t: int) -> bool:
  """Whether p lies over triangle t (0: (r, c), (r + 1, c), (r + 1, c + 1); 1: the other) of the
  cell whose corner (r, c) is v0, or within OVER_SLACK of a cell's size of it."""
  u = (p[0] - v0[0]) / dx
  v = (p[1] - v0[1]) / dy
  if u < -OVER_SLACK or v < -OVER_SLACK or u > 1.0 + OVER_SLACK or v > 1.0 + OVER_SLACK:
    return False
  return wp.where(t == 0, v >= u - OVER_SLACK, v <= u + OVER_SLACK)


@wp.func
def point_shape(q: wp.vec3, band: float) -> Shape:
  """A terrain point as a Shape (a sphere of radius 0 grown by the margin band)."""
  s = Shape()
  s.gtype = GeomType.SPHERE
  s.pos = q
  s.rot = wp.identity(n=3, dtype=float)
  s.size = wp.vec3(0.0)
  s.mesh = -1
  s.center = q
  s.inflate = band
  return s


@wp.func
def _closest_on_segment(p0: wp.vec3, p1: wp.vec3, x: wp.vec3) -> wp.vec3:
  e = p1 - p0
  t = wp.clamp(wp.dot(x - p0, e) / wp.max(wp.dot(e, e), 1.0e-30), 0.0, 1.0)
  return p0 + t * e


@wp.func
def _sample(hfield: Heightfield, r: int, c: int) -> float:
  """The heightfield's elevation sample at grid row r, column c (in [0, 1])."""
  return hfield.data[hfield.adr + r * hfield.ncol + c]


@wp.func
def grid_vertex(hfield: Heightfield, dx: float, dy: float, r: int, c: int) -> wp.vec3:
  return wp.vec3(dx * float(c) - hfield.size[0], dy * float(r) - hfield.size[1], _sample(hfield, r, c) * hfield.size[2])


@wp.func
def _ridge(e0: wp.vec3, e1: wp.vec3, o1: wp.vec3, o2: wp.vec3, eps: float) -> bool:
  """Whether edge e0-e1, between triangles (e0, e1, o1) and (e0, e1, o2), is a ridge: o2 lies
  below the plane of the first triangle."""
  n = wp.cross(e1 - e0, o1 - e0)
  n = wp.where(n[2] < 0.0, -n, n)
  return wp.dot(n, o2 - e0) < -eps * wp.length(n)


@wp.func
def _valley(e0: wp.vec3, e1: wp.vec3, o1: wp.vec3, o2: wp.vec3, eps: float) -> bool:
  """Whether edge e0-e1, between triangles (e0, e1, o1) and (e0, e1, o2), is a valley (a concave
  fold): o2 lies above the plane of the first triangle (a flat edge is neither)."""
  n = wp.cross(e1 - e0, o1 - e0)
  n = wp.where(n[2] < 0.0, -n, n)
  return wp.dot(n, o2 - e0) > eps * wp.length(n)


@wp.func
def _peak(hfield: Heightfield, dx: float, dy: float, r: int, c: int, eps: float) -> bool:
  """Whether grid vertex (r, c) stands above the mean of its (up to 4) grid neighbours; a
  vertex on the terrain's border always counts."""
  if r == 0 or c == 0 or r == hfield.nrow - 1 or c == hfield.ncol - 1:
    return True
  h = _sample(hfield, r, c)
  around = 0.25 * (_sample(hfield, r - 1, c) + _sample(hfield, r + 1, c) + _sample(hfield, r, c - 1)
                   + _sample(hfield, r, c + 1))
  return (h - around) * hfield.size[2] > eps


@wp.func
def _feature(hfield: Heightfield, dx: float, dy: float, r: int, c: int, k: int, p00: wp.vec3, p01: wp.vec3,
             p10: wp.vec3, p11: wp.vec3, eps: float) -> tuple[wp.vec3, wp.vec3, wp.vec3, wp.vec3, bool]:
  """Feature k of cell (r, c) as a segment e0-e1 (a point when e0 = e1), an edge's two
  triangles' third vertices o1, o2, and whether it is convex (a peak or a ridge): 0 the vertex
  p00; 1, 2 the edges p00-p01 and p00-p10; 3 the diagonal p00-p11; 4, 5 the far edges p01-p11
  and p10-p11; 6, 7, 8 the far vertices p01, p10 and p11 (4 to 8 belong to the cells on the far
  border of the visited range). An edge on the terrain's border counts as a ridge."""
  e0 = p00
  e1 = p00
  o1 = p00
  o2 = p00
  border = bool(False)
  convex = bool(False)
  if k == 0:
    convex = _peak(hfield, dx, dy, r, c, eps)
  elif k == 1:
    e1 = p01
    o1 = p11
    o2 = grid_vertex(hfield, dx, dy, wp.max(r - 1, 0), c)
    border = r == 0
  elif k == 2:
    e1 = p10
    o1 = p11
    o2 = grid_vertex(hfield, dx, dy, r, wp.max(c - 1, 0))
    border = c == 0
  elif k == 3:
    e1 = p11
    o1 = p10
    o2 = p01
  elif k == 4:
    e0 = p01
    e1 = p11
    o1 = p00
    o2 = grid_vertex(hfield, dx, dy, r + 1, wp.min(c + 2, hfield.ncol - 1))
    border = c + 2 > hfield.ncol - 1
  elif k == 5:
    e0 = p10
    e1 = p11
    o1 = p00
    o2 = grid_vertex(hfield, dx, dy, wp.min(r + 2, hfield.nrow - 1), c + 1)
    border = r + 2 > hfield.nrow - 1
  elif k == 6:
    e0 = p01
    e1 = p01
    convex = _peak(hfield, dx, dy, r, c + 1, eps)
  elif k == 7:
    e0 = p10
    e1 = p10
    convex = _peak(hfield, dx, dy, r + 1, c, eps)
  else:
    e0 = p11
    e1 = p11
    convex = _peak(hfield, dx, dy, r + 1, c + 1, eps)
  if k >= 1 and k <= 5:
    convex = border or _ridge(e0, e1, o1, o2, eps)
  return e0, e1, o1, o2, convex


@wp.func
def fold_answer_kept(hfield: Heightfield, dx: float, dy: float, r: int, c: int, job: int, p00: wp.vec3,
                      p01: wp.vec3, p10: wp.vec3, p11: wp.vec3, normal: wp.vec3, eps: float) -> bool:
  """Whether point-pass job ``job``'s answer (B's surface normal ``normal``) is kept: always,
  but for a concave edge's point, only where B leans away from one of the edge's two triangles,
  which then touches B at that edge alone; where both triangles' faces hold contacts of B, the
  edge's point between them adds nothing."""
  k = (job - 2) // 3
  if (job - 2) % 3 != 0 or k < 1 or k > 5:
    return True
  e0, e1, o1, o2, convex = _feature(hfield, dx, dy, r, c, k, p00, p01, p10, p11, eps)
  if convex:
    return True
  axis = wp.normalize(e1 - e0)
  into1 = (o1 - e0) - wp.dot(o1 - e0, axis) * axis  # from the edge into each triangle, in its plane
  into2 = (o2 - e0) - wp.dot(o2 - e0, axis) * axis
  return wp.dot(normal, into1) < 0.0 or wp.dot(normal, into2) < 0.0


@wp.func
def cell_corners(hfield: Heightfield, dx: float, dy: float, r: int,
          c: int) -> tuple[wp.vec3, wp.vec3, wp.vec3, wp.vec3, wp.vec3, wp.vec3]:
  """Cell (r, c)'s corners p00, p01, p10, p11 and the upward normals of its triangles
  (p00, p10, p11) and (p00, p11, p01)."""
  p00 = grid_vertex(hfield, dx, dy, r, c)
  p01 = grid_vertex(hfield, dx, dy, r, c + 1)
  p10 = grid_vertex(hfield, dx, dy, r + 1, c)
  p11 = grid_vertex(hfield, dx, dy, r + 1, c + 1)
  na = wp.normalize(wp.cross(p10 - p00, p11 - p00))
  na = wp.where(na[2] < 0.0, -na, na)
  nb = wp.normalize(wp.cross(p11 - p00, p01 - p00))
  nb = wp.where(nb[2] < 0.0, -nb, nb)
  return p00, p01, p10, p11, na, nb


@wp.func
def feature_point(hfield: Heightfield, dx: float, dy: float, r: int, c: int, r1: int, c1: int, job: int,
                   p00: wp.vec3, p01: wp.vec3, p10: wp.vec3, p11: wp.vec3, center: wp.vec3, eps: float,
                   valleys: bool) -> tuple[wp.vec3, bool]:
  """The terrain point of point-pass job (2 ...) of cell (r, c), and whether it is one: job
  2 + 3 k + end is feature k's point nearest B's centre (end 0) or a ridge's ends (1, 2).
  Only convex features (ridges, peaks) can poke into a geom (elsewhere the surface points
  inside it are the plane pass's business); a face of B meets a ridge deepest at an end. With
  ``valleys`` the point of a concave edge (a fold up into the next triangle) nearest B's centre
  is one too: a round B beside the fold, over the next triangle, touches this triangle only at
  that edge, which its plane's deepest point (beyond the triangle) does not see. The far-border
  features belong to the range's last row and column of cells (r1, c1)."""
  k = (job - 2) // 3
  end = (job - 2) % 3
  if (end > 0 and (k < 1 or k > 5)) or ((k == 4 or k == 6 or k == 8) and c < c1) or (
      (k == 5 or k == 7 or k == 8) and r < r1):
    return p00, False
  e0, e1, o1, o2, convex = _feature(hfield, dx, dy, r, c, k, p00, p01, p10, p11, eps)
  q = _closest_on_segment(e0, e1, center)
  if end == 1:
    q = e0
  elif end == 2:
    q = e1
  return q, convex or (valleys and end == 0 and k >= 1 and k <= 5 and _valley(e0, e1, o1, o2, eps))


@wp.func
def unit_axis(k: int) -> wp.vec3:
  return wp.vec3(wp.where(k == 0, 1.0, 0.0), wp.where(k == 1, 1.0, 0.0), wp.where(k == 2, 1.0, 0.0))


@wp.func
def cell_size(hfield: Heightfield) -> tuple[float, float]:
  """A grid cell's width dx (along x, the columns) and depth dy (along y, the rows)."""
  return 2.0 * hfield.size[0] / float(hfield.ncol - 1), 2.0 * hfield.size[1] / float(hfield.nrow - 1)
