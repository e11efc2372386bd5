"""Minkowski Portal Refinement: penetration depth, normal and midpoint of two convex shapes.

The Minkowski difference A - B is explored through support points only. Every portal
vertex keeps the two support points it came from so the contact position can be
interpolated on both surfaces.
"""

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.support import hull_point
from mjx_supportfield.support import mesh_support_index
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
  of [0, 1] (seen: -0.6 and 0.8 on a sliver along a 4 cm hull edge), and clamping them one after
  the other picked a point of the portal over 2 cm from the foot: the contact point came out 11 mm
  below the cylinder (tests/test_fuzz.py, REGRESSIONS). Outside the portal the nearest point of
  its edges is interpolated instead; inside, the coordinates are the same as before.
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


@wp.func
def apart_along_centres(a: Shape, b: Shape, ms: MeshSupport, mode: int, scale: float) -> bool:
  """Whether A and B are proven apart along the line through their centres: the test of MPR's
  first step from interior_point, so mpr() from there misses exactly for these pairs."""
  p0 = interior_point(a, b, scale)
  d = wp.normalize(-p0.v)
  return wp.dot(_support(a, b, ms, d, mode).v, d) <= 0.0


@wp.func
def mpr(a: Shape, b: Shape, ms: MeshSupport, mode: int, p0: Vertex, scale: float, tol: float, iterations: int) -> MprResult:
  """Penetration of A and B by MPR from interior point p0 of A - B; hit == 0 when they do not overlap.

  scale: a length of the pair (degeneracy thresholds are relative to it); tol: convergence
  tolerance relative to scale; iterations: cap of each loop (no unbounded loop on the GPU).
  """
  eps = 1.0e-10 * scale
  atol = tol * scale

  # portal discovery
  d = wp.normalize(-p0.v)
  p1 = _support(a, b, ms, d, mode)
  if wp.dot(p1.v, d) <= 0.0:
    return miss()
  d = wp.cross(p0.v, p1.v)
  if wp.length(d) < eps * scale:
    return _single_point(p1)
  d = wp.normalize(d)
  p2 = _support(a, b, ms, d, mode)
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
    p3 = _support(a, b, ms, d, mode)
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
    p4 = _support(a, b, ms, n, mode)
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
  mode: int,
  p0: Vertex,
  scale: float,
  tol: float,
  iterations: int,
  refine: int,
  least: float,
  size: float,
) -> MprResult:
  """MPR from interior point p0, then up to ``refine`` reruns along the last normal; the
  shallowest answer wins. The reruns start ``behind_origin(..., least)``. size: a length of the
  smaller shape (its bounding radius) for the face checks below; 0 turns them off.

  MPR answers where the ray from its interior point through the origin leaves A - B: the
  penetration along that ray, not the smallest one. Restarting from a point behind the origin
  on the normal (``behind_origin``) sends the ray along the normal; on curved surfaces this
  walks to the point whose surface normal is the ray, the minimum.

  It stays on the face it found, though: a deep pair's A - B has several faces that the origin
  projects into, and the ray and the reruns settle on one of them, not always the nearest. An
  answer deeper than ``FACE_RATIO`` x ``size`` is checked along the face normals of both shapes
  at their support points and the cross products of their edges there (``shallowest_face``),
  and rerun, then refined, along the one with the smallest overlap when that is shallower: a
  dodecahedron in a tetrahedron came out 2.95 mm deep along one of its faces, where a face of the
  tetrahedron gives 2.11 mm and the refinement from there 1.89 mm, the penetration depth. An
  answer deeper than ``DEEP_RATIO`` x ``scale`` has its first face check take every hull face,
  and is also checked along both shapes' local axes and rerun along any shallower one (two 1 mm
  plates crossing at a small angle, offset sideways, came out 0.7 m deep along their length
  instead of MuJoCo C's 2.5 mm across their thickness).
  """
  best = mpr(a, b, ms, mode, p0, scale, tol, iterations)
  if best.hit == 0:
    return best
  # the ray already running along the normal is MPR's fixed point: nothing to refine
  refining = bool(wp.dot(best.normal, wp.normalize(-p0.v)) <= 1.0 - 1.0e-6)
  deep = best.depth > DEEP_RATIO * scale
  faces = wp.where(best.depth > FACE_RATIO * size and size > 0.0, FACE_JUMPS, 0)  # face checks left
  k = int(0)  # next local axis to check
  nrerun = int(0)  # reruns along the normal so far
  # one MPR call site for the reruns, the face checks and the axis checks keeps the kernels'
  # stack small
  for _ in range(refine + 12 + FACE_JUMPS * (refine + 1)):
    u = wp.vec3(best.normal)
    start = float(best.depth)
    if refining and (nrerun >= refine or best.depth <= 1.0e-6 * scale):
      refining = False
    jump = bool(False)
    if not refining and faces > 0:
      faces -= 1
      face = shallowest_face(a, b, ms, mode, best.normal)
      if deep and faces == FACE_JUMPS - 1:
        # far deeper than contacts get: all the hulls' faces, not only those at hand
        face = _scan_planes(a, a, b, ms, mode, 1.0, face)
        face = _scan_planes(b, a, b, ms, mode, -1.0, face)
      # a face that ties with the answer (its own face, up to rounding) is not worth an MPR
      jump = face[3] > 0.0 and face[3] < (1.0 - FACE_GAIN) * best.depth - tol * scale
      if jump:
        u = wp.vec3(face[0], face[1], face[2])
        start = face[3]
      else:
        faces = 0
    if not refining and not jump:
      if not deep:
        break
      found = bool(False)
      while k < 12 and not found:
        u = _axis(a, b, k)
        k += 1
        start = wp.dot(_support(a, b, ms, u, mode).v, u)
        found = start > 0.0 and start < best.depth - tol * scale
      if not found:
        break
    r = mpr(a, b, ms, mode, behind_origin(a, b, ms, mode, u, start, scale, least), scale, tol, iterations)
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
      if jump:
        # MPR left along the face normal; refine from where it landed, then check its faces
        refining = wp.dot(r.normal, u) <= 1.0 - 1.0e-6
        nrerun = 0
    elif jump:
      faces = 0  # nothing shallower along that face: checking again would rerun the same MPR
  return best


