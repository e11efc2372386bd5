"""Multi-contact: more points of a contact patch than MPR's (or GJK/EPA's) one.

Face clipping (face_manifold) first. Where the contact normal n lies along a flat face of one
shape (a box face, a cylinder's end, a hull polygon of MuJoCo's), that face is the reference
and the other shape's feature facing it (its face most anti-parallel to the reference face,
or the line of a cylinder's side or a capsule lying on it) the incident one: the incident
polygon clipped to the reference face's side planes is the patch, and its corners below the
reference plane are the contacts (MuJoCo's multi-CCD does the same from EPA's features).

Pose perturbation for the rest (edge against edge, curved surfaces): after the first contact
(normal n, depth d0, point p0), shape A is tilted by +-eps about the two diagonals of the
contact plane, around p0. A tilted A digs into B at another end of the patch; MPR finds the
witness points there, A's is mapped back to A's true pose, and the point is kept when it still
penetrates along n and is not a duplicate of one already kept. A tilt that lands back on a
point already found (the faces meet at a larger angle than eps, so the same vertex stays
deepest) is retried once, TILT_GROWTH times steeper: 0.09 rad at the default eps, about the
0.089 rad within which MuJoCo's multi-CCD takes two faces as touching.

Most tilts need no MPR. The tilted MPR looks along n, and the face of A' - B its ray leaves
through is usually a vertex of one shape against a flat face of the other: A''s vertex through
B's face that faces A, or B's vertex through A''s face that faces B. A face and a support query
give each, and where the ray provably leaves through one of them the tilt's answer follows in
closed form (tilt_closed_form); only the rest (edge against edge, curved sides) run the tilted
MPR.
"""

import math

import warp as wp
from mujoco_warp._src.collision_gjk import EDGE_TOL
from mujoco_warp._src.collision_gjk import FACE_TOL
from mujoco_warp._src.collision_gjk import INTERSECT_TOL
from mujoco_warp._src.collision_gjk import _area4
from mujoco_warp._src.collision_gjk import _halfspace
from mujoco_warp._src.collision_gjk import _plane_intersect
from mujoco_warp._src.collision_gjk import _plane_normal
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import GeomType

from mjx_supportfield.mpr import MprResult
from mjx_supportfield.mpr import BEHIND
from mjx_supportfield.mpr import behind_origin
from mjx_supportfield.mpr import mpr
from mjx_supportfield.support import count_supports
from mjx_supportfield.support import hull_point
from mjx_supportfield.support import mesh_support_index
from mjx_supportfield.support import support_world
from mjx_supportfield.types import SUPPORT_REFINED
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

NPERTURB = 4  # tilts: +-eps about each diagonal of the contact plane
# a tilted MPR starts next to its answer: it needs few iterations, and its point only has to
# land on the right corner of the patch (its depth is measured again in the true pose). At the
# main MPR's tolerance, float32 noise of the tilted poses kept it iterating to the cap.
TILT_TOL = 1.0e-6
TILT_ITERATIONS = 16
TILT_GROWTH = 9.0  # the retry's tilt, in units of eps
MISSED = wp.constant(-1.0e30)  # depth of a tilt whose shapes do not overlap
UNKNOWN = wp.constant(1.0e30)  # depth of a tilt the closed form cannot answer: MPR must
# a closed-form point may lie this far (x the pair's scale) off the other shape's face: a
# corner sitting on a face's edge is on the face up to float32 noise
ON_FACE_TOL = 1.0e-5

# polygons whose normals' dot products with a direction differ by less are coplanar pieces
COPLANAR = 1.0e-5
mat43 = wp.types.matrix(shape=(4, 3), dtype=float)


@wp.struct
class Patch:
  """Extra contact points (at most NPERTURB), all with the first contact's normal."""

  n: int
  pos: mat43  # midpoints
  depth: wp.vec4


@wp.func
def _tilted(a: Shape, pivot: wp.vec3, rot: wp.mat33) -> Shape:
  out = a
  out.rot = rot @ a.rot
  out.pos = pivot + rot @ (a.pos - pivot)
  out.center = pivot + rot @ (a.center - pivot)
  return out


@wp.func
def _mesh_ties(ms: MeshSupport, mesh: int, d: wp.vec3, rtol: float, slack: float) -> int:
  """1 + the support vertex's hull neighbours that tie with it (capped at 3): enough to tell a
  vertex from an edge from a face, without count_supports' flood fill."""
  best = mesh_support_index(ms, mesh, d, SUPPORT_REFINED)
  top = wp.dot(hull_point(ms, mesh, best), d)
  extent = wp.max(wp.length(hull_point(ms, mesh, best) - ms.hull_center[mesh]), 1.0e-12)
  if ms.nbr_num.shape[0] == 0:
    return count_supports(GeomType.MESH, wp.vec3(0.0), mesh, ms, d, wp.max(rtol, slack / extent))
  tol = wp.max(rtol * extent, slack)
  g = ms.hull_adr[mesh] + best
  n = int(1)
  for k in range(ms.nbr_num[g]):
    if n < 3 and wp.dot(hull_point(ms, mesh, ms.nbr[ms.nbr_adr[g] + k]), d) >= top - tol:
      n += 1
  return n


