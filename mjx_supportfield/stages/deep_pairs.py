"""Deep-pair check: MPR's deep answers checked against the faces of both shapes, after the
convex narrow phase and before the multi-contact pass.

MPR answers where the ray from its interior point through the origin leaves A - B, then reruns
along the normal it found. On a deep polytope pair A - B has several faces that the origin
projects into, and MPR can settle on one that is not the nearest: deeper than the true
penetration, along a normal tens of degrees from it (tests/test_deep_pairs.py). A polytope pair's penetration
direction is a face normal of either shape or a cross product of their edges: the check scans
every face normal of both shapes, walks from the best of them (and from MPR's normal) over the
crosses of the edges at the support points (on small hulls tries every edge pair), and reruns MPR
along the direction of least overlap (its refinement settles on that face of A - B).

The scan reads every hull face, too heavy for the convex kernel's registers; only answers the
convex kernel finds suspicious (``narrowphase.suspect_deep``: deeper than ``DEEP_GATE`` x the
smaller shape's bounding radius, with a face on either shape) come here, through a queue of
``DEEP_PAIRS_PER_WORLD`` rows a world. A world's pairs beyond its rows keep MPR's answer, counted
(``stats(d)["deep_pairs_unchecked"]``); the rows are the world's own, so that other worlds'
deep pairs never decide whether its pairs are checked.

A pair that stays deep call after call (robot links whose meshes overlap at rest) is not checked
every call: the check stamps the pair's warm-start entry (warmstart.py's ``slot_checked``), and
while MPR, warm-started from the normal the check left, lands within a few degrees of it, the
convex kernel keeps that verdict (narrowphase.deep_verdict_holds, counted as
``stats(d)["deep_pairs_reused"]``) and rechecks the pair only every ``DEEP_RECHECK_CALLS`` calls,
at a phase of its own: MPR warm-started on a face stays on it, so only a new check finds that
another face became the nearest.

On a GPU the check's time is its longest thread's: a few deep pairs a world, each a scan of
hundreds of faces and a walk over edge-edge directions, leave most of the GPU idle. Each pair's
face scan, each round of its walks and its edge-pair scan are dealt to lanes (``DEEP_LANES``
threads at most, fewer when many pairs are queued), and the lanes' answers merge to the earliest
candidate of least overlap, the answer one thread scanning them all in order gives, bit for bit.
The check runs as faces (lanes), ``EDGE_ROUNDS`` walk rounds (lanes), edge pairs (lanes) and the
finish (a thread a pair).

This module owns the queue and the check's scratch (``Buffers``), its kernels (``deep_kernels``)
and its stage class, ``DeepPairs``. A checked pair leaves as the convex kernel would have left it:
queued for multi-contact (``narrowphase.Buffers``' patch queue, so its manifold follows the
corrected normal) or written as one contact; its warm-start normal is corrected too.
"""

import dataclasses
import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry.mpr import BEHIND
from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import MprSettings
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.geometry.mpr import settings_of
from mjx_supportfield.geometry.multicontact import Patch
from mjx_supportfield.geometry.shapes import posed_pair
from mjx_supportfield.geometry.support import hull_point
from mjx_supportfield.geometry.support import support_funcs
from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import contact_mixing
from mjx_supportfield.launch.contact_quota import contact_outputs
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.grid import GRID_THREADS
from mjx_supportfield.launch.grid import HEAVY_REGISTERS
from mjx_supportfield.options import Options
from mjx_supportfield.stages import warmstart
from mjx_supportfield.stages.narrowphase import wants_patch
from mjx_supportfield.stages.narrowphase import write_pair_contacts
from mjx_supportfield.types import FAR
from mjx_supportfield.types import SUPPORT_FIELD
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# queue rows per world (pooled over the worlds): a robot whose link meshes overlap at rest has
# tens of deep answers a world; a pair beyond the queue only keeps MPR's answer (counted)
DEEP_PAIRS_PER_WORLD = 64
# a direction must overlap less than this fraction of the overlap along MPR's normal to be worth
# an MPR: one that ties with MPR's own face (float32 rounding apart) would only rerun the same answer
MIN_GAIN = 1.0e-4
# a direction is skipped when a lower bound of its overlap exceeds the best overlap by this
# fraction of the pair's scale (plus float rounding at the shapes' distance from the origin)
PRUNE_SLACK = 1.0e-4
FLOAT_EPS = 1.1920929e-07  # float32's machine epsilon
EDGE_ROUNDS = 4  # rounds of the walk over edge-edge directions (round_lane), a launch each
# pairs with at most this many edge pairs (a box has 3 edge directions) also try every one: two
# support queries each
EDGE_PAIR_BUDGET = 1024
# a pair's scans (its faces, its edge pairs on small hulls) are dealt to up to DEEP_LANES threads
# on a GPU, as many as LANE_THREADS threads leave to each queued pair (_lanes); one thread a pair
# on the CPU, where threads run one after another anyway
DEEP_LANES = 16
LANE_THREADS = 1 << 16
# candidate indices of B's faces follow A's (lanes merge to the earliest of equal answers)
FACES_OF_B = 1 << 20


