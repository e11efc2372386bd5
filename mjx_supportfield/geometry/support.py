"""Support functions: closed forms for primitives, the support field for convex meshes.

The stage every narrow phase queries; ``support_funcs(mode)`` builds its functions for one
support mode (Options.support_mode), fixed when the kernels are generated.
"""

import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.types import FAR
from mjx_supportfield.types import SUPPORT_EXACT
from mjx_supportfield.types import SUPPORT_FIELD
from mjx_supportfield.types import SUPPORT_REFINED
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


@wp.func
def hull_point(ms: MeshSupport, mesh: int, local: int) -> wp.vec3:
  return ms.hull_pos[ms.hull_adr[mesh] + local]


# a field cell is a 16-bit word: the local hull index of the cell's support vertex in the low
# 14 bits and a 2-bit code about the quad spanned by cells (i, j) .. (i + 1, j + 1), proven at
# build time (support_field._certify):
#   CERTIFIED      this vertex is the support for every direction of the quad (one read);
#   CORNERS_EXACT  the best of the quad's 4 corner vertices is;
#   WITH_EXTRAS    the best of the 4 corners and a few more vertices is: the low 14 bits then
#                  point into the mesh's ``extra`` list, which holds the cell's own vertex (its
#                  low 14 bits) with the number of extra vertices above them, then those vertices.
CERTIFIED = 0x8000
CORNERS_EXACT = 0x4000
WITH_EXTRAS = 0xC000
PROOF_MASK = 0xC000
INDEX_MASK = 0x3FFF
EXTRA_COUNT_SHIFT = 14
MAX_EXTRAS = 3  # extra vertices a quad may list (2 bits of count)
# the 26 directions from the centre of a 3 x 3 x 3 grid to its other points: the seeds of a
# field's hill climbs and the sample points of a shape without vertices of its own
GRID_DIRECTIONS = 26


@wp.func
def field_word(ms: MeshSupport, mesh: int, i: int, j: int) -> int:
  res = ms.field_res[mesh]
  return int(ms.field[ms.field_adr[mesh] + j * res + i])


@wp.func
def _extras_head(ms: MeshSupport, mesh: int, word: int) -> int:
  """The first entry of the extras list a WITH_EXTRAS word points to."""
  return int(ms.extra[ms.extra_adr[mesh] + (word & INDEX_MASK)])


@wp.func
def field_cell(ms: MeshSupport, mesh: int, i: int, j: int) -> int:
  word = field_word(ms, mesh, i, j)
  if (word & PROOF_MASK) == WITH_EXTRAS:
    word = _extras_head(ms, mesh, word)
  return word & INDEX_MASK


@wp.func
def _cell_coords(ms: MeshSupport, mesh: int, d: wp.vec3) -> wp.vec2:
  """Continuous (u, v) field coordinates of direction d: u along theta, v along phi."""
  fres = float(ms.field_res[mesh])
  theta = wp.atan2(d[1], d[0])
  phi = wp.acos(wp.clamp(d[2] / wp.max(wp.length(d), 1.0e-30), -1.0, 1.0))
  return wp.vec2((theta + wp.pi) / (2.0 * wp.pi) * fres, phi / wp.pi * (fres - 1.0))


@wp.func
def field_lookup(ms: MeshSupport, mesh: int, d: wp.vec3, with_extras: bool) -> tuple[int, bool]:
  """Support vertex from the field for direction d (mesh frame), and whether it is proven exact.

  A certified quad answers with one read; otherwise the best of its 4 corner cells, which is
  exact where the quad is flagged CORNERS_EXACT; ``with_extras`` also weighs the listed extra
  vertices of a WITH_EXTRAS quad, which makes it exact there too.
  """
  res = ms.field_res[mesh]
  uv = _cell_coords(ms, mesh, d)
  i0 = int(wp.floor(uv[0]))
  j0 = wp.clamp(int(wp.floor(uv[1])), 0, res - 1)
  i1 = (i0 + 1) % res
  i0 = ((i0 % res) + res) % res
  j1 = wp.min(j0 + 1, res - 1)

  word = field_word(ms, mesh, i0, j0)
  proof = word & PROOF_MASK
  extras_at = ms.extra_adr[mesh] + (word & INDEX_MASK)  # where a WITH_EXTRAS word points
  if proof == WITH_EXTRAS:
    word = int(ms.extra[extras_at])
  best = word & INDEX_MASK
  # candidates beside the cell's own vertex: none (certified), the 3 other corners, the extras
  nextra = wp.where(with_extras and proof == WITH_EXTRAS, word >> EXTRA_COUNT_SHIFT, 0)
  ncandidate = wp.where(proof == CERTIFIED, 0, 3 + nextra)
  best_dot = wp.dot(hull_point(ms, mesh, best), d)
  for k in range(ncandidate):
    c = int(0)
    if k < 3:
      c = field_cell(ms, mesh, wp.where(k == 1, i0, i1), wp.where(k == 0, j0, j1))
    else:
      c = int(ms.extra[extras_at + k - 2])
    cd = wp.dot(hull_point(ms, mesh, c), d)
    if cd > best_dot:
      best = c
      best_dot = cd
  return best, proof == CERTIFIED or proof == CORNERS_EXACT or (proof == WITH_EXTRAS and with_extras)