@wp.func
def _ties(s: Shape, ms: MeshSupport, d_world: wp.vec3, rtol: float, slack: float) -> int:
  """How many support points a shape has in direction d within rtol of its extent, or within
  slack: 1 for a point, 2 for an edge or a line, 3 for a face (or more, counted, for boxes and
  meshes)."""
  d = wp.normalize(wp.transpose(s.rot) @ d_world)
  if s.gtype == GeomType.BOX:
    return count_supports(s.gtype, s.size, s.mesh, ms, d, wp.max(rtol, slack / wp.max(wp.length(s.size), 1.0e-12)))
  if s.gtype == GeomType.MESH:
    return _mesh_ties(ms, s.mesh, d, rtol, slack)
  if s.gtype == GeomType.CYLINDER:
    tol = wp.max(rtol * wp.length(wp.vec2(s.size[0], s.size[1])), slack)
    if wp.sqrt(wp.max(1.0 - d[2] * d[2], 0.0)) * s.size[0] <= tol:
      return 3  # an end disk
    if wp.abs(d[2]) * s.size[1] <= tol:
      return 2  # a line of the side
  if s.gtype == GeomType.CAPSULE:
    if wp.abs(d[2]) * s.size[1] <= wp.max(rtol * (s.size[0] + s.size[1]), slack):
      return 2
  return 1


@wp.func
def patch_possible(a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3, eps: float, depth: float) -> bool:
  """Whether the contact can have more points than the first: both shapes must offer at least
  an edge along the normal (face-face, face-edge, parallel edges), up to what a tilt by eps
  brings in (eps x the shape's extent) or what sinks as deep as the first contact (``depth``,
  margin band included). Vertex contacts skip the multi-contact stage."""
  return _ties(a, ms, normal, eps, depth) >= 2 and _ties(b, ms, -normal, eps, depth) >= 2


@wp.func
def keep_first(first: MprResult, patch: Patch, min_spacing: float, tol: float) -> bool:
  """Whether MPR's own point belongs to the contact set besides the patch's points.

  Three or more patch points span a face contact and MPR's point, somewhere on that face, is
  left out unless deeper than all of them by more than tol: on a face it lands on one corner
  or another as the bodies rock, and writing it made the contact count flicker. It is also
  left out when it duplicates a patch point.
  """
  deepest = float(-1.0e30)
  for j in range(patch.n):
    deepest = wp.max(deepest, patch.depth[j])
    if wp.length(first.pos - wp.vec3(patch.pos[j, 0], patch.pos[j, 1], patch.pos[j, 2])) < min_spacing:
      return False
  return patch.n < 3 or first.depth > deepest + tol


@wp.func
def _tilt_axis(normal: wp.vec3, k: int) -> wp.vec3:
  """Axis of tilt k: a diagonal of the contact plane (k < 2: one, else the other)."""
  frame = make_frame(normal)
  t1 = wp.vec3(frame[1, 0], frame[1, 1], frame[1, 2])
  t2 = wp.vec3(frame[2, 0], frame[2, 1], frame[2, 2])
  return wp.normalize(wp.where(k < 2, t1 + t2, t1 - t2))


@wp.func
def tilt_rotation(normal: wp.vec3, eps: float, k: int, attempt: int) -> wp.mat33:
  """Rotation of tilt k (+-eps about a diagonal of the contact plane), attempt 0 or 1 (the
  retry, TILT_GROWTH times steeper)."""
  angle = float(wp.where(k % 2 == 0, eps, -eps))
  if attempt == 1:
    angle *= TILT_GROWTH
  return wp.quat_to_matrix(wp.quat_from_axis_angle(_tilt_axis(normal, k), angle))


@wp.func
def _mapped_back(first: MprResult, rot: wp.mat33, pa: wp.vec3, pb: wp.vec3) -> wp.vec4:
  """A tilt's answer from its witness points in the tilted pose: A's rotates back with A; the
  midpoint (xyz) and the depth along the first normal (w)."""
  pa = first.pos + wp.transpose(rot) @ (pa - first.pos)
  pos = 0.5 * (pa + pb)
  return wp.vec4(pos[0], pos[1], pos[2], wp.dot(pa - pb, first.normal))


@wp.func
def tilt_mpr(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  rot: wp.mat33
) -> wp.vec4:
  """MPR with A tilted by ``rot`` about the first contact: the point (xyz) and its depth along
  the first normal (w), A's witness point rotated back with A; depth MISSED when the tilted
  shapes do not overlap."""
  # every tilted MPR starts warm: looking along the first normal, from behind the origin
  tilted = _tilted(a, first.pos, rot)
  q0 = behind_origin(tilted, b, ms, mode, first.normal, first.depth, scale, BEHIND)
  r = mpr(tilted, b, ms, mode, q0, scale, wp.max(tol, TILT_TOL), wp.min(iterations, TILT_ITERATIONS))
  if r.hit == 0:
    return wp.vec4(0.0, 0.0, 0.0, MISSED)
  # witness points in the tilted pose (pa - pb = depth * normal)
  return _mapped_back(first, rot, r.pos + 0.5 * r.depth * r.normal, r.pos - 0.5 * r.depth * r.normal)


@wp.func
def _polygon_toward(ms: MeshSupport, mesh: int, vertex: int, u: wp.vec3) -> int:
  """The hull polygon (global index) around hull vertex ``vertex`` whose normal is nearest to
  direction u (mesh frame); -1 when the mesh has no polygons. Of coplanar polygons (MuJoCo
  leaves some faces split, a dodecahedron's pentagon into a triangle and a quadrilateral) the
  one with more corners."""
  g = ms.hull_adr[mesh] + vertex
  best = int(-1)
  best_dot = float(-2.0)
  best_num = int(0)
  for k in range(ms.vert_poly_num[g]):
    p = ms.poly_adr[mesh] + ms.vert_poly[ms.vert_poly_adr[g] + k]
    c = wp.dot(ms.poly_normal[p], u)
    num = ms.poly_vert_num[p]
    if num >= 3 and (c > best_dot + COPLANAR or (c > best_dot - COPLANAR and num > best_num)):
      best = p
      best_dot = c
      best_num = num
  return best