@dataclasses.dataclass
class Buffers:
  """The queue of suspicious deep answers that the convex kernel fills."""

  count: wp.array  # (2,) answers queued, answers that kept the verdict
  world_count: wp.array  # (nworld,) each world's answers sent to the check, those beyond its rows included
  pair: wp.array  # indices into the pair list
  result: wp.array  # MPR's normal (xyz) and depth (w), margin band included
  pos: wp.array  # MPR's point
  # the check's own, a row each: the margin band, the overlap along MPR's normal
  band: wp.array
  along: wp.array
  # each lane's answer and the index of its candidate (a row's lanes side by side)
  lane_best: wp.array
  lane_index: wp.array
  # the walks' rounds, two buffers that alternate: each walk's answer and whether it goes on (a
  # row's two walks side by side), and each lane's answer and its cross's number
  walk_cur: wp.array
  walk_live: wp.array
  round_best: wp.array
  round_index: wp.array
  max_lanes: int = 0  # lanes a pair at most; 0: DEEP_LANES on a GPU, 1 on the CPU
  per_world: int = DEEP_PAIRS_PER_WORLD  # rows of the queue each world has to itself


@wp.struct
class Witness:
  """Points known to lie in A and in B. Along any direction u they bound the overlap from below
  without a support query (A reaches at least as far along u as its points, B at least as far
  against it), so that the scans skip most directions: a robot link's hull has hundreds of faces,
  and only those that face the other shape can beat MPR's answer."""

  a0: wp.vec3  # A's interior point
  a1: wp.vec3  # A's support point along MPR's normal
  b0: wp.vec3
  b1: wp.vec3
  # how far a bound must exceed the best overlap to skip the direction (float rounding of both);
  # FAR skips nothing: with support_mode="field" a support can fall short of the hull's extent
  slack: float


@wp.func
def _a_reach(w: Witness, u: wp.vec3) -> float:
  """How far A reaches along u at least."""
  return wp.max(wp.dot(u, w.a0), wp.dot(u, w.a1))


@wp.func
def _b_reach(w: Witness, u: wp.vec3) -> float:
  """How far B reaches against u at least (the least of its points' projections on u)."""
  return wp.min(wp.dot(u, w.b0), wp.dot(u, w.b1))


@wp.func
def _hull_face_bound(s: Shape, a: Shape, b: Shape, w: Witness, sign: float, n: wp.vec3, offset: float) -> float:
  """A lower bound of the overlap along the hull face of s (A when sign is 1, B when -1) whose
  world normal is n and plane offset ``offset``: the face's own side is exact, its plane."""
  if sign > 0.0:
    return wp.dot(n, a.pos) + offset + a.inflate - _b_reach(w, n)
  return _a_reach(w, -n) + wp.dot(n, b.pos) + offset + b.inflate


@wp.func
def _edge_count(s: Shape, ms: MeshSupport, vertex: int) -> int:
  """Edges of s at its support point: a box's 3 directions, a mesh's hull edges at its support
  vertex; none for curved shapes."""
  if s.gtype == GeomType.BOX:
    return 3
  if s.gtype == GeomType.MESH:
    return ms.nbr_num[ms.hull_adr[s.mesh] + vertex]
  return 0


@wp.func
def _edge(s: Shape, ms: MeshSupport, vertex: int, k: int) -> wp.vec3:
  """The k-th edge (world direction, not unit) of s at its support point (see _edge_count)."""
  if s.gtype == GeomType.BOX:
    return wp.vec3(s.rot[0, k], s.rot[1, k], s.rot[2, k])
  other = ms.nbr[ms.nbr_adr[ms.hull_adr[s.mesh] + vertex] + k]
  return s.rot @ (hull_point(ms, s.mesh, other) - hull_point(ms, s.mesh, vertex))


@wp.func
def _vertex_or(s: Shape, ms: MeshSupport, vertex: int, otherwise: wp.vec3) -> wp.vec3:
  """World position of a mesh shape's hull vertex; ``otherwise`` (a point of s) for other types."""
  if s.gtype == GeomType.MESH:
    return s.pos + s.rot @ hull_point(ms, s.mesh, vertex)
  return otherwise


