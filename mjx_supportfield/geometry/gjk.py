"""GJK distance and EPA penetration of two convex shapes: an alternative to MPR.

GJK (Gilbert-Johnson-Keerthi) walks a simplex of at most four points of the Minkowski
difference M = A - B towards the origin. Each step adds the support point of M opposite the
current closest point v, then keeps the smallest face of the simplex (vertex, edge, triangle)
whose Voronoi region holds the origin. It stops when the new support point is no nearer the
origin along v than v itself (|v| is then the distance, the barycentric weights give the
witness points on both shapes) or when the simplex encloses the origin (the shapes overlap).

EPA (expanding polytope) starts from that simplex, completed to a tetrahedron around the
origin, and pushes out the polytope face nearest the origin with the support point along its
normal until that face lies on the boundary of M: its distance is the penetration depth, its
outward normal the contact normal (from A to B). The polytope lives in fixed-size local
arrays; when they are full EPA answers with the nearest face so far (a lower bound).

``gjk_epa`` keeps ``mpr_refined``'s contract. Spheres and capsules enter GJK as their core
point / segment and the radii plus A's margin band (``inflate``) are added afterwards, so a
pair that only overlaps through radii or the band is answered from the GJK distance (exact,
and accurate for shallow contacts); EPA runs only when the cores themselves overlap. Support
directions that a face or an edge of a box, mesh, cylinder or capsule core faces head-on
(several support points: ``count_supports``) are turned by a tiny angle so that ties break
the same way every time. All loops are bounded and every threshold is relative to ``scale``.
"""

import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import Vertex
from mjx_supportfield.geometry.mpr import miss
from mjx_supportfield.geometry.support import count_supports
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.types import FAR
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

EPS = 1.0e-6  # lengths below EPS x scale are degenerate (float32 coordinates of the pair)
TIE_RTOL = 1.0e-6  # support points within TIE_RTOL x the shape's extent tie
TIE_ANGLE = 1.0e-5  # [rad] turn of a direction with tied support points
EPA_VERTS = 64  # polytope vertices at most (EPA stops growing there)
EPA_FACES = 2 * EPA_VERTS - 4  # faces of a closed triangulated polytope with EPA_VERTS vertices
EPA_HORIZON = EPA_VERTS  # horizon edges at most (the horizon is a loop through the vertices)

mat43 = wp.types.matrix(shape=(4, 3), dtype=float)
_verts = wp.types.matrix(shape=(EPA_VERTS, 3), dtype=float)
_planes = wp.types.matrix(shape=(EPA_FACES, 4), dtype=float)
_face_ints = wp.types.vector(length=3 * EPA_FACES, dtype=int)
_face_flags = wp.types.vector(length=EPA_FACES, dtype=int)
_horizon_ints = wp.types.vector(length=3 * EPA_HORIZON, dtype=int)
_horizon_flags = wp.types.vector(length=EPA_HORIZON, dtype=int)


@wp.struct
class Simplex:
  """Up to four points of A - B, their points on A, and the weights of the point nearest the origin."""

  n: int
  v: mat43  # a - b
  a: mat43  # on A (the point on B is a - v)
  lam: wp.vec4


@wp.struct
class GjkResult:
  """Distance of two shapes. separated == 0: they overlap or touch (dist is 0)."""

  separated: int
  dist: float
  normal: wp.vec3  # unit, from A to B
  pa: wp.vec3  # nearest point of A
  pb: wp.vec3  # nearest point of B
  simplex: Simplex  # last GJK simplex (EPA starts from it)


@wp.struct
class EpaResult:
  ok: int  # 0: A - B is flat around the origin, no polytope could be built (normal: the flat's, or 0)
  depth: float
  normal: wp.vec3  # from A to B
  pa: wp.vec3
  pb: wp.vec3


# --- support ------------------------------------------------------------------------------


@wp.func
def _ambiguous(s: Shape, ms: MeshSupport, d: wp.vec3) -> bool:
  """Whether s has several support points for world direction d (a face or an edge faces d)."""
  local = wp.transpose(s.rot) @ d
  tol = TIE_RTOL * wp.length(local)
  if s.gtype == GeomType.CAPSULE:
    return wp.abs(local[2]) <= tol
  if s.gtype == GeomType.CYLINDER:
    return wp.abs(local[2]) <= tol or wp.sqrt(local[0] * local[0] + local[1] * local[1]) <= tol
  if s.gtype == GeomType.BOX or s.gtype == GeomType.MESH:
    return count_supports(s.gtype, s.size, s.mesh, ms, local, TIE_RTOL) > 1
  return False


