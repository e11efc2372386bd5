"""Posing: a geom of one world as a Shape, and a pair as the narrow phase collides it.

Shared by every stage that collides shapes (the convex narrow phase, multi-contact, the
heightfield and non-convex stages). This module owns ``posed_shape`` and ``posed_pair``; it
launches nothing.
"""

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


@wp.func
def posed_shape(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  geomid: int,
  worldid: int,
) -> Shape:
  """Geom ``geomid`` of world ``worldid`` as a Shape (world frame, no inflation)."""
  s = Shape()
  s.gtype = geom_type[geomid]
  s.pos = geom_xpos_in[worldid, geomid]
  s.rot = geom_xmat_in[worldid, geomid]
  s.size = geom_size[worldid % geom_size.shape[0], geomid]
  s.mesh = -1
  s.center = s.pos
  s.inflate = 0.0
  if s.gtype == GeomType.MESH:
    s.mesh = geom_dataid[worldid % geom_dataid.shape[0], geomid]
    s.center = s.pos + s.rot @ ms.hull_center[s.mesh]
  return s


@wp.func
def posed_pair(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  band: float,
  geoms: wp.vec2i,
  worldid: int,
):
  """A pair as the narrow phase collides it: A grown by the margin band, B, and the pair's scale
  (the sum of the bounding radii; thresholds are relative to it)."""
  a = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[0], worldid)
  b = posed_shape(geom_type, geom_dataid, geom_size, geom_xpos_in, geom_xmat_in, ms, geoms[1], worldid)
  a.inflate = band
  rb = worldid % geom_rbound.shape[0]
  return a, b, wp.max(geom_rbound[rb, geoms[0]] + geom_rbound[rb, geoms[1]], 1.0e-9)
