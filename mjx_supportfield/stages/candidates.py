"""Contact candidates of one pair: several sources propose points, duplicates merge, and the
deepest point plus the ones farthest from those chosen are written (heightfields, non-convex
meshes); a source may ask for every candidate deeper than a depth (``Candidates.keep``) too."""

import warp as wp
from mujoco_warp._src.math import make_frame
from mujoco_warp._src.types import vec5

from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import write_row
from mjx_supportfield.types import FAR

NCANDIDATE = 32  # room for contact candidates per pair before the final choice (the most any source asks)
ROOM = 16  # candidates a source keeps unless it asks for more (empty_with_room)
MAX_CONTACTS = 8  # most contacts of the spread choice per pair (Options.max_contacts_per_pair bounds it too)
SAME_NORMAL = 0.9999  # cosine above which two candidates' normals are one (a terrain triangle's plane)

mat_cand = wp.types.matrix(shape=(NCANDIDATE, 3), dtype=float)
vec_cand = wp.types.vector(length=NCANDIDATE, dtype=float)
vec_order = wp.types.vector(length=NCANDIDATE, dtype=int)


@wp.struct
class Candidates:
  """Contact candidates (depth includes the margin band; normals from geom 1 to geom 2)."""

  n: int
  pos: mat_cand
  normal: mat_cand
  depth: vec_cand
  cut: int  # 1 when the source had to skip part of the work (the caller's overflow)
  room: int  # candidates kept at most (<= NCANDIDATE); past it a deeper one replaces the shallowest
  keep: float  # candidates deeper than this are written beyond max_contacts (FAR: none)
  # 1 marks a candidate that is one of many points of a geom's face (a mesh's hull vertex under a
  # terrain triangle): beyond max_contacts such a one is written only where no candidate written
  # before has its normal, so that a face on one plane gives that plane's few points, not one a
  # vertex
  on_face: vec_order


@wp.func
def empty() -> Candidates:
  """No candidates, room for ROOM."""
  return empty_with_room(ROOM)


@wp.func
def empty_with_room(room: int) -> Candidates:
  """No candidates, room for ``room`` (at most NCANDIDATE)."""
  c = Candidates()
  c.n = 0
  c.cut = 0
  c.keep = FAR
  c.room = wp.min(room, NCANDIDATE)
  return c


# Candidates are read and written in place through these accessors: Warp reads an element of a
# struct's vector or matrix field by copying the whole field first, and for the candidates'
# fields (hundreds of bytes, indexed at run time) each copy goes through the thread's local memory


@wp.func_native("""return c.depth.c[k];""")
def depth_at(c: wp.ref[Candidates], k: int) -> float:
  """Candidate k's depth."""
  ...


@wp.func_native("""return wp::vec_t<3, float>(c.pos.data[k][0], c.pos.data[k][1], c.pos.data[k][2]);""")
def pos_at(c: wp.ref[Candidates], k: int) -> wp.vec3:
  """Candidate k's position."""
  ...


@wp.func_native("""return wp::vec_t<3, float>(c.normal.data[k][0], c.normal.data[k][1], c.normal.data[k][2]);""")
def normal_at(c: wp.ref[Candidates], k: int) -> wp.vec3:
  """Candidate k's normal."""
  ...


@wp.func_native("""
for (int i = 0; i < 3; ++i) {
  c.pos.data[k][i] = pos.c[i];
  c.normal.data[k][i] = normal.c[i];
}
c.depth.c[k] = depth;
c.on_face.c[k] = on_face;
""")
def _put(c: wp.ref[Candidates], k: int, pos: wp.vec3, normal: wp.vec3, depth: float, on_face: int):
  ...


@wp.func_native("""return c.on_face.c[k];""")
def on_face_at(c: wp.ref[Candidates], k: int) -> int:
  """Whether candidate k is one of many points of a face (Candidates.on_face)."""
  ...


@wp.func
def add_candidate(c: wp.ref[Candidates], pos: wp.vec3, normal: wp.vec3, depth: float, spacing: float):
  """Adds a candidate to ``c`` in place (by reference: the candidates are kilobytes, and a copy
  in and out of each call goes through the thread's local memory): one within ``spacing`` of it
  keeps the deeper of the two; a full list gives up its shallowest for a deeper one."""
  add_tagged(c, pos, normal, depth, spacing, 0)


