"""Contact manifolds of single pairs: counts, positions, depths and normals against MuJoCo C
(mj_forward) and the analytic answers.

Plane-box, plane-cylinder and box-box go through MuJoCo Warp's analytic routines in the plugin;
box-box is the primitive box_box, MuJoCo C's own algorithm, so the plugin's manifolds equal
MuJoCo C's (count and positions) to float32 precision. Stock MuJoCo Warp sends box-box through
its GJK/EPA multi-contact path instead, which gives 4 of the overlap polygon's 5 corners in the
rotated face-on-face case below; that is why these are compared with MuJoCo C, not with stock.

Mesh-mesh, box-mesh and cylinder-box go through MPR (or GJK/EPA) and face clipping
(faceclip.face_pair, clip_faces): the normal lies along a face of one shape, and the other's facing
face, edge or line is clipped to it. A face on a face gets every corner of the overlap polygon
(up to 5; MuJoCo C's multi-CCD keeps 4 of them), an edge or a cylinder's side the two ends of
the line, a cylinder's end MuJoCo's quadrilateral of its 16-gon; every point of MuJoCo C's
deeper than 0.5 mm has a plugin point of the same pair within 3 mm.

Every case overlaps by a known depth; the lower body of the pair is static (world geoms do not
collide with each other or the floor), so each pair is alone.
"""

import dataclasses
import os
from typing import Optional

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import angle_deg
from conftest import contacts
from conftest import load
from conftest import on_gpu

H = 0.05  # half-size of every cube
CUBE = " ".join(f"{x} {y} {z}" for x in (-H, H) for y in (-H, H) for z in (-H, H))
R2 = H * np.sqrt(2.0)  # centre-to-edge distance of a cube turned 45 degrees about an axis
R3 = H * np.sqrt(3.0)  # centre-to-corner distance
CYL_R, CYL_H = 0.03, 0.05
DEPTH = 1e-3
TOP = 1.1  # top face of the static lower cubes (centres at z = 1.05)


def _vertex_down_quat():
  """Quaternion (w, x, y, z) that turns the cube's corner (1, 1, 1) to point straight down."""
  a = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
  axis = np.cross(a, [0.0, 0.0, -1.0])
  angle = np.arctan2(np.linalg.norm(axis), -a[2])
  return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)])


QV = " ".join(f"{x:.9f}" for x in _vertex_down_quat())

XML = f"""
<mujoco>
  <asset><mesh name="cube" vertex="{CUBE}"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 .1"/>
    <body pos="0 0 {H - DEPTH}"><freejoint/><geom name="box_flat" type="box" size="{H} {H} {H}"/></body>
    <body pos="0.5 0 {H - DEPTH}" euler="0 0 30"><freejoint/><geom name="box_turned" type="box" size="{H} {H} {H}"/></body>
    <body pos="1 0 0.069"><freejoint/><geom name="box_edge" type="box" size="{H} {H} {H}" euler="0 45 0"/></body>
    <body pos="1.5 0 {R3 - DEPTH:.9f}" quat="{QV}"><freejoint/><geom name="box_vertex" type="box" size="{H} {H} {H}"/></body>
    <body pos="2 0 {CYL_H - DEPTH}"><freejoint/><geom name="cyl_end" type="cylinder" size="{CYL_R} {CYL_H}"/></body>

    <geom name="face_lo" pos="0 1 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="0.01 1.02 {TOP + H - DEPTH}" euler="0 0 20"><freejoint/><geom name="face_hi" type="box" size="{H} {H} {H}"/></body>
    <geom name="edge_lo" pos="0.5 1 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="0.5 1 1.169"><freejoint/><geom name="edge_hi" type="box" size="{H} {H} {H}" euler="0 45 0"/></body>
    <geom name="cross_lo" pos="1 1 1.05" type="box" size="{H} {H} {H}" euler="45 0 0"/>
    <body pos="1 1 1.189"><freejoint/><geom name="cross_hi" type="box" size="{H} {H} {H}" euler="0 45 0"/></body>
    <geom name="vertex_lo" pos="1.5 1 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="1.5 1 {TOP + R3 - DEPTH:.9f}" quat="{QV}"><freejoint/><geom name="vertex_hi" type="box" size="{H} {H} {H}"/></body>

    <geom name="mesh_lo" pos="0 2 1.05" type="mesh" mesh="cube"/>
    <body pos="0.01 2.02 {TOP + H - DEPTH}" euler="0 0 20"><freejoint/><geom name="mesh_hi" type="mesh" mesh="cube"/></body>
    <geom name="meshal_lo" pos="0.5 2 1.05" type="mesh" mesh="cube"/>
    <body pos="0.52 2.01 {TOP + H - DEPTH}"><freejoint/><geom name="meshal_hi" type="mesh" mesh="cube"/></body>
    <geom name="cylbox_lo" pos="1 2 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="1 2 {TOP + CYL_H - DEPTH}"><freejoint/><geom name="cylbox_hi" type="cylinder" size="{CYL_R} {CYL_H}"/></body>
    <geom name="boxmesh_lo" pos="1.5 2 1.05" type="mesh" mesh="cube"/>
    <body pos="1.51 2.02 {TOP + H - DEPTH}" euler="0 0 20"><freejoint/><geom name="boxmesh_hi" type="box" size="{H} {H} {H}"/></body>
    <geom name="medge_lo" pos="2 2 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="2 2 1.169"><freejoint/><geom name="medge_hi" type="mesh" mesh="cube" euler="0 45 0"/></body>
    <geom name="cyltilt_lo" pos="3 2 1.05" type="box" size="{H} {H} {H}"/>
    <body pos="3 2 1.1488" euler="-2 0.5 30"><freejoint/><geom name="cyltilt_hi" type="cylinder" size="{CYL_R} {CYL_H}"/></body>
    <geom name="cylside_lo" pos="2.5 2 1.05" type="box" size=".08 .08 {H}"/>
    <body pos="2.5 2 {TOP + CYL_R - DEPTH}" euler="0 90 0"><freejoint/><geom name="cylside_hi" type="cylinder" size="{CYL_R} {CYL_H}"/></body>
  </worldbody>
</mujoco>
"""