@wp.func
def _edge_ends(s: Shape, ms: MeshSupport) -> int:
  """Edge ends of s: a mesh's hull edges counted at both ends; a box's 3 directions; 0 else."""
  if s.gtype == GeomType.BOX:
    return 3
  if s.gtype == GeomType.MESH and ms.hull_num[s.mesh] > 0:
    # the hull vertices' neighbour lists lie one after another (support_field.py)
    first = ms.hull_adr[s.mesh]
    last = first + ms.hull_num[s.mesh] - 1
    return ms.nbr_adr[last] + ms.nbr_num[last] - ms.nbr_adr[first]
  return 0


@functools.lru_cache(maxsize=None)
def deep_funcs(mode: int) -> SimpleNamespace:
  """The check's device functions on the support functions of support mode ``mode``
  (support_funcs, mpr_funcs), in the check's order: ``start_of``, ``face_lane``, ``round_lane``,
  ``edge_lane``, ``rerun_along``."""
  support = support_funcs(mode)
  mesh_support_index = support.mesh_support_index
  support_world = support.support_world
  behind_origin = mpr_funcs(mode).behind_origin
  mpr_refined_from = mpr_funcs(mode).mpr_refined_from

  @wp.func
  def overlap_along(a: Shape, b: Shape, ms: MeshSupport, u: wp.vec3) -> float:
    """How far A and B overlap along unit direction u (from A to B): A's support minus B's."""
    return wp.dot(support_world(a, ms, u) - support_world(b, ms, -u), u)

  @wp.func
  def _shallower(a: Shape, b: Shape, ms: MeshSupport, u: wp.vec3, best: wp.vec4) -> wp.vec4:
    """best (a direction from A to B and the overlap of A and B along it), or u with its overlap
    when that is smaller."""
    h = overlap_along(a, b, ms, u)
    if h < best[3]:
      return wp.vec4(u[0], u[1], u[2], h)
    return best

  @wp.func
  def witness(a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3, scale: float) -> Witness:
    """The witness points of a pair whose MPR normal is ``normal`` (from A to B)."""
    w = Witness()
    w.a0 = a.center
    w.a1 = support_world(a, ms, normal)
    w.b0 = b.center
    w.b1 = support_world(b, ms, -normal)
    w.slack = FAR
    if wp.static(mode != SUPPORT_FIELD):
      w.slack = PRUNE_SLACK * scale + 32.0 * FLOAT_EPS * (wp.length(a.pos) + wp.length(b.pos))
    return w

  @wp.func
  def _face_lane(s: Shape, a: Shape, b: Shape, ms: MeshSupport, w: Witness, sign: float, best: wp.vec4,
                 index: int, base: int, lane: int, nlane: int):
    """best improved by the outward face normals (times sign: every direction points from A to B)
    of s, A or B, that fall to ``lane`` of ``nlane`` (every nlane-th from the lane-th): a mesh's
    hull faces, a box's six, a cylinder's two ends. Curved sides have no face: there MPR's
    refinement along the normal already walks to the nearest point. Also returns the index of
    best's direction in the sequence of all candidates (``base`` + the face's), or ``index`` when
    none of these improved it: lanes' answers merge by it (_merge_lanes) as one lane's would."""
    if s.gtype == GeomType.MESH:
      adr = ms.plane_adr[s.mesh]
      for f in range(lane, ms.plane_num[s.mesh], nlane):
        plane = ms.plane[adr + f]
        n = s.rot @ wp.vec3(plane[0], plane[1], plane[2])
        if _hull_face_bound(s, a, b, w, sign, n, plane[3]) <= best[3] + w.slack:
          h = overlap_along(a, b, ms, sign * n)
          if h < best[3]:
            best = wp.vec4(sign * n[0], sign * n[1], sign * n[2], h)
            index = base + f
    elif s.gtype == GeomType.BOX or s.gtype == GeomType.CYLINDER:
      first = wp.where(s.gtype == GeomType.BOX, 0, 4)  # a cylinder's faces: its axis, both ways
      for f in range(first + lane, 6, nlane):
        c = f // 2
        u = wp.where(f % 2 == 0, sign, -sign) * wp.vec3(s.rot[0, c], s.rot[1, c], s.rot[2, c])
        h = overlap_along(a, b, ms, u)
        if h < best[3]:
          best = wp.vec4(u[0], u[1], u[2], h)
          index = base + f
    return best, index

  @wp.func
  def _support_vertex(s: Shape, ms: MeshSupport, d: wp.vec3) -> int:
    """Local hull index of a mesh shape's support vertex for world direction d; -1 for other types."""
    if s.gtype == GeomType.MESH:
      return mesh_support_index(ms, s.mesh, wp.transpose(s.rot) @ d)
    return -1

  @wp.func
  def round_lane(a: Shape, b: Shape, ms: MeshSupport, w: Witness, cur: wp.vec4, lane: int, nlane: int):
    """One round of the edge-edge walk: cur improved by the cross products of the edges of A and B
    at their support points along cur's direction (each turned to point from A to B) that fall to
    ``lane`` of ``nlane`` (numbered A's edge first), with the number of the cross that gave the
    answer (-1: cur's), by which lanes merge (_merge_lanes). A polytope pair's penetration
    direction need not be a face normal of either shape; where it is an edge-edge direction, its
    edges lie at the support points of directions near it."""
    u = wp.vec3(cur[0], cur[1], cur[2])
    va = _support_vertex(a, ms, u)
    vb = _support_vertex(b, ms, -u)
    pa = _vertex_or(a, ms, va, w.a1)
    pb = _vertex_or(b, ms, vb, w.b1)
    nb = _edge_count(b, ms, vb)
    best = cur
    index = int(-1)
    for k in range(lane, _edge_count(a, ms, va) * nb, nlane):
      h = _cross_direction(a, b, ms, w, _edge(a, ms, va, k / nb), _edge(b, ms, vb, k % nb), pa, pb, u, best)
      if h[3] < best[3]:
        best = h
        index = k
    return best, index

  @wp.func
  def _cross_direction(
    a: Shape, b: Shape, ms: MeshSupport, w: Witness, ea: wp.vec3, eb: wp.vec3, pa: wp.vec3, pb: wp.vec3,
    u: wp.vec3, best: wp.vec4
  ) -> wp.vec4:
    """best improved by the cross product of edges ea (of A, through point pa) and eb (of B, through
    pb), turned to the side of u."""
    c = wp.cross(ea, eb)
    if wp.length(c) > 1.0e-6 * wp.length(ea) * wp.length(eb):
      c = wp.normalize(c)
      c = wp.where(wp.dot(c, u) < 0.0, -c, c)
      if wp.max(_a_reach(w, c), wp.dot(c, pa)) - wp.min(_b_reach(w, c), wp.dot(c, pb)) <= best[3] + w.slack:
        best = _shallower(a, b, ms, c, best)
    return best

  @wp.func
  def _crosses_with_edge(
    a: Shape, b: Shape, ms: MeshSupport, w: Witness, ea: wp.vec3, pa: wp.vec3, u: wp.vec3, best: wp.vec4
  ) -> wp.vec4:
    """best improved by the crosses of edge ea of A (through point pa) with every edge of B (each once)."""
    if b.gtype == GeomType.BOX:
      for k in range(3):
        eb = wp.vec3(b.rot[0, k], b.rot[1, k], b.rot[2, k])
        best = _cross_direction(a, b, ms, w, ea, eb, pa, w.b1, u, best)
    elif b.gtype == GeomType.MESH:
      for v in range(ms.hull_num[b.mesh]):
        g = ms.hull_adr[b.mesh] + v
        for k in range(ms.nbr_num[g]):
          other = ms.nbr[ms.nbr_adr[g] + k]
          if other > v:
            eb = b.rot @ (hull_point(ms, b.mesh, other) - hull_point(ms, b.mesh, v))
            best = _cross_direction(a, b, ms, w, ea, eb, pa, _vertex_or(b, ms, v, w.b1), u, best)
    return best

  @wp.func
  def _edge_cross_lane(a: Shape, b: Shape, ms: MeshSupport, w: Witness, best: wp.vec4, lane: int, nlane: int):
    """best improved by the crosses of the edges of A that fall to ``lane`` of ``nlane`` (A's box
    directions or hull vertices, every nlane-th from the lane-th, with the edges that leave them)
    with every edge of B, turned to the side of best's direction. Also returns the A item whose
    crosses last improved best, -1 if none did (_merge_lanes)."""
    u = wp.vec3(best[0], best[1], best[2])
    index = int(-1)
    if a.gtype == GeomType.BOX:
      for k in range(lane, 3, nlane):
        before = best[3]
        best = _crosses_with_edge(a, b, ms, w, wp.vec3(a.rot[0, k], a.rot[1, k], a.rot[2, k]), w.a1, u, best)
        if best[3] < before:
          index = k
    elif a.gtype == GeomType.MESH:
      for v in range(lane, ms.hull_num[a.mesh], nlane):
        g = ms.hull_adr[a.mesh] + v
        before = best[3]
        for k in range(ms.nbr_num[g]):
          other = ms.nbr[ms.nbr_adr[g] + k]
          if other > v:
            ea = a.rot @ (hull_point(ms, a.mesh, other) - hull_point(ms, a.mesh, v))
            best = _crosses_with_edge(a, b, ms, w, ea, _vertex_or(a, ms, v, w.a1), u, best)
        if best[3] < before:
          index = v
    return best, index

  @wp.func
  def start_of(a: Shape, b: Shape, ms: MeshSupport, normal: wp.vec3, along: float, scale: float):
    """The check's start on a pair whose MPR normal is ``normal`` (A and B overlap ``along`` it):
    its witness points, and ``normal`` with that overlap (xyz, w), the answer to beat."""
    w = witness(a, b, ms, normal, scale)
    return w, wp.vec4(normal[0], normal[1], normal[2], wp.where(along < FAR, along, FAR))

  @wp.func
  def face_lane(a: Shape, b: Shape, ms: MeshSupport, w: Witness, start: wp.vec4, lane: int, nlane: int):
    """start improved by the face normals of A, then of B, that fall to ``lane`` of ``nlane``
    (_face_lane), with the index of its direction (-1: start's)."""
    best, index = _face_lane(a, a, b, ms, w, 1.0, start, -1, 0, lane, nlane)
    return _face_lane(b, a, b, ms, w, -1.0, best, index, FACES_OF_B, lane, nlane)

  @wp.func
  def edge_lane(a: Shape, b: Shape, ms: MeshSupport, w: Witness, walked: wp.vec4, lane: int, nlane: int):
    """On small hulls, walked improved by every edge pair whose edge of A falls to ``lane`` of
    ``nlane`` (_edge_cross_lane; the walk can stop short of an edge-edge direction far from where
    it starts), with the index of its A item (-1: walked's)."""
    if _edge_ends(a, ms) * _edge_ends(b, ms) <= 4 * EDGE_PAIR_BUDGET:
      return _edge_cross_lane(a, b, ms, w, walked, lane, nlane)
    return walked, int(-1)

  @wp.func
  def rerun_along(
    a: Shape, b: Shape, ms: MeshSupport, res: MprResult, least: wp.vec4, along: float, scale: float,
    mpr_options: MprSettings,
  ) -> MprResult:
    """MPR's answer res (A and B overlap ``along`` its normal), or MPR rerun (and refined) along
    least's direction, the one of least overlap, when that comes out shallower."""
    tol = mpr_options.tolerance
    if not (least[3] < (1.0 - MIN_GAIN) * along - tol * scale):
      return res
    u = wp.vec3(least[0], least[1], least[2])
    r = mpr_refined_from(a, b, ms, behind_origin(a, b, ms, u, least[3], scale, BEHIND), scale, tol,
                         mpr_options.iterations, mpr_options.refine, BEHIND)
    # the rerun wins where it is shallower, or where the shapes overlap less along its normal
    # than along MPR's: MPR stopped short of A - B's boundary (a depth below the overlap along
    # its own normal) is no answer to keep
    if r.hit != 0 and (r.depth < res.depth - tol * scale or overlap_along(a, b, ms, r.normal) < along - tol * scale):
      return r
    return res

  return SimpleNamespace(overlap_along=overlap_along, start_of=start_of, face_lane=face_lane, round_lane=round_lane,
                         edge_lane=edge_lane, rerun_along=rerun_along)