@wp.func
def hill_climb(ms: MeshSupport, mesh: int, start: int, d: wp.vec3) -> int:
  """Steepest ascent on the convex-hull graph; a local maximum is the global one."""
  hadr = ms.hull_adr[mesh]
  cur = start
  cur_dot = wp.dot(hull_point(ms, mesh, cur), d)
  for _ in range(ms.hull_num[mesh]):
    nxt = cur
    g = hadr + cur
    adr = ms.nbr_adr[g]
    for k in range(ms.nbr_num[g]):
      nb = ms.nbr[adr + k]
      nd = wp.dot(hull_point(ms, mesh, nb), d)
      if nd > cur_dot:
        nxt = nb
        cur_dot = nd
    if nxt == cur:
      break
    cur = nxt
  return cur


@wp.func
def hull_scan(ms: MeshSupport, mesh: int, d: wp.vec3) -> int:
  """Exhaustive scan of the hull vertices (first maximum wins)."""
  best = int(0)
  best_dot = float(-FAR)
  for k in range(ms.hull_num[mesh]):
    kd = wp.dot(hull_point(ms, mesh, k), d)
    if kd > best_dot:
      best = k
      best_dot = kd
  return best


@wp.func
def prism_support(top: wp.mat33, bottom: float, d: wp.vec3) -> wp.vec3:
  """Support point of a vertical triangular prism: top vertices in the rows of ``top``, base at
  z = bottom (a heightfield cell's half, see heightfield.py)."""
  best = int(0)
  best_dot = float(-FAR)
  for i in range(3):
    s = top[i, 0] * d[0] + top[i, 1] * d[1] + wp.where(d[2] > 0.0, top[i, 2], bottom) * d[2]
    if s > best_dot:
      best = i
      best_dot = s
  return wp.vec3(top[best, 0], top[best, 1], wp.where(d[2] > 0.0, top[best, 2], bottom))


@functools.lru_cache(maxsize=None)
def support_funcs(mode: int) -> SimpleNamespace:
  """The support functions of support mode ``mode`` (types.SUPPORT_*): ``mesh_support_index``,
  ``support_local`` and ``support_world``.

  The mode is fixed when the kernels that call them are generated, not read at run time: each
  stage above (mpr_funcs, gjk_funcs, ...) builds its device functions on these for one mode, and
  the kernel factories on those, so a model compiles only its own mode's code.
  """

  @wp.func
  def mesh_support_index(ms: MeshSupport, mesh: int, d: wp.vec3) -> int:
    """Local hull index of the support vertex of a mesh in direction d (mesh frame)."""
    # the static branches are resolved when the kernel is generated: one mode's code holds
    # only its own query (an else, not code after a return, which would still be generated)
    if wp.static(mode == SUPPORT_EXACT):
      return hull_scan(ms, mesh, d)
    else:
      if ms.field_res[mesh] == 0:
        return hull_scan(ms, mesh, d)
      best, proven = field_lookup(ms, mesh, d, wp.static(mode != SUPPORT_FIELD))
      if wp.static(mode == SUPPORT_REFINED):
        if not proven:
          best = hill_climb(ms, mesh, best, d)
      return best

  @wp.func
  def support_local(gtype: int, size: wp.vec3, mesh: int, ms: MeshSupport, d: wp.vec3) -> wp.vec3:
    """Support point of a geom in its own frame for direction d (need not be unit)."""
    if gtype == GeomType.SPHERE:
      return size[0] * wp.normalize(d)
    if gtype == GeomType.BOX:
      return wp.vec3(
        wp.where(d[0] >= 0.0, size[0], -size[0]),
        wp.where(d[1] >= 0.0, size[1], -size[1]),
        wp.where(d[2] >= 0.0, size[2], -size[2]),
      )
    if gtype == GeomType.CAPSULE:
      return wp.vec3(0.0, 0.0, wp.where(d[2] >= 0.0, size[1], -size[1])) + size[0] * wp.normalize(d)
    if gtype == GeomType.ELLIPSOID:
      s2 = wp.cw_mul(wp.cw_mul(size, size), d)
      return s2 / wp.max(wp.sqrt(wp.dot(s2, d)), 1.0e-30)
    if gtype == GeomType.CYLINDER:
      rxy = wp.sqrt(d[0] * d[0] + d[1] * d[1])
      x = float(0.0)
      y = float(0.0)
      if rxy > 1.0e-12:
        x = size[0] * d[0] / rxy
        y = size[0] * d[1] / rxy
      return wp.vec3(x, y, wp.where(d[2] >= 0.0, size[1], -size[1]))
    if gtype == GeomType.MESH:
      return hull_point(ms, mesh, mesh_support_index(ms, mesh, d))
    return wp.vec3(0.0)

  @wp.func
  def support_world(s: Shape, ms: MeshSupport, d: wp.vec3) -> wp.vec3:
    """Support point of a posed shape (inflated by s.inflate) for world direction d.

    A HFIELD shape is one prism of a heightfield in the query's frame: top vertices in the
    rows of ``rot``, base height in ``size[0]``, ``pos`` zero.
    """
    p = wp.vec3(0.0)
    if s.gtype == GeomType.HFIELD:
      p = prism_support(s.rot, s.size[0], d)
    else:
      p = s.pos + s.rot @ support_local(s.gtype, s.size, s.mesh, ms, wp.transpose(s.rot) @ d)
    if s.inflate > 0.0:
      p = p + s.inflate * wp.normalize(d)
    return p

  return SimpleNamespace(mesh_support_index=mesh_support_index, support_local=support_local,
                         support_world=support_world)