@wp.func
def _in_polygon(ms: MeshSupport, mesh: int, poly: int, x: wp.vec3, tol: float) -> bool:
  """Whether point x (mesh frame, in the polygon's plane) lies inside hull polygon ``poly``,
  up to tol."""
  normal = ms.poly_normal[poly]
  adr = ms.poly_vert_adr[poly]
  nvert = ms.poly_vert_num[poly]
  prev = hull_point(ms, mesh, ms.poly_vert[adr + nvert - 1])
  # inside a convex polygon, x is on the same side of every edge, whatever the winding
  left = bool(False)
  right = bool(False)
  for j in range(nvert):
    cur = hull_point(ms, mesh, ms.poly_vert[adr + j])
    e = cur - prev
    side = wp.dot(wp.cross(e, x - prev), normal)
    slack = tol * wp.length(e)
    if side > slack:
      left = True
    if side < -slack:
      right = True
    prev = cur
  return not (left and right)


@wp.func
def _face_toward(s: Shape, ms: MeshSupport, u: wp.vec3, mode: int) -> tuple[wp.vec3, wp.vec3, int]:
  """The flat face of s whose outward normal is nearest to world direction u: its normal and a
  point of its plane (world; grown by s.inflate) and an id for _in_face (a box face, a
  cylinder's end, a mesh's hull polygon); id -1 when s has no flat face there."""
  lu = wp.transpose(s.rot) @ u
  normal = wp.vec3(0.0)
  point = wp.vec3(0.0)
  face = int(-1)
  if s.gtype == GeomType.BOX:
    k = int(0)
    for i in range(1, 3):
      if wp.abs(lu[i]) > wp.abs(lu[k]):
        k = i
    sign = wp.where(lu[k] >= 0.0, 1.0, -1.0)
    normal[k] = sign
    point[k] = sign * s.size[k]
    face = 2 * k + wp.where(sign > 0.0, 1, 0)
  elif s.gtype == GeomType.CYLINDER:
    sign = wp.where(lu[2] >= 0.0, 1.0, -1.0)
    normal = wp.vec3(0.0, 0.0, sign)
    point = wp.vec3(0.0, 0.0, sign * s.size[1])
    face = wp.where(sign > 0.0, 1, 0)
  elif s.gtype == GeomType.MESH:
    vertex = mesh_support_index(ms, s.mesh, lu, mode)
    face = _polygon_toward(ms, s.mesh, vertex, lu)
    if face >= 0:
      normal = ms.poly_normal[face]
      point = hull_point(ms, s.mesh, vertex)
  normal = s.rot @ normal
  return normal, s.pos + s.rot @ point + s.inflate * normal, face


@wp.func
def _in_face(s: Shape, ms: MeshSupport, face: int, x: wp.vec3, tol: float) -> bool:
  """Whether world point x, in the plane of _face_toward's face ``face`` of s, lies on that face
  (up to tol; the grown box or cylinder stands for s grown by s.inflate)."""
  local = wp.transpose(s.rot) @ (x - s.pos)
  grow = s.inflate + tol
  if s.gtype == GeomType.BOX:
    return (wp.abs(local[0]) <= s.size[0] + grow and wp.abs(local[1]) <= s.size[1] + grow
            and wp.abs(local[2]) <= s.size[2] + grow)
  if s.gtype == GeomType.CYLINDER:
    return wp.length(wp.vec2(local[0], local[1])) <= s.size[0] + grow
  if s.gtype == GeomType.MESH:
    return _in_polygon(ms, s.mesh, face, local - s.inflate * ms.poly_normal[face], tol)
  return False


NO_FACE = wp.constant(0)
OFF_FACE = wp.constant(1)
EXIT_FACE = wp.constant(2)


@wp.func
def _vertex_on_face(v: Shape, f: Shape, ms: MeshSupport, mode: int, ray: wp.vec3, tol: float
                    ) -> tuple[wp.vec3, wp.vec3, float, int]:
  """A face of the Minkowski difference V - F seen by MPR's ray from the origin along ``ray``:
  the flat face of ``f`` facing ``v`` (outward normal nearest to -ray) against the vertex of v
  deepest through it. Returns that vertex, its foot on the face (MPR's two witness points when
  the ray leaves V - F through this face), the depth (<= 0: V and F are apart) and NO_FACE
  (f has no flat face there), OFF_FACE (the ray leaves through another face of V - F, or
  MPR's witness would not be the foot) or EXIT_FACE.

  The ray meets the face's plane at depth / cos; it leaves V - F there exactly when that point
  of the plane lies on the face (a convex body's boundary meets the ray once)."""
  normal, point, face = _face_toward(f, ms, -ray, mode)
  if face < 0:
    return wp.vec3(0.0), wp.vec3(0.0), 1.0, NO_FACE
  m = -normal  # the outward normal of this face of V - F
  vertex = support_world(v, ms, m, mode)
  depth = wp.dot(vertex - point, m)
  foot = vertex - depth * m
  cos = wp.dot(ray, m)
  status = OFF_FACE
  if cos > 0.0 and _in_face(f, ms, face, vertex - depth / cos * ray, tol) and _in_face(f, ms, face, foot, tol):
    status = EXIT_FACE
  return vertex, foot, depth, status