@wp.func
def _lanes(n: int, lane_threads: int, max_lanes: int) -> int:
  """Lanes a pair's scans are dealt to when n pairs share ``lane_threads`` threads: a few pairs
  (few worlds, or the few a call rechecks) get many lanes, so that the check's time follows the
  longest lane's share of a hull instead of a whole hull scanned by one thread."""
  return wp.clamp(lane_threads // wp.max(n, 1), 1, max_lanes)


@wp.func
def _merge_lanes(lane_best: wp.array(dtype=wp.vec4), lane_index: wp.array(dtype=int), first: int,
                 nlane: int) -> wp.vec4:
  """The lanes' answers at first .. first + nlane - 1 merged as one lane scanning every candidate
  in order would have found them: the least overlap, of equal ones the earliest candidate."""
  best = lane_best[first]
  index = lane_index[first]
  for lane in range(1, nlane):
    h = lane_best[first + lane]
    if h[3] < best[3] or (h[3] == best[3] and lane_index[first + lane] < index):
      best = h
      index = lane_index[first + lane]
  return best


@wp.func
def _queued_normal(deep_result: wp.array(dtype=wp.vec4), s: int) -> wp.vec3:
  queued = deep_result[s]
  return wp.vec3(queued[0], queued[1], queued[2])


@functools.lru_cache(maxsize=None)
def deep_kernels(mode: int) -> SimpleNamespace:
  """The check's kernels for support mode ``mode``, in that mode's module (types.mode_module), in
  launch order: ``faces`` (lanes: the face normals), ``round`` (lanes, EDGE_ROUNDS launches: the
  edge-edge walks from the best face and from MPR's normal, a round each), ``edges`` (lanes:
  every edge pair of small hulls) and ``finish`` (a pair: MPR rerun along the least overlap, the
  answer queued for multi-contact or written)."""
  funcs = deep_funcs(mode)
  overlap_along, start_of, face_lane = funcs.overlap_along, funcs.start_of, funcs.face_lane
  round_lane, edge_lane, rerun_along = funcs.round_lane, funcs.edge_lane, funcs.rerun_along
  module = mode_module(__name__, mode)

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def deep_faces(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    deep_count: wp.array(dtype=int),
    deep_pair: wp.array(dtype=int),
    deep_result: wp.array(dtype=wp.vec4),
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    lane_threads: int,
    max_lanes: int,
    # Out:
    deep_band: wp.array(dtype=float),
    deep_along: wp.array(dtype=float),
    lane_best: wp.array(dtype=wp.vec4),
    lane_index: wp.array(dtype=int),
  ):
    """Each queued pair's face normals, dealt to its lanes (_lanes): each lane's best of MPR's
    normal and its share of the faces."""
    tid = wp.tid()
    n = wp.min(deep_count[0], deep_pair.shape[0])
    nlane = _lanes(n, lane_threads, max_lanes)
    lane = tid % nlane
    for s in range(tid / nlane, n, lane_threads / nlane):
      cid = deep_pair[s]
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      _, margin, gap, _condim, _friction, _solref, _solreffriction, _solimp, _adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      band = wp.max(margin + gap, 0.0)
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                               geoms, worldid)
      normal = _queued_normal(deep_result, s)
      along = overlap_along(a, b, ms, normal)
      w, start = start_of(a, b, ms, normal, along, scale)
      best, index = face_lane(a, b, ms, w, start, lane, nlane)
      lane_best[s * nlane + lane] = best
      lane_index[s * nlane + lane] = index
      if lane == 0:
        deep_band[s] = band
        deep_along[s] = along

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def deep_round(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    deep_count: wp.array(dtype=int),
    deep_pair: wp.array(dtype=int),
    deep_result: wp.array(dtype=wp.vec4),
    deep_band: wp.array(dtype=float),
    deep_along: wp.array(dtype=float),
    pair_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    lane_threads: int,
    max_lanes: int,
    lane_best: wp.array(dtype=wp.vec4),
    lane_index: wp.array(dtype=int),
    rnd: int,
    # Out:
    walk_cur: wp.array2d(dtype=wp.vec4),
    walk_live: wp.array2d(dtype=int),
    round_best: wp.array2d(dtype=wp.vec4),
    round_index: wp.array2d(dtype=int),
  ):
    """Round ``rnd`` of each queued pair's two walks (walk 0 from the best of the faces' lanes,
    walk 1 from MPR's normal where a face beat it), dealt to lanes: the previous round's lanes
    merged, and the walk stops where they did not improve it, as one thread's walk stops.
    Buffers alternate between rounds (index rnd % 2), so a lane never reads what another lane of
    the same round writes."""
    tid = wp.tid()
    n = wp.min(deep_count[0], deep_pair.shape[0])
    nlane = _lanes(2 * n, lane_threads, max_lanes)
    lane = tid % nlane
    now = rnd % 2
    before = 1 - now
    for q in range(tid / nlane, 2 * n, lane_threads / nlane):
      s = q / 2
      cid = deep_pair[s]
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                               deep_band[s], pair_in[cid], pair_worldid_in[cid])
      w, start = start_of(a, b, ms, _queued_normal(deep_result, s), deep_along[s], scale)
      cur = start
      live = False
      if rnd == 0:
        nface = _lanes(n, lane_threads, max_lanes)
        faces = _merge_lanes(lane_best, lane_index, s * nface, nface)
        if q % 2 == 0:
          cur = faces
          live = True
        else:
          live = faces[3] < start[3]  # else the walk from MPR's normal is walk 0's
      else:
        cur = walk_cur[before, q]
        if walk_live[before, q] != 0:
          merged = _merge_lanes(round_best[before], round_index[before], q * nlane, nlane)
          live = merged[3] < cur[3]
          if live:
            cur = merged
      best = cur
      index = int(-1)
      if live:
        best, index = round_lane(a, b, ms, w, cur, lane, nlane)
      round_best[now, q * nlane + lane] = best
      round_index[now, q * nlane + lane] = index
      if lane == 0:
        walk_cur[now, q] = cur
        walk_live[now, q] = int(live)

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def deep_edges(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    deep_count: wp.array(dtype=int),
    deep_pair: wp.array(dtype=int),
    deep_result: wp.array(dtype=wp.vec4),
    deep_band: wp.array(dtype=float),
    deep_along: wp.array(dtype=float),
    pair_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    lane_threads: int,
    max_lanes: int,
    last_best: wp.array(dtype=wp.vec4),
    last_index: wp.array(dtype=int),
    # Out:
    lane_best: wp.array(dtype=wp.vec4),
    lane_index: wp.array(dtype=int),
  ):
    """Each queued pair's edge pairs on small hulls, dealt to its lanes (edge_lane), from the
    better of its two walks (the last round's lanes merged)."""
    tid = wp.tid()
    n = wp.min(deep_count[0], deep_pair.shape[0])
    nlane = _lanes(n, lane_threads, max_lanes)
    lane = tid % nlane
    for s in range(tid / nlane, n, lane_threads / nlane):
      cid = deep_pair[s]
      worldid = pair_worldid_in[cid]
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                               deep_band[s], pair_in[cid], worldid)
      w, _ = start_of(a, b, ms, _queued_normal(deep_result, s), deep_along[s], scale)
      nround = _lanes(2 * n, lane_threads, max_lanes)
      walked = _merge_lanes(last_best, last_index, 2 * s * nround, nround)
      near = _merge_lanes(last_best, last_index, (2 * s + 1) * nround, nround)
      if near[3] < walked[3]:
        walked = near
      best, index = edge_lane(a, b, ms, w, walked, lane, nlane)
      lane_best[s * nlane + lane] = best
      lane_index[s * nlane + lane] = index

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def deep_finish(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    mpr_options: MprSettings,
    max_contacts: int,
    mc_perturbation: float,
    warm_start: int,
    ws_stamp: wp.array(dtype=int),
    ws_slot_stamp: wp.array2d(dtype=int),
    ws_slot_key: wp.array2d(dtype=int),
    deep_count: wp.array(dtype=int),
    deep_pair: wp.array(dtype=int),
    deep_result: wp.array(dtype=wp.vec4),
    deep_pos: wp.array(dtype=wp.vec3),
    deep_along: wp.array(dtype=float),
    lane_threads: int,
    max_lanes: int,
    lane_best: wp.array(dtype=wp.vec4),
    lane_index: wp.array(dtype=int),
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    nthread: int,
    quota: ContactQuota,
    # Out:
    ws_slot_value: wp.array2d(dtype=wp.vec4),
    ws_slot_checked: wp.array2d(dtype=int),
    patch_count: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    # Data out:
    contacts_out: ContactRows,
  ):
    """Each queued pair, one thread: its lanes' edge pairs merged into the least overlap, MPR rerun
    along it where it is shallower (rerun_along), then queued for multi-contact or written as the
    convex kernel does."""
    tid = wp.tid()
    n = wp.min(deep_count[0], deep_pair.shape[0])
    nlane = _lanes(n, lane_threads, max_lanes)
    for s in range(tid, n, nthread):
      cid = deep_pair[s]
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      band = wp.max(margin + gap, 0.0)
      a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                               geoms, worldid)
      res = MprResult()
      res.hit = 1
      queued = deep_result[s]
      res.normal = wp.vec3(queued[0], queued[1], queued[2])
      res.depth = wp.abs(queued[3])
      res.pos = deep_pos[s]
      least = _merge_lanes(lane_best, lane_index, s * nlane, nlane)
      checked = rerun_along(a, b, ms, res, least, deep_along[s], scale, mpr_options)
      # the SDFs' answer (queued negated) kept: one contact, unperturbed, as the convex kernel
      # writes it
      sdf_kept = queued[3] < 0.0 and checked.depth == res.depth and checked.normal == res.normal
      res = checked
      value = wp.vec4(res.normal[0], res.normal[1], res.normal[2], res.depth)
      if warm_start:
        key = geoms[0] * geom_type.shape[0] + geoms[1]
        stored = warmstart.update(ws_slot_stamp, ws_slot_key, ws_slot_value, ws_stamp[worldid], worldid, key, value)
        if stored >= 0:
          ws_slot_checked[worldid, stored] = ws_stamp[worldid]
      if not sdf_kept and wants_patch(geom_type, geoms, a, b, ms, res, max_contacts, mc_perturbation):
        slot = wp.atomic_add(patch_count, 0, 1)
        patch_pair[slot] = cid
        patch_result[slot] = value
        patch_pos[slot] = res.pos
        continue
      extra = Patch()
      extra.n = 0
      write_pair_contacts(
        res, extra, 0.0, 0.0, 1, band, naconmax_in, margin, gap, condim, friction, solref, solreffriction, solimp,
        adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
      )

  return SimpleNamespace(faces=deep_faces, round=deep_round, edges=deep_edges, finish=deep_finish)