def _rot2(deg):
  c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
  return np.array([[c, -s], [s, c]])


def _square(centre, half, deg=0.0):
  """Corners (4, 2) of a square, counter-clockwise."""
  return np.asarray(centre) + np.array([[-half, -half], [half, -half], [half, half], [-half, half]]) @ _rot2(deg).T


def _clip(poly, a, b):
  """The part of convex polygon ``poly`` left of the directed line a -> b (Sutherland-Hodgman)."""
  out = []
  side = [(b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) for p in poly]
  for i, p in enumerate(poly):
    j = (i + 1) % len(poly)
    if side[i] >= 0:
      out.append(p)
    if side[i] * side[j] < 0:
      out.append(p + (poly[j] - p) * side[i] / (side[i] - side[j]))
  return np.array(out)


def _overlap(p, q):
  """Intersection of two convex counter-clockwise polygons."""
  for i in range(len(q)):
    p = _clip(p, q[i], q[(i + 1) % len(q)])
  return p


def _area(poly):
  x, y = poly[:, 0], poly[:, 1]
  return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _hull(points):
  """Convex hull (counter-clockwise) of 2D points, monotone chain."""
  pts = sorted({(float(x), float(y)) for x, y in points})
  if len(pts) < 3:
    return np.array(pts)

  def chain(seq):
    out = []
    for p in seq:
      while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                               - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
        out.pop()
      out.append(p)
    return out

  lower, upper = chain(pts), chain(pts[::-1])
  return np.array(lower[:-1] + upper[:-1])


def _disc(centre, r, n=720):
  t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
  return np.asarray(centre) + r * np.stack([np.cos(t), np.sin(t)], axis=1)


@dataclasses.dataclass(frozen=True)
class Case:
  """One pair: the normal points from geom a to geom b; the contact midpoints lie at height z.

  points: the analytic contact points (analytic pairs; exactly these, in any order), or None;
  patch: the true contact patch as a convex counter-clockwise polygon (x, y) (MPR pairs).
  """

  a: str
  b: str
  depth: float
  z: float
  points: Optional[np.ndarray] = None
  patch: Optional[np.ndarray] = None


def _flat(xy, z):
  xy = np.asarray(xy, dtype=np.float64)
  return np.column_stack([xy, np.full(len(xy), z)])


EDGE_DEPTH = R2 - 0.069  # a cube on an edge, its centre 0.069 above the face
CROSS_DEPTH = 2.0 * R2 - (1.189 - 1.05)  # two crossed edges
FACE_PATCH = _overlap(_square((0.0, 1.0), H), _square((0.01, 1.02), H, 20.0))
MESH_PATCH = _overlap(_square((0.0, 2.0), H), _square((0.01, 2.02), H, 20.0))

