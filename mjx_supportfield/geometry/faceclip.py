"""Face clipping: the multi-contact patch of a pair touching face on feature.

Where the contact normal lies along a flat face of one shape (a box face, a cylinder's end, a
hull polygon of MuJoCo's), that face is the reference and the other shape's feature facing it
the incident one (face_pair); the incident polygon clipped to the reference face's side planes
gives the contacts (clip_faces). This module owns those device functions (faces, clipping,
corner choice, the ``Manifold`` slots) for multicontact_pass.py's kernels; the tilts, for the
other pairs, are multicontact.py's. It launches nothing.
"""
import functools
import math
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.collision_gjk import EDGE_TOL
from mujoco_warp._src.collision_gjk import FACE_TOL
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.multicontact import ON_FACE_TOL
from mjx_supportfield.geometry.multicontact import polygon_toward
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.types import FAR
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape


# --- Face clipping ------------------------------------------------------------------------
#
# Where the contact normal lies along a flat face of one shape (within MuJoCo's multi-CCD
# tolerance), the contact patch is that face (the reference) against the other shape's facing
# feature (the incident face, or a line of a cylinder's side or a capsule): the incident polygon
# clipped to the reference face's side planes, its corners within the margin band of the
# reference plane. The clipped polygon is never built: its corners are streamed (each incident
# edge clipped on its own, Cyrus-Beck; each reference corner tested inside the incident
# polygon) into a fixed set of scalar slots. Polygons are read from the model's arrays each time
# a corner is needed: a thread-local polygon buffer would live in local memory on a GPU, which
# makes the clipping slower than the tilts it replaces.

MAX_MANIFOLD = 5  # contacts of a clipped pair (Options.max_contacts_per_pair's bound)
# reference corners x incident corners above which a face pair goes to the tilts: the clipping
# loops over every pair of them, one thread a pair, and the kernel waits for its longest thread.
# Robot links' hulls have faces of tens of corners (a 40-gon on a triangle, a pot's 24-gon on a
# box face), whose tilts land on the deepest edge alone: those are within it; two 24-gons, or an
# aluminium extrusion's 76-gon end on a 76-gon, are not
FACE_PAIR_BUDGET = 200
DISK_CORNERS = 16  # MuJoCo's polygon for a cylinder's end
QUAD_ROUNDS = 2  # alternations between a quadrilateral's diagonals in _largest_quad

# kinds of Face
FACE_NONE = wp.constant(0)
FACE_BOX = wp.constant(1)  # index: 2 * axis, + 1 on the negative side
FACE_MESH = wp.constant(2)  # index: the hull polygon (global)
FACE_DISK = wp.constant(3)  # index: 0 the cylinder's top end, 1 its bottom
# a line of a cylinder's side or of a capsule, or a tilted face's edge: p0, p1 (nvert 2); a
# tilted face's corner p0 with its two edges to p1 and p2 (nvert 3), or alone (nvert 1)
FACE_SEGMENT = wp.constant(4)

# Manifold.status
CLIPPED = wp.constant(0)
TILTS = wp.constant(1)  # no face pair (curved, edge on edge), polygons over budget: the tilts
# the first contact takes a clipped corner's place when they are all shallower than it by this
# fraction of its depth
MISSED_DEPTH = 0.1
# where more than max_contacts corners compete, the deepest is chosen first only when it is
# deeper than every extreme corner by this fraction of the first contact's depth: on a face
# lying flat on a face all corners are as deep, and float32 rounding would pick a different one
# each step
DEEPEST_MARGIN = 0.1


# corners of each box face in MuJoCo's order (collision_gjk._box_face), 3 bits a corner (bit 0
# set for +x, bit 1 for +y, bit 2 for +z), 12 bits a face: read with shifts, as a table indexed
# at run time would sit in local memory on a GPU
_BOX_FACE_CORNERS = ((7, 3, 1, 5), (2, 6, 4, 0), (2, 3, 7, 6), (4, 5, 1, 0), (6, 7, 5, 4), (3, 2, 0, 1))
_BOX_FACE_CODES = [sum(c << (3 * k) for k, c in enumerate(face)) for face in _BOX_FACE_CORNERS]


@wp.func
def _box_face_code(face: int) -> int:
  """The packed corners of box face ``face``."""
  return wp.where(face == 0, wp.static(_BOX_FACE_CODES[0]), wp.where(face == 1, wp.static(_BOX_FACE_CODES[1]),
    wp.where(face == 2, wp.static(_BOX_FACE_CODES[2]), wp.where(face == 3, wp.static(_BOX_FACE_CODES[3]),
    wp.where(face == 4, wp.static(_BOX_FACE_CODES[4]), wp.static(_BOX_FACE_CODES[5]))))))


@wp.struct
class Face:
  """A flat feature of a shape: a face (kind, index, corners) with its outward normal (world),
  or a segment (FACE_SEGMENT, in the shape's frame: p0 to p1; or a tilted face's corner p0 and
  its edges to p1 and p2, or that corner alone)."""

  kind: int
  index: int
  nvert: int
  adr: int  # a hull polygon's first corner in MeshSupport.poly_pos
  normal: wp.vec3
  p0: wp.vec3
  p1: wp.vec3
  p2: wp.vec3


@wp.struct
class Manifold:
  """A clipped pair's contacts (status CLIPPED): midpoints, in the reference shape's frame, and
  signed distances (negative: penetration) of the true surfaces, margin band removed. Contact
  ``first`` (-1: none) is the first contact's, whose position is the caller's (world)."""

  status: int
  n: int
  ref_is_b: bool  # the reference face is B's (else A's)
  first: int
  pos0: wp.vec3
  pos1: wp.vec3
  pos2: wp.vec3
  pos3: wp.vec3
  pos4: wp.vec3
  dist0: float
  dist1: float
  dist2: float
  dist3: float
  dist4: float