class DeepPairs:
  """The deep-pair check: what it reads of the model, its per-Data queue, and the step's launches
  (the stage contract: docs/architecture.md)."""

  def __init__(self, options: Options, support_mode: SupportMode, mesh_support: MeshSupport, mpr_types: tuple):
    self.options, self.support_mode, self.mesh_support = options, support_mode, mesh_support
    self.mpr_types = mpr_types  # no MPR pair, no deep answer to check

  def make_buffers(self, d, st) -> Buffers:
    """The queue for Data ``d``'s worlds, of as many pairs as the broad phase lists."""
    nworld, capacity = d.nworld, st.broad.capacity
    rows = max(1, min(capacity, nworld * DEEP_PAIRS_PER_WORLD))
    # rows x lanes never exceeds LANE_THREADS (_lanes), nor rows with one lane
    lane_slots = max(rows, LANE_THREADS)
    return Buffers(count=wp.zeros(2, dtype=int), world_count=wp.zeros(nworld, dtype=int),
                   pair=wp.zeros(rows, dtype=int), result=wp.zeros(rows, dtype=wp.vec4),
                   pos=wp.zeros(rows, dtype=wp.vec3), band=wp.zeros(rows, dtype=float),
                   along=wp.zeros(rows, dtype=float), lane_best=wp.zeros(lane_slots, dtype=wp.vec4),
                   lane_index=wp.zeros(lane_slots, dtype=int), walk_cur=wp.zeros((2, 2 * rows), dtype=wp.vec4),
                   walk_live=wp.zeros((2, 2 * rows), dtype=int),
                   round_best=wp.zeros((2, max(2 * rows, LANE_THREADS)), dtype=wp.vec4),
                   round_index=wp.zeros((2, max(2 * rows, LANE_THREADS)), dtype=int),
                   per_world=DEEP_PAIRS_PER_WORLD)  # read here, not at import: tests lower it

  def launch(self, m, d, st) -> None:
    """The deep answers the MPR kernel queued, checked; the checked pairs join the narrow phase's
    multi-contact queue."""
    pairs, b, narrow, warm, quota = st.broad, st.deep, st.narrow, st.warm, st.quota.quota
    opt = self.options
    if not self.mpr_types or opt.narrowphase == "gjk":
      return
    kernels = deep_kernels(self.support_mode)
    nthread = max(1, min(b.pair.shape[0], GRID_THREADS))
    max_lanes = b.max_lanes or (DEEP_LANES if d.nacon.device.is_cuda else 1)
    lane_threads = LANE_THREADS if max_lanes > 1 else nthread
    geometry = [m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, d.geom_xpos, d.geom_xmat, self.mesh_support,
                b.count, b.pair, b.result, b.band, b.along]
    params = [m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_rbound, d.geom_xpos, d.geom_xmat]

    def check():
      wp.launch(
        kernels.faces,
        dim=lane_threads,
        inputs=params + [self.mesh_support, b.count, b.pair, b.result, pairs.pair, pairs.pairid, pairs.pair_worldid,
                         lane_threads, max_lanes],
        outputs=[b.band, b.along, b.lane_best, b.lane_index],
      )
      for rnd in range(EDGE_ROUNDS):
        wp.launch(
          kernels.round,
          dim=lane_threads,
          inputs=geometry + [pairs.pair, pairs.pair_worldid, lane_threads, max_lanes, b.lane_best, b.lane_index, rnd],
          outputs=[b.walk_cur, b.walk_live, b.round_best, b.round_index],
        )
      last = (EDGE_ROUNDS - 1) % 2
      wp.launch(
        kernels.edges,
        dim=lane_threads,
        inputs=geometry + [pairs.pair, pairs.pair_worldid, lane_threads, max_lanes, b.round_best[last],
                           b.round_index[last]],
        outputs=[b.lane_best, b.lane_index],
      )
      wp.launch(
        kernels.finish,
        dim=nthread,
        inputs=params + [d.naconmax, self.mesh_support,
          settings_of(opt), opt.mpr_pair_contacts,
          opt.mc_perturbation, opt.warm_start, warm.stamp, warm.slot_stamp, warm.slot_key,
          b.count, b.pair, b.result, b.pos, b.along, lane_threads, max_lanes, b.lane_best, b.lane_index,
          pairs.pair, pairs.pairid, pairs.pair_worldid, nthread, quota,
        ],
        outputs=[warm.slot_value, warm.slot_checked, narrow.patch_count, narrow.patch_pair, narrow.patch_result,
                 narrow.patch_pos] + contact_outputs(d),
      )

    # in a graph, the check's launches are skipped on the device when no answer was queued (most
    # steps of most scenes), as MuJoCo Warp gates its own launches; outside one, a host-side test
    # would cost a synchronization a step, more than the launches that exit at once
    if m.opt.graph_conditional and d.nacon.device.is_capturing:
      wp.capture_if(b.count, on_true=check)
    else:
      check()
