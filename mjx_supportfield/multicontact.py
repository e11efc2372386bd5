"""Multi-contact by pose perturbation: more points of a contact patch from the same MPR.

After MPR's contact (normal n, depth d0, point p0), shape A is tilted by +-eps about the two
diagonals of the contact plane, around p0. A tilted A digs into B at another end of the
patch; MPR finds the witness points there, A's is mapped back to A's true pose, and the
point is kept when it still penetrates along n and is not a duplicate of one already kept.
"""

import warp as wp
from mujoco_warp._src.math import make_frame

from mjx_supportfield.mpr import MprResult
from mjx_supportfield.mpr import Vertex
from mjx_supportfield.mpr import mpr
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

NPERTURB = 4  # tilts: +-eps about each diagonal of the contact plane

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
def perturbed_contacts(
  a: Shape, b: Shape, ms: MeshSupport, mode: int, first: MprResult, scale: float, tol: float, iterations: int,
  eps: float, min_spacing: float
) -> Patch:
  """Up to NPERTURB further contact points of A and B around ``first`` (see the module doc)."""
  patch = Patch()
  patch.n = 0
  n = first.normal
  frame = make_frame(n)
  t1 = wp.vec3(frame[1, 0], frame[1, 1], frame[1, 2])
  t2 = wp.vec3(frame[2, 0], frame[2, 1], frame[2, 2])
  for k in range(NPERTURB):
    axis = wp.normalize(wp.where(k < 2, t1 + t2, t1 - t2))
    angle = wp.where(k % 2 == 0, eps, -eps)
    rot = wp.quat_to_matrix(wp.quat_from_axis_angle(axis, angle))
    tilted = _tilted(a, first.pos, rot)
    # warm start: look along the first normal, from just behind the origin
    q0 = Vertex()
    q0.v = -0.5 * wp.max(first.depth, 1.0e-6 * scale) * n
    r = mpr(tilted, b, ms, mode, q0, scale, tol, iterations)
    if r.hit == 0:
      continue
    # witness points in the tilted pose (pa - pb = depth * normal); A's rotates back with A
    pa = r.pos + 0.5 * r.depth * r.normal
    pb = r.pos - 0.5 * r.depth * r.normal
    pa = first.pos + wp.transpose(rot) @ (pa - first.pos)
    depth = wp.dot(pa - pb, n)
    if depth <= 0.0:
      continue
    pos = 0.5 * (pa + pb)
    dup = bool(False)
    for j in range(patch.n):
      if wp.length(pos - wp.vec3(patch.pos[j, 0], patch.pos[j, 1], patch.pos[j, 2])) < min_spacing:
        dup = True
    if dup:
      continue
    for c in range(3):
      patch.pos[patch.n, c] = pos[c]
    patch.depth[patch.n] = depth
    patch.n += 1
  return patch