@wp.func
def tilt_closed_form(a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, rot: wp.mat33
                     ) -> wp.vec4:
  """tilt_mpr's answer without MPR where the tilted MPR's ray leaves A' - B (A' = A tilted by
  ``rot`` about the first contact) through a vertex of one shape against a flat face of the
  other; depth UNKNOWN where it does not (edge against edge, curved faces) or may not.

  MPR's ray runs along the first normal n. Two faces of A' - B are tried: A''s vertex deepest
  through B's face that faces A, and B's vertex deepest through A''s face that faces B (a
  face of B - A', whose ray runs along -n). Either proves the shapes apart when its depth is
  not positive, as MPR's own first step would.
  """
  at = _tilted(a, first.pos, rot)
  n = first.normal
  tol = ON_FACE_TOL * scale
  va, foot_b, depth_a, status_a = _vertex_on_face(at, b, ms, mode, n, tol)
  vb, foot_a, depth_b, status_b = _vertex_on_face(b, at, ms, mode, -n, tol)
  if (status_a != NO_FACE and depth_a <= 0.0) or (status_b != NO_FACE and depth_b <= 0.0):
    return wp.vec4(0.0, 0.0, 0.0, MISSED)
  if status_a == EXIT_FACE:
    return _mapped_back(first, rot, va, foot_b)
  if status_b == EXIT_FACE:
    return _mapped_back(first, rot, foot_a, vb)
  return wp.vec4(0.0, 0.0, 0.0, UNKNOWN)


@wp.func
def tilt_point(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  rot: wp.mat33
) -> wp.vec4:
  """A tilt's point and depth (see tilt_mpr): in closed form where it can be, else by MPR."""
  q = tilt_closed_form(a, b, ms, mode, first, scale, rot)
  if q[3] == UNKNOWN:
    q = tilt_mpr(a, b, ms, mode, first, scale, tol, iterations, rot)
  return q


@wp.func
def perturbed_contacts(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  eps: float, min_spacing: float, attempts: wp.array2d(dtype=wp.vec4), row: int
) -> Patch:
  """Up to NPERTURB further contact points of A and B around ``first`` (see the module doc).

  With ``row`` >= 0, ``attempts[row, attempt * NPERTURB + k]`` holds tilt_point of that tilt
  and attempt, computed beforehand in parallel; with row < 0 the attempts are computed here, as
  needed.
  """
  patch = Patch()
  patch.n = 0
  for k in range(NPERTURB):
    for attempt in range(2):
      q = wp.vec4()
      if row >= 0:
        q = attempts[row, attempt * NPERTURB + k]
      else:
        q = tilt_point(a, b, ms, mode, first, scale, tol, iterations, tilt_rotation(first.normal, eps, k, attempt))
      if q[3] == MISSED:
        break
      pos = wp.vec3(q[0], q[1], q[2])
      depth = q[3]
      if attempt == 1:
        # a steep tilt's point is no deeper than the first contact: its float32 noise made one
        # deeper than the shapes' overlap
        depth = wp.min(depth, first.depth)
        if wp.length(pos - first.pos) < min_spacing:
          # the steeper tilt found the first contact again: keep MPR's exact point, not this copy
          depth = first.depth
          pos = first.pos
      if depth <= 0.0:
        break
      dup = bool(False)
      for j in range(patch.n):
        if wp.length(pos - wp.vec3(patch.pos[j, 0], patch.pos[j, 1], patch.pos[j, 2])) < min_spacing:
          dup = True
      if dup or (attempt == 0 and wp.length(pos - first.pos) < min_spacing):
        continue  # back where a point already is: tilt steeper
      for c in range(3):
        patch.pos[patch.n, c] = pos[c]
      patch.depth[patch.n] = depth
      patch.n += 1
      break
  return patch


# --- Face clipping ------------------------------------------------------------------------
#
# Where the contact normal lies along a flat face of one shape (within MuJoCo's multi-CCD
# tolerance), the contact patch is that face (the reference) against the other shape's facing
# feature (the incident face, or a line of a cylinder's side or a capsule): the incident polygon
# clipped to the reference face's side planes, its corners below the reference plane. The
# clipping follows MuJoCo's multi-CCD (collision_gjk._polygon_clip / _polygon_quad) step for step
# and takes the faces' corners in MuJoCo's order, so a face on a face gives MuJoCo C's points;
# its buffers are local, a thread's own, instead of MuJoCo Warp's scratch arrays.

MAXPOLY = 40  # corners of a clipped polygon; a face pair with more goes to the tilts
MAX_MANIFOLD = 5  # contacts of a clipped pair (Options.max_contacts_per_pair's bound)
mat_poly = wp.types.matrix(shape=(2 * MAXPOLY, 3), dtype=float)  # two buffers: read one, write the other
mat_manifold = wp.types.matrix(shape=(MAX_MANIFOLD, 3), dtype=float)
vec_manifold = wp.types.vector(length=MAX_MANIFOLD, dtype=float)
vec_chosen = wp.types.vector(length=MAX_MANIFOLD, dtype=int)

# kinds of Face
FACE_NONE = wp.constant(0)
FACE_BOX = wp.constant(1)  # index: MuJoCo's box face number (0 +x, 1 -x, 2 +y, 3 -y, 4 +z, 5 -z)
FACE_MESH = wp.constant(2)  # index: the hull polygon (global)
FACE_DISK = wp.constant(3)  # index: 0 the cylinder's top end, 1 its bottom; MuJoCo's 16-gon
FACE_SEGMENT = wp.constant(4)  # a line of a cylinder's side or of a capsule: p0, p1

# corners of each box face in MuJoCo's order (collision_gjk._box_face): bit 0 set for +x, bit 1
# for +y, bit 2 for +z
_BOX_FACE_CORNERS = wp.constant(wp.types.vector(length=24, dtype=int)(
  7, 3, 1, 5, 2, 6, 4, 0, 2, 3, 7, 6, 4, 5, 1, 0, 6, 7, 5, 4, 3, 2, 0, 1))
