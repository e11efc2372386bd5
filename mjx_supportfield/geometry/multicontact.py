"""Multi-contact: more points of a contact patch than MPR's (or GJK/EPA's) one.

Pairs touching face on feature along the normal get their patch by face clipping (faceclip.py).

Pose perturbation for the rest (edge against edge, curved surfaces): after the first contact
(normal n, depth d0, point p0), shape A is tilted by +-eps about the two diagonals of the
contact plane, around p0. A tilted A digs into B at another end of the patch; MPR finds the
witness points there, A's is mapped back to A's true pose, and the point is kept when it still
penetrates along n and is not a duplicate of one already kept. A tilt that lands back on a
point already found (the faces meet at a larger angle than eps, so the same vertex stays
deepest) is retried once, TILT_GROWTH times steeper: 0.09 rad at the default eps, about the
0.089 rad within which MuJoCo's multi-CCD takes two faces as touching.

Most tilts need no MPR. The tilted MPR looks along n, and the face of A' - B its ray leaves
through is usually a vertex of one shape against a flat face of the other (a box face, a
cylinder's end, a hull polygon of MuJoCo's): A''s vertex through B's face that faces A, or B's
vertex through A''s face that faces B. A face and a support query give each, and where the
ray provably leaves through one of them the tilt's answer follows in closed form
(tilt_closed_form); only the rest (edge against edge, curved sides) run the tilted MPR.

This module owns the tilts' device functions (``tilt_rotation``; ``tilt_closed_form``,
``tilt_mpr``, ``perturbed_contacts``, built for one support mode by ``tilt_funcs``) and the
``Patch`` they fill, for multicontact_pass.py's kernels; it launches nothing.
"""
import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.mpr import BEHIND
from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.geometry.support import REFINED
from mjx_supportfield.geometry.support import count_supports
from mjx_supportfield.geometry.support import hull_point
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.types import FAR
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

NPERTURB = 4  # tilts: +-eps about each diagonal of the contact plane
# a tilted MPR starts next to its answer: it needs few iterations, and its point only has to
# land on the right corner of the patch (its depth is measured again in the true pose). At the
# main MPR's tolerance, float32 noise of the tilted poses kept it iterating to the cap.
TILT_TOL = 1.0e-6
TILT_ITERATIONS = 16
TILT_GROWTH = 9.0  # the retry's tilt, in units of eps
MISSED = wp.constant(-FAR)  # depth of a tilt whose shapes do not overlap
UNKNOWN = wp.constant(FAR)  # depth of a tilt the closed form cannot answer: MPR must
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
  best = REFINED.mesh_support_index(ms, mesh, d)
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
  deepest = float(-FAR)
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
def polygon_toward(ms: MeshSupport, mesh: int, vertex: int, u: wp.vec3) -> int:
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
def _in_polygon(ms: MeshSupport, poly: int, x: wp.vec3, tol: float) -> bool:
  """Whether point x (mesh frame, in the polygon's plane) lies inside hull polygon ``poly``,
  up to tol."""
  normal = ms.poly_normal[poly]
  adr = ms.poly_vert_adr[poly]
  nvert = ms.poly_vert_num[poly]
  prev = ms.poly_pos[adr + nvert - 1]
  # inside a convex polygon, x is on the same side of every edge, whatever the winding
  left = bool(False)
  right = bool(False)
  for j in range(nvert):
    cur = ms.poly_pos[adr + j]
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
    return _in_polygon(ms, face, local - s.inflate * ms.poly_normal[face], tol)
  return False


NO_FACE = wp.constant(0)
OFF_FACE = wp.constant(1)
EXIT_FACE = wp.constant(2)