@wp.func
def _nudge(d: wp.vec3) -> wp.vec3:
  """d turned by TIE_ANGLE about a fixed, generic axis."""
  t = wp.cross(d, wp.vec3(0.36, 0.48, 0.8))
  if wp.length(t) < 0.1 * wp.length(d):
    t = wp.cross(d, wp.vec3(0.8, -0.6, 0.0))
  return wp.normalize(d) + TIE_ANGLE * wp.normalize(t)


@wp.func
def _thin(s: Shape) -> bool:
  return s.gtype == GeomType.SPHERE or s.gtype == GeomType.CAPSULE


@wp.func
def _core(s: Shape) -> Shape:
  """s without its inflation and, for spheres and capsules, without the radius (a point / segment)."""
  out = s
  out.inflate = 0.0
  if _thin(s):
    out.size = wp.vec3(0.0, s.size[1], s.size[2])
  return out


@wp.func
def _rim(s: Shape) -> float:
  """What _core strips off s: its inflation, plus the radius of a sphere or capsule."""
  return s.inflate + wp.where(_thin(s), s.size[0], 0.0)


# --- nearest point of a simplex -----------------------------------------------------------


@wp.func
def _segment(p: wp.vec3, q: wp.vec3) -> wp.vec2:
  """Barycentric weights of the point of segment pq nearest the origin."""
  e = q - p
  ee = wp.dot(e, e)
  t = float(0.0)
  if ee > 0.0:
    t = wp.clamp(-wp.dot(p, e) / ee, 0.0, 1.0)
  return wp.vec2(1.0 - t, t)


@wp.func
def _edges_nearest(p: wp.vec3, q: wp.vec3, r: wp.vec3) -> wp.vec3:
  """Weights of the nearest point of the three edges of triangle pqr (a sliver triangle)."""
  s1 = _segment(p, q)
  s2 = _segment(q, r)
  s3 = _segment(r, p)
  c1 = s1[0] * p + s1[1] * q
  c2 = s2[0] * q + s2[1] * r
  c3 = s3[0] * r + s3[1] * p
  out = wp.vec3(s1[0], s1[1], 0.0)
  best = wp.dot(c1, c1)
  if wp.dot(c2, c2) < best:
    out = wp.vec3(0.0, s2[0], s2[1])
    best = wp.dot(c2, c2)
  if wp.dot(c3, c3) < best:
    out = wp.vec3(s3[1], 0.0, s3[0])
  return out


@wp.func
def _triangle(p: wp.vec3, q: wp.vec3, r: wp.vec3) -> wp.vec3:
  """Barycentric weights of the point of triangle pqr nearest the origin.

  Tests the Voronoi regions of the vertices, then of the edges, then the face (the dot
  products below are those of -p, -q, -r with the edges pq and pr).
  """
  pq = q - p
  pr = r - p
  d1 = -wp.dot(pq, p)
  d2 = -wp.dot(pr, p)
  if d1 <= 0.0 and d2 <= 0.0:
    return wp.vec3(1.0, 0.0, 0.0)
  d3 = -wp.dot(pq, q)
  d4 = -wp.dot(pr, q)
  if d3 >= 0.0 and d4 <= d3:
    return wp.vec3(0.0, 1.0, 0.0)
  wr = d1 * d4 - d3 * d2  # r's (unnormalised) weight: <= 0 beyond edge pq
  if wr <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
    t = d1 / (d1 - d3)
    return wp.vec3(1.0 - t, t, 0.0)
  d5 = -wp.dot(pq, r)
  d6 = -wp.dot(pr, r)
  if d6 >= 0.0 and d5 <= d6:
    return wp.vec3(0.0, 0.0, 1.0)
  wq = d5 * d2 - d1 * d6
  if wq <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
    t = d2 / (d2 - d6)
    return wp.vec3(1.0 - t, 0.0, t)
  wpp = d3 * d6 - d5 * d4
  if wpp <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
    t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    return wp.vec3(0.0, 1.0 - t, t)
  total = wpp + wq + wr
  if total <= 0.0 or wpp < 0.0 or wq < 0.0 or wr < 0.0:
    return _edges_nearest(p, q, r)  # rounding on a sliver: the face region is empty
  return wp.vec3(wpp, wq, wr) / total