BEHIND = 0.1  # restarts' interior points: this x the pair's scale behind the origin, at most


@wp.func
def behind_origin(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, normal: wp.vec3, depth: float, scale: float, least: float
) -> Vertex:
  """An interior point of A - B behind the origin along ``normal``: MPR's ray from there runs
  along ``normal``.

  Half the larger of ``depth`` and ``least`` x scale behind the origin, but never past half of
  how far A - B reaches behind it (one support query), so thin shapes keep it inside. With
  least = 0, half a resting contact's few µm is too close: there the portal search is
  ill-conditioned and runs out of iterations (on a settled pile of meshes, 9 % of the tilted
  MPRs missed that way); BEHIND avoids that.
  """
  back = wp.dot(_support(a, b, ms, -normal, mode).v, -normal)
  dist = wp.max(wp.min(wp.max(depth, least * scale), back), 1.0e-6 * scale)
  q0 = Vertex()
  q0.v = -0.5 * dist * normal
  return q0


DEEP_RATIO = 0.1  # MPR depths beyond this x the pair's scale are checked along the shapes' axes
FACE_RATIO = 0.03  # MPR depths beyond this x the smaller shape's size are checked along the faces at hand
FACE_JUMPS = 2  # face checks (each may rerun and refine MPR) per pair at most
FACE_GAIN = 1.0e-4  # a face check reruns MPR for an overlap at least this fraction below the depth
FACE_COS = 1.0 - 1.0e-4  # a hull polygon whose normal is this close to a direction faces it


