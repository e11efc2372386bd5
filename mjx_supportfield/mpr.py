"""Minkowski Portal Refinement: penetration depth, normal and midpoint of two convex shapes.

The Minkowski difference A - B is explored through support points only. Every portal
vertex keeps the two support points it came from so the contact position can be
interpolated on both surfaces.
"""

import warp as wp

from mjx_supportfield.support import support_world
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


@wp.struct
class Vertex:
  v: wp.vec3  # a - b
  a: wp.vec3
  b: wp.vec3


@wp.struct
class MprResult:
  hit: int
  depth: float
  normal: wp.vec3  # from shape A to shape B
  pos: wp.vec3  # midpoint between the surfaces


@wp.func
def _support(a: Shape, b: Shape, ms: MeshSupport, d: wp.vec3, mode: int) -> Vertex:
  out = Vertex()
  out.a = support_world(a, ms, d, mode)
  out.b = support_world(b, ms, -d, mode)
  out.v = out.a - out.b
  return out


@wp.func
def _portal_normal(v1: wp.vec3, v2: wp.vec3, v3: wp.vec3) -> wp.vec3:
  return wp.normalize(wp.cross(v2 - v1, v3 - v1))


@wp.func
def _miss() -> MprResult:
  r = MprResult()
  r.hit = 0
  r.depth = 0.0
  return r


@wp.func
def _single_point(p: Vertex) -> MprResult:
  """Origin on the segment v0-v1 (or touching at v1): depth along v1."""
  r = MprResult()
  r.hit = 1
  n = wp.length(p.v)
  r.depth = n
  if n > 0.0:
    r.normal = p.v / n
  else:
    r.normal = wp.vec3(0.0, 0.0, 1.0)
  r.pos = 0.5 * (p.a + p.b)
  return r