_DISK_COS = wp.constant(wp.types.vector(length=16, dtype=float)(*[math.cos(i * math.pi / 8.0) for i in range(16)]))
_DISK_SIN = wp.constant(wp.types.vector(length=16, dtype=float)(*[math.sin(i * math.pi / 8.0) for i in range(16)]))

# Manifold.status
CLIPPED = wp.constant(0)
TILTS = wp.constant(1)  # no face pair (curved, edge on edge) or too many corners: the tilts
QUAD_TIE = 1.0e-6  # relative area below which two quadrilaterals tie (float32 rounding)
DUPLICATE = 1.0e-4  # clipped corners this close (x the polygon's size) are one
FIFTH_TIE = 1.0e-3  # and two fifth corners (the middle of an arc of a round end has two)
FIFTH_MARGIN = 0.1  # a fifth contact only where one arc of the quadrilateral gains this much more
# the first contact takes a clipped corner's place when they are all shallower than it by this
# fraction of its depth
MISSED_DEPTH = 0.1


@wp.struct
class Face:
  """A flat feature of a posed shape: a face (kind, index, corners) with its outward normal, or a
  segment (p0, p1)."""

  kind: int
  index: int
  nvert: int
  normal: wp.vec3  # world, unit
  p0: wp.vec3
  p1: wp.vec3


@wp.struct
class Manifold:
  """A clipped pair's contacts (status CLIPPED): midpoints and signed distances (negative:
  penetration) of the true surfaces, margin band removed."""

  status: int
  n: int
  pos: mat_manifold
  dist: vec_manifold


@wp.func
def _no_face() -> Face:
  f = Face()
  f.kind = FACE_NONE
  f.nvert = 0
  return f


@wp.func
def _flat_face(s: Shape, ms: MeshSupport, u: wp.vec3, mode: int) -> Face:
  """The flat face of s whose outward normal is nearest to world direction u (a box face, a
  cylinder's end, a mesh's hull polygon around its support vertex); kind FACE_NONE where s has
  none."""
  lu = wp.transpose(s.rot) @ u
  f = _no_face()
  local = wp.vec3(0.0)
  if s.gtype == GeomType.BOX:
    k = int(0)
    for i in range(1, 3):
      if wp.abs(lu[i]) > wp.abs(lu[k]):
        k = i
    sign = wp.where(lu[k] >= 0.0, 1.0, -1.0)
    local[k] = sign
    f.kind = FACE_BOX
    f.index = 2 * k + wp.where(sign > 0.0, 0, 1)
    f.nvert = 4
  elif s.gtype == GeomType.CYLINDER:
    sign = wp.where(lu[2] >= 0.0, 1.0, -1.0)
    local = wp.vec3(0.0, 0.0, sign)
    f.kind = FACE_DISK
    f.index = wp.where(sign > 0.0, 0, 1)
    f.nvert = 16
  elif s.gtype == GeomType.MESH:
    poly = _polygon_toward(ms, s.mesh, mesh_support_index(ms, s.mesh, lu, mode), lu)
    if poly >= 0:
      local = ms.poly_normal[poly]
      f.kind = FACE_MESH
      f.index = poly
      f.nvert = ms.poly_vert_num[poly]
  f.normal = s.rot @ local
  return f


@wp.func
def _incident(s: Shape, ms: MeshSupport, u: wp.vec3, mode: int) -> Face:
  """The feature of s facing world direction u (toward the reference face): its face nearest u,
  or for a cylinder lying on its side or a capsule the line of its surface along u; kind
  FACE_NONE where s meets the reference face in a point of a curved surface."""
  if s.gtype == GeomType.BOX or s.gtype == GeomType.MESH:
    return _flat_face(s, ms, u, mode)
  f = _no_face()
  lu = wp.transpose(s.rot) @ u
  if s.gtype == GeomType.CYLINDER and wp.abs(lu[2]) >= FACE_TOL:
    return _flat_face(s, ms, u, mode)
  if (s.gtype == GeomType.CYLINDER or s.gtype == GeomType.CAPSULE) and wp.abs(lu[2]) <= EDGE_TOL:
    axis = s.rot @ wp.vec3(0.0, 0.0, s.size[1])
    side = wp.vec3(0.0)
    if s.gtype == GeomType.CYLINDER:
      side = s.rot @ (s.size[0] * wp.normalize(wp.vec3(lu[0], lu[1], 0.0)))
    else:
      side = s.size[0] * u
    f.kind = FACE_SEGMENT
    f.nvert = 2
    f.normal = u
    f.p0 = s.pos + side - axis
    f.p1 = s.pos + side + axis
  return f


@wp.func
def _face_vertex(s: Shape, ms: MeshSupport, f: Face, k: int) -> wp.vec3:
  """Corner k of face f of s (world), in MuJoCo's order: clockwise seen from outside."""
  if f.kind == FACE_BOX:
    code = _BOX_FACE_CORNERS[4 * f.index + k]
    local = wp.vec3(wp.where((code & 1) != 0, s.size[0], -s.size[0]), wp.where((code & 2) != 0, s.size[1], -s.size[1]),
                    wp.where((code & 4) != 0, s.size[2], -s.size[2]))
    return s.rot @ local + s.pos
  if f.kind == FACE_MESH:
    # MuJoCo's hull polygons run counter-clockwise; collision_gjk._mesh_face reverses them
    return s.rot @ hull_point(ms, s.mesh, ms.poly_vert[ms.poly_vert_adr[f.index] + f.nvert - 1 - k]) + s.pos
  if f.kind == FACE_DISK:
    sign = wp.where(f.index != 0, -1.0, 1.0)
    local = wp.vec3(s.size[0] * _DISK_COS[k], -sign * s.size[0] * _DISK_SIN[k], sign * s.size[1])
    return s.rot @ local + s.pos
  return wp.where(k == 0, f.p0, f.p1)