ANALYTIC = {
  "box-plane face": Case("floor", "box_flat", DEPTH, -DEPTH / 2, _flat(_square((0, 0), H), -DEPTH / 2)),
  "box-plane face turned": Case("floor", "box_turned", DEPTH, -DEPTH / 2, _flat(_square((0.5, 0), H, 30), -DEPTH / 2)),
  "box-plane edge": Case("floor", "box_edge", EDGE_DEPTH, -EDGE_DEPTH / 2, _flat([(1, -H), (1, H)], -EDGE_DEPTH / 2)),
  "box-plane vertex": Case("floor", "box_vertex", DEPTH, -DEPTH / 2, _flat([(1.5, 0)], -DEPTH / 2)),
  "box-box face": Case("face_lo", "face_hi", DEPTH, TOP - DEPTH / 2, _flat(FACE_PATCH, TOP - DEPTH / 2)),
  "box-box edge-face": Case("edge_lo", "edge_hi", EDGE_DEPTH, TOP - EDGE_DEPTH / 2,
                            _flat([(0.5, 1 - H), (0.5, 1 + H)], TOP - EDGE_DEPTH / 2)),
  "box-box edge-edge": Case("cross_lo", "cross_hi", CROSS_DEPTH, 1.05 + R2 - CROSS_DEPTH / 2,
                            _flat([(1, 1)], 1.05 + R2 - CROSS_DEPTH / 2)),
  "box-box vertex-face": Case("vertex_lo", "vertex_hi", DEPTH, TOP - DEPTH / 2, _flat([(1.5, 1)], TOP - DEPTH / 2)),
}
# cylinder on its end: the rim points are MuJoCo's choice (3, 120 degrees apart); checked below
CYL_PLANE = Case("floor", "cyl_end", DEPTH, -DEPTH / 2, patch=_disc((2, 0), CYL_R))
MPR = {
  "mesh-mesh face turned": Case("mesh_lo", "mesh_hi", DEPTH, TOP - DEPTH / 2, patch=MESH_PATCH),
  "mesh-mesh face aligned": Case("meshal_lo", "meshal_hi", DEPTH, TOP - DEPTH / 2,
                                 patch=_overlap(_square((0.5, 2.0), H), _square((0.52, 2.01), H))),
  "box-mesh face turned": Case("boxmesh_lo", "boxmesh_hi", DEPTH, TOP - DEPTH / 2,
                               patch=_overlap(_square((1.5, 2.0), H), _square((1.51, 2.02), H, 20.0))),
  "cylinder end on box": Case("cylbox_lo", "cylbox_hi", DEPTH, TOP - DEPTH / 2, patch=_disc((1, 2), CYL_R)),
}
# a face on a face: the overlap polygon's corners (5 and 4 of them), each a contact
POLYGON_CASES = ("mesh-mesh face turned", "mesh-mesh face aligned", "box-mesh face turned")
LINES = {
  "mesh edge on box": Case("medge_lo", "medge_hi", EDGE_DEPTH, TOP - EDGE_DEPTH / 2,
                           _flat([(2, 2 - H), (2, 2 + H)], TOP - EDGE_DEPTH / 2)),
  "cylinder side on box": Case("cylside_lo", "cylside_hi", DEPTH, TOP - DEPTH / 2,
                               _flat([(2.5 - CYL_H, 2), (2.5 + CYL_H, 2)], TOP - DEPTH / 2)),
}
# a cylinder's end 2 degrees off a box's face: its 16-gon's corners lie at different depths
TILTED_END = Case("cyltilt_lo", "cyltilt_hi", 0.0, 0.0)
ROUND_END = "cylinder end on box"
EDGE_16 = 2.0 * CYL_R * np.sin(np.pi / 16.0)  # a side of the 16-gon MuJoCo takes for a cylinder's end
MUJOCO_MPR_COUNT = 4  # MuJoCo C's multiccd on the face cases
NARROWPHASES = ("mpr", "gjk")


@dataclasses.dataclass
class Manifold:
  """Contacts of one pair, normals oriented from geom a to geom b."""

  dist: np.ndarray
  pos: np.ndarray
  normal: np.ndarray