@wp.func
def _shallower(a: Shape, b: Shape, ms: MeshSupport, mode: int, u: wp.vec3, best: wp.vec4) -> wp.vec4:
  """best (a direction from A to B and the overlap of A and B along it), or u with its overlap
  when that is smaller."""
  h = wp.dot(_support(a, b, ms, u, mode).v, u)
  if h < best[3]:
    return wp.vec4(u[0], u[1], u[2], h)
  return best


@wp.func
def _support_vertex(s: Shape, ms: MeshSupport, d: wp.vec3, mode: int) -> int:
  """Local hull index of a mesh shape's support vertex for world direction d; -1 for other types."""
  if s.gtype == GeomType.MESH:
    return mesh_support_index(ms, s.mesh, wp.transpose(s.rot) @ d, mode)
  return -1


@wp.func
def _faces_at_support(
  s: Shape, vertex: int, a: Shape, b: Shape, ms: MeshSupport, mode: int, d: wp.vec3, sign: float, best: wp.vec4
) -> wp.vec4:
  """best improved by the outward normals (times sign) of the faces of s (A or B) that hold its
  support point for direction d (a mesh's: its support vertex): a mesh's hull polygons around
  that vertex, a box's three faces at its corner, a cylinder's cap and side. Curved shapes have
  none: there the refinement along the normal already finds the nearest point."""
  local = wp.transpose(s.rot) @ d
  if s.gtype == GeomType.BOX:
    for c in range(3):
      axis = wp.vec3(s.rot[0, c], s.rot[1, c], s.rot[2, c])
      best = _shallower(a, b, ms, mode, sign * wp.where(local[c] >= 0.0, 1.0, -1.0) * axis, best)
  elif s.gtype == GeomType.CYLINDER:
    axis = wp.vec3(s.rot[0, 2], s.rot[1, 2], s.rot[2, 2])
    best = _shallower(a, b, ms, mode, sign * wp.where(local[2] >= 0.0, 1.0, -1.0) * axis, best)
    rxy = wp.sqrt(local[0] * local[0] + local[1] * local[1])
    if rxy > 1.0e-6 * wp.length(local):
      best = _shallower(a, b, ms, mode, sign * (s.rot @ wp.vec3(local[0] / rxy, local[1] / rxy, 0.0)), best)
  elif s.gtype == GeomType.MESH:
    # a face of the hull along d: the faces around all its corners (those across its edges
    # included), else the faces around the support vertex
    face = _face_along(ms, s.mesh, vertex, local)
    ncorner = int(1)
    if face >= 0:
      ncorner = ms.poly_vert_num[face]
    for c in range(ncorner):
      corner = vertex
      if face >= 0:
        corner = ms.poly_vert[ms.poly_vert_adr[face] + c]
      g = ms.hull_adr[s.mesh] + corner
      for k in range(ms.vert_poly_num[g]):
        poly = ms.poly_adr[s.mesh] + ms.vert_poly[ms.vert_poly_adr[g] + k]
        best = _shallower(a, b, ms, mode, sign * (s.rot @ ms.poly_normal[poly]), best)
  return best


@wp.func
def _face_along(ms: MeshSupport, mesh: int, vertex: int, d: wp.vec3) -> int:
  """The hull polygon (global index) around hull vertex ``vertex`` that faces direction d (mesh
  frame) when one does, else -1."""
  g = ms.hull_adr[mesh] + vertex
  dn = wp.normalize(d)
  for k in range(ms.vert_poly_num[g]):
    poly = ms.poly_adr[mesh] + ms.vert_poly[ms.vert_poly_adr[g] + k]
    if wp.dot(ms.poly_normal[poly], dn) > FACE_COS and ms.poly_vert_num[poly] >= 3:
      return poly
  return -1