@functools.lru_cache(maxsize=None)
def tilt_funcs(mode: int) -> SimpleNamespace:
  """The tilts' device functions on the support functions of support mode ``mode``
  (support_funcs, mpr_funcs): ``tilt_mpr``, ``tilt_closed_form``, ``tilt_point`` and
  ``perturbed_contacts``."""
  support = support_funcs(mode)
  mesh_support_index = support.mesh_support_index
  support_world = support.support_world
  mpr = mpr_funcs(mode).mpr
  behind_origin = mpr_funcs(mode).behind_origin

  @wp.func
  def tilt_mpr(
    a: Shape, b: Shape, ms: MeshSupport, first: MprResult, scale: float, tol: float, iterations: int,
    rot: wp.mat33
  ) -> wp.vec4:
    """MPR with A tilted by ``rot`` about the first contact: the point (xyz) and its depth along
    the first normal (w), A's witness point rotated back with A; depth MISSED when the tilted
    shapes do not overlap."""
    # every tilted MPR starts warm: looking along the first normal, from behind the origin
    tilted = _tilted(a, first.pos, rot)
    q0 = behind_origin(tilted, b, ms, first.normal, first.depth, scale, BEHIND)
    r = mpr(tilted, b, ms, q0, scale, wp.max(tol, TILT_TOL), wp.min(iterations, TILT_ITERATIONS))
    if r.hit == 0:
      return wp.vec4(0.0, 0.0, 0.0, MISSED)
    # witness points in the tilted pose (pa - pb = depth * normal)
    return _mapped_back(first, rot, r.pos + 0.5 * r.depth * r.normal, r.pos - 0.5 * r.depth * r.normal)

  @wp.func
  def _face_toward(s: Shape, ms: MeshSupport, u: wp.vec3) -> tuple[wp.vec3, wp.vec3, int]:
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
      vertex = mesh_support_index(ms, s.mesh, lu)
      face = polygon_toward(ms, s.mesh, vertex, lu)
      if face >= 0:
        normal = ms.poly_normal[face]
        point = hull_point(ms, s.mesh, vertex)
    normal = s.rot @ normal
    return normal, s.pos + s.rot @ point + s.inflate * normal, face

  @wp.func
  def _vertex_on_face(v: Shape, f: Shape, ms: MeshSupport, ray: wp.vec3, tol: float
                      ) -> tuple[wp.vec3, wp.vec3, float, int]:
    """A face of the Minkowski difference V - F seen by MPR's ray from the origin along ``ray``:
    the flat face of ``f`` facing ``v`` (outward normal nearest to -ray) against the vertex of v
    deepest through it. Returns that vertex, its foot on the face (MPR's two witness points when
    the ray leaves V - F through this face), the depth (<= 0: V and F are apart) and NO_FACE
    (f has no flat face there), OFF_FACE (the ray leaves through another face of V - F, or
    MPR's witness would not be the foot) or EXIT_FACE.

    The ray meets the face's plane at depth / cos; it leaves V - F there exactly when that point
    of the plane lies on the face (a convex body's boundary meets the ray once)."""
    normal, point, face = _face_toward(f, ms, -ray)
    if face < 0:
      return wp.vec3(0.0), wp.vec3(0.0), 1.0, NO_FACE
    m = -normal  # the outward normal of this face of V - F
    vertex = support_world(v, ms, m)
    depth = wp.dot(vertex - point, m)
    foot = vertex - depth * m
    cos = wp.dot(ray, m)
    status = OFF_FACE
    if cos > 0.0 and _in_face(f, ms, face, vertex - depth / cos * ray, tol) and _in_face(f, ms, face, foot, tol):
      status = EXIT_FACE
    return vertex, foot, depth, status

  @wp.func
  def tilt_closed_form(a: Shape, b: Shape, ms: MeshSupport, first: MprResult, scale: float, rot: wp.mat33
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
    va, foot_b, depth_a, status_a = _vertex_on_face(at, b, ms, n, tol)
    vb, foot_a, depth_b, status_b = _vertex_on_face(b, at, ms, -n, tol)
    if (status_a != NO_FACE and depth_a <= 0.0) or (status_b != NO_FACE and depth_b <= 0.0):
      return wp.vec4(0.0, 0.0, 0.0, MISSED)
    if status_a == EXIT_FACE:
      return _mapped_back(first, rot, va, foot_b)
    if status_b == EXIT_FACE:
      return _mapped_back(first, rot, foot_a, vb)
    return wp.vec4(0.0, 0.0, 0.0, UNKNOWN)

  @wp.func
  def tilt_point(
    a: Shape, b: Shape, ms: MeshSupport, first: MprResult, scale: float, tol: float, iterations: int,
    rot: wp.mat33
  ) -> wp.vec4:
    """A tilt's point and depth (see tilt_mpr): in closed form where it can be, else by MPR."""
    q = tilt_closed_form(a, b, ms, first, scale, rot)
    if q[3] == UNKNOWN:
      q = tilt_mpr(a, b, ms, first, scale, tol, iterations, rot)
    return q

  @wp.func
  def perturbed_contacts(
    a: Shape, b: Shape, ms: MeshSupport, first: MprResult, scale: float, tol: float, iterations: int,
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
          q = tilt_point(a, b, ms, first, scale, tol, iterations, tilt_rotation(first.normal, eps, k, attempt))
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

  return SimpleNamespace(tilt_mpr=tilt_mpr, tilt_closed_form=tilt_closed_form, tilt_point=tilt_point,
                         perturbed_contacts=perturbed_contacts)