@wp.func
def add_tagged(c: wp.ref[Candidates], pos: wp.vec3, normal: wp.vec3, depth: float, spacing: float, on_face: int):
  """add_candidate, the candidate marked as one of many points of a face or not (Candidates.on_face)."""
  for k in range(c.n):
    if wp.length(pos_at(c, k) - pos) < spacing:
      if depth > depth_at(c, k):
        _put(c, k, pos, normal, depth, on_face)
      return
  if c.n < c.room:
    _put(c, c.n, pos, normal, depth, on_face)
    c.n = c.n + 1
    return
  shallowest = int(0)
  for k in range(c.room):
    if depth_at(c, k) < depth_at(c, shallowest):
      shallowest = k
  if depth > depth_at(c, shallowest):
    _put(c, shallowest, pos, normal, depth, on_face)


@wp.func
def _new_normal(c: wp.ref[Candidates], chosen: vec_order, taken: int, k: int) -> bool:
  """Whether candidate k's normal differs from that of each of the first ``taken`` chosen."""
  n = normal_at(c, k)
  for j in range(taken):
    if wp.dot(normal_at(c, chosen[j]), n) > SAME_NORMAL:
      return False
  return True


@wp.func
def choose(c: wp.ref[Candidates], max_contacts: int) -> vec_order:
  """Candidates to write, in order (-1 past the end): the deepest, then each time the one
  farthest from those already visited, up to max_contacts (at most MAX_CONTACTS); the rest
  of that order only where deeper than ``c.keep`` (and, for a point of a face, on a plane of its
  own: Candidates.on_face)."""
  out = vec_order()
  for k in range(NCANDIDATE):
    out[k] = -1
  if c.n == 0:
    return out
  spread = wp.min(max_contacts, MAX_CONTACTS)
  nearest = vec_cand()  # distance to the nearest visited candidate; -1 once visited
  cur = int(0)
  for k in range(c.n):
    nearest[k] = FAR
    if depth_at(c, k) > depth_at(c, cur):
      cur = k
  taken = int(0)
  step = int(0)
  while cur >= 0 and (step < spread or c.keep < FAR):
    if step < spread or (depth_at(c, cur) > c.keep and (on_face_at(c, cur) == 0 or _new_normal(c, out, taken, cur))):
      out[taken] = cur
      taken += 1
    nearest[cur] = -1.0
    at = pos_at(c, cur)
    cur = int(-1)
    best_dist = float(-1.0)
    for k in range(c.n):
      if nearest[k] >= 0.0:
        nearest[k] = wp.min(nearest[k], wp.length(pos_at(c, k) - at))
        if nearest[k] > best_dist:
          cur = k
          best_dist = nearest[k]
    step += 1
  return out


@wp.func
def write_candidates(
  c: wp.ref[Candidates],
  max_contacts: int,
  rot: wp.mat33,
  origin: wp.vec3,
  band: float,
  naconmax_in: int,
  margin: float,
  gap: float,
  condim: int,
  friction: vec5,
  solref: wp.vec2,
  solreffriction: wp.vec2,
  solimp: vec5,
  adhesion: float,
  geoms: wp.vec2i,
  pairid: wp.vec2i,
  worldid: int,
  contacts_out: ContactRows,
  quota: ContactQuota,
):
  """Writes the candidates that choose picks (given in a frame: world = origin + rot @ local) as
  contacts with MuJoCo Warp's write_contact; the margin band comes off the depth and the position."""
  chosen = choose(c, max_contacts)
  count = int(0)
  for k in range(NCANDIDATE):
    if chosen[k] >= 0:
      count += 1
  for k in range(count):  # a runtime bound, so the loop is not unrolled: one write_row call site
    i = chosen[k]
    normal = rot @ normal_at(c, i)
    pos = origin + rot @ pos_at(c, i)
    write_row(
      quota, worldid, naconmax_in, k, band - depth_at(c, i), pos - 0.5 * band * normal, make_frame(normal), margin, gap,
      condim, friction, solref, solreffriction, solimp, adhesion, geoms, pairid, contacts_out,
    )