@wp.func
def _outside(p: wp.vec3, q: wp.vec3, r: wp.vec3, opposite: wp.vec3, eps: float) -> bool:
  """Whether the origin lies beyond plane pqr, away from the tetrahedron's vertex opposite.

  A flat tetrahedron (opposite within eps of the plane) counts as outside so that its
  faces are searched instead.
  """
  n = wp.cross(q - p, r - p)
  height = wp.dot(n, opposite - p)
  if wp.abs(height) <= eps * wp.length(n):
    return True
  return -wp.dot(n, p) * height < 0.0


@wp.func
def _tetrahedron(v: mat43, eps: float) -> tuple[wp.vec4, bool]:
  """Weights of the point of tetrahedron v nearest the origin, and whether v encloses the origin."""
  best = wp.vec4(0.0)
  best_d = float(FAR)
  inside = bool(True)
  for f in range(4):
    i = (f + 1) % 4
    j = (f + 2) % 4
    k = (f + 3) % 4
    if _outside(v[i], v[j], v[k], v[f], eps):
      inside = False
      w = _triangle(v[i], v[j], v[k])
      c = w[0] * v[i] + w[1] * v[j] + w[2] * v[k]
      if wp.dot(c, c) < best_d:
        best_d = wp.dot(c, c)
        best = wp.vec4(0.0)
        best[i] = w[0]
        best[j] = w[1]
        best[k] = w[2]
  if not inside:
    return best, False
  e1 = v[1] - v[0]
  e2 = v[2] - v[0]
  e3 = v[3] - v[0]
  det = wp.dot(e1, wp.cross(e2, e3))
  l1 = wp.max(-wp.dot(v[0], wp.cross(e2, e3)) / det, 0.0)
  l2 = wp.max(-wp.dot(e1, wp.cross(v[0], e3)) / det, 0.0)
  l3 = wp.max(-wp.dot(e1, wp.cross(e2, v[0])) / det, 0.0)
  l0 = wp.max(1.0 - l1 - l2 - l3, 0.0)
  return wp.vec4(l0, l1, l2, l3) / (l0 + l1 + l2 + l3), True


@wp.func
def _reduce(s: Simplex, eps: float) -> Simplex:
  """s cut down to the vertices that carry its point nearest the origin, with their weights
  (all four stay when the tetrahedron encloses the origin)."""
  lam = wp.vec4(1.0, 0.0, 0.0, 0.0)
  keep_all = bool(False)
  if s.n == 2:
    w2 = _segment(s.v[0], s.v[1])
    lam = wp.vec4(w2[0], w2[1], 0.0, 0.0)
  elif s.n == 3:
    w3 = _triangle(s.v[0], s.v[1], s.v[2])
    lam = wp.vec4(w3[0], w3[1], w3[2], 0.0)
  elif s.n == 4:
    lam, keep_all = _tetrahedron(s.v, eps)
  out = s
  k = int(0)
  for i in range(s.n):
    if lam[i] > 0.0 or keep_all:
      out.v[k] = s.v[i]
      out.a[k] = s.a[i]
      out.lam[k] = lam[i]
      k += 1
  out.n = k
  return out


@wp.func
def _point(s: Simplex) -> wp.vec3:
  """The simplex's point nearest the origin (weights from _reduce)."""
  p = wp.vec3(0.0)
  for i in range(s.n):
    p += s.lam[i] * s.v[i]
  return p


@wp.func
def _point_on_a(s: Simplex) -> wp.vec3:
  p = wp.vec3(0.0)
  for i in range(s.n):
    p += s.lam[i] * s.a[i]
  return p


# --- GJK ----------------------------------------------------------------------------------


# --- EPA ----------------------------------------------------------------------------------


