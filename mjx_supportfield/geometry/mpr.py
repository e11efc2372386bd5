"""Minkowski Portal Refinement: penetration depth, normal and midpoint of two convex shapes.

The Minkowski difference A - B is explored through support points only. Every portal
vertex keeps the two support points it came from so the contact position can be
interpolated on both surfaces.
"""

import functools
from types import SimpleNamespace

import warp as wp

from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


@wp.struct
class MprSettings:
  """MPR's options (Options.mpr_*) as the kernels take them, one argument instead of three."""

  tolerance: float  # convergence tolerance, relative to the pair's length scale
  iterations: int  # cap of each MPR (or GJK / EPA) loop
  refine: int  # reruns along the last normal (mpr_refined_from)


@functools.lru_cache(maxsize=None)
def settings(tolerance: float, iterations: int, refine: int) -> MprSettings:
  """The MprSettings of these options, made once and reused by every launch."""
  s = MprSettings()
  s.tolerance, s.iterations, s.refine = tolerance, iterations, refine
  return s


def settings_of(options) -> MprSettings:
  """The MprSettings of an Options."""
  return settings(options.mpr_tolerance, options.mpr_iterations, options.mpr_refine)


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
def _portal_normal(v1: wp.vec3, v2: wp.vec3, v3: wp.vec3) -> wp.vec3:
  return wp.normalize(wp.cross(v2 - v1, v3 - v1))


@wp.func
def miss() -> MprResult:
  """No contact."""
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
def _on_segment(a: wp.vec3, b: wp.vec3, w: wp.vec3) -> float:
  """Parameter t in [0, 1] of the point a + t (b - a) nearest to w."""
  e = b - a
  ee = wp.dot(e, e)
  if ee <= 0.0:
    return 0.0
  return wp.clamp(wp.dot(w - a, e) / ee, 0.0, 1.0)


@wp.func
def _midpoint(p1: Vertex, p2: Vertex, p3: Vertex, w: wp.vec3) -> wp.vec3:
  """Midpoint of the two shapes' points at w, a point of the portal triangle (barycentric).

  w (the origin's foot on the portal plane) can fall outside the final portal: MPR keeps the
  ray from its interior point inside it, not the foot. On a thin portal (a cylinder's rim or a
  hull's vertex against a long hull edge) the foot's barycentric coordinates then run far out
  of [0, 1], and clamping them one after the other can pick a point of the portal centimetres
  from the foot, a contact point below the shapes (tests/test_fuzz.py, REGRESSIONS). Outside the
  portal the nearest point of its edges is interpolated instead; inside, w's own coordinates.
  """
  e1 = p2.v - p1.v
  e2 = p3.v - p1.v
  r = w - p1.v
  d11 = wp.dot(e1, e1)
  d12 = wp.dot(e1, e2)
  d22 = wp.dot(e2, e2)
  det = d11 * d22 - d12 * d12
  l2 = float(0.0)
  l3 = float(0.0)
  if det > 0.0:
    r1 = wp.dot(r, e1)
    r2 = wp.dot(r, e2)
    l2 = (d22 * r1 - d12 * r2) / det
    l3 = (d11 * r2 - d12 * r1) / det
    if not (l2 >= 0.0 and l2 <= 1.0 and l3 >= 0.0 and l3 <= 1.0 - l2):  # outside (or NaN)
      t12 = _on_segment(p1.v, p2.v, w)
      t13 = _on_segment(p1.v, p3.v, w)
      t23 = _on_segment(p2.v, p3.v, w)
      dist12 = wp.length(p1.v + t12 * e1 - w)
      dist13 = wp.length(p1.v + t13 * e2 - w)
      dist23 = wp.length(p2.v + t23 * (p3.v - p2.v) - w)
      l2 = t12
      l3 = 0.0
      if dist13 < wp.min(dist12, dist23):
        l2 = 0.0
        l3 = t13
      elif dist23 < dist12:
        l2 = 1.0 - t23
        l3 = t23
  l1 = 1.0 - l2 - l3
  return 0.5 * (l1 * (p1.a + p1.b) + l2 * (p2.a + p2.b) + l3 * (p3.a + p3.b))