def _select(geom, dist, pos, normal, a, b):
  sel = [i for i in range(len(dist)) if {int(geom[i][0]), int(geom[i][1])} == {a, b}]
  sign = np.array([1.0 if int(geom[i][0]) == a else -1.0 for i in sel])
  return Manifold(np.asarray(dist, dtype=np.float64)[sel], np.asarray(pos, dtype=np.float64)[sel],
                  sign[:, None] * np.asarray(normal, dtype=np.float64)[sel] if sel else np.zeros((0, 3)))


def collide(narrowphase: str = "mpr") -> dict:
  """{case name: (plugin Manifold, MuJoCo C Manifold)} from one collision of the scene."""
  sim = load(XML, naconmax=256)
  mjm, mjd = sim.mjm, sim.mjd
  sf.install(mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  assert int(sim.d.nacon.numpy()[0]) <= sim.d.naconmax, "contacts beyond the buffer: raise naconmax"
  c = contacts(sim.d, 0)
  sf.uninstall(sim.m)
  n, ref = mjd.ncon, mjd.contact
  out = {}
  for name, case in {**ANALYTIC, "cylinder-plane end": CYL_PLANE, **MPR, **LINES, "cylinder end tilted": TILTED_END}.items():
    a = int(mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, case.a))
    b = int(mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, case.b))
    got = _select(c.geom, c.dist, c.pos, c.normal, a, b)
    want = _select(ref.geom[:n], ref.dist[:n], ref.pos[:n], ref.frame[:n, :3], a, b)
    out[name] = (got, want)
  return out


@pytest.fixture(scope="module")
def manifolds():
  return collide()


@pytest.fixture(scope="module")
def manifolds_gjk():
  return collide("gjk")


def _by_narrowphase(request, narrowphase):
  return request.getfixturevalue("manifolds" if narrowphase == "mpr" else "manifolds_gjk")


def _covered(got: np.ndarray, want: np.ndarray) -> np.ndarray:
  """For each point of ``want``, its distance to the nearest point of ``got``."""
  if len(got) == 0:
    return np.full(len(want), np.inf)
  return np.linalg.norm(want[:, None, :] - got[None, :, :], axis=2).min(axis=1)


def _match(got, want, tol):
  """Largest distance of a one-to-one nearest-point matching of two equal-sized point sets."""
  d = np.linalg.norm(got[:, None, :] - want[None, :, :], axis=2)
  nearest = d.argmin(axis=1)
  assert len(set(nearest.tolist())) == len(got), f"two points share one nearest point:\n{got}\n{want}"
  worst = float(d[np.arange(len(got)), nearest].max())
  assert worst < tol, f"points {worst:.2e} m apart:\n{np.round(got, 6)}\n{np.round(want, 6)}"


def _check_depth_normal(m: Manifold, case: Case, tol_depth=1e-5, tol_deg=0.01):
  np.testing.assert_allclose(-m.dist, case.depth, atol=tol_depth)
  angles = [angle_deg(n, [0.0, 0.0, 1.0]) for n in m.normal]
  assert max(angles) < tol_deg, f"normal off +z by {max(angles):.4f} deg"
  np.testing.assert_allclose(m.pos[:, 2], case.z, atol=tol_depth)


@pytest.mark.parametrize("name", list(ANALYTIC) + ["cylinder-plane end"])
def test_analytic_pairs_equal_mujoco(manifolds, name):
  """Analytic routines: the same number of contacts as MuJoCo C, at the same places, as deep."""
  got, want = manifolds[name]
  assert len(want.dist) > 0, f"{name}: MuJoCo C finds no contact; the case is mis-built"
  assert len(got.dist) == len(want.dist), f"{name}: {len(got.dist)} contacts, MuJoCo C {len(want.dist)}"
  _match(got.pos, want.pos, 2e-5)
  np.testing.assert_allclose(np.sort(got.dist), np.sort(want.dist), atol=2e-6)
  for n in got.normal:
    assert angle_deg(n, want.normal[0]) < 0.01


@pytest.mark.parametrize("name", list(ANALYTIC))
def test_analytic_pairs_exact(manifolds, name):
  """Boxes: the contacts are the analytic corners of the overlap (face: every corner of the
  overlap polygon; edge: the edge's two ends; vertex and crossed edges: one point)."""
  case = ANALYTIC[name]
  got, _ = manifolds[name]
  assert len(got.dist) == len(case.points), f"{name}: {len(got.dist)} contacts, expected {len(case.points)}"
  _match(got.pos, case.points, 2e-5)
  _check_depth_normal(got, case)