@wp.func
def _probe(s: Simplex, k: int) -> wp.vec3:
  """k-th (of 6) search direction away from the affine hull of a simplex of 1 to 3 points."""
  if s.n == 1:
    axis = wp.vec3(0.0)
    axis[k // 2] = wp.where(k % 2 == 0, 1.0, -1.0)
    return axis
  if s.n == 2:
    e = wp.normalize(s.v[1] - s.v[0])
    u = wp.cross(e, wp.vec3(0.36, 0.48, 0.8))
    if wp.length(u) < 0.1:
      u = wp.cross(e, wp.vec3(0.8, -0.6, 0.0))
    u = wp.normalize(u)
    angle = float(k) * wp.pi / 3.0
    return wp.cos(angle) * u + wp.sin(angle) * wp.cross(e, u)
  n = wp.normalize(wp.cross(s.v[1] - s.v[0], s.v[2] - s.v[0]))
  return wp.where(k % 2 == 0, n, -n)


@wp.func
def _off_hull(s: Simplex, p: wp.vec3) -> float:
  """Distance of p from the affine hull of a simplex of 1 to 3 points."""
  r = p - s.v[0]
  if s.n == 1:
    return wp.length(r)
  if s.n == 2:
    return wp.length(wp.cross(r, wp.normalize(s.v[1] - s.v[0])))
  return wp.abs(wp.dot(r, wp.normalize(wp.cross(s.v[1] - s.v[0], s.v[2] - s.v[0]))))


@wp.func
def _plane(p: wp.vec3, q: wp.vec3, r: wp.vec3, eps: float) -> wp.vec4:
  """Unit normal and origin distance of triangle pqr (counter-clockwise seen from outside).

  A sliver (height below eps) gets distance FAR so that it is never the nearest face.
  """
  n = wp.cross(q - p, r - p)
  ln = wp.length(n)
  longest = wp.max(wp.length(q - p), wp.max(wp.length(r - p), wp.length(r - q)))
  if ln <= eps * longest:
    return wp.vec4(0.0, 0.0, 0.0, FAR)
  n = n / ln
  return wp.vec4(n[0], n[1], n[2], wp.dot(n, p))


@wp.func
def _sees(plane: wp.vec4, p: wp.vec3, eps: float) -> bool:
  """Whether p lies in front of a face (a sliver, whose plane is unknown, counts as seen)."""
  return plane[3] >= FAR or wp.dot(wp.vec3(plane[0], plane[1], plane[2]), p) - plane[3] > eps


# --- the narrow-phase entry ---------------------------------------------------------------


@wp.func
def _axis(s: Shape) -> wp.vec3:
  """Direction of a capsule core (zero for a sphere's point core)."""
  return wp.where(s.gtype == GeomType.CAPSULE, wp.vec3(s.rot[0, 2], s.rot[1, 2], s.rot[2, 2]), wp.vec3(0.0))


@wp.func
def _flat_normal(a: Shape, b: Shape) -> wp.vec3:
  """Unit normal of the flat A - B of two point / segment cores, towards B's centre where it can.

  Its span is that of the capsule axes: their cross product, else the part of the centre
  line across the one axis, else any direction across it.
  """
  hint = b.center - a.center
  ea = _axis(a)
  eb = _axis(b)
  e = wp.where(wp.length(ea) > 0.0, ea, eb)
  n = wp.cross(ea, eb)
  if wp.length(n) < 1.0e-4:
    n = hint - wp.dot(hint, e) * e
    if wp.length(n) <= 1.0e-4 * wp.length(hint):
      n = wp.where(wp.length(e) > 0.0, wp.cross(e, wp.vec3(0.36, 0.48, 0.8)), wp.vec3(0.0, 0.0, 1.0))
  n = wp.normalize(n)
  return wp.where(wp.dot(n, hint) < 0.0, -n, n)


@wp.func
def _point_in_hull(hull: Shape, ms: MeshSupport, p: wp.vec3) -> wp.vec4:
  """The hull face plane of a mesh shape that world point p lies farthest in front of: its
  outward unit normal (world) and p's signed distance to it (<= 0: p is inside the hull, at
  that distance from its surface; > 0: p is at least that far outside)."""
  local = wp.transpose(hull.rot) @ (p - hull.pos)
  adr = ms.plane_adr[hull.mesh]
  best = float(-FAR)
  normal = wp.vec3(0.0)
  for f in range(ms.plane_num[hull.mesh]):
    plane = ms.plane[adr + f]
    n = wp.vec3(plane[0], plane[1], plane[2])
    dist = wp.dot(n, local) - plane[3]
    if dist > best:
      best = dist
      normal = n
  n = hull.rot @ normal
  return wp.vec4(n[0], n[1], n[2], best)


@wp.func
def _sunk_sphere(a: Shape, b: Shape, ms: MeshSupport, reach: float) -> MprResult:
  """gjk_epa's answer for a sphere whose centre lies inside a mesh's hull (the other shape),
  miss() for one farther than ``reach`` from it, and hit = -1 when GJK has to decide (the
  centre lies outside but within reach, a pair of other types, a mesh without planes)."""
  r = MprResult()
  r.hit = -1
  sphere_a = a.gtype == GeomType.SPHERE and b.gtype == GeomType.MESH
  sphere_b = b.gtype == GeomType.SPHERE and a.gtype == GeomType.MESH
  if not (sphere_a or sphere_b):
    return r
  hull = a  # the mesh, and the sphere's centre
  p = b.pos
  if sphere_a:
    hull = b
    p = a.pos
  if ms.plane_num[hull.mesh] == 0:
    return r
  q = _point_in_hull(hull, ms, p)
  if q[3] > reach:
    return miss()
  if q[3] > 0.0:
    return r
  face = wp.vec3(q[0], q[1], q[2])
  foot = p - q[3] * face  # on the face plane
  # from A to B: out of the mesh's face when B is the sphere, into it when A is
  n = wp.where(sphere_b, face, -face)
  pa = wp.where(sphere_b, foot, p)
  pb = wp.where(sphere_b, p, foot)
  r.hit = 1
  r.depth = _rim(a) + _rim(b) - q[3]
  r.normal = n
  r.pos = 0.5 * (pa + _rim(a) * n + pb - _rim(b) * n)
  return r


@functools.lru_cache(maxsize=None)
def gjk_funcs(mode: int) -> SimpleNamespace:
  """GJK's and EPA's device functions on the support functions of support mode ``mode``
  (support_funcs): ``gjk_distance`` and ``gjk_epa``."""
  support_world = support_funcs(mode).support_world

  @wp.func
  def _support(a: Shape, b: Shape, ms: MeshSupport, d: wp.vec3) -> Vertex:
    """Support point of A - B for direction d, with the shapes' own points."""
    dd = d
    if _ambiguous(a, ms, d) or _ambiguous(b, ms, -d):
      dd = _nudge(d)
    out = Vertex()
    out.a = support_world(a, ms, dd)
    out.b = support_world(b, ms, -dd)
    out.v = out.a - out.b
    return out

  @wp.func
  def _gjk(a: Shape, b: Shape, ms: MeshSupport, scale: float, tol: float, iterations: int, cutoff: float
           ) -> GjkResult:
    """Distance of A and B by GJK; returns as soon as it is proven to exceed cutoff (dist is then a lower bound)."""
    eps = EPS * scale
    atol = tol * scale
    s = Simplex()
    s.n = 0
    v = a.center - b.center  # a point of A - B: the first search direction
    if wp.length(v) < eps:
      v = wp.vec3(eps, 0.0, 0.0)
    vn = float(wp.length(v))
    res = GjkResult()
    overlap = int(0)
    for _ in range(iterations):
      w = _support(a, b, ms, -v / vn)
      lower = wp.dot(v, w.v) / vn  # every point x of A - B has x . v / |v| >= lower
      if lower > cutoff:
        res.separated = 1
        res.dist = lower
        res.simplex = s
        return res
      if s.n > 0 and vn - lower <= atol:
        break
      dup = bool(False)
      for i in range(s.n):
        if wp.length(s.v[i] - w.v) <= eps:
          dup = True
      if dup:
        break
      prev = s
      s.v[s.n] = w.v
      s.a[s.n] = w.a
      s.n += 1
      s = _reduce(s, eps)
      vnew = _point(s)
      vnew_n = wp.length(vnew)
      if s.n == 4 or vnew_n <= eps:
        overlap = 1
        v = vnew
        vn = vnew_n
        break
      if prev.n > 0 and vnew_n >= vn:
        s = prev  # rounding: no progress left
        break
      v = vnew
      vn = vnew_n

    res.simplex = s
    res.pa = _point_on_a(s)
    res.pb = res.pa - _point(s)
    if overlap == 1:
      res.separated = 0
      res.dist = 0.0
      return res
    res.separated = 1
    res.dist = vn
    res.normal = -v / vn
    if s.n == 3:
      # a face of A - B: its plane is better defined than the direction of a short v
      n = wp.cross(s.v[1] - s.v[0], s.v[2] - s.v[0])
      if wp.length(n) > scale * vn:
        n = wp.normalize(n)
        if wp.dot(n, v) > 0.0:
          n = -n
        res.normal = n
        res.dist = -wp.dot(n, s.v[0])
    return res

  @wp.func
  def gjk_distance(a: Shape, b: Shape, ms: MeshSupport, scale: float, tol: float, iterations: int) -> GjkResult:
    """Distance and nearest points of A and B (inflate included) by GJK.

    separated == 0 (dist 0) when they overlap or touch (closer than EPS x scale). scale: a
    length of the pair (thresholds are relative to it); tol: convergence tolerance relative to
    scale; iterations: GJK's iteration cap.
    """
    ra = _rim(a)
    rb = _rim(b)
    res = _gjk(_core(a), _core(b), ms, scale, tol, iterations, FAR)
    if res.separated == 0 or res.dist <= ra + rb + EPS * scale:
      res.separated = 0
      res.dist = 0.0
      return res
    res.dist -= ra + rb
    res.pa += ra * res.normal
    res.pb -= rb * res.normal
    return res

  @wp.func
  def _grow(a: Shape, b: Shape, ms: MeshSupport, s: Simplex, eps: float) -> Simplex:
    """s completed to a tetrahedron (n == 4) by the supports farthest from its affine hull.

    Adding points keeps the origin inside; n stays below 4 where A - B is flat (thinner than eps).
    """
    out = s
    for _ in range(3):
      if out.n == 0 or out.n >= 4:
        break
      best = Vertex()
      best_h = float(0.0)
      for k in range(6):
        if out.n == 3 and k >= 2:
          break
        w = _support(a, b, ms, _probe(out, k))
        h = _off_hull(out, w.v)
        if h > best_h:
          best_h = h
          best = w
      if best_h <= eps:
        break
      out.v[out.n] = best.v
      out.a[out.n] = best.a
      out.n += 1
    return out

  @wp.func
  def _epa(a: Shape, b: Shape, ms: MeshSupport, start: Simplex, scale: float, tol: float, iterations: int
           ) -> EpaResult:
    """Penetration of overlapping A and B: EPA from a GJK simplex that holds the origin.

    Faces live in slots with their vertex ids (counter-clockwise seen from outside), the face
    across each edge, and a state: 0 free, 1 on the polytope, 2 seen from the new point. The
    seen faces are flood-filled from the nearest face, so they form one patch; its border (the
    horizon) must be a single loop, else the step is dropped and EPA stops.
    """
    eps = EPS * scale
    atol = tol * scale
    res = EpaResult()
    res.ok = 0
    s = _grow(a, b, ms, start, eps)
    if s.n < 4:
      if s.n == 3:  # A - B is flat around the origin: no depth across its plane
        res.normal = wp.normalize(wp.cross(s.v[1] - s.v[0], s.v[2] - s.v[0]))
      return res

    verts = _verts()
    averts = _verts()
    planes = _planes()
    faces = _face_ints()
    adj = _face_ints()  # adj[3f + e]: the face across edge e, faces[3f + e] -> faces[3f + (e + 1) % 3]
    state = _face_flags()
    seen = _face_flags()  # flood-fill queue of the seen faces
    horizon = _horizon_ints()  # per horizon edge: its two vertices and the face outside it
    after = _horizon_flags()  # per horizon edge: the edge that follows it on the loop
    slot = _horizon_flags()  # per horizon edge: the slot of its new face
    # the tetrahedron: face f is opposite vertex f; across its edge e lies the face opposite
    # the face's third vertex
    for i in range(4):
      verts[i] = s.v[i]
      averts[i] = s.a[i]
    for f in range(4):
      i = (f + 1) % 4
      j = (f + 2) % 4
      k = (f + 3) % 4
      if wp.dot(wp.cross(s.v[j] - s.v[i], s.v[k] - s.v[i]), s.v[f] - s.v[i]) > 0.0:
        j = (f + 3) % 4
        k = (f + 2) % 4
      faces[3 * f] = i
      faces[3 * f + 1] = j
      faces[3 * f + 2] = k
      adj[3 * f] = k
      adj[3 * f + 1] = i
      adj[3 * f + 2] = j
      state[f] = 1
      planes[f] = _plane(s.v[i], s.v[j], s.v[k], eps)
    nv = int(4)
    nslots = int(4)  # slots in use or freed
    nlive = int(4)  # faces on the polytope

    best = wp.vec4(0.0, 0.0, 0.0, -FAR)  # plane of the nearest face so far, and its vertices
    bi = int(0)
    bj = int(0)
    bk = int(0)
    for _ in range(iterations):
      fmin = int(0)
      dmin = float(2.0 * FAR)
      for f in range(nslots):
        if state[f] == 1 and planes[f, 3] < dmin:
          fmin = f
          dmin = planes[f, 3]
      if planes[fmin, 3] < best[3] - eps:
        break  # the nearest face only recedes: rounding broke the polytope, keep the last good face
      best = planes[fmin]
      bi = faces[3 * fmin]
      bj = faces[3 * fmin + 1]
      bk = faces[3 * fmin + 2]
      n = wp.vec3(best[0], best[1], best[2])
      w = _support(a, b, ms, n)
      if wp.dot(w.v, n) - best[3] <= atol or nv == EPA_VERTS:
        break

      # flood-fill the faces that see w, from the nearest one
      state[fmin] = 2
      seen[0] = fmin
      nseen = int(1)
      head = int(0)
      for _ in range(EPA_FACES):  # each face enters the queue once
        if head == nseen:
          break
        f = seen[head]
        head += 1
        for e in range(3):
          g = adj[3 * f + e]
          if state[g] == 1 and _sees(planes[g], w.v, eps):
            state[g] = 2
            seen[nseen] = g
            nseen += 1
      # the horizon: edges between a seen face and an unseen one
      ne = int(0)
      ok = bool(True)
      for q in range(nseen):
        f = seen[q]
        for e in range(3):
          g = adj[3 * f + e]
          if state[g] != 2:
            if ne < EPA_HORIZON:
              horizon[3 * ne] = faces[3 * f + e]
              horizon[3 * ne + 1] = faces[3 * f + (e + 1) % 3]
              horizon[3 * ne + 2] = g
              ne += 1
            else:
              ok = False
      # it must be one loop: each edge has exactly one successor, and the walk from edge 0
      # returns after ne steps
      for h in range(ne):
        after[h] = -1
        for m in range(ne):
          if horizon[3 * m] == horizon[3 * h + 1]:
            if after[h] >= 0:
              ok = False
            after[h] = m
        if after[h] < 0:
          ok = False
      if ok:
        h = int(0)
        for m in range(ne):
          h = after[h]
          if h == 0 and m < ne - 1:
            ok = False
        ok = ok and h == 0
      if not ok or nlive - nseen + ne > EPA_FACES:
        for q in range(nseen):
          state[seen[q]] = 1
        break

      # the seen faces go; a fan of new faces joins the horizon to w
      verts[nv] = w.v
      averts[nv] = w.a
      for q in range(nseen):
        state[seen[q]] = 0
      for h in range(ne):
        f = int(0)
        if h < nseen:
          f = seen[h]
        else:
          f = nslots  # a slot freed by an earlier step, else a new one
          for c in range(nslots):
            if state[c] == 0:
              f = c
              break
          if f == nslots:
            nslots += 1
        slot[h] = f
        state[f] = 1
      for h in range(ne):
        f = slot[h]
        i = horizon[3 * h]
        j = horizon[3 * h + 1]
        g = horizon[3 * h + 2]
        faces[3 * f] = i
        faces[3 * f + 1] = j
        faces[3 * f + 2] = nv
        adj[3 * f] = g
        adj[3 * f + 1] = slot[after[h]]
        planes[f] = _plane(verts[i], verts[j], w.v, eps)
        for e in range(3):
          if faces[3 * g + e] == j and faces[3 * g + (e + 1) % 3] == i:
            adj[3 * g + e] = f
      for h in range(ne):
        adj[3 * slot[after[h]] + 2] = slot[h]
      nv += 1
      nlive += ne - nseen

    n = wp.vec3(best[0], best[1], best[2])
    # witnesses: the weights of the origin's projection onto the face
    p = best[3] * n
    lam = _triangle(verts[bi] - p, verts[bj] - p, verts[bk] - p)
    foot = lam[0] * verts[bi] + lam[1] * verts[bj] + lam[2] * verts[bk]
    if wp.length(foot - p) > eps:
      # the projection lies off the nearest face: faces coplanar with it tie (A - B is flat there,
      # e.g. a box's face against a mesh vertex) and the tie broke towards a face beside the
      # projection, whose weights put the witnesses up to the flat's size away from the contact.
      # The face that holds the projection (nearest to it) gives the witnesses instead.
      off = wp.length(foot - p)
      for f in range(nslots):
        if state[f] == 1:
          i = faces[3 * f]
          j = faces[3 * f + 1]
          k = faces[3 * f + 2]
          w3 = _triangle(verts[i] - p, verts[j] - p, verts[k] - p)
          near = w3[0] * verts[i] + w3[1] * verts[j] + w3[2] * verts[k]
          if wp.length(near - p) < off:
            off = wp.length(near - p)
            lam = w3
            bi = i
            bj = j
            bk = k
    res.ok = 1
    res.depth = best[3]
    res.normal = n
    res.pa = lam[0] * averts[bi] + lam[1] * averts[bj] + lam[2] * averts[bk]
    res.pb = res.pa - (lam[0] * verts[bi] + lam[1] * verts[bj] + lam[2] * verts[bk])
    return res

  @wp.func
  def gjk_epa(a: Shape, b: Shape, ms: MeshSupport, scale: float, tol: float, iterations: int) -> MprResult:
    """Penetration of A (grown by a.inflate) and B by GJK, and EPA where their cores overlap.

    Same contract as mpr_refined: hit == 0 when they are apart (by more than EPS x scale);
    else depth (>= 0), the unit normal from A to B, and pos, the midpoint of the two surfaces'
    witness points. scale: a length of the pair (thresholds are relative to it); tol:
    convergence tolerance relative to scale; iterations: cap of GJK's and of EPA's loop.
    """
    ra = _rim(a)
    rb = _rim(b)
    rims = ra + rb
    touch = EPS * scale  # closer than this is touching
    # a sphere against a mesh: from the hull's face planes when its centre is sunk in the hull
    # (EPA would build a polytope for what one pass over the planes answers exactly)
    sunk = _sunk_sphere(a, b, ms, rims + touch + tol * scale)
    if sunk.hit >= 0:
      return sunk
    ca = _core(a)
    cb = _core(b)
    g = _gjk(ca, cb, ms, scale, tol, iterations, rims + touch + tol * scale)
    depth = float(0.0)
    n = wp.vec3(0.0)
    pa = g.pa
    pb = g.pb
    if g.separated == 1:
      if g.dist > rims + touch:
        return miss()
      depth = wp.max(rims - g.dist, 0.0)
      n = g.normal
    elif _thin(a) and _thin(b):
      # a point / segment core meets another: A - B is flat there and its penetration is the
      # rims, along the flat's normal
      depth = rims
      n = _flat_normal(a, b)
    else:
      e = _epa(ca, cb, ms, g.simplex, scale, tol, iterations)
      if e.ok == 1:
        depth = wp.max(rims + e.depth, 0.0)  # touching cores: the origin may lie a rounding error outside
        n = e.normal
        pa = e.pa
        pb = e.pb
      else:
        depth = rims  # A - B is flat: a flat mesh against a point / segment core, or two flat meshes
        n = e.normal
        if wp.length(n) == 0.0:
          n = _flat_normal(a, b)
        elif wp.dot(n, b.center - a.center) < 0.0:
          n = -n
    r = MprResult()
    r.hit = 1
    r.depth = depth
    r.normal = n
    r.pos = 0.5 * (pa + ra * n + pb - rb * n)
    return r

  return SimpleNamespace(gjk_distance=gjk_distance, gjk_epa=gjk_epa)
