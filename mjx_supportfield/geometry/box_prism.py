"""Whether a box and a heightfield triangle's prism are apart, by separating axes.

Two convex polytopes overlap unless some axis parts them: a face normal of either, or the cross
product of an edge direction of each. The gap along an axis is at most their distance, so an
axis that parts them by the margin band proves them apart by at least the band. The heightfield
stage tests the prism's own faces (its top plane and side walls) with support queries for every
geom; ``box_axes_part`` adds the box's three axes and the cross products of the box's edges with
the prism's (its top edges, base edges and vertical edges), so that a box's prism goes to GJK/EPA
only when no axis parts them by the band, and most prisms under a box lying on rough terrain
(whose GJK runs found nothing) are left out.

This module launches nothing.
"""

import warp as wp

from mjx_supportfield.types import Shape

mat63 = wp.types.matrix(shape=(6, 3), dtype=float)

NAXIS = 24  # the box's 3 axes, then 7 prism edge directions x the box's 3 edge directions
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
def box_axes_part(t0: wp.vec3, t1: wp.vec3, t2: wp.vec3, bottom: float, box: Shape, band: float) -> bool:
  """Whether an axis of the box, or of an edge of the box's and an edge of the prism's under
  triangle (t0, t1, t2) down to z = bottom, parts the two by ``band`` or more (both in one
  frame): then GJK/EPA finds no contact there."""
  p = _prism_vertices(t0, t1, t2, bottom)
  for k in range(NAXIS):
    u = _axis(p, box.rot, k)
    if wp.length_sq(u) > 0.0:
      lo = wp.dot(p[0], u)
      hi = lo
      for i in range(1, 6):
        x = wp.dot(p[i], u)
        lo = wp.min(lo, x)
        hi = wp.max(hi, x)
      centre = wp.dot(box.pos, u)
      radius = float(0.0)
      for i in range(3):
        radius += box.size[i] * wp.abs(wp.dot(_column(box.rot, i), u))
      if centre - radius - hi >= band or lo - centre - radius >= band:
        return True
  return False