@wp.func(inline=True)
def _polygon_quad(p: mat_poly, base: int, n: int) -> wp.vec4i:
  """collision_gjk._polygon_quad on a local buffer: the corners (indices from base) of a
  quadrilateral of locally largest area in the convex polygon of n > 4 corners at p[base:]. A
  corner moves on only for QUAD_TIE more area: on a round end (equal quadrilaterals) float32
  rounding chose another one every step, and a cylinder resting on its end crept."""
  b = int(1)
  c = int(2)
  d = int(3)
  res = wp.vec4i(0, b, c, d)
  # corners are read in place: a helper taking the buffer copied all of it at each call
  m = _area4(wp.vec3(p[base, 0], p[base, 1], p[base, 2]), wp.vec3(p[base + 1, 0], p[base + 1, 1], p[base + 1, 2]),
             wp.vec3(p[base + 2, 0], p[base + 2, 1], p[base + 2, 2]),
             wp.vec3(p[base + 3, 0], p[base + 3, 1], p[base + 3, 2]))
  for a in range(n):
    pa = wp.vec3(p[base + a, 0], p[base + a, 1], p[base + a, 2])
    while True:
      pb = wp.vec3(p[base + b, 0], p[base + b, 1], p[base + b, 2])
      pc = wp.vec3(p[base + c, 0], p[base + c, 1], p[base + c, 2])
      e = base + (d + 1) % n
      m_next = _area4(pa, pb, pc, wp.vec3(p[e, 0], p[e, 1], p[e, 2]))
      if m_next <= m * (1.0 + QUAD_TIE):
        break
      m = m_next
      d = (d + 1) % n
      res = wp.vec4i(a, b, c, d)
      while True:
        e = base + (c + 1) % n
        m_next = _area4(pa, wp.vec3(p[base + b, 0], p[base + b, 1], p[base + b, 2]), wp.vec3(p[e, 0], p[e, 1], p[e, 2]),
                        wp.vec3(p[base + d, 0], p[base + d, 1], p[base + d, 2]))
        if m_next <= m * (1.0 + QUAD_TIE):
          break
        m = m_next
        c = (c + 1) % n
        res = wp.vec4i(a, b, c, d)
      while True:
        e = base + (b + 1) % n
        m_next = _area4(pa, wp.vec3(p[e, 0], p[e, 1], p[e, 2]), wp.vec3(p[base + c, 0], p[base + c, 1], p[base + c, 2]),
                        wp.vec3(p[base + d, 0], p[base + d, 1], p[base + d, 2]))
        if m_next <= m * (1.0 + QUAD_TIE):
          break
        m = m_next
        b = (b + 1) % n
        res = wp.vec4i(a, b, c, d)
    if b == a:
      b = (b + 1) % n
      if c == b:
        c = (c + 1) % n
        if d == c:
          d = (d + 1) % n
  return res


@wp.func(inline=True)
def _widest_fifth(p: mat_poly, base: int, n: int, quad: wp.vec4i, tangent: wp.vec3) -> int:
  """The corner (index from base) that adds most area to the quadrilateral ``quad`` of the
  convex polygon of n corners at p[base:] (it lies on an arc between two of the quad's corners,
  and adds the triangle it makes with them), or -1 when no arc's best corner adds clearly more
  (FIFTH_MARGIN) than every other arc's: on a symmetric patch (a round end, a cube turned on a
  cube) the fifth corner would jump between arcs as the bodies settle. Within an arc, of
  corners that add as much, the one farthest along ``tangent``."""
  best = int(-1)
  gain = float(0.0)
  key = float(0.0)
  runner = float(0.0)  # the best gain of the other arcs
  for j in range(4):
    lo = quad[j]
    hi = quad[(j + 1) % 4]
    span = (hi - lo + n) % n
    arc_best = int(-1)
    arc_gain = float(0.0)
    arc_key = float(0.0)
    for k in range(1, span):
      i = (lo + k) % n
      x = wp.vec3(p[base + i, 0], p[base + i, 1], p[base + i, 2])
      x0 = wp.vec3(p[base + lo, 0], p[base + lo, 1], p[base + lo, 2])
      x1 = wp.vec3(p[base + hi, 0], p[base + hi, 1], p[base + hi, 2])
      g = wp.length(wp.cross(x - x0, x1 - x0))
      along = wp.dot(x, tangent)
      if g > arc_gain * (1.0 + FIFTH_TIE) or (arc_best >= 0 and g >= arc_gain * (1.0 - FIFTH_TIE) and along > arc_key):
        arc_best = i
        arc_gain = wp.max(g, arc_gain)
        arc_key = along
    if arc_gain > gain:
      runner = gain
      best = arc_best
      gain = arc_gain
      key = arc_key
    else:
      runner = wp.max(runner, arc_gain)
  if gain <= runner * (1.0 + FIFTH_MARGIN):
    best = -1
  return best


