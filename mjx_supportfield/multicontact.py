"""Multi-contact by pose perturbation: more points of a contact patch from the same MPR.

After MPR's contact (normal n, depth d0, point p0), shape A is tilted by +-eps about the two
diagonals of the contact plane, around p0. A tilted A digs into B at another end of the
patch; MPR finds the witness points there, A's is mapped back to A's true pose, and the
point is kept when it still penetrates along n and is not a duplicate of one already kept.
A tilt that lands back on a point already found (the faces meet at a larger angle than eps,
so the same vertex stays deepest) is retried once, TILT_GROWTH times steeper: 0.09 rad at the
default eps, about the 0.089 rad within which MuJoCo's multi-CCD takes two faces as touching.
"""

import warp as wp
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import GeomType

from mjx_supportfield.mpr import MprResult
from mjx_supportfield.mpr import behind_origin
from mjx_supportfield.mpr import mpr
from mjx_supportfield.support import count_supports
from mjx_supportfield.support import hull_point
from mjx_supportfield.support import mesh_support_index
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
def _mesh_ties(ms: MeshSupport, mesh: int, d: wp.vec3, rtol: float) -> int:
  """1 + the support vertex's hull neighbours that tie with it (capped at 3): enough to tell a
  vertex from an edge from a face, without count_supports' flood fill."""
  best = mesh_support_index(ms, mesh, d, SUPPORT_REFINED)
  top = wp.dot(hull_point(ms, mesh, best), d)
  tol = rtol * wp.max(wp.length(hull_point(ms, mesh, best) - ms.hull_center[mesh]), 1.0e-12)
  if ms.nbr_num.shape[0] == 0:
    return count_supports(GeomType.MESH, wp.vec3(0.0), mesh, ms, d, rtol)
  g = ms.hull_adr[mesh] + best
  n = int(1)
  for k in range(ms.nbr_num[g]):
    if n < 3 and wp.dot(hull_point(ms, mesh, ms.nbr[ms.nbr_adr[g] + k]), d) >= top - tol:
      n += 1
  return n


@wp.func
def _ties(s: Shape, ms: MeshSupport, d_world: wp.vec3, rtol: float) -> int:
  """How many support points a shape has in direction d within rtol of its extent: 1 for a
  point, 2 for an edge or a line, 3 for a face (or more, counted, for boxes and meshes)."""
  d = wp.normalize(wp.transpose(s.rot) @ d_world)
  if s.gtype == GeomType.BOX:
    return count_supports(s.gtype, s.size, s.mesh, ms, d, rtol)
  if s.gtype == GeomType.MESH:
    return _mesh_ties(ms, s.mesh, d, rtol)
  if s.gtype == GeomType.CYLINDER:
    extent = wp.length(wp.vec2(s.size[0], s.size[1]))
    if wp.sqrt(wp.max(1.0 - d[2] * d[2], 0.0)) * s.size[0] <= rtol * extent:
      return 3  # an end disk
    if wp.abs(d[2]) * s.size[1] <= rtol * extent:
      return 2  # a line of the side
  if s.gtype == GeomType.CAPSULE:
    if wp.abs(d[2]) * s.size[1] <= rtol * (s.size[0] + s.size[1]):
      return 2
  return 1


@wp.func
def patch_possible(a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3, eps: float) -> bool:
  """Whether tilting by eps can find more points: a tilt brings in a point only if it is within
  eps x the shape's extent of the deepest along the normal, so both shapes must offer at least
  an edge there (face-face, face-edge, parallel edges). Vertex contacts skip the tilted MPRs."""
  return _ties(a, ms, normal, eps) >= 2 and _ties(b, ms, -normal, eps) >= 2


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
def _tilted_point(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  axis: wp.vec3, angle: float
) -> wp.vec4:
  """MPR with A tilted by ``angle`` about ``axis`` through the first contact: the point (xyz)
  and its depth along the first normal (w), A's witness point rotated back with A; depth
  MISSED when the tilted shapes do not overlap."""
  rot = wp.quat_to_matrix(wp.quat_from_axis_angle(axis, angle))
  # every tilted MPR starts warm: looking along the first normal, from just behind the origin
  q0 = behind_origin(first.normal, first.depth, scale)
  r = mpr(_tilted(a, first.pos, rot), b, ms, mode, q0, scale, wp.max(tol, TILT_TOL), wp.min(iterations, TILT_ITERATIONS))
  if r.hit == 0:
    return wp.vec4(0.0, 0.0, 0.0, MISSED)
  # witness points in the tilted pose (pa - pb = depth * normal); A's rotates back with A
  pa = r.pos + 0.5 * r.depth * r.normal
  pb = r.pos - 0.5 * r.depth * r.normal
  pa = first.pos + wp.transpose(rot) @ (pa - first.pos)
  pos = 0.5 * (pa + pb)
  return wp.vec4(pos[0], pos[1], pos[2], wp.dot(pa - pb, first.normal))


@wp.func
def tilt_attempt(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  eps: float, k: int, attempt: int
) -> wp.vec4:
  """Attempt ``attempt`` (0, or 1: TILT_GROWTH times steeper) of tilt k (point, depth; see
  _tilted_point), on its own: all eight of a pair can run in eight threads
  (narrowphase.tilt_kernel) and be handed to perturbed_contacts."""
  angle = float(wp.where(k % 2 == 0, eps, -eps))
  if attempt == 1:
    angle *= TILT_GROWTH
  return _tilted_point(a, b, ms, mode, first, scale, tol, iterations, _tilt_axis(first.normal, k), angle)


@wp.func
def perturbed_contacts(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  eps: float, min_spacing: float, attempts: wp.array2d(dtype=wp.vec4), row: int
) -> Patch:
  """Up to NPERTURB further contact points of A and B around ``first`` (see the module doc).

  With ``row`` >= 0, ``attempts[row, attempt * NPERTURB + k]`` holds tilt_attempt(k, attempt),
  computed beforehand in parallel; with row < 0 the attempts are computed here, as needed.
  """
  patch = Patch()
  patch.n = 0
  for k in range(NPERTURB):
    axis = _tilt_axis(first.normal, k)
    angle = float(wp.where(k % 2 == 0, eps, -eps))
    for attempt in range(2):
      q = wp.vec4()
      if row >= 0:
        q = attempts[row, attempt * NPERTURB + k]
      else:
        q = _tilted_point(a, b, ms, mode, first, scale, tol, iterations, axis, angle)
      angle *= TILT_GROWTH
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