@wp.struct
class Picks:
  """The streamed corners of a clipped polygon, by their coordinates (a, b) along two directions
  u, v across the reference face (a corner's height follows from the incident plane it lies
  on): the first distinct ones (up to MAX_MANIFOLD; n = MAX_MANIFOLD + 1 once more came), the
  deepest, and the extremes along u, v and the two diagonals, both ways. Scalar fields, no arrays: an array indexed
  at run time lives in local memory on a GPU, and every register held through the streaming
  loops is one the clipping cannot use."""

  n: int
  whole: bool  # the incident polygon lies within the side planes and the band, uncut
  a0: float
  b0: float
  a1: float
  b1: float
  a2: float
  b2: float
  a3: float
  b3: float
  a4: float
  b4: float
  deep_a: float
  deep_b: float
  deep_h: float
  e0a: float  # farthest along +u
  e0b: float
  e1a: float  # -u
  e1b: float
  e2a: float  # +v
  e2b: float
  e3a: float  # -v
  e3b: float
  e4a: float  # +u +v
  e4b: float
  e5a: float  # +u -v
  e5b: float
  e6a: float  # -u +v
  e6b: float
  e7a: float  # -u -v
  e7b: float
  e4s: float  # how far each diagonal extreme lies along its direction (u ± v, unnormalised)
  e5s: float
  e6s: float
  e7s: float


@wp.func
def _component(v: wp.vec3, k: int) -> float:
  """v[k] without a run-time index (which would put v in local memory on a GPU)."""
  return wp.where(k == 0, v[0], wp.where(k == 1, v[1], v[2]))


@wp.func
def _along_axis(k: int, value: float) -> wp.vec3:
  """value along axis k (0, 1, 2)."""
  return wp.vec3(wp.where(k == 0, value, 0.0), wp.where(k == 1, value, 0.0), wp.where(k == 2, value, 0.0))


@wp.func
def _no_face() -> Face:
  f = Face()
  f.kind = FACE_NONE
  f.index = 0
  f.nvert = 0
  f.adr = 0
  f.normal = wp.vec3(0.0)
  f.p0 = wp.vec3(0.0)
  f.p1 = wp.vec3(0.0)
  f.p2 = wp.vec3(0.0)
  return f


@wp.func
def _disk_cos(k: int) -> float:
  """cos(k pi / 8) from its five values in the first quadrant (sin(k pi / 8) = _disk_cos(k + 12)):
  sinf and cosf keep a local array for their argument reduction on a GPU."""
  j = k % 16
  t = j % 8
  t = wp.where(t > 4, 8 - t, t)
  c = wp.where(t == 0, 1.0, wp.where(t == 1, wp.static(math.cos(math.pi / 8.0)), wp.where(
    t == 2, wp.static(math.cos(math.pi / 4.0)), wp.where(t == 3, wp.static(math.cos(3.0 * math.pi / 8.0)), 0.0))))
  return wp.where(j > 4 and j < 12, -c, c)


@wp.func
def _corner(s: Shape, ms: MeshSupport, f: Face, k: int) -> wp.vec3:
  """Corner k of face f of s, in the shape's frame, in MuJoCo's order (collision_gjk._box_face,
  _mesh_face, _cylinder_face): clockwise seen from outside. MuJoCo's choice of corners follows
  from where its clipped polygon starts (clip_faces)."""
  if f.kind == FACE_BOX:
    code = (_box_face_code(f.index) >> (3 * k)) & 7
    return wp.vec3(wp.where((code & 1) != 0, s.size[0], -s.size[0]), wp.where((code & 2) != 0, s.size[1], -s.size[1]),
                   wp.where((code & 4) != 0, s.size[2], -s.size[2]))
  if f.kind == FACE_MESH:
    # MuJoCo's hull polygons run counter-clockwise; collision_gjk._mesh_face reverses them
    return ms.poly_pos[f.adr + f.nvert - 1 - k]
  if f.kind == FACE_DISK:
    # MuJoCo's 16-gon (collision_gjk._cylinder_face): its corners are where MuJoCo C's contacts lie
    sign = wp.where(f.index != 0, -1.0, 1.0)
    return wp.vec3(s.size[0] * _disk_cos(k), -sign * s.size[0] * _disk_cos(k + 12), sign * s.size[1])
  return wp.vec3(0.0)  # a segment: _segment_manifold reads its ends itself


@wp.func
def _new_picks() -> Picks:
  p = Picks()
  p.n = 0
  p.whole = True
  p.a0 = 0.0
  p.b0 = 0.0
  p.a1 = 0.0
  p.b1 = 0.0
  p.a2 = 0.0
  p.b2 = 0.0
  p.a3 = 0.0
  p.b3 = 0.0
  p.a4 = 0.0
  p.b4 = 0.0
  p.deep_a = 0.0
  p.deep_b = 0.0
  p.deep_h = FAR
  # extremes start beyond any corner, so that the first corner takes every slot
  p.e0a = -FAR
  p.e0b = 0.0
  p.e1a = FAR
  p.e1b = 0.0
  p.e2a = 0.0
  p.e2b = -FAR
  p.e3a = 0.0
  p.e3b = FAR
  p.e4a = 0.0
  p.e4b = 0.0
  p.e5a = 0.0
  p.e5b = 0.0
  p.e6a = 0.0
  p.e6b = 0.0
  p.e7a = 0.0
  p.e7b = 0.0
  p.e4s = -FAR
  p.e5s = -FAR
  p.e6s = -FAR
  p.e7s = -FAR
  return p


@wp.func
def _near(a: wp.vec3, b: wp.vec3, spacing: float) -> bool:
  return wp.length_sq(a - b) < spacing * spacing


@wp.func
def _near2(a0: float, b0: float, a1: float, b1: float, spacing: float) -> bool:
  return (a0 - a1) * (a0 - a1) + (b0 - b1) * (b0 - b1) < spacing * spacing


@wp.func
def _pick(p: Picks, a: float, b: float, h: float, band: float, spacing: float) -> Picks:
  """Picks with the corner at (a, b), height h over the reference plane, streamed in: ignored
  above the margin band; else kept among the first distinct corners, and in the deepest and
  extreme slots where it beats them (ties keep the earlier corner)."""
  out = p
  if h > band:
    out.whole = False
    return out
  seen = ((p.n > 0 and _near2(a, b, p.a0, p.b0, spacing)) or (p.n > 1 and _near2(a, b, p.a1, p.b1, spacing))
          or (p.n > 2 and _near2(a, b, p.a2, p.b2, spacing)) or (p.n > 3 and _near2(a, b, p.a3, p.b3, spacing))
          or (p.n > 4 and _near2(a, b, p.a4, p.b4, spacing)))
  if not seen:
    if p.n == 0:
      out.a0 = a
      out.b0 = b
    elif p.n == 1:
      out.a1 = a
      out.b1 = b
    elif p.n == 2:
      out.a2 = a
      out.b2 = b
    elif p.n == 3:
      out.a3 = a
      out.b3 = b
    elif p.n == 4:
      out.a4 = a
      out.b4 = b
    out.n = wp.min(p.n + 1, MAX_MANIFOLD + 1)
  if h < out.deep_h:
    out.deep_a = a
    out.deep_b = b
    out.deep_h = h
  if a > out.e0a:
    out.e0a = a
    out.e0b = b
  if a < out.e1a:
    out.e1a = a
    out.e1b = b
  if b > out.e2b:
    out.e2a = a
    out.e2b = b
  if b < out.e3b:
    out.e3a = a
    out.e3b = b
  if a + b > out.e4s:
    out.e4a = a
    out.e4b = b
    out.e4s = a + b
  if a - b > out.e5s:
    out.e5a = a
    out.e5b = b
    out.e5s = a - b
  if b - a > out.e6s:
    out.e6a = a
    out.e6b = b
    out.e6s = b - a
  if -a - b > out.e7s:
    out.e7a = a
    out.e7b = b
    out.e7s = -a - b
  return out


