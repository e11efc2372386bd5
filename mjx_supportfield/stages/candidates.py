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
# sources of a box's or a mesh's candidates of a terrain triangle (Candidates.tag): its prism's
# answer, the geom's deepest point under the triangle's plane, a corner (hull vertex) under it
TAG_PRISM = 0
TAG_DEEPEST = 1
TAG_VERTEX = 2

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
  # a box's or a mesh's candidate of terrain triangle t: 4 t + 1 + its source (TAG_PRISM,
  # TAG_DEEPEST, TAG_VERTEX; 0: no triangle's). Such a geom gets one contact a triangle, its
  # prism's answer where there is one, as MuJoCo C gets one a prism, not one a corner
  tag: vec_order


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
c.tag.c[k] = tag;
""")
def _put(c: wp.ref[Candidates], k: int, pos: wp.vec3, normal: wp.vec3, depth: float, tag: int):
  ...


@wp.func_native("""return c.tag.c[k];""")
def tag_at(c: wp.ref[Candidates], k: int) -> int:
  """Candidate k's terrain triangle tag (Candidates.tag)."""
  ...


@wp.func
def triangle_tag(triangle: int, source: int) -> int:
  """Candidates.tag of a box's or a mesh's candidate of terrain triangle ``triangle`` from
  ``source`` (TAG_PRISM, TAG_DEEPEST or TAG_VERTEX)."""
  return 4 * triangle + 1 + source


@wp.func
def add_candidate(c: wp.ref[Candidates], pos: wp.vec3, normal: wp.vec3, depth: float, spacing: float):
  """Adds a candidate to ``c`` in place (by reference: the candidates are kilobytes, and a copy
  in and out of each call goes through the thread's local memory): one within ``spacing`` of it
  keeps the deeper of the two; a full list gives up its shallowest for a deeper one."""
  add_tagged(c, pos, normal, depth, spacing, 0)


@wp.func
def add_tagged(c: wp.ref[Candidates], pos: wp.vec3, normal: wp.vec3, depth: float, spacing: float, tag: int):
  """add_candidate, the candidate tagged with its terrain triangle (Candidates.tag)."""
  for k in range(c.n):
    if wp.length(pos_at(c, k) - pos) < spacing:
      if depth > depth_at(c, k):
        _put(c, k, pos, normal, depth, tag)
      return
  if c.n < c.room:
    _put(c, c.n, pos, normal, depth, tag)
    c.n = c.n + 1
    return
  shallowest = int(0)
  for k in range(c.room):
    if depth_at(c, k) < depth_at(c, shallowest):
      shallowest = k
  if depth > depth_at(c, shallowest):
    _put(c, shallowest, pos, normal, depth, tag)


@wp.func
def _stands_for_triangle(c: wp.ref[Candidates], k: int) -> bool:
  """Whether tagged candidate k is its terrain triangle's contact: the prism's answer where
  there is one, else the triangle's deepest candidate (Candidates.tag)."""
  tag = tag_at(c, k)
  prism = (tag - 1) % 4 == TAG_PRISM
  for j in range(c.n):
    other = tag_at(c, j)
    if j != k and other != 0 and (other - 1) // 4 == (tag - 1) // 4:
      other_prism = (other - 1) % 4 == TAG_PRISM
      if other_prism and not prism:
        return False
      if other_prism == prism and (depth_at(c, j) > depth_at(c, k) or (depth_at(c, j) == depth_at(c, k) and j < k)):
        return False
  return True


@wp.func
def _writes(c: wp.ref[Candidates], taken: int, spread: int, k: int) -> bool:
  """Whether the choice writes visited candidate k after ``taken`` chosen: within the spread,
  or beyond it when deeper than ``c.keep``; of a box's or a mesh's candidates of one terrain
  triangle, only the one that stands for it (Candidates.tag)."""
  if tag_at(c, k) != 0 and not _stands_for_triangle(c, k):
    return False
  return taken < spread or depth_at(c, k) > c.keep


@wp.func
def choose(c: wp.ref[Candidates], max_contacts: int) -> vec_order:
  """Candidates to write, in order (-1 past the end): the deepest, then each time the one
  farthest from those already visited, up to max_contacts (at most MAX_CONTACTS) written; the
  rest of that order only where deeper than ``c.keep``; a box's or a mesh's candidates one a
  terrain triangle (_writes)."""
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
  while cur >= 0 and (taken < spread or c.keep < FAR):
    if _writes(c, taken, spread, cur):
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
