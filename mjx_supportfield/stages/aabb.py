"""AABB update: one world-frame box per geom per world, inflated by margin and gap."""

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.types import FAR  # a plane's extent: finite, so sums and comparisons stay defined
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def _is_finite(p: wp.vec3, r: wp.mat33) -> bool:
  ok = wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])
  for i in range(3):
    for j in range(3):
      ok = ok and wp.isfinite(r[i, j])
  return ok


@wp.func
def _plane_box(pos: wp.vec3, normal: wp.vec3, inflate: float) -> tuple[wp.vec3, wp.vec3]:
  """Box of a plane's solid half-space: bounded only along an axis the normal is parallel to."""
  lo = wp.vec3(-FAR)
  hi = wp.vec3(FAR)
  for k in range(3):
    if wp.abs(normal[k]) == 1.0:
      if normal[k] > 0.0:
        hi[k] = pos[k] + inflate
      else:
        lo[k] = pos[k] - inflate
  return lo, hi


@wp.kernel
def update_aabbs(
  # Model:
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_aabb: wp.array3d(dtype=wp.vec3),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  # Data in:
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  # Out:
  aabb_lo_out: wp.array2d(dtype=wp.vec3),
  aabb_hi_out: wp.array2d(dtype=wp.vec3),
  nonfinite_out: wp.array(dtype=int),
):
  """World AABB of each geom; an empty box (lo > hi) for absent meshes and non-finite poses."""
  worldid, geomid = wp.tid()
  pos = geom_xpos_in[worldid, geomid]
  rot = geom_xmat_in[worldid, geomid]
  gtype = geom_type[geomid]
  inflate = geom_margin[worldid % geom_margin.shape[0], geomid] + geom_gap[worldid % geom_gap.shape[0], geomid]

  empty = False
  if not _is_finite(pos, rot):
    empty = True
    nonfinite_out[worldid] = 1
  if gtype == GeomType.MESH and geom_dataid[worldid % geom_dataid.shape[0], geomid] < 0:
    empty = True  # per-world mesh assignment: this geom is absent from this world

  if empty:
    aabb_lo_out[worldid, geomid] = wp.vec3(FAR)
    aabb_hi_out[worldid, geomid] = wp.vec3(-FAR)
    return

  if gtype == GeomType.PLANE:
    lo, hi = _plane_box(pos, wp.vec3(rot[0, 2], rot[1, 2], rot[2, 2]), inflate)
    aabb_lo_out[worldid, geomid] = lo
    aabb_hi_out[worldid, geomid] = hi
    return

  aabb_id = worldid % geom_aabb.shape[0]
  center = pos + rot @ geom_aabb[aabb_id, geomid, 0]
  half = geom_aabb[aabb_id, geomid, 1]
  ext = wp.vec3(0.0)
  for i in range(3):
    ext[i] = wp.abs(rot[i, 0]) * half[0] + wp.abs(rot[i, 1]) * half[1] + wp.abs(rot[i, 2]) * half[2] + inflate
  aabb_lo_out[worldid, geomid] = center - ext
  aabb_hi_out[worldid, geomid] = center + ext