# the support functions of the queries that need the exact support vertex whatever the model's
# mode: the tie counts (count_supports, multicontact's) flood from it
REFINED = support_funcs(SUPPORT_REFINED)


@wp.func
def box_corner(s: Shape, k: int) -> wp.vec3:
  """Corner k (bits 0, 1, 2: +x, +y, +z) of a posed box, world frame."""
  local = wp.vec3(wp.where((k & 1) != 0, 1.0, -1.0) * s.size[0], wp.where((k & 2) != 0, 1.0, -1.0) * s.size[1],
                  wp.where((k & 4) != 0, 1.0, -1.0) * s.size[2])
  return s.pos + s.rot @ local


TIE_STACK = 64  # largest tie set count_supports walks; larger ones report TIE_STACK
_tie_stack = wp.types.vector(length=TIE_STACK, dtype=int)


@wp.func
def count_supports(gtype: int, size: wp.vec3, mesh: int, ms: MeshSupport, d: wp.vec3, rtol: float) -> int:
  """Number of distinct support points of a geom for direction d (its frame).

  A vertex ties when its dot product is within rtol (relative to the shape's extent) of
  the maximum. Boxes: 2^(axes with d ~ 0). Meshes: the tied vertices form a face or an
  edge of the hull, which is connected in the hull graph, so a flood fill from the exact
  support vertex finds them all. Curved primitives have a unique support point (1).
  """
  dn = wp.normalize(d)
  if gtype == GeomType.BOX:
    n = int(1)
    for k in range(3):
      if wp.abs(dn[k]) * size[k] <= rtol * wp.length(size):
        n *= 2
    return n
  if gtype == GeomType.MESH:
    best = REFINED.mesh_support_index(ms, mesh, dn)
    top = wp.dot(hull_point(ms, mesh, best), dn)
    extent = wp.length(hull_point(ms, mesh, best) - ms.hull_center[mesh])
    tol = rtol * wp.max(extent, 1.0e-12)
    if ms.nbr_num.shape[0] == 0 or ms.nbr_num[ms.hull_adr[mesh] + best] == 0:
      n = int(0)  # no hull graph: scan
      for k in range(ms.hull_num[mesh]):
        if wp.dot(hull_point(ms, mesh, k), dn) >= top - tol:
          n += 1
      return n
    stack = _tie_stack()
    stack[0] = best
    count = int(1)
    head = int(0)
    hadr = ms.hull_adr[mesh]
    while head < count:
      g = hadr + stack[head]
      head += 1
      for k in range(ms.nbr_num[g]):
        nb = ms.nbr[ms.nbr_adr[g] + k]
        if wp.dot(hull_point(ms, mesh, nb), dn) >= top - tol:
          seen = bool(False)
          for s in range(count):
            if stack[s] == nb:
              seen = True
          if not seen and count < TIE_STACK:
            stack[count] = nb
            count += 1
    return count
  return 1
