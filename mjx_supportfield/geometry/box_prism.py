"""Whether a box and a heightfield triangle's prism are apart, by separating axes.

Two convex polytopes overlap unless some axis parts them: a face normal of either, or the cross
product of an edge direction of each. The gap along an axis is at most their distance, so an
axis that parts them by the margin band proves them apart by at least the band. The heightfield
stage tests the prism's own faces (its top plane and side walls) with support queries for every
geom; ``box_axes_part`` adds the box's three axes and the cross products of the box's edges with
the prism's (its top edges, base edges and vertical edges), so that a box's prism goes to GJK/EPA
only when no axis parts them by the band, and most prisms under a box lying on rough terrain
(whose GJK runs found nothing) are left out.

The same axes, with the prism's own faces, give the exact penetration of a box and a prism
(``box_prism_penetration``): of two convex polytopes, the least overlap over those axes is their
penetration depth. ``box_prism_contact`` adds the point EPA would end on, between the two shapes'
deepest features along that axis. MuJoCo Warp's float32 GJK/EPA on a terrain prism that a box's
face rests on is ill-conditioned and can return a wrong answer (deeper than the penetration, a
normal into the terrain, or none); the heightfield stage takes this one there instead.

This module launches nothing.
"""

import warp as wp
from mujoco_warp._src.math import closest_segment_to_segment_points

from mjx_supportfield.geometry.support import box_corner
from mjx_supportfield.types import Shape

mat63 = wp.types.matrix(shape=(6, 3), dtype=float)

NAXIS = 24  # the box's 3 axes, then 7 prism edge directions x the box's 3 edge directions
NFACE = 5  # the prism's own face normals: its top, its three side walls, its base
PARALLEL = 1.0e-6  # sine below which a prism edge and a box edge are parallel (no axis of their own)


@wp.func
def _prism_vertices(t0: wp.vec3, t1: wp.vec3, t2: wp.vec3, bottom: float) -> mat63:
  """Rows 0-2 the top triangle, 3-5 the base under it."""
  v = mat63()
  v[0] = t0
  v[1] = t1
  v[2] = t2
  v[3] = wp.vec3(t0[0], t0[1], bottom)
  v[4] = wp.vec3(t1[0], t1[1], bottom)
  v[5] = wp.vec3(t2[0], t2[1], bottom)
  return v


@wp.func
def _column(m: wp.mat33, k: int) -> wp.vec3:
  return wp.vec3(m[0, k], m[1, k], m[2, k])