@wp.func(inline=True)
def _deepest_first(p: mat_poly, base: int, n: int, normal: wp.vec3, flat: bool, max_contacts: int
                   ) -> tuple[vec_chosen, int]:
  """The deepest of the n corners at p[base:] (the lowest along the reference face's normal),
  then, where the incident face is tilted (not ``flat``), its two neighbours, the deeper first:
  an incident edge lying on the reference face ends there. Then each time the corner farthest
  from those chosen."""
  chosen = vec_chosen()
  deepest = int(0)
  for i in range(1, n):
    low = wp.vec3(p[base + deepest, 0], p[base + deepest, 1], p[base + deepest, 2])
    if wp.dot(wp.vec3(p[base + i, 0], p[base + i, 1], p[base + i, 2]), normal) < wp.dot(low, normal):
      deepest = i
  chosen[0] = deepest
  count = int(1)
  if not flat:
    prev = (deepest + n - 1) % n
    after = (deepest + 1) % n
    before = wp.vec3(p[base + prev, 0], p[base + prev, 1], p[base + prev, 2])
    if wp.dot(before, normal) < wp.dot(wp.vec3(p[base + after, 0], p[base + after, 1], p[base + after, 2]), normal):
      after = prev
      prev = (deepest + 1) % n
    chosen[1] = after
    count = wp.min(max_contacts, 2)
    if count < max_contacts:
      chosen[2] = prev
      count = 3
  while count < max_contacts:
    best = int(0)
    best_dist = float(-1.0)
    for i in range(n):
      nearest = float(1.0e30)
      for j in range(count):
        taken = base + chosen[j]
        x = wp.vec3(p[base + i, 0], p[base + i, 1], p[base + i, 2])
        nearest = wp.min(nearest, wp.length_sq(x - wp.vec3(p[taken, 0], p[taken, 1], p[taken, 2])))
      if nearest > best_dist:
        best = i
        best_dist = nearest
    chosen[count] = best
    count += 1
  return chosen, count


@wp.func(inline=True)
def _chosen_corners(p: mat_poly, base: int, n: int, segment: bool, normal: wp.vec3, tangent: wp.vec3, flat: bool,
                    max_contacts: int) -> tuple[vec_chosen, int]:
  """Which of the n clipped corners at p[base:] become contacts: all up to max_contacts; a
  clipped segment's two farthest; on a face parallel to the reference one (``flat``, as MuJoCo
  takes a face on a face) MuJoCo's quadrilateral of largest area plus, as a fifth contact, the
  corner that widens it most (_polygon_quad climbs from a fixed start to a local maximum, half
  the largest area on a square with chamfered corners such as a carton's bottom; MuJoCo C's own
  choice among equal quadrilaterals of a round end is float rounding's); else (and below four
  contacts) the deepest corners first (_deepest_first)."""
  chosen = vec_chosen()
  count = int(0)
  if segment and n > 2:
    ends = wp.vec2i(0, 1)
    far = float(0.0)
    for i in range(n):
      for j in range(i + 1, n):
        x = wp.vec3(p[base + j, 0], p[base + j, 1], p[base + j, 2])
        d2 = wp.length_sq(x - wp.vec3(p[base + i, 0], p[base + i, 1], p[base + i, 2]))
        if d2 > far:
          far = d2
          ends = wp.vec2i(i, j)
    chosen[0] = ends[0]
    chosen[1] = ends[1]
    count = int(2)
  elif n <= max_contacts:
    for i in range(n):
      chosen[i] = i
    count = n
  elif flat and max_contacts >= 4:
    quad = _polygon_quad(p, base, n)
    for i in range(4):
      chosen[i] = quad[i]
    count = int(4)
    fifth = int(-1)
    if max_contacts > 4:
      fifth = _widest_fifth(p, base, n, quad, tangent)
    if fifth >= 0:
      chosen[4] = fifth
      count = int(5)
  else:
    chosen, count = _deepest_first(p, base, n, normal, flat, max_contacts)
  return chosen, count