@wp.func
def _put(mf: Manifold, x: wp.vec3, h: float, spacing: float, limit: int) -> Manifold:
  """mf with corner x (height h) appended, unless it is full (limit) or x repeats a corner."""
  if mf.n >= limit:
    return mf
  if ((mf.n > 0 and _near(x, mf.pos0, spacing)) or (mf.n > 1 and _near(x, mf.pos1, spacing))
      or (mf.n > 2 and _near(x, mf.pos2, spacing)) or (mf.n > 3 and _near(x, mf.pos3, spacing))):
    return mf
  out = mf
  if mf.n == 0:
    out.pos0 = x
    out.dist0 = h
  elif mf.n == 1:
    out.pos1 = x
    out.dist1 = h
  elif mf.n == 2:
    out.pos2 = x
    out.dist2 = h
  elif mf.n == 3:
    out.pos3 = x
    out.dist3 = h
  else:
    out.pos4 = x
    out.dist4 = h
  out.n = mf.n + 1
  return out


@wp.func
def manifold_pos(mf: Manifold, k: int) -> wp.vec3:
  """Contact k's position (a chain of selects: no run-time index)."""
  return wp.where(k == 0, mf.pos0, wp.where(k == 1, mf.pos1, wp.where(k == 2, mf.pos2, wp.where(k == 3, mf.pos3,
                                                                                                  mf.pos4))))


@wp.func
def manifold_dist(mf: Manifold, k: int) -> float:
  """Contact k's signed distance."""
  return wp.where(k == 0, mf.dist0, wp.where(k == 1, mf.dist1, wp.where(k == 2, mf.dist2, wp.where(k == 3, mf.dist3,
                                                                                                     mf.dist4))))


@wp.func
def _set_dist(mf: Manifold, k: int, dist: float) -> Manifold:
  out = mf
  if k == 0:
    out.dist0 = dist
  elif k == 1:
    out.dist1 = dist
  elif k == 2:
    out.dist2 = dist
  elif k == 3:
    out.dist3 = dist
  else:
    out.dist4 = dist
  return out


@wp.func
def _set_pos(mf: Manifold, k: int, pos: wp.vec3) -> Manifold:
  out = mf
  if k == 0:
    out.pos0 = pos
  elif k == 1:
    out.pos1 = pos
  elif k == 2:
    out.pos2 = pos
  elif k == 3:
    out.pos3 = pos
  else:
    out.pos4 = pos
  return out


@wp.func
def _cross2(a: wp.vec2, b: wp.vec2) -> float:
  return a[0] * b[1] - a[1] * b[0]