def test_cylinder_on_end_on_plane(manifolds):
  """Three points on the rim (MuJoCo's choice), at the overlap depth, around the axis: the
  triangle they span holds the cylinder's centre, so the contact can carry it."""
  got, _ = manifolds["cylinder-plane end"]
  assert len(got.dist) == 3
  _check_depth_normal(got, CYL_PLANE)
  radial = np.linalg.norm(got.pos[:, :2] - [2.0, 0.0], axis=1)
  np.testing.assert_allclose(radial, CYL_R, atol=1e-5)
  # the centre is inside: a convex combination of the three points (1/3 each when evenly spread)
  w = np.linalg.solve(np.vstack([got.pos[:, :2].T, np.ones(3)]), [2.0, 0.0, 1.0])
  assert np.all(w > 0.2), w


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("name", list(MPR) + list(LINES) + ["cylinder end tilted"])
def test_clipped_manifold_covers_mujoco(request, narrowphase, name):
  """The 3 mm rule: every point of MuJoCo C's deeper than 0.5 mm has a plugin point of the same
  pair within 3 mm (for these exact cases, within 0.05 mm); at most 5 points. On the flat round
  end MuJoCo C's square among the 16-gon's four equal ones is float rounding's: there its points
  are corners of the 16-gon next to the plugin's (within one side)."""
  got, want = _by_narrowphase(request, narrowphase)[name]
  deep = want.pos[want.dist <= -5e-4]
  assert len(deep) > 0, f"{name}: MuJoCo C finds no deep point; the case is mis-built"
  assert 1 <= len(got.dist) <= 5, f"{name}: {len(got.dist)} contacts"
  far = _covered(got.pos, deep)
  tol = EDGE_16 * 1.01 if name in (ROUND_END, "cylinder end tilted") else 5e-5
  assert far.max() < tol, f"{name}: MuJoCo C's points {np.round(deep[far >= tol], 5)} uncovered ({far.max():.2e} m)"


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("name", POLYGON_CASES)
def test_face_on_face_gets_the_overlap_corners(request, narrowphase, name):
  """A face on a face: a contact at every corner of the overlap polygon, and no other point
  (MuJoCo C's multi-CCD writes 4 of the 5 corners of the turned cases)."""
  case = MPR[name]
  got, want = _by_narrowphase(request, narrowphase)[name]
  corners = _flat(case.patch, case.z)
  assert len(got.dist) == len(corners), f"{name}: {len(got.dist)} contacts, {len(corners)} corners"
  _match(got.pos, corners, 2e-5)
  assert len(want.dist) == MUJOCO_MPR_COUNT, f"{name}: MuJoCo C now gives {len(want.dist)}; update the docs"


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("name", list(LINES))
def test_line_on_face_gets_its_ends(request, narrowphase, name):
  """A cube's edge or a cylinder's side lying on a face: the line's two ends, at the depth."""
  case = LINES[name]
  got, _ = _by_narrowphase(request, narrowphase)[name]
  assert len(got.dist) == 2, f"{name}: {len(got.dist)} contacts"
  _match(got.pos, case.points, 2e-5)
  _check_depth_normal(got, case)


@pytest.mark.parametrize("name", list(MPR))
def test_mpr_points_in_patch_with_depth_and_normal(manifolds, name):
  case = MPR[name]
  got, _ = manifolds[name]
  _check_depth_normal(got, case)
  poly = case.patch
  for i in range(len(poly)):  # inside every edge's half-plane, 0.01 mm tolerance
    a, b = poly[i], poly[(i + 1) % len(poly)]
    e = b - a
    side = (e[0] * (got.pos[:, 1] - a[1]) - e[1] * (got.pos[:, 0] - a[0])) / np.linalg.norm(e)
    assert np.all(side > -1e-5), f"{name}: point {got.pos[side.argmin()]} outside the patch by {-side.min():.2e} m"


@pytest.mark.parametrize("name", list(MPR))
def test_mpr_points_span_patch(manifolds, name):
  """The points' convex hull covers most of the patch (> 60 %; 4 points on a disc cover at most
  2/pi = 64 %) and at least as much as MuJoCo C's points."""
  case = MPR[name]
  got, want = manifolds[name]
  patch = _area(case.patch)
  cover = _area(_hull(got.pos[:, :2])) / patch
  cover_ref = _area(_hull(want.pos[:, :2])) / patch
  assert cover > 0.6, f"{name}: the points cover {cover:.1%} of the patch (MuJoCo C {cover_ref:.1%})"
  assert cover >= cover_ref - 1e-3, f"{name}: the points cover {cover:.1%} of the patch, MuJoCo C's {cover_ref:.1%}"


