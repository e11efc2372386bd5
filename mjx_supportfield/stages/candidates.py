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


@wp.func
def row(m: mat_cand, k: int) -> wp.vec3:
  """Row k of a candidate matrix as a vector."""
  return wp.vec3(m[k, 0], m[k, 1], m[k, 2])


@wp.func
def _put(c: Candidates, k: int, pos: wp.vec3, normal: wp.vec3, depth: float) -> Candidates:
  out = c
  for i in range(3):
    out.pos[k, i] = pos[i]
    out.normal[k, i] = normal[i]
  out.depth[k] = depth
  return out


@wp.func
def add_candidate(c: Candidates, pos: wp.vec3, normal: wp.vec3, depth: float, spacing: float) -> Candidates:
  """Adds a candidate: one within ``spacing`` of it keeps the deeper of the two; a full list
  gives up its shallowest for a deeper one."""
  for k in range(c.n):
    if wp.length(row(c.pos, k) - pos) < spacing:
      if depth > c.depth[k]:
        return _put(c, k, pos, normal, depth)
      return c
  if c.n < c.room:
    out = _put(c, c.n, pos, normal, depth)
    out.n = c.n + 1
    return out
  shallowest = int(0)
  for k in range(c.room):
    if c.depth[k] < c.depth[shallowest]:
      shallowest = k
  if depth > c.depth[shallowest]:
    return _put(c, shallowest, pos, normal, depth)
  return c


@wp.func
def choose(c: Candidates, max_contacts: int) -> vec_order:
  """Candidates to write, in order (-1 past the end): the deepest, then each time the one
  farthest from those already visited, up to max_contacts (at most MAX_CONTACTS); the rest
  of that order only where deeper than ``c.keep``."""
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
    if c.depth[k] > c.depth[cur]:
      cur = k
  taken = int(0)
  step = int(0)
  while cur >= 0 and (step < spread or c.keep < FAR):
    if step < spread or c.depth[cur] > c.keep:
      out[taken] = cur
      taken += 1
    nearest[cur] = -1.0
    at = row(c.pos, cur)
    cur = int(-1)
    best_dist = float(-1.0)
    for k in range(c.n):
      if nearest[k] >= 0.0:
        nearest[k] = wp.min(nearest[k], wp.length(row(c.pos, k) - at))
        if nearest[k] > best_dist:
          cur = k
          best_dist = nearest[k]
    step += 1
  return out


@wp.func
def write_candidates(
  c: Candidates,
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
    normal = rot @ row(c.normal, i)
    pos = origin + rot @ row(c.pos, i)
    write_row(
      quota, worldid, naconmax_in, k, band - c.depth[i], pos - 0.5 * band * normal, make_frame(normal), margin, gap,
      condim, friction, solref, solreffriction, solimp, adhesion, geoms, pairid, contacts_out,
    )