@wp.func
def _local_normal(ms: MeshSupport, f: Face) -> wp.vec3:
  """The outward normal of face f (not a segment) in its shape's frame."""
  if f.kind == FACE_BOX:
    return _along_axis(f.index // 2, wp.where(f.index % 2 == 0, 1.0, -1.0))
  if f.kind == FACE_DISK:
    return wp.vec3(0.0, 0.0, wp.where(f.index == 0, 1.0, -1.0))
  return ms.poly_normal[f.index]


@wp.func
def _face_frame(ref_shape: Shape, ref: Face, ms: MeshSupport) -> wp.mat33:
  """The reference face's frame in its shape's frame, as rows u, v, m: m its outward normal, u
  from its corner halfway round to its corner 0 (a box face's diagonal, a round end's diameter
  through its corners 0 and 8), v = m x u. Corners stream in its coordinates (a, b) across the
  face and z along m; the extremes along u and v are a box face's corners, clear of ties."""
  m = _local_normal(ms, ref)
  u = _corner(ref_shape, ms, ref, 0) - _corner(ref_shape, ms, ref, ref.nvert // 2)
  u = wp.normalize(u - wp.dot(u, m) * m)
  v = wp.cross(m, u)
  return wp.mat33(u[0], u[1], u[2], v[0], v[1], v[2], m[0], m[1], m[2])


@wp.func
def _ref_corner(ref_shape: Shape, ref: Face, ms: MeshSupport, frame: wp.mat33, k: int) -> wp.vec2:
  """Corner k of the reference face, across the face (its z is the plane's offset)."""
  r = frame @ _corner(ref_shape, ms, ref, k)
  return wp.vec2(r[0], r[1])


@wp.func
def _inc_corner(inc_shape: Shape, inc: Face, ms: MeshSupport, to_face: wp.quat, shift: wp.vec3, k: int) -> wp.vec3:
  """Corner k of the incident face in the reference face's frame (a, b, z)."""
  return wp.quat_rotate(to_face, _corner(inc_shape, ms, inc, k)) + shift


@wp.func
def _clip_segment(ref_shape: Shape, ref: Face, ms: MeshSupport, frame: wp.mat33, wr: float, p: wp.vec2,
                  q: wp.vec2, slack: float) -> wp.vec2:
  """Cyrus-Beck: the piece [t0, t1] of segment p + t (q - p), t in [0, 1], across the reference
  face within its side planes (t0 > t1: none). A segment leaves a convex polygon's prism as one
  piece. wr: +1 where the face's corners turn counter-clockwise about its normal, else -1; a
  point on a side plane counts up to ``slack``."""
  d = q - p
  t0 = float(0.0)
  t1 = float(1.0)
  a = _ref_corner(ref_shape, ref, ms, frame, ref.nvert - 1)
  for k in range(ref.nvert):
    b = _ref_corner(ref_shape, ref, ms, frame, k)
    e = b - a
    inward = wr * wp.vec2(-e[1], e[0])
    num = wp.dot(p - a, inward) + slack * wp.length(e)
    den = wp.dot(d, inward)
    if den > 0.0:
      t0 = wp.max(t0, -num / den)
    elif den < 0.0:
      t1 = wp.min(t1, -num / den)
    elif num < 0.0:
      t1 = -1.0
    a = b
    if t0 > t1:
      break
  return wp.vec2(t0, t1)


@wp.func
def _incident_plane(inc_shape: Shape, inc: Face, ms: MeshSupport, to_face: wp.quat, shift: wp.vec3) -> wp.vec4:
  """The incident polygon's plane in the reference face's frame, from its corners: unit normal
  (xyz, either way round) and offset (w). Recomputed where needed rather than held."""
  i0 = _inc_corner(inc_shape, inc, ms, to_face, shift, 0)
  i1 = _inc_corner(inc_shape, inc, ms, to_face, shift, 1)
  i2 = _inc_corner(inc_shape, inc, ms, to_face, shift, 2)
  normal = wp.normalize(wp.cross(i1 - i0, i2 - i1))
  return wp.vec4(normal[0], normal[1], normal[2], wp.dot(i0, normal))


@wp.func
def _lift(a: float, b: float, plane: wp.vec4) -> wp.vec3:
  """The point at (a, b) across the reference face on the incident plane (face frame)."""
  return wp.vec3(a, b, (plane[3] - a * plane[0] - b * plane[1]) / plane[2])


@wp.func
def _corner64(s: Shape, ms: MeshSupport, f: Face, k: int) -> wp.vec3d:
  """Corner k of face f in its shape's frame, in float64."""
  x = _corner(s, ms, f, k)
  return wp.vec3d(wp.float64(x[0]), wp.float64(x[1]), wp.float64(x[2]))


@wp.func
def _quad_area(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d) -> wp.float64:
  """collision_gjk._area4: the area of quadrilateral abcd of a flat face."""
  return wp.float64(0.5) * wp.length(wp.cross(d - a, b - d) + wp.cross(c - b, a - c))


@wp.func
def _climb(s: Shape, f: Face, ms: MeshSupport, start: int, b0: int, c0: int, d0: int):
  """collision_gjk._polygon_quad's climb on face f of s read in place, from its corner ``start``
  on and the quadrilateral (0, b0, c0, d0) counted from there: the corners (counted from start)
  of a quadrilateral of locally largest area, and that area. The four corners are held as they
  climb, so that each step reads only the one that moves (a local array of them would sit in
  local memory on a GPU); each climb goes at most once round the face."""
  n = f.nvert
  b = int(b0)
  c = int(c0)
  d = int(d0)
  res = wp.vec4i(0, b, c, d)
  pa = _corner64(s, ms, f, start % n)
  pb = _corner64(s, ms, f, (start + b) % n)
  pc = _corner64(s, ms, f, (start + c) % n)
  pd = _corner64(s, ms, f, (start + d) % n)
  m = _quad_area(pa, pb, pc, pd)
  for a in range(n):
    if a > 0:
      pa = _corner64(s, ms, f, (start + a) % n)
    for _step in range(n):
      p_next = _corner64(s, ms, f, (start + (d + 1) % n) % n)
      m_next = _quad_area(pa, pb, pc, p_next)
      if m_next <= m:
        break
      m = m_next
      d = (d + 1) % n
      pd = p_next
      res = wp.vec4i(a, b, c, d)
      for _step in range(n):
        p_next = _corner64(s, ms, f, (start + (c + 1) % n) % n)
        m_next = _quad_area(pa, pb, p_next, pd)
        if m_next <= m:
          break
        m = m_next
        c = (c + 1) % n
        pc = p_next
        res = wp.vec4i(a, b, c, d)
      for _step in range(n):
        p_next = _corner64(s, ms, f, (start + (b + 1) % n) % n)
        m_next = _quad_area(pa, p_next, pc, pd)
        if m_next <= m:
          break
        m = m_next
        b = (b + 1) % n
        pb = p_next
        res = wp.vec4i(a, b, c, d)
    if b == a:
      b = (b + 1) % n
      pb = _corner64(s, ms, f, (start + b) % n)
      if c == b:
        c = (c + 1) % n
        pc = _corner64(s, ms, f, (start + c) % n)
        if d == c:
          d = (d + 1) % n
          pd = _corner64(s, ms, f, (start + d) % n)
  return res, m


@wp.func
def _polygon_quad(s: Shape, f: Face, ms: MeshSupport, start: int) -> wp.vec4i:
  """collision_gjk._polygon_quad on face f of s, from its corner ``start`` on: the corners
  (counted from start) of a quadrilateral of locally largest area.

  Areas are taken in float64 in the shape's own frame, as MuJoCo C takes them in float64: its
  climb moves on for gains of a few 1e-7 of the area, below float32's rounding, and in the world
  frame float32 rounding would change with the pose, choosing another quadrilateral from step to
  step (a cylinder resting on its end crept). MuJoCo's climb starts from the first four corners;
  where those lie on one straight edge of the face (a pie slice of a pot's bottom) only the
  rounding of its world frame moves it on, and exact in the shape's frame it would stay there: a
  second climb from corners spread round the face is taken where it ends larger."""
  n = f.nvert
  quad, area = _climb(s, f, ms, start, 1, 2, 3)
  spread, spread_area = _climb(s, f, ms, start, n // 4, n // 2, (3 * n) // 4)
  if spread_area > area * wp.float64(1.0 + 1.0e-9):
    return spread
  return quad


@wp.func
def _stream_polygon(ref_shape: Shape, ref: Face, inc_shape: Shape, inc: Face, ms: MeshSupport, frame: wp.mat33,
                    to_face: wp.quat, shift: wp.vec3, plane_offset: float, band: float, spacing: float,
                    slack: float) -> Picks:
  """The corners of the incident polygon clipped to the reference face's side planes, streamed
  into Picks, in the reference face's frame (_face_frame: ``frame`` from the reference shape's
  frame, to_face and shift from the incident shape's; the reference plane at z =
  plane_offset): each incident edge clipped on its own (_clip_segment), its piece's ends; and
  each reference corner inside the incident polygon seen along the normal, lifted onto the
  incident plane."""
  r0 = _ref_corner(ref_shape, ref, ms, frame, 0)
  wr = wp.where(_cross2(_ref_corner(ref_shape, ref, ms, frame, 1) - r0,
                        _ref_corner(ref_shape, ref, ms, frame, 2) - r0) >= 0.0, 1.0, -1.0)
  picks = _new_picks()
  p = _inc_corner(inc_shape, inc, ms, to_face, shift, inc.nvert - 1)
  for e in range(inc.nvert):
    q = _inc_corner(inc_shape, inc, ms, to_face, shift, e)
    t = _clip_segment(ref_shape, ref, ms, frame, wr, wp.vec2(p[0], p[1]), wp.vec2(q[0], q[1]), slack)
    if t[0] > 0.0 or t[1] < 1.0:
      picks.whole = False
    if t[0] <= t[1]:
      # each corner once: an edge gives where it enters (the previous edge gave its start when
      # that is inside) and where it ends or leaves
      if t[0] > 0.0:
        x = p + t[0] * (q - p)
        picks = _pick(picks, x[0], x[1], x[2] - plane_offset, band, spacing)
      x = wp.where(t[1] >= 1.0, q, p + t[1] * (q - p))
      picks = _pick(picks, x[0], x[1], x[2] - plane_offset, band, spacing)
    p = q
  plane = _incident_plane(inc_shape, inc, ms, to_face, shift)
  i0 = _inc_corner(inc_shape, inc, ms, to_face, shift, 0)
  i1 = _inc_corner(inc_shape, inc, ms, to_face, shift, 1)
  i2 = _inc_corner(inc_shape, inc, ms, to_face, shift, 2)
  wi = wp.where(_cross2(wp.vec2(i1[0] - i0[0], i1[1] - i0[1]), wp.vec2(i2[0] - i1[0], i2[1] - i1[1])) >= 0.0,
                1.0, -1.0)
  for k in range(ref.nvert):
    r = _ref_corner(ref_shape, ref, ms, frame, k)
    inside = bool(True)
    a3 = _inc_corner(inc_shape, inc, ms, to_face, shift, inc.nvert - 1)
    a = wp.vec2(a3[0], a3[1])
    for j in range(inc.nvert):
      b3 = _inc_corner(inc_shape, inc, ms, to_face, shift, j)
      b = wp.vec2(b3[0], b3[1])
      if wi * _cross2(b - a, r - a) < -slack * wp.length(b - a):
        inside = False
        break
      a = b
    if inside:
      picks.whole = False
      picks = _pick(picks, r[0], r[1], _lift(r[0], r[1], plane)[2] - plane_offset, band, spacing)
  return picks


@wp.func
def _extreme(p: Picks, k: int) -> wp.vec2:
  """Extreme k of the streamed corners: along +u, -u, +v, -v, then the four diagonals."""
  a = wp.where(k == 0, p.e0a, wp.where(k == 1, p.e1a, wp.where(k == 2, p.e2a, wp.where(k == 3, p.e3a, wp.where(
    k == 4, p.e4a, wp.where(k == 5, p.e5a, wp.where(k == 6, p.e6a, p.e7a)))))))
  b = wp.where(k == 0, p.e0b, wp.where(k == 1, p.e1b, wp.where(k == 2, p.e2b, wp.where(k == 3, p.e3b, wp.where(
    k == 4, p.e4b, wp.where(k == 5, p.e5b, wp.where(k == 6, p.e6b, p.e7b)))))))
  return wp.vec2(a, b)


@wp.func
def _candidate(p: Picks, k: int) -> wp.vec2:
  """Streamed corner k: the eight extremes (0 to 7, _extreme), then the first distinct corners
  (8 to 12)."""
  if k < 8:
    return _extreme(p, k)
  return wp.vec2(wp.where(k == 8, p.a0, wp.where(k == 9, p.a1, wp.where(k == 10, p.a2, wp.where(k == 11, p.a3, p.a4)))),
                 wp.where(k == 8, p.b0, wp.where(k == 9, p.b1, wp.where(k == 10, p.b2, wp.where(k == 11, p.b3, p.b4)))))


@wp.func
def _sorted4(q: wp.vec4i) -> wp.vec4i:
  """q's entries in increasing order (a sorting network): the corners go out in candidate order,
  whichever diagonal was found first."""
  a = wp.min(q[0], q[1])
  b = wp.max(q[0], q[1])
  c = wp.min(q[2], q[3])
  d = wp.max(q[2], q[3])
  lo = wp.min(a, c)
  hi = wp.max(b, d)
  m1 = wp.max(a, c)
  m2 = wp.min(b, d)
  return wp.vec4i(lo, wp.min(m1, m2), wp.max(m1, m2), hi)


@wp.func
def _sides(p: Picks, ncand: int, i: int, k: int) -> wp.vec2i:
  """The candidates farthest from the line through candidates i and k on either side (the same
  index on both where every candidate lies on one side or on the line): with i and k, the
  quadrilateral of largest area on that diagonal. Ties keep the earlier candidate."""
  a = _candidate(p, i)
  d = _candidate(p, k) - a
  left = int(i)
  right = int(k)
  most = float(0.0)
  least = float(0.0)
  for m in range(ncand):
    c = _cross2(d, _candidate(p, m) - a)
    if c > most:
      most = c
      left = m
    if c < least:
      least = c
      right = m
  return wp.vec2i(left, right)


@wp.func
def _largest_quad(p: Picks) -> wp.vec4i:
  """Of the streamed corners kept (_candidate: the eight extremes and the first MAX_MANIFOLD
  distinct ones), four spanning a largest quadrilateral: MuJoCo C keeps its clipped polygon's
  quadrilateral of largest area (collision_gjk._polygon_quad), and the extremes along the face
  frame's axes alone can fall on fewer or other corners (one corner farthest both along u and
  against v: three of a triangle cut by a 40-gon where MuJoCo keeps four). A largest
  quadrilateral's corners each lie farthest across the diagonal between their neighbours, so
  from the farthest pair the corners farthest on either side are taken, then the farthest on
  either side of that diagonal, QUAD_ROUNDS times: a few tens of tests where trying every four
  of 13 candidates took 715, and on a GPU a kernel waits for its longest thread."""
  ncand = 8 + wp.min(p.n, MAX_MANIFOLD)
  i = int(0)
  k = int(0)
  far = float(0.0)
  for m in range(ncand):
    pm = _candidate(p, m)
    for n in range(m + 1, ncand):
      dist = wp.length_sq(_candidate(p, n) - pm)
      if dist > far:
        far = dist
        i = m
        k = n
  sides = _sides(p, ncand, i, k)
  for _ in range(QUAD_ROUNDS):
    across = _sides(p, ncand, sides[0], sides[1])
    i = across[1]
    k = across[0]
    sides = _sides(p, ncand, i, k)
  return _sorted4(wp.vec4i(i, sides[0], k, sides[1]))


@wp.func
def _chosen(picks: Picks, plane_offset: float, plane: wp.vec4, spacing: float, max_contacts: int,
            depth_margin: float) -> Manifold:
  """Which streamed corners become contacts: all when there are no more than max_contacts
  (distinct); else the deepest (where clearly deepest, DEEPEST_MARGIN) and the four streamed
  corners spanning the largest quadrilateral (_largest_quad), in that order, repeats dropped. Corners lifted onto the incident plane,
  heights over the reference plane (z = plane_offset) in dist, all in the face frame."""
  mf = Manifold()
  mf.status = CLIPPED
  mf.n = 0
  mf.ref_is_b = False
  mf.first = -1
  if picks.n <= max_contacts:
    for k in range(MAX_MANIFOLD):
      a = wp.where(k == 0, picks.a0, wp.where(k == 1, picks.a1, wp.where(k == 2, picks.a2, wp.where(
        k == 3, picks.a3, picks.a4))))
      b = wp.where(k == 0, picks.b0, wp.where(k == 1, picks.b1, wp.where(k == 2, picks.b2, wp.where(
        k == 3, picks.b3, picks.b4))))
      x = _lift(a, b, plane)
      mf = _put(mf, x, x[2] - plane_offset, 0.0, picks.n)
    return mf
  quad = _largest_quad(picks)
  c0 = _candidate(picks, quad[0])
  c1 = _candidate(picks, quad[1])
  c2 = _candidate(picks, quad[2])
  c3 = _candidate(picks, quad[3])
  x0 = _lift(c0[0], c0[1], plane)
  x1 = _lift(c1[0], c1[1], plane)
  x2 = _lift(c2[0], c2[1], plane)
  x3 = _lift(c3[0], c3[1], plane)
  if picks.deep_h < wp.min(wp.min(x0[2], x1[2]), wp.min(x2[2], x3[2])) - plane_offset - depth_margin:
    x = _lift(picks.deep_a, picks.deep_b, plane)
    mf = _put(mf, x, x[2] - plane_offset, spacing, max_contacts)
  mf = _put(mf, x0, x0[2] - plane_offset, spacing, max_contacts)
  mf = _put(mf, x1, x1[2] - plane_offset, spacing, max_contacts)
  mf = _put(mf, x2, x2[2] - plane_offset, spacing, max_contacts)
  mf = _put(mf, x3, x3[2] - plane_offset, spacing, max_contacts)
  return mf


@wp.func
def _segment_manifold(ref_shape: Shape, ref: Face, inc: Face, ms: MeshSupport, frame: wp.mat33, to_face: wp.quat,
                      shift: wp.vec3, plane_offset: float, band: float, spacing: float, slack: float,
                      max_contacts: int) -> Manifold:
  """A line (a cylinder's side, a capsule's, a tilted face's edge) on the reference face: the
  ends of its piece within the side planes, those within the band (face frame). A tilted face's
  corner with its two edges (nvert 3): both edges so, the corner once (up to max_contacts, at
  least 2); the corner alone (nvert 1): itself, where it lies within the side planes and the
  band, else nothing (clip_faces then leaves the pair to the tilts, which keep its first
  contact)."""
  mf = Manifold()
  mf.status = CLIPPED
  mf.n = 0
  mf.ref_is_b = False
  mf.first = -1
  limit = wp.where(inc.nvert == 3, wp.max(2, wp.min(3, max_contacts)), 2)
  r0 = _ref_corner(ref_shape, ref, ms, frame, 0)
  wr = wp.where(_cross2(_ref_corner(ref_shape, ref, ms, frame, 1) - r0,
                        _ref_corner(ref_shape, ref, ms, frame, 2) - r0) >= 0.0, 1.0, -1.0)
  p = wp.quat_rotate(to_face, inc.p0) + shift
  for e in range(wp.where(inc.nvert == 3, 2, 1)):
    q = wp.quat_rotate(to_face, wp.where(e == 0, inc.p1, inc.p2)) + shift
    if inc.nvert == 1:
      # the corner alone is a segment of no length, kept where it lies within the side planes:
      # where its edge enters them is a point of neither MuJoCo's contact nor the corner
      q = p
    t = _clip_segment(ref_shape, ref, ms, frame, wr, wp.vec2(p[0], p[1]), wp.vec2(q[0], q[1]), slack)
    if t[0] <= t[1]:
      # the second edge starts at the corner the first gave already
      x = p + t[0] * (q - p)
      if (e == 0 or t[0] > 0.0) and x[2] - plane_offset <= band:
        mf = _put(mf, x, x[2] - plane_offset, spacing, limit)
      x = p + t[1] * (q - p)
      if inc.nvert >= 2 and x[2] - plane_offset <= band:
        mf = _put(mf, x, x[2] - plane_offset, spacing, limit)
  return mf


@wp.func
def face_code(f: Face) -> int:
  """A face as one int (kind and index), for the queue between face_pair and clip_faces."""
  return f.index * 8 + f.kind


@wp.func
def _tilted_face_feature(s: Shape, ms: MeshSupport, f: Face, u: wp.vec3) -> Face:
  """The feature of face f (not a segment) leading toward world direction u where f is tilted
  from u by more than MuJoCo's face tolerance: as in MuJoCo's multi-CCD, not a face on a face
  but an edge on a face, an edge of f through its corner furthest along u that lies across u
  (within EDGE_TOL), as a segment (nvert 2); where neither edge through that corner does, the
  corner alone (nvert 1). Where both do (a round polygon's rim, tilted), MuJoCo takes the first
  in its hull's bookkeeping: both are kept (nvert 3, the nearer to lying across u to p1).
  Clipping the whole tilted face instead gave every corner of it within the band: on a
  chamfered box resting on an edge, the chamfer's far corners beside the edge's, near-duplicate
  contacts that stiffen the soft contact."""
  lu = wp.transpose(s.rot) @ u
  lead = int(0)
  top = wp.dot(_corner(s, ms, f, 0), lu)
  for k in range(1, f.nvert):
    h = wp.dot(_corner(s, ms, f, k), lu)
    if h > top:
      top = h
      lead = k
  x = _corner(s, ms, f, lead)
  before = _corner(s, ms, f, (lead + f.nvert - 1) % f.nvert) - x
  after = _corner(s, ms, f, (lead + 1) % f.nvert) - x
  # |cos| of each edge's angle to u: the one nearer to lying across u
  cos_before = wp.abs(wp.dot(before, lu)) / wp.max(wp.length(before), 1.0e-12)
  cos_after = wp.abs(wp.dot(after, lu)) / wp.max(wp.length(after), 1.0e-12)
  seg = _no_face()
  seg.kind = FACE_SEGMENT
  seg.normal = u
  seg.p0 = x
  seg.p1 = x + wp.where(cos_after < cos_before, after, before)
  seg.p2 = x + wp.where(cos_after < cos_before, before, after)
  seg.nvert = wp.where(wp.min(cos_before, cos_after) < EDGE_TOL, wp.where(wp.max(cos_before, cos_after) < EDGE_TOL, 3, 2),
                       1)
  return seg


@wp.func
def _budget(ref: Face, inc: Face) -> int:
  """The corner pairs a face pair may clip: FACE_PAIR_BUDGET, or a whole 16-gon on a 16-gon for
  a cylinder's end on another's (stacked cylinders), whose tilts would all land around the
  deepest point of the rim instead of spanning the overlap of the two ends."""
  return wp.where(ref.kind == FACE_DISK and inc.kind == FACE_DISK, DISK_CORNERS * DISK_CORNERS, FACE_PAIR_BUDGET)


@functools.lru_cache(maxsize=None)
def faceclip_funcs(mode: int) -> SimpleNamespace:
  """Face clipping's device functions on the support functions of support mode ``mode``
  (support_funcs; a mesh's face is the hull polygon around its support vertex): ``face_pair``
  and ``clip_faces``."""
  mesh_support_index = support_funcs(mode).mesh_support_index

  @wp.func
  def _flat_face(s: Shape, ms: MeshSupport, u: wp.vec3) -> Face:
    """The flat face of s whose outward normal is nearest to world direction u (a box face, a
    cylinder's end, a mesh's hull polygon around its support vertex); kind FACE_NONE where s has
    none."""
    lu = wp.transpose(s.rot) @ u
    f = _no_face()
    local = wp.vec3(0.0)
    if s.gtype == GeomType.BOX:
      k = wp.where(wp.abs(lu[1]) > wp.abs(lu[0]), 1, 0)
      k = wp.where(wp.abs(lu[2]) > wp.abs(_component(lu, k)), 2, k)
      sign = wp.where(_component(lu, k) >= 0.0, 1.0, -1.0)
      local = _along_axis(k, sign)
      f.kind = FACE_BOX
      f.index = 2 * k + wp.where(sign > 0.0, 0, 1)
      f.nvert = 4
    elif s.gtype == GeomType.CYLINDER:
      sign = wp.where(lu[2] >= 0.0, 1.0, -1.0)
      local = wp.vec3(0.0, 0.0, sign)
      f.kind = FACE_DISK
      f.index = wp.where(sign > 0.0, 0, 1)
      f.nvert = DISK_CORNERS
    elif s.gtype == GeomType.MESH:
      poly = polygon_toward(ms, s.mesh, mesh_support_index(ms, s.mesh, lu), lu)
      if poly >= 0:
        local = ms.poly_normal[poly]
        f.kind = FACE_MESH
        f.index = poly
        f.nvert = ms.poly_vert_num[poly]
        f.adr = ms.poly_vert_adr[poly]
    f.normal = s.rot @ local
    return f

  @wp.func
  def _incident(s: Shape, ms: MeshSupport, u: wp.vec3) -> Face:
    """The feature of s facing world direction u (toward the reference face): its face nearest u
    where that face lies across u within FACE_TOL, else that face's edge or corner leading along
    u (_tilted_face_feature); for a cylinder lying on its side or a capsule the line of its
    surface along u; kind FACE_NONE where s meets the reference face in a point of a curved
    surface."""
    if s.gtype == GeomType.BOX or s.gtype == GeomType.MESH:
      f = _flat_face(s, ms, u)
      if f.kind == FACE_NONE or wp.dot(f.normal, u) >= FACE_TOL:
        return f
      return _tilted_face_feature(s, ms, f, u)
    f = _no_face()
    lu = wp.transpose(s.rot) @ u
    if s.gtype == GeomType.CYLINDER and wp.abs(lu[2]) >= FACE_TOL:
      return _flat_face(s, ms, u)
    if (s.gtype == GeomType.CYLINDER or s.gtype == GeomType.CAPSULE) and wp.abs(lu[2]) <= EDGE_TOL:
      axis = wp.vec3(0.0, 0.0, s.size[1])
      side = s.size[0] * lu
      if s.gtype == GeomType.CYLINDER:
        side = s.size[0] * wp.normalize(wp.vec3(lu[0], lu[1], 0.0))
      f.kind = FACE_SEGMENT
      f.nvert = 2
      f.normal = u
      f.p0 = side - axis
      f.p1 = side + axis
    return f

  @wp.func
  def _face_from_code(s: Shape, ms: MeshSupport, code: int, toward: wp.vec3) -> Face:
    """The face of s that face_code gave ``code``; a segment is found again facing world
    direction ``toward``."""
    kind = code & 7
    if kind == FACE_SEGMENT:
      return _incident(s, ms, toward)
    f = _no_face()
    f.kind = kind
    f.index = code >> 3
    f.nvert = 4
    if kind == FACE_DISK:
      f.nvert = DISK_CORNERS
    elif kind == FACE_MESH:
      f.nvert = ms.poly_vert_num[f.index]
      f.adr = ms.poly_vert_adr[f.index]
    local = _local_normal(ms, f)
    f.normal = s.rot @ local
    return f

  @wp.func
  def face_pair(a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3) -> wp.vec3i:
    """Whether A and B touch face on feature along the first contact's normal (from A to B): the
    flat face of one of them along it (within MuJoCo's multi-CCD tolerance FACE_TOL) is the
    reference, the other shape's feature facing it the incident one. Where both shapes offer such
    a face and the two are parallel (within FACE_TOL), A's is the reference, as in MuJoCo.
    Returns (1 where the reference is B's, else 0; the reference's face_code; the incident's), or
    x = -1 where the pair is left to the tilts: neither has a face there, the other shape meets
    it in a point of a curved surface, or the polygons are over their budget (_budget)."""
    none = wp.vec3i(-1, 0, 0)
    fa = _flat_face(a, ms, normal)
    fb = _flat_face(b, ms, -normal)
    ca = wp.where(fa.kind != FACE_NONE, wp.dot(fa.normal, normal), -2.0)
    cb = wp.where(fb.kind != FACE_NONE, wp.dot(fb.normal, -normal), -2.0)
    if wp.max(ca, cb) < FACE_TOL:
      return none
    # a face on a face (MuJoCo's test: the two faces anti-parallel within FACE_TOL): A's is the
    # reference, as in MuJoCo; else the face along the normal
    face_face = ca >= FACE_TOL and cb >= FACE_TOL and wp.dot(fa.normal, fb.normal) <= -FACE_TOL
    ref_is_b = not (ca >= FACE_TOL and (face_face or ca >= cb))
    ref = fa
    inc = _no_face()
    if ref_is_b:
      ref = fb
      inc = _incident(a, ms, -fb.normal)
    else:
      inc = _incident(b, ms, -fa.normal)
      # a face on a face: of B's face facing A's and B's face along the normal, the nearer to
      # the normal, as MuJoCo's faces are those at its contact's support points (the one facing
      # A's face alone took the other half of a pad split into coplanar triangles; the one found
      # along the normal alone, a sliver beside a pot's bottom, around the support vertex)
      if face_face and (inc.kind == FACE_SEGMENT or wp.dot(fb.normal, normal) < wp.dot(inc.normal, normal)):
        inc = fb
    if inc.kind == FACE_NONE or ref.nvert * inc.nvert > _budget(ref, inc):
      return none
    return wp.vec3i(wp.where(ref_is_b, 1, 0), face_code(ref), face_code(inc))

  @wp.func
  def clip_faces(a: Shape, b: Shape, ms: MeshSupport, first: MprResult, scale: float, max_contacts: int,
                 spacing: float, faces: wp.vec3i) -> Manifold:
    """The contacts of A and B by face clipping on the faces face_pair found (``faces``): the
    incident feature clipped to the reference face's side planes, its corners within the margin
    band of the reference plane (module notes), at most max_contacts. Status TILTS where no corner
    lies within the band (not the face the first contact is on) or the incident face stands on
    edge.

    A is grown by its inflate (the margin band, as the narrow phase poses it); the faces are the
    true ones and the band widens the height at which a corner still counts. ``scale``: the pair's
    size (posed_pair), for tolerances; ``spacing``: corners closer are one.
    """
    out = Manifold()
    out.status = TILTS
    out.n = 0
    out.ref_is_b = False
    out.first = -1
    ref_is_b = faces[0] == 1
    band = a.inflate
    bare = a
    bare.inflate = 0.0
    ref_shape = bare
    inc_shape = b
    if ref_is_b:
      ref_shape = b
      inc_shape = bare
    ref = _face_from_code(ref_shape, ms, faces[1], wp.vec3(0.0))
    inc = _face_from_code(inc_shape, ms, faces[2], -ref.normal)
    # everything in the reference face's frame (_face_frame): the reference corners across it,
    # the incident corners with their height
    frame = _face_frame(ref_shape, ref, ms)
    to_face = wp.quat_from_matrix(frame @ (wp.transpose(ref_shape.rot) @ inc_shape.rot))
    shift = frame @ (wp.transpose(ref_shape.rot) @ (inc_shape.pos - ref_shape.pos))
    plane_offset = (frame @ _corner(ref_shape, ms, ref, 0))[2]
    max_contacts = wp.min(max_contacts, MAX_MANIFOLD)
    if inc.kind == FACE_SEGMENT:
      out = _segment_manifold(ref_shape, ref, inc, ms, frame, to_face, shift, plane_offset, band, spacing,
                              ON_FACE_TOL * scale, max_contacts)
    else:
      if wp.abs(_incident_plane(inc_shape, inc, ms, to_face, shift)[2]) < 1.0e-3:
        return out  # the incident face stands on edge: no polygon to clip
      picks = _stream_polygon(ref_shape, ref, inc_shape, inc, ms, frame, to_face, shift, plane_offset, band, spacing,
                              ON_FACE_TOL * scale)
      if picks.whole and picks.n > max_contacts and max_contacts >= 4:
        # the incident polygon lies on the reference face uncut: MuJoCo's clipped polygon is that
        # polygon, each of the reference face's side planes having moved its start on by one
        # corner, and MuJoCo C's contacts its quadrilateral of largest area climbed to from there
        start = ref.nvert % inc.nvert
        quad = _polygon_quad(inc_shape, inc, ms, start)
        out.status = CLIPPED
        for k in range(4):
          x = _inc_corner(inc_shape, inc, ms, to_face, shift, (start + quad[k]) % inc.nvert)
          out = _put(out, x, x[2] - plane_offset, 0.0, 4)
      else:
        out = _chosen(picks, plane_offset, _incident_plane(inc_shape, inc, ms, to_face, shift), spacing, max_contacts,
                      DEEPEST_MARGIN * first.depth)
    if out.n == 0:
      out.status = TILTS
      return out  # nothing within the band: not the face the first contact is on
    # each contact midway between its corner and the corner's foot on the plane, in the reference
    # shape's frame
    frame = _face_frame(ref_shape, ref, ms)
    for k in range(out.n):
      x = manifold_pos(out, k)
      out = _set_pos(out, k, wp.transpose(frame) @ wp.vec3(x[0], x[1], x[2] - 0.5 * manifold_dist(out, k)))
    # no corner deeper than the first contact; the deepest corner carries its depth (exact where
    # the corners' is not: a round end's deepest point lies between two corners of its 16-gon)
    floor = band - first.depth
    deepest = int(0)
    for k in range(out.n):
      out = _set_dist(out, k, wp.max(manifold_dist(out, k), floor))
      if manifold_dist(out, k) < manifold_dist(out, deepest):
        deepest = k
    out.ref_is_b = ref_is_b
    out.first = -1
    if manifold_dist(out, deepest) > floor + MISSED_DEPTH * first.depth:
      # the corners miss the first contact (an edge crossing the reference face's rim beside the
      # incident face): it takes the last place
      out.first = wp.min(out.n, max_contacts - 1)
      out = _set_dist(out, out.first, floor)
      out.n = out.first + 1
    else:
      out = _set_dist(out, deepest, floor)
    return out

  return SimpleNamespace(face_pair=face_pair, clip_faces=clip_faces)