@wp.func
def _prism_edge(p: mat63, k: int) -> wp.vec3:
  """Unit edge direction k of the prism: 0-2 its top edges, 3-5 its base edges, 6 vertical."""
  if k == 6:
    return wp.vec3(0.0, 0.0, 1.0)
  first = (k // 3) * 3
  return wp.normalize(p[first + (k % 3 + 1) % 3] - p[first + k % 3])


@wp.func
def _axis(p: mat63, rot: wp.mat33, k: int) -> wp.vec3:
  """Axis k, unit length (zero for a parallel pair of edges): the box's axes, then the edge pairs."""
  if k < 3:
    return _column(rot, k)
  pair = k - 3
  a = wp.cross(_prism_edge(p, pair // 3), _column(rot, pair % 3))
  length = wp.length(a)
  if length < PARALLEL:
    return wp.vec3(0.0)
  return a / length


@wp.func
def _extents(p: mat63, box: Shape, u: wp.vec3) -> wp.vec4:
  """Along u: the prism's lowest and highest vertex, the box's centre and its half extent."""
  lo = wp.dot(p[0], u)
  hi = lo
  for i in range(1, 6):
    x = wp.dot(p[i], u)
    lo = wp.min(lo, x)
    hi = wp.max(hi, x)
  radius = float(0.0)
  for i in range(3):
    radius += box.size[i] * wp.abs(wp.dot(_column(box.rot, i), u))
  return wp.vec4(lo, hi, wp.dot(box.pos, u), radius)


@wp.func
def box_axes_part(t0: wp.vec3, t1: wp.vec3, t2: wp.vec3, bottom: float, box: Shape, band: float) -> bool:
  """Whether an axis of the box, or of an edge of the box's and an edge of the prism's under
  triangle (t0, t1, t2) down to z = bottom, parts the two by ``band`` or more (both in one
  frame): then GJK/EPA finds no contact there."""
  p = _prism_vertices(t0, t1, t2, bottom)
  for k in range(NAXIS):
    u = _axis(p, box.rot, k)
    if wp.length_sq(u) > 0.0:
      e = _extents(p, box, u)  # lo, hi, centre, radius
      if e[2] - e[3] - e[1] >= band or e[0] - e[2] - e[3] >= band:
        return True
  return False


@wp.func
def _prism_face(p: mat63, k: int) -> wp.vec3:
  """Unit outward normal of the prism's face k: 0 its top, 1-3 its side walls, 4 its base."""
  if k == 0:
    n = wp.cross(p[1] - p[0], p[2] - p[0])
    return wp.normalize(wp.where(n[2] < 0.0, -n, n))
  if k == 4:
    return wp.vec3(0.0, 0.0, -1.0)
  e = p[k % 3] - p[k - 1]
  n = wp.vec3(e[1], -e[0], 0.0)
  other = p[(k + 1) % 3]
  return wp.normalize(wp.where(wp.dot(n, other - p[k - 1]) > 0.0, -n, n))


@wp.func
def box_prism_penetration(t0: wp.vec3, t1: wp.vec3, t2: wp.vec3, bottom: float, box: Shape) -> wp.vec4:
  """The least overlap of the box and the prism under triangle (t0, t1, t2) down to z = bottom,
  over the box's axes, the prism's faces and the edge pairs' axes (both in one frame): the unit
  normal from the prism to the box (x, y, z) and the overlap along it (w; 0 or less: apart)."""
  p = _prism_vertices(t0, t1, t2, bottom)
  best = wp.vec4(0.0, 0.0, 1.0, 1.0e30)
  for k in range(NAXIS + NFACE):
    u = wp.vec3(0.0)
    if k < NAXIS:
      u = _axis(p, box.rot, k)
    else:
      u = _prism_face(p, k - NAXIS)
    if wp.length_sq(u) > 0.0:
      e = _extents(p, box, u)
      up = e[1] - (e[2] - e[3])  # the box pushed out along +u (e: lo, hi, centre, radius)
      down = e[2] + e[3] - e[0]  # along -u
      if up < best[3]:
        best = wp.vec4(u[0], u[1], u[2], up)
      if down < best[3]:
        best = wp.vec4(-u[0], -u[1], -u[2], down)
  return best


@wp.func
def _in_box(box: Shape, x: wp.vec3, tol: float) -> bool:
  local = wp.transpose(box.rot) @ (x - box.pos)
  return (wp.abs(local[0]) <= box.size[0] + tol and wp.abs(local[1]) <= box.size[1] + tol
          and wp.abs(local[2]) <= box.size[2] + tol)


@wp.func
def _in_prism(p: mat63, x: wp.vec3, tol: float) -> bool:
  """Whether x lies in the prism grown by tol (its side walls and top plane, then its base)."""
  for k in range(1, 5):
    on = wp.where(k == 4, p[3], p[k - 1])  # a vertex of face k
    if wp.dot(x - on, _prism_face(p, k)) > tol:
      return False
  top = _prism_face(p, 0)
  return wp.dot(x - p[0], top) <= tol


@wp.func
def box_prism_contact(t0: wp.vec3, t1: wp.vec3, t2: wp.vec3, bottom: float, box: Shape,
                      tol: float) -> tuple[wp.vec4, wp.vec3]:
  """The penetration of the box and the prism under triangle (t0, t1, t2) down to z = bottom
  (box_prism_penetration) and its contact point, midway between the two shapes' deepest
  features along the normal (those within tol of the deepest): a corner of either where one
  is alone (the witness EPA ends on), the closest points of two edges, else the mean of the
  features' points that lie in both shapes (a face resting on a face: any point of their
  overlap is EPA's). Returns the point and the overlap (w), and the normal from the prism to
  the box."""
  pen = box_prism_penetration(t0, t1, t2, bottom, box)
  n = wp.vec3(pen[0], pen[1], pen[2])
  depth = pen[3]
  p = _prism_vertices(t0, t1, t2, bottom)
  e = _extents(p, box, n)
  low = e[2] - e[3]  # the box's deepest along -n
  high = e[1]  # the prism's along n
  nbox = int(0)
  box_sum = wp.vec3(0.0)
  box_a = wp.vec3(0.0)
  box_b = wp.vec3(0.0)
  for i in range(8):
    x = box_corner(box, i)
    if wp.dot(x, n) <= low + tol:
      box_b = wp.where(nbox == 1, x, box_b)
      box_a = wp.where(nbox == 0, x, box_a)
      box_sum += x
      nbox += 1
  nprism = int(0)
  prism_sum = wp.vec3(0.0)
  prism_a = wp.vec3(0.0)
  prism_b = wp.vec3(0.0)
  for i in range(6):
    if wp.dot(p[i], n) >= high - tol:
      prism_b = wp.where(nprism == 1, p[i], prism_b)
      prism_a = wp.where(nprism == 0, p[i], prism_a)
      prism_sum += p[i]
      nprism += 1
  half = 0.5 * depth * n
  pos = 0.5 * (box_sum / float(nbox) + prism_sum / float(nprism))
  if nbox == 1:
    pos = box_a + half
  elif nprism == 1:
    pos = prism_a - half
  elif nbox == 2 and nprism == 2:
    on_box, on_prism = closest_segment_to_segment_points(box_a, box_b, prism_a, prism_b)
    pos = 0.5 * (on_box + on_prism)
  else:
    shared = wp.vec3(0.0)
    nshared = int(0)
    for i in range(8):
      x = box_corner(box, i)
      if wp.dot(x, n) <= low + tol and _in_prism(p, x + half, tol + depth):
        shared += x + half
        nshared += 1
    for i in range(6):
      if wp.dot(p[i], n) >= high - tol and _in_box(box, p[i] - half, tol + depth):
        shared += p[i] - half
        nshared += 1
    if nshared > 0:
      pos = shared / float(nshared)
  return wp.vec4(pos[0], pos[1], pos[2], depth), n