@wp.func
def _closest_on_triangle(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
  """Point of triangle abc closest to the origin (Voronoi-region walk)."""
  ab = b - a
  ac = c - a
  ap = -a
  d1 = wp.dot(ab, ap)
  d2 = wp.dot(ac, ap)
  if d1 <= 0.0 and d2 <= 0.0:
    return a
  bp = -b
  d3 = wp.dot(ab, bp)
  d4 = wp.dot(ac, bp)
  if d3 >= 0.0 and d4 <= d3:
    return b
  vc = d1 * d4 - d3 * d2
  if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
    return a + (d1 / (d1 - d3)) * ab
  cp = -c
  d5 = wp.dot(ab, cp)
  d6 = wp.dot(ac, cp)
  if d6 >= 0.0 and d5 <= d6:
    return c
  vb = d5 * d2 - d1 * d6
  if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
    return a + (d2 / (d2 - d6)) * ac
  va = d3 * d6 - d5 * d4
  if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
  denom = 1.0 / (va + vb + vc)
  return a + ab * (vb * denom) + ac * (vc * denom)


@wp.func
def _midpoint(p0: Vertex, p1: Vertex, p2: Vertex, p3: Vertex, n: wp.vec3) -> wp.vec3:
  """Barycentric projection of the origin into the portal, applied to both shapes' points."""
  b0 = wp.dot(wp.cross(p1.v, p2.v), p3.v)
  b1 = wp.dot(wp.cross(p3.v, p2.v), p0.v)
  b2 = wp.dot(wp.cross(p0.v, p1.v), p3.v)
  b3 = wp.dot(wp.cross(p2.v, p1.v), p0.v)
  s = b0 + b1 + b2 + b3
  if s <= 0.0:
    b0 = 0.0
    b1 = wp.dot(wp.cross(p2.v, p3.v), n)
    b2 = wp.dot(wp.cross(p3.v, p1.v), n)
    b3 = wp.dot(wp.cross(p1.v, p2.v), n)
    s = b1 + b2 + b3
  if s == 0.0:
    return 0.25 * (p1.a + p1.b + p2.a + p2.b)
  inv = 1.0 / s
  pa = (b0 * p0.a + b1 * p1.a + b2 * p2.a + b3 * p3.a) * inv
  pb = (b0 * p0.b + b1 * p1.b + b2 * p2.b + b3 * p3.b) * inv
  return 0.5 * (pa + pb)


@wp.func
def mpr(a: Shape, b: Shape, ms: MeshSupport, mode: int, scale: float, tol: float, iterations: int) -> MprResult:
  """Penetration of A and B by MPR; hit == 0 when they do not overlap.

  scale: a length of the pair (degeneracy thresholds are relative to it); tol: convergence
  tolerance relative to scale; iterations: cap of each loop (no unbounded loop on the GPU).
  """
  eps = 1.0e-10 * scale
  atol = tol * scale
  p0 = Vertex()
  p0.a = a.center
  p0.b = b.center
  p0.v = a.center - b.center
  if wp.length(p0.v) < eps:
    p0.v = wp.vec3(1.0e-6 * scale, 0.0, 0.0)

  # portal discovery
  d = wp.normalize(-p0.v)
  p1 = _support(a, b, ms, d, mode)
  if wp.dot(p1.v, d) <= 0.0:
    return _miss()
  d = wp.cross(p0.v, p1.v)
  if wp.length(d) < eps * scale:
    return _single_point(p1)
  d = wp.normalize(d)
  p2 = _support(a, b, ms, d, mode)
  if wp.dot(p2.v, d) <= 0.0:
    return _miss()
  d = wp.cross(p1.v - p0.v, p2.v - p0.v)
  if wp.length(d) < eps * scale:
    return _single_point(p1)
  d = wp.normalize(d)
  if wp.dot(d, p0.v) > 0.0:
    tmp = p1
    p1 = p2
    p2 = tmp
    d = -d

  p3 = Vertex()
  found = int(0)
  for _ in range(iterations):
    p3 = _support(a, b, ms, d, mode)
    if wp.dot(p3.v, d) <= 0.0:
      return _miss()
    if wp.dot(wp.cross(p1.v, p3.v), p0.v) < 0.0:
      p2 = p3
      d = wp.cross(p1.v - p0.v, p3.v - p0.v)
    elif wp.dot(wp.cross(p3.v, p2.v), p0.v) < 0.0:
      p1 = p3
      d = wp.cross(p3.v - p0.v, p2.v - p0.v)
    else:
      found = 1
      break
    if wp.length(d) < eps * scale:
      return _single_point(p1)
    d = wp.normalize(d)
  if found == 0:
    return _miss()

  # refine the portal until the origin is behind it, then push it to the boundary
  inside = int(0)
  for _ in range(iterations):
    n = _portal_normal(p1.v, p2.v, p3.v)
    if inside == 0 and wp.dot(n, p1.v) >= 0.0:
      inside = 1
    p4 = _support(a, b, ms, n, mode)
    d4 = wp.dot(p4.v, n)
    if inside == 0 and d4 < 0.0:
      return _miss()
    gap = wp.min(d4 - wp.dot(p1.v, n), wp.min(d4 - wp.dot(p2.v, n), d4 - wp.dot(p3.v, n)))
    if gap <= atol:
      break
    x = wp.cross(p4.v, p0.v)
    if wp.dot(p1.v, x) > 0.0:
      if wp.dot(p2.v, x) > 0.0:
        p1 = p4
      else:
        p3 = p4
    else:
      if wp.dot(p3.v, x) > 0.0:
        p2 = p4
      else:
        p1 = p4
  n = _portal_normal(p1.v, p2.v, p3.v)
  if inside == 0 and wp.dot(n, p1.v) < 0.0:
    return _miss()

  r = MprResult()
  r.hit = 1
  w = _closest_on_triangle(p1.v, p2.v, p3.v)
  depth = wp.length(w)
  r.depth = depth
  if depth > eps:
    r.normal = w / depth
  else:
    r.normal = n
  r.pos = _midpoint(p0, p1, p2, p3, r.normal)
  return r