@wp.func
def interior_point(a: Shape, b: Shape, scale: float) -> Vertex:
  """The centre difference, nudged off the origin: an interior point of A - B."""
  p0 = Vertex()
  p0.a = a.center
  p0.b = b.center
  p0.v = a.center - b.center
  if wp.length(p0.v) < 1.0e-10 * scale:
    p0.a = a.center + wp.vec3(1.0e-6 * scale, 0.0, 0.0)
    p0.v = p0.a - p0.b
  return p0


BEHIND = 0.1  # restarts' interior points: this x the pair's scale behind the origin, at most


DEEP_RATIO = 0.1  # MPR depths beyond this x the pair's scale are checked along the shapes' axes
LOCAL_AXES = 12  # the signed local axes of both shapes such a depth is checked along (_axis)


@wp.func
def _axis(a: Shape, b: Shape, k: int) -> wp.vec3:
  """The k-th of the LOCAL_AXES signed local axes of A (k < 6) and B."""
  rot = a.rot
  if k >= 6:
    rot = b.rot
  col = k % 3
  sign = wp.where((k // 3) % 2 == 0, 1.0, -1.0)
  return sign * wp.vec3(rot[0, col], rot[1, col], rot[2, col])


@functools.lru_cache(maxsize=None)
def mpr_funcs(mode: int) -> SimpleNamespace:
  """MPR's device functions on the support functions of support mode ``mode`` (support_funcs):
  ``apart_along_centres``, ``mpr``, ``mpr_refined_from``, ``behind_origin`` and ``mpr_refined``."""
  support_world = support_funcs(mode).support_world

  @wp.func
  def _support(a: Shape, b: Shape, ms: MeshSupport, d: wp.vec3) -> Vertex:
    out = Vertex()
    out.a = support_world(a, ms, d)
    out.b = support_world(b, ms, -d)
    out.v = out.a - out.b
    return out

  @wp.func
  def apart_along_centres(a: Shape, b: Shape, ms: MeshSupport, scale: float) -> bool:
    """Whether A and B are proven apart along the line through their centres: the test of MPR's
    first step from interior_point, so mpr() from there misses exactly for these pairs."""
    p0 = interior_point(a, b, scale)
    d = wp.normalize(-p0.v)
    return wp.dot(_support(a, b, ms, d).v, d) <= 0.0

  @wp.func
  def mpr(a: Shape, b: Shape, ms: MeshSupport, p0: Vertex, scale: float, tol: float, iterations: int) -> MprResult:
    """Penetration of A and B by MPR from interior point p0 of A - B; hit == 0 when they do not overlap.

    scale: a length of the pair (degeneracy thresholds are relative to it); tol: convergence
    tolerance relative to scale; iterations: cap of each loop (no unbounded loop on the GPU).
    """
    eps = 1.0e-10 * scale
    atol = tol * scale

    # portal discovery
    d = wp.normalize(-p0.v)
    p1 = _support(a, b, ms, d)
    if wp.dot(p1.v, d) <= 0.0:
      return miss()
    d = wp.cross(p0.v, p1.v)
    if wp.length(d) < eps * scale:
      return _single_point(p1)
    d = wp.normalize(d)
    p2 = _support(a, b, ms, d)
    if wp.dot(p2.v, d) <= 0.0:
      return miss()
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
      p3 = _support(a, b, ms, d)
      if wp.dot(p3.v, d) <= 0.0:
        return miss()
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
      return miss()

    # refine the portal until the origin is behind it, then push it to the boundary
    inside = int(0)
    for _ in range(iterations):
      n = _portal_normal(p1.v, p2.v, p3.v)
      if inside == 0 and wp.dot(n, p1.v) >= 0.0:
        inside = 1
      p4 = _support(a, b, ms, n)
      d4 = wp.dot(p4.v, n)
      if inside == 0 and d4 < 0.0:
        return miss()
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
      return miss()

    # the portal lies on the boundary of A - B: its plane's distance to the origin is the
    # depth along its normal (on curved boundaries the plane is the tangent plane there)
    r = MprResult()
    r.hit = 1
    r.normal = n
    r.depth = wp.max(wp.dot(n, p1.v), 0.0)
    r.pos = _midpoint(p1, p2, p3, r.depth * n)
    return r

  @wp.func
  def mpr_refined_from(
    a: Shape,
    b: Shape,
    ms: MeshSupport,
    p0: Vertex,
    scale: float,
    tol: float,
    iterations: int,
    refine: int,
    least: float,
  ) -> MprResult:
    """MPR from interior point p0, then up to ``refine`` reruns along the last normal; the
    shallowest answer wins. The reruns start ``behind_origin(..., least)``.

    MPR answers where the ray from its interior point through the origin leaves A - B: the
    penetration along that ray, not the smallest one. Restarting from a point behind the origin
    on the normal (``behind_origin``) sends the ray along the normal; on curved surfaces this
    walks to the point whose surface normal is the ray, the minimum.

    It stays on the face it found, though: an answer deeper than ``DEEP_RATIO`` x ``scale`` is
    also checked along both shapes' local axes and rerun along any shallower one (two 1 mm plates
    crossing at a small angle, offset sideways, came out 0.7 m deep along their length instead of
    MuJoCo C's 2.5 mm across their thickness).
    """
    best = mpr(a, b, ms, p0, scale, tol, iterations)
    if best.hit == 0:
      return best
    # the ray already running along the normal is MPR's fixed point: nothing to refine
    refining = bool(wp.dot(best.normal, wp.normalize(-p0.v)) <= 1.0 - 1.0e-6)
    deep = best.depth > DEEP_RATIO * scale
    k = int(0)  # next local axis to check
    nrerun = int(0)  # reruns along the normal so far
    # one MPR call site for the reruns and the axis checks keeps the kernels' stack small
    for _ in range(refine + LOCAL_AXES):
      u = wp.vec3(best.normal)
      start = float(best.depth)
      if refining and (nrerun >= refine or best.depth <= 1.0e-6 * scale):
        refining = False
      if not refining:
        if not deep:
          break
        found = bool(False)
        while k < LOCAL_AXES and not found:
          u = _axis(a, b, k)
          k += 1
          start = wp.dot(_support(a, b, ms, u).v, u)
          found = start > 0.0 and start < best.depth - tol * scale
        if not found:
          break
      r = mpr(a, b, ms, behind_origin(a, b, ms, u, start, scale, least), scale, tol, iterations)
      if refining:
        nrerun += 1
        if r.hit == 0 or r.depth >= best.depth - tol * scale:
          refining = False
          continue
        # the same normal again (a flat face of a polytope, or converged): nothing left to gain
        if wp.dot(r.normal, best.normal) > 1.0 - 1.0e-6:
          refining = False
        best = r
      elif r.hit != 0 and r.depth < best.depth - tol * scale:
        best = r
    return best

  @wp.func
  def behind_origin(
    a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3, depth: float, scale: float, least: float
  ) -> Vertex:
    """An interior point of A - B behind the origin along ``normal``: MPR's ray from there runs
    along ``normal``.

    Half the larger of ``depth`` and ``least`` x scale behind the origin, but never past half of
    how far A - B reaches behind it (one support query), so thin shapes keep it inside. With
    least = 0, half a resting contact's few µm is too close: there the portal search is
    ill-conditioned and runs out of iterations (tilted MPRs on resting meshes missed that way);
    BEHIND avoids that.
    """
    back = wp.dot(_support(a, b, ms, -normal).v, -normal)
    dist = wp.max(wp.min(wp.max(depth, least * scale), back), 1.0e-6 * scale)
    q0 = Vertex()
    q0.v = -0.5 * dist * normal
    return q0

  @wp.func
  def mpr_refined(
    a: Shape, b: Shape, ms: MeshSupport, scale: float, tol: float, iterations: int, refine: int, least: float
  ) -> MprResult:
    """Cold MPR: from the centre difference, refined along the normal (see ``mpr_refined_from``)."""
    return mpr_refined_from(a, b, ms, interior_point(a, b, scale), scale, tol, iterations, refine, least)

  return SimpleNamespace(apart_along_centres=apart_along_centres, mpr=mpr, mpr_refined_from=mpr_refined_from,
                         behind_origin=behind_origin, mpr_refined=mpr_refined)