def test_mpr_deepest_matches_mujoco(manifolds):
  for name in MPR:
    got, want = manifolds[name]
    assert got.dist.min() == pytest.approx(want.dist.min(), abs=1e-5), name
    assert angle_deg(got.normal[got.dist.argmin()], want.normal[want.dist.argmin()]) < 0.01, name


REPRO = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "repro")


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
def test_tilted_face_sunk_in_a_face_gets_every_sunk_corner(narrowphase):
  """tests/data/repro/ramp_tetra_points.xml: a tetrahedron's face about 5 degrees off a box's,
  its three corners sunk 9.0, 7.7 and 5.6 mm. MuJoCo C writes a contact at each; the
  perturbation tilts found two (the third corner was no tilt's deepest point)."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(REPRO, "ramp_tetra_points.xml"))
  sim = load(None, mjm=mjm)
  sf.install(mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  ref = sim.mjd.contact[: sim.mjd.ncon]
  deep = np.array([r.pos for r in ref if r.dist <= -5e-4])
  assert len(deep) == 3
  far = _covered(c.pos.astype(np.float64), deep)
  assert far.max() < 1e-3, f"MuJoCo C's points {np.round(deep[far >= 1e-3], 4)} uncovered"
  np.testing.assert_allclose(np.sort(c.dist), np.sort([r.dist for r in ref]), atol=5e-5)


def _prism_on_box(sides: int, yaw_deg: float) -> str:
  """A prism of ``sides`` corners round (0.03 m radius, 0.04 m tall) standing on a box's top
  face, turned by yaw_deg, its bottom 1 mm into the box."""
  angles = np.arange(sides) * 2.0 * np.pi / sides
  vertex = " ".join(f"{0.03 * np.cos(t):.6f} {0.03 * np.sin(t):.6f} {z}" for z in (-0.02, 0.02) for t in angles)
  return f"""
<mujoco>
  <asset><mesh name="prism" vertex="{vertex}"/></asset>
  <worldbody>
    <geom name="table" type="box" size=".1 .1 .05"/>
    <body pos="0.01 -0.005 0.069" euler="0 0 {yaw_deg}"><freejoint/><geom name="prism" type="mesh" mesh="prism"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("sides,yaw", [(8, 10.0), (24, 7.0)])