@wp.func
def _clipped(ref_shape: Shape, ref: Face, inc_shape: Shape, inc: Face, ms: MeshSupport, band: float, max_contacts: int,
             floor: float) -> Manifold:
  """The incident feature clipped to the reference face's side planes (collision_gjk._polygon_clip),
  the corners within ``band`` of the reference plane, reduced to max_contacts (_chosen_corners).
  Each contact lies midway between its corner and the corner's foot on the reference plane, its
  distance the corner's height over that plane, no deeper than ``floor``.

  The polygons are taken relative to the reference face's first corner: in world coordinates
  float32 rounding moved clipped corners of a cylinder's end across the side planes they lie on
  and changed which quadrilateral _polygon_quad picks."""
  out = Manifold()
  out.status = CLIPPED
  out.n = 0
  m = ref.normal
  origin = _face_vertex(ref_shape, ms, ref, 0)
  poly = mat_poly()
  for k in range(inc.nvert):
    v = _face_vertex(inc_shape, ms, inc, k) - origin
    for c in range(3):
      poly[k, c] = v[c]
  src = int(0)
  npoly = inc.nvert
  a = wp.vec3(0.0)
  for e in range(ref.nvert):
    b = _face_vertex(ref_shape, ms, ref, (e + 1) % ref.nvert) - origin
    pd, pn = _plane_normal(a, b, m)
    dst = MAXPOLY - src
    nclip = int(0)
    for i in range(npoly):
      p = wp.vec3(poly[src + i, 0], poly[src + i, 1], poly[src + i, 2])
      q = wp.vec3(poly[src + (i + 1) % npoly, 0], poly[src + (i + 1) % npoly, 1], poly[src + (i + 1) % npoly, 2])
      inside1 = _halfspace(a, pn, p)
      inside2 = _halfspace(a, pn, q)
      if inside1 and not inside2 or inside2 and not inside1:
        t = _plane_intersect(pn, pd, p, q)
        if t > -INTERSECT_TOL and t < 1.0 + INTERSECT_TOL and nclip < MAXPOLY:
          x = p + wp.clamp(t, 0.0, 1.0) * (q - p)
          for c in range(3):
            poly[dst + nclip, c] = x[c]
          nclip += 1
      if inside2 and nclip < MAXPOLY:
        for c in range(3):
          poly[dst + nclip, c] = q[c]
        nclip += 1
    src = dst
    npoly = nclip
    a = b
  # the corners near enough to the reference plane, in order, without repeats: clipping leaves
  # pairs of corners float32 rounding apart, which stalled _polygon_quad's climb (no area gained)
  size = float(0.0)
  for i in range(npoly):
    size = wp.max(size, wp.length(wp.vec3(poly[src + i, 0], poly[src + i, 1], poly[src + i, 2])))
  kept = int(0)
  for i in range(npoly):
    x = wp.vec3(poly[src + i, 0], poly[src + i, 1], poly[src + i, 2])
    last = src + wp.max(kept - 1, 0)
    repeat = kept > 0 and wp.length(x - wp.vec3(poly[last, 0], poly[last, 1], poly[last, 2])) <= DUPLICATE * size
    if wp.dot(x, m) <= band and not repeat:
      for c in range(3):
        poly[src + kept, c] = x[c]
      kept += 1
  last = src + wp.max(kept - 1, 0)
  closing = wp.vec3(poly[last, 0], poly[last, 1], poly[last, 2]) - wp.vec3(poly[src, 0], poly[src, 1], poly[src, 2])
  if kept > 1 and wp.length(closing) <= DUPLICATE * size:
    kept -= 1
  flat = inc.kind != FACE_SEGMENT and wp.dot(inc.normal, m) <= -FACE_TOL
  tangent = _face_vertex(ref_shape, ms, ref, 1) - origin  # fixed on the reference face: breaks ties
  chosen, count = _chosen_corners(poly, src, kept, inc.kind == FACE_SEGMENT, m, tangent, flat, max_contacts)
  for k in range(count):
    x = wp.vec3(poly[src + chosen[k], 0], poly[src + chosen[k], 1], poly[src + chosen[k], 2])
    h = wp.dot(x, m)
    pos = origin + x - 0.5 * h * m
    for c in range(3):
      out.pos[k, c] = pos[c]
    out.dist[k] = wp.max(h, floor)
  out.n = count
  return out


@wp.func
def face_manifold(a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, max_contacts: int
                  ) -> Manifold:
  """The contacts of A and B by face clipping, where the first contact's normal n (from A to B)
  lies along a flat face of one of them (within MuJoCo's multi-CCD tolerance FACE_TOL): that
  face is the reference, the other shape's feature facing it the incident one. Where both
  shapes offer such a face and the two are parallel (within FACE_TOL), A's is the reference,
  as in MuJoCo. Status TILTS where neither does, the other shape meets the face in a point
  of a curved surface, or the polygons have more than MAXPOLY corners together.

  A is grown by its inflate (the margin band, as the narrow phase poses it); the faces are the
  true ones and the band widens the depth at which a corner still counts. ``scale``: the pair's
  size (posed_pair), for tolerances.
  """
  out = Manifold()
  out.status = TILTS
  out.n = 0
  band = a.inflate
  bare = a
  bare.inflate = 0.0
  n = first.normal
  fa = _flat_face(bare, ms, n, mode)
  fb = _flat_face(b, ms, -n, mode)
  ca = float(-2.0)
  cb = float(-2.0)
  if fa.kind != FACE_NONE:
    ca = wp.dot(fa.normal, n)
  if fb.kind != FACE_NONE:
    cb = wp.dot(fb.normal, -n)
  if wp.max(ca, cb) < FACE_TOL:
    return out
  floor = band - first.depth  # no corner deeper than the first contact
  max_contacts = wp.min(max_contacts, MAX_MANIFOLD)
  # a face on a face (MuJoCo's test: the two faces anti-parallel within FACE_TOL): A's is the
  # reference, as in MuJoCo; else the face along n
  face_face = ca >= FACE_TOL and cb >= FACE_TOL and wp.dot(fa.normal, fb.normal) <= -FACE_TOL
  if ca >= FACE_TOL and (face_face or ca >= cb):
    inc = _incident(b, ms, -fa.normal, mode)
    if inc.kind != FACE_NONE and fa.nvert + inc.nvert <= MAXPOLY:
      out = _clipped(bare, fa, b, inc, ms, band, max_contacts, floor)
  else:
    inc = _incident(bare, ms, -fb.normal, mode)
    if inc.kind != FACE_NONE and fb.nvert + inc.nvert <= MAXPOLY:
      out = _clipped(b, fb, bare, inc, ms, band, max_contacts, floor)
  if out.status == CLIPPED and out.n == 0:
    out.status = TILTS  # nothing within the band: not the face the first contact is on
  if out.status == CLIPPED:
    deepest = int(0)
    for k in range(1, out.n):
      if out.dist[k] < out.dist[deepest]:
        deepest = k
    if out.dist[deepest] > floor + MISSED_DEPTH * first.depth:
      # the corners miss the first contact (an edge crossing the reference face's rim beside
      # the incident face): it takes the last place
      k = wp.min(out.n, max_contacts - 1)
      pos = first.pos - 0.5 * band * n
      for c in range(3):
        out.pos[k, c] = pos[c]
      out.dist[k] = floor
      out.n = k + 1
    else:
      # the deepest corner carries the first contact's depth, exact where the corners' is not: a
      # round end's deepest point lies between two corners of its 16-gon, and a face a few
      # degrees off the normal (MuJoCo's face on a face takes A's) measures along its own normal
      out.dist[deepest] = floor
  return out