@wp.func
def _edge_count(s: Shape, ms: MeshSupport, vertex: int) -> int:
  """Edges of s at its support point: a box's 3, a mesh's hull edges at its support vertex."""
  if s.gtype == GeomType.BOX:
    return 3
  if s.gtype == GeomType.MESH:
    return ms.nbr_num[ms.hull_adr[s.mesh] + vertex]
  return 0


@wp.func
def _edge(s: Shape, ms: MeshSupport, vertex: int, k: int) -> wp.vec3:
  """The k-th edge (world direction, not unit) of s at its support point (see _edge_count)."""
  if s.gtype == GeomType.BOX:
    return wp.vec3(s.rot[0, k], s.rot[1, k], s.rot[2, k])
  g = ms.hull_adr[s.mesh] + vertex
  other = ms.nbr[ms.nbr_adr[g] + k]
  return s.rot @ (hull_point(ms, s.mesh, other) - hull_point(ms, s.mesh, vertex))


@wp.func
def shallowest_face(a: Shape, b: Shape, ms: MeshSupport, mode: int, normal: wp.vec3) -> wp.vec4:
  """Of the face normals of A at its support point along ``normal``, of B at its support point
  along -normal (negated: every direction points from A to B) and the cross products of the
  edges there, the direction along which A and B overlap least, and that overlap (xyz, w).

  A polytope pair's penetration depth is its overlap along a face normal of either shape or along
  a cross product of their edges; MPR's answer lies on a face of A - B, and the faces of A - B
  that the shapes' support features make there are its neighbours, one of which is shallower
  when MPR did not settle on the nearest face.
  """
  va = _support_vertex(a, ms, normal, mode)
  vb = _support_vertex(b, ms, -normal, mode)
  best = wp.vec4(normal[0], normal[1], normal[2], 1.0e30)
  best = _faces_at_support(a, va, a, b, ms, mode, normal, 1.0, best)
  best = _faces_at_support(b, vb, a, b, ms, mode, -normal, -1.0, best)
  nb = _edge_count(b, ms, vb)
  for i in range(_edge_count(a, ms, va)):
    ea = _edge(a, ms, va, i)
    for j in range(nb):
      eb = _edge(b, ms, vb, j)
      c = wp.cross(ea, eb)
      if wp.length(c) > 1.0e-6 * wp.length(ea) * wp.length(eb):
        c = wp.normalize(c)
        best = _shallower(a, b, ms, mode, wp.where(wp.dot(c, normal) < 0.0, -c, c), best)
  return best


@wp.func
def _scan_planes(s: Shape, a: Shape, b: Shape, ms: MeshSupport, mode: int, sign: float, best: wp.vec4) -> wp.vec4:
  """best improved by every hull face normal (times sign) of mesh shape s (A or B)."""
  if s.gtype != GeomType.MESH:
    return best
  adr = ms.plane_adr[s.mesh]
  for f in range(ms.plane_num[s.mesh]):
    plane = ms.plane[adr + f]
    best = _shallower(a, b, ms, mode, sign * (s.rot @ wp.vec3(plane[0], plane[1], plane[2])), best)
  return best


@wp.func
def _axis(a: Shape, b: Shape, k: int) -> wp.vec3:
  """The k-th of the 12 signed local axes of A (k < 6) and B."""
  rot = a.rot
  if k >= 6:
    rot = b.rot
  col = k % 3
  sign = wp.where((k // 3) % 2 == 0, 1.0, -1.0)
  return sign * wp.vec3(rot[0, col], rot[1, col], rot[2, col])


@wp.func
def mpr_refined(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, scale: float, tol: float, iterations: int, refine: int, least: float
) -> MprResult:
  """Cold MPR: from the centre difference, refined along the normal (see ``mpr_refined_from``;
  no face checks)."""
  return mpr_refined_from(a, b, ms, mode, interior_point(a, b, scale), scale, tol, iterations, refine, least, 0.0)