def test_polygon_end_on_face_gets_mujocos_quadrilateral(narrowphase, sides, yaw):
  """A polygon end (a can's 24-gon bottom, an octagon) lying whole on a box's face: MuJoCo C's
  four contacts are the quadrilateral of largest area its climb reaches from where its clipped
  polygon starts, and the plugin's are the same corners (within 0.05 mm), at the depth. The
  tilts put points elsewhere on the rim (up to one side of the polygon off)."""
  sim = load(_prism_on_box(sides, yaw))
  sf.install(sim.mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  ref = sim.mjd.contact[: sim.mjd.ncon]
  want = np.array([r.pos for r in ref])
  assert len(want) == 4, f"MuJoCo C now gives {len(want)} contacts"
  assert c.n == 4, f"{c.n} contacts"
  _match(c.pos.astype(np.float64), want, 5e-5)
  np.testing.assert_allclose(c.dist, -0.001, atol=2e-5)


def _chamfered_carton(tilt_x: float, tilt_y: float, depth: float = 8e-4, past_rim=None, margin: float = 0.0) -> str:
  """A carton (a box 40 x 40 x 80 mm whose four upright edges are chamfered 1.3 mm, a mesh, as
  robosuite's milk) turned tilt_x degrees about x, then tilt_y about its own y, its lowest corner
  ``depth`` into a box's top face (negative: above it). past_rim (dx, dy, gap): the box moved
  along x or y so that its edge lies ``gap`` short of the lowest corner toward (dx, dy); margin:
  the box's."""
  a, c, h = 0.02, 0.0013, 0.04
  octagon = [(a - c, a), (c - a, a), (-a, a - c), (-a, c - a), (c - a, -a), (a - c, -a), (a, c - a), (a, a - c)]
  corners = np.array([[x, y, z] for z in (-h, h) for x, y in octagon])
  quat = np.zeros(4)
  mujoco.mju_euler2Quat(quat, np.radians([tilt_x, tilt_y, 0.0]), "XYZ")
  rot = np.zeros(9)
  mujoco.mju_quat2Mat(rot, quat)
  world = corners @ rot.reshape(3, 3).T
  lowest = world[:, 2].min()
  table = 'pos="0 0 -.05"'
  if past_rim is not None:
    dx, dy, gap = past_rim
    corner = world[world[:, 2].argmin(), :2]
    x = corner[0] - dx * (0.1 + gap) if dx else corner[0]
    y = corner[1] - dy * (0.1 + gap) if dy else corner[1]
    table = f'pos="{x:.9f} {y:.9f} -.05"'
  if margin:
    table += f' margin="{margin}"'
  vertex = " ".join(f"{x} {y} {z}" for x, y, z in corners)
  return f"""
<mujoco>
  <asset><mesh name="carton" vertex="{vertex}"/></asset>
  <worldbody>
    <geom name="table" type="box" {table} size=".1 .1 .05"/>
    <body pos="0 0 {-lowest - depth:.9f}" quat="{' '.join(f'{q:.12f}' for q in quat)}">
      <freejoint/><geom name="carton" type="mesh" mesh="carton"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("tilt,count", [((22.5, 0.0), 2), ((22.5, 10.0), 1), ((3.0, 0.0), 4)])
def test_tilted_face_touches_by_its_edge_or_corner(narrowphase, tilt, count):
  """A chamfered carton resting on an edge (its bottom 22.5 degrees off the table's face, more
  than MuJoCo's face tolerance) touches by the bottom's lowest edge: MuJoCo C's two contacts at
  its ends, not also the chamfers' corners 1.8 mm beside them (clipping the tilted bottom gave
  those: near-duplicates that stiffen the soft contact). Turned about y too, no edge lies along
  the face, and MuJoCo C writes the lowest corner alone. Tilted 3 degrees (within the tolerance)
  it is a face on a face: four corners of the clipped bottom."""
  sim = load(_chamfered_carton(*tilt))
  sf.install(sim.mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  ref = sim.mjd.contact[: sim.mjd.ncon]
  assert len(ref) == count, f"MuJoCo C now gives {len(ref)} contacts"
  assert c.n == count, f"{c.n} contacts, MuJoCo C {count}"
  _match(c.pos.astype(np.float64), np.array([r.pos for r in ref]), 5e-5)
  np.testing.assert_allclose(np.sort(c.dist), np.sort([r.dist for r in ref]), atol=2e-5)


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
@pytest.mark.parametrize("toward", [(-1, 0), (0, -1)])
def test_lone_corner_past_the_rim_gives_mujocos_contact(narrowphase, toward):
  """The carton turned about x and y (its lowest corner alone faces the table) hovering 1 mm over
  a table with a 2 mm margin, that corner 0.05 mm past the table's edge: the contact normal lies
  within MuJoCo's face tolerance of the table's, yet the corner is off the face. MuJoCo C writes
  its one contact (the closest points'); the plugin wrote the point where the corner's edge
  enters the face, up to 0.06 mm beside it, a point on neither shape's contact."""
  sim = load(_chamfered_carton(22.5, 10.0, depth=-1e-3, past_rim=(*toward, 5e-5), margin=2e-3))
  sf.install(sim.mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  ref = sim.mjd.contact[: sim.mjd.ncon]
  assert len(ref) == 1, f"MuJoCo C now gives {len(ref)} contacts"
  assert c.n == 1, f"{c.n} contacts, MuJoCo C 1"
  _match(c.pos.astype(np.float64), np.array([r.pos for r in ref]), 2e-5)
  np.testing.assert_allclose(c.dist, [r.dist for r in ref], atol=2e-5)


def _hovering_box_corner_scene(height: float, past_rim: float, turn_deg: float, margin: float) -> str:
  """A 40 x 40 x 80 mm box tilted (22.5 deg, 10 deg) whose lowest corner hovers ``height`` above a
  table with ``margin``, ``past_rim`` beyond the table's edge, the table turned ``turn_deg`` from
  that edge's direction."""
  a, h = 0.02, 0.04
  corners = np.array([[x, y, z] for z in (-h, h) for x, y in ((a, a), (-a, a), (-a, -a), (a, -a))])
  quat = np.zeros(4)
  mujoco.mju_euler2Quat(quat, np.radians([22.5, 10.0, 0.0]), "XYZ")
  rot = np.zeros(9)
  mujoco.mju_quat2Mat(rot, quat)
  world = corners @ rot.reshape(3, 3).T
  lift = -world[:, 2].min() + height
  world[:, 2] += lift
  k = int(np.argmin(world[:, 2]))
  ring = (k // 4) * 4
  edges = [world[ring + (k + s) % 4] - world[k] for s in (-1, 1)]
  edge = min(edges, key=lambda e: abs(e[2]) / np.linalg.norm(e))
  along = edge[:2] / np.linalg.norm(edge[:2])
  across = np.array([-along[1], along[0]])
  turn = np.radians(turn_deg)
  out = -np.sin(turn) * along + np.cos(turn) * across
  centre = world[k, :2] - (0.1 + past_rim) * out
  yaw = np.degrees(np.arctan2(out[1], out[0]))
  vertex = " ".join(f"{x} {y} {z}" for x, y, z in corners)
  return f"""
<mujoco>
  <asset><mesh name="box" vertex="{vertex}"/></asset>
  <worldbody>
    <geom name="table" type="box" pos="{centre[0]:.9f} {centre[1]:.9f} -.05" euler="0 0 {yaw:.9f}" size=".1 .1 .05"
          margin="{margin}"/>
    <body pos="0 0 {lift:.9f}" quat="{' '.join(f'{q:.12f}' for q in quat)}">
      <freejoint/><geom name="box" type="mesh" mesh="box"/>
    </body>
  </worldbody>
</mujoco>
"""


# the defect follows the CPU's float32 rounding: on a GPU the same refinement lands on C's point,
# so there the test must pass
@pytest.mark.xfail(condition=not on_gpu(), strict=True,
                   reason="known: on the CPU a corner hovering within a margin just past a turned table's edge "
                   "gets MPR's contact about 50 mm along the edge from MuJoCo C's, off the box")
def test_corner_hovering_in_margin_past_the_rim_gets_mujocos_point():
  sim = load(_hovering_box_corner_scene(0.001, 0.00003, 50.0, 0.002))
  ref = np.array([c.pos for c in sim.mjd.contact[: sim.mjd.ncon]])
  assert len(ref) == 1
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  got = contacts(sim.d, 0)
  assert got.n >= 1
  assert min(float(np.linalg.norm(p - ref[0])) for p in got.pos.astype(float)) < 3e-3


@pytest.mark.parametrize("narrowphase", NARROWPHASES)
def test_cylinder_end_on_cylinder_end_gets_mujocos_points(narrowphase):
  """A cylinder standing on another's end, 4 degrees off and half a radius aside, 2 mm deep: the
  two 16-gons are clipped (a 16-gon on a 16-gon is over FACE_PAIR_BUDGET; faceclip's _budget lets
  this pair through) and MuJoCo C's points of the overlap, every one deeper than 0.5 mm, are
  among the plugin's. The tilts found the deepest rim point but not the clipped corners beside it."""
  r, h, depth, tilt = 0.025, 0.022, 2e-3, np.radians(4.0)
  lift = h * np.cos(tilt) + r * np.sin(tilt) - depth  # the upper end's lowest rim point 2 mm down
  xml = f"""
  <mujoco>
    <worldbody>
      <geom name="lower" type="cylinder" size="{r} {h}" pos="0 0 {1 - h}"/>
      <body pos="{0.5 * r} 0 {1 + lift}" euler="{np.degrees(tilt)} 0 0">
        <freejoint/><geom name="upper" type="cylinder" size="{r} {h}"/>
      </body>
    </worldbody>
  </mujoco>"""
  sim = load(xml)
  sf.install(sim.mjm, sim.m, sf.Options(narrowphase=narrowphase))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  deep = np.array([x.pos for x in sim.mjd.contact[: sim.mjd.ncon] if x.dist <= -5e-4])
  assert len(deep) >= 2
  far = _covered(c.pos.astype(np.float64), deep)
  assert far.max() < 1e-3, f"MuJoCo C's points {np.round(deep[far >= 1e-3], 4)} uncovered"
  assert c.dist.min() == pytest.approx(sim.mjd.contact.dist[: sim.mjd.ncon].min(), abs=1e-4)
