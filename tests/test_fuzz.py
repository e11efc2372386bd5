"""Property tests (issue #7, item 6): random convex hulls and poses through the plugin's MPR
narrow phase, checked against exhaustive references.

- hull against hull: the separating-axis test over both hulls' face normals and all edge-edge
  cross products (numpy, float64) gives the exact penetration depth of two convex polytopes;
- hull against a primitive (sphere, capsule, ellipsoid, cylinder, box): MuJoCo C's
  ``mj_geomDistance``.

Properties: no NaN; unit normals; a contact exists exactly when the shapes are closer than the
pair's margin (outside a thin band around it); the depth is never below the exact penetration
depth, and for two hulls it is the shapes' overlap along the reported normal; every contact
point lies in both shapes' bounding boxes expanded by the margin (and the multi-contact tilt).

One example is one model: a static hull A and a free shape B, with one pose of B per world, so
each example costs one install and one collision call. The examples are few (CPU time) and fixed:
example k of a test is drawn by numpy's PCG64 seeded with (test, k), so every run, whichever
other test modules are collected, draws the same ones. They used to come from Hypothesis
(derandomized, no database), which was not enough: recent Hypothesis (6.155 here) mixes into its
draws numeric constants it collects from the source of every imported module outside
site-packages and the tests, i.e. this package and whatever benchmarks/ or models/ helper
another test module imports (test_stability, test_heightfield), so the examples changed with the
set of collected modules, with any edit to the plugin's source and with Hypothesis' version.
The draws keep what made Hypothesis' examples useful: 1 float in 8 is a bound of its range or 0
(axis-aligned turns, extents just touching).

Cases the fuzzing found are kept below as regression tests (REGRESSIONS).
"""

import os

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import contacts
from conftest import load
from mjx_supportfield.geometry import sdf

NPOSE = 8  # poses of B per example, one per world
NEXAMPLE = 12  # examples per property test
MARGIN = 1e-3  # each geom's margin; MuJoCo adds the two, so contacts are reported up to 2 mm apart
PAIR_MARGIN = 2 * MARGIN
BAND = 2e-4  # |signed distance - pair margin| below this: either answer is right
SPECIAL = 1 / 8  # share of float draws that take a bound of their range or 0


@pytest.fixture(scope="module", autouse=True)
def sdf_cache(tmp_path_factory):
  """Random hulls would fill the session's disk cache: build into a temporary one."""
  saved = os.environ["MJX_SUPPORTFIELD_CACHE"]
  os.environ["MJX_SUPPORTFIELD_CACHE"] = str(tmp_path_factory.mktemp("install_cache"))
  yield
  os.environ["MJX_SUPPORTFIELD_CACHE"] = saved


# --- random examples ------------------------------------------------------------------------------


def draw_float(rng, lo: float, hi: float) -> float:
  """Uniform in [lo, hi]; SPECIAL of the draws are lo, hi or 0 (when in range) instead."""
  if rng.random() < SPECIAL:
    special = [v for v in (lo, hi, 0.0) if lo <= v <= hi]
    return float(special[rng.integers(len(special))])
  return float(rng.uniform(lo, hi))


def draw_hull(rng) -> np.ndarray:
  """6 to 24 points on and inside a random ellipsoid with semi-axes 1 to 6 cm."""
  n = int(rng.integers(6, 25))
  axes = np.array([draw_float(rng, 0.01, 0.06) for _ in range(3)])
  p = rng.normal(size=(n, 3))
  p /= np.linalg.norm(p, axis=1, keepdims=True)
  p *= rng.uniform(0.5, 1.0, (n, 1)) ** (1 / 3)
  return p * axes


def draw_poses(rng) -> list:
  """NPOSE (direction, overlap fraction, quaternion) triples for shape B."""
  out = []
  for _ in range(NPOSE):
    u = np.array([draw_float(rng, -1.0, 1.0) for _ in range(3)]) + 1e-3
    quat = np.array([draw_float(rng, -1.0, 1.0) for _ in range(4)]) + [1e-3, 0, 0, 0]
    t = draw_float(rng, -0.15, 0.3)
    out.append((u / np.linalg.norm(u), t, quat / np.linalg.norm(quat)))
  return out


def example_rng(test: int, k: int):
  """The generator of example k of property test ``test`` (1: hull-hull, 2: hull-primitive)."""
  return np.random.default_rng([test, k])


PRIMITIVES = {
  "sphere": lambda s: f'size="{s[0]:.6g}"',
  "capsule": lambda s: f'size="{s[0]:.6g} {s[1]:.6g}"',
  "cylinder": lambda s: f'size="{s[0]:.6g} {s[1]:.6g}"',
  "ellipsoid": lambda s: f'size="{s[0]:.6g} {s[1]:.6g} {s[2]:.6g}"',
  "box": lambda s: f'size="{s[0]:.6g} {s[1]:.6g} {s[2]:.6g}"',
}


# --- scenes and references ------------------------------------------------------------------------


def vertex_attr(points) -> str:
  return " ".join(f"{x:.7g}" for x in np.ravel(points))


def scene(hull_a, b_geom: str, b_asset: str = "") -> str:
  return f"""<mujoco><option gravity="0 0 0"/><default><geom margin="{MARGIN}"/></default>
    <asset><mesh name="A" vertex="{vertex_attr(hull_a)}"/>{b_asset}</asset><worldbody>
    <geom name="A" type="mesh" mesh="A"/>
    <body name="B"><freejoint/>{b_geom}</body></worldbody></mujoco>"""


def build(xml: str):
  """MjModel, or None where MuJoCo's compiler refuses the random shape."""
  try:
    return mujoco.MjModel.from_xml_string(xml)
  except ValueError:
    return None


def mesh_points(mjm, mjd, g: int) -> np.ndarray:
  """World positions (float64) of geom g's mesh vertices."""
  mesh = mjm.geom_dataid[g]
  v = mjm.mesh_vert[mjm.mesh_vertadr[mesh] : mjm.mesh_vertadr[mesh] + mjm.mesh_vertnum[mesh]]
  return mjd.geom_xpos[g] + v @ mjd.geom_xmat[g].reshape(3, 3).T


def support(points, u) -> float:
  return float(np.max(points @ u))


def placements(mjm, poses_b) -> np.ndarray:
  """qpos per world: B turned by its quaternion and moved along u until the shapes' extents along
  u overlap by the fraction t (t < 0: a gap)."""
  mjd = mujoco.MjData(mjm)
  qpos = np.tile(mjm.qpos0, (len(poses_b), 1))
  for w, (u, t, quat) in enumerate(poses_b):
    mjd.qpos[:] = 0
    mjd.qpos[3:7] = quat
    mujoco.mj_kinematics(mjm, mjd)
    h_a = geom_support(mjm, mjd, 0, u)
    h_b = geom_support(mjm, mjd, 1, -u)
    qpos[w, :3] = u * (h_a + h_b) * (1 - t)
    qpos[w, 3:7] = quat
  return qpos


def geom_support(mjm, mjd, g: int, u) -> float:
  """Support of geom g along u (meshes: vertices; primitives: its AABB corners, enough here)."""
  if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
    return support(mesh_points(mjm, mjd, g), u)
  return support(aabb_corners(mjm, mjd, g), u)


def aabb_corners(mjm, mjd, g: int) -> np.ndarray:
  center, half = mjm.geom_aabb[g, :3], mjm.geom_aabb[g, 3:]
  local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half + center
  return mjd.geom_xpos[g] + local @ mjd.geom_xmat[g].reshape(3, 3).T


def hull_axes(mjm, mjd, g: int):
  """Unit face normals and edge directions of geom g's convex hull (world frame)."""
  tris = sdf.hull_triangles(mjm, mjm.geom_dataid[g])
  p = mesh_points(mjm, mjd, g)
  normals = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
  edges = np.concatenate([p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 1]], p[tris[:, 0]] - p[tris[:, 2]]])
  return normalized(normals), normalized(edges)


def normalized(v) -> np.ndarray:
  n = np.linalg.norm(v, axis=1, keepdims=True)
  keep = n[:, 0] > 1e-12
  return v[keep] / n[keep]


def overlap(pa, pb, n) -> np.ndarray:
  """Overlap of the projections of A and B along unit axes n (k, 3): A's extent past B's."""
  a, b = pa @ n.T, pb @ n.T
  return np.minimum(a.max(0) - b.min(0), b.max(0) - a.min(0))


def sat_depth(mjm, mjd) -> float:
  """Exact penetration depth of two convex polytopes; for separated ones (where the axes give
  only a lower bound of the gap) minus MuJoCo C's distance."""
  na, ea = hull_axes(mjm, mjd, 0)
  nb, eb = hull_axes(mjm, mjd, 1)
  cross = normalized(np.cross(ea[:, None, :], eb[None, :, :]).reshape(-1, 3))
  axes = np.concatenate([na, nb, cross])
  depth = float(overlap(mesh_points(mjm, mjd, 0), mesh_points(mjm, mjd, 1), axes).min())
  return depth if depth > 0 else -mujoco.mj_geomDistance(mjm, mjd, 0, 1, 1.0, None)


# --- the properties -------------------------------------------------------------------------------


def check_world(sim, w: int, depth_ref: float, size: float, overlap_along=None):
  """The plugin's contacts in world w against the reference penetration depth (negative: gap)."""
  c = contacts(sim.d, w)
  label = f"world {w}: reference depth {depth_ref:.6g}"
  assert np.all(np.isfinite(c.dist)) and np.all(np.isfinite(c.pos)) and np.all(np.isfinite(c.frame)), label
  np.testing.assert_allclose(np.linalg.norm(c.normal, axis=1), 1.0, atol=1e-5, err_msg=label)
  if depth_ref + PAIR_MARGIN > BAND:
    assert c.n > 0, f"{label}: the shapes are within the margin but the plugin has no contact"
  if depth_ref + PAIR_MARGIN < -BAND:
    assert c.n == 0, f"{label}: the shapes are apart but the plugin reports {c.dist}"
  if c.n == 0:
    return
  k = int(np.argmin(c.dist))
  depth = -float(c.dist[k])
  # never shallower than the exact depth: pushing B out by less leaves the shapes overlapping
  assert depth >= depth_ref - 1e-5, f"{label}: plugin depth {depth:.6g} is shallower than the exact one"
  # MPR's normal need not be the best one (seen: 2x the exact depth, 8 % of the size); catch gross errors
  assert depth <= depth_ref + 0.15 * size, f"{label}: plugin depth {depth:.6g} (shape size {size:.3g})"
  if overlap_along is not None:
    along = overlap_along(c.normal[k], c.geom[k])
    assert abs(along - depth) <= 2e-5, f"{label}: depth {depth:.6g} but overlap along its normal {along:.6g}"
  slack = PAIR_MARGIN + 1e-4 + 0.005 * size  # margin, float32, the multi-contact tilt
  for g in (0, 1):
    lo, hi = box_of(sim, w, g)
    for p in c.pos:
      assert np.all(p >= lo - slack) and np.all(p <= hi + slack), f"{label}: point {p} outside geom {g}'s box"


def box_of(sim, w: int, g: int):
  """World AABB of geom g in world w: its mesh vertices', or its rotated local box's."""
  mjm, mjd = sim.mjm, sim.worlds[w]
  points = mesh_points(mjm, mjd, g) if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH else aabb_corners(mjm, mjd, g)
  return points.min(0), points.max(0)


def run(mjm, qpos):
  """The plugin's contacts for every world (one per row of qpos), plus MuJoCo C's kinematics of
  each world."""
  nworld = len(qpos)
  sim = load(None, mjm=mjm, nworld=nworld, qpos=qpos)
  sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  sim.worlds = []
  for w in range(nworld):
    mjd = mujoco.MjData(mjm)
    mjd.qpos[:] = qpos[w]
    mujoco.mj_kinematics(mjm, mjd)
    sim.worlds.append(mjd)
  return sim


def hull_hull_model(hull_a, hull_b):
  b_mesh = f'<mesh name="B" vertex="{vertex_attr(hull_b)}"/>'
  return build(scene(hull_a, '<geom name="B" type="mesh" mesh="B"/>', b_mesh))


def hull_primitive_model(hull_a, kind: str, size_b):
  return build(scene(hull_a, f'<geom name="B" type="{kind}" {PRIMITIVES[kind](size_b)}/>'))


def check_hull_hull(mjm, qpos):
  sim = run(mjm, qpos)
  size = 2 * min(mjm.geom_rbound[0], mjm.geom_rbound[1])
  for w in range(len(qpos)):
    mjd = sim.worlds[w]
    pa, pb = mesh_points(mjm, mjd, 0), mesh_points(mjm, mjd, 1)

    def along(n, geoms):
      first, second = (pa, pb) if geoms[0] == 0 else (pb, pa)
      return float(np.max(first @ n) - np.min(second @ n))

    check_world(sim, w, sat_depth(mjm, mjd), size, along)


def check_hull_primitive(mjm, qpos):
  sim = run(mjm, qpos)
  size = 2 * min(mjm.geom_rbound[0], mjm.geom_rbound[1])
  for w in range(len(qpos)):
    dist = mujoco.mj_geomDistance(mjm, sim.worlds[w], 0, 1, 1.0, None)
    check_world(sim, w, -dist, size)


def hull_hull_example(k: int):
  """Model and qpos (NPOSE worlds) of example k; shapes MuJoCo's compiler refuses are drawn again."""
  rng = example_rng(1, k)
  while (mjm := hull_hull_model(draw_hull(rng), draw_hull(rng))) is None:
    pass
  return mjm, placements(mjm, draw_poses(rng))


def hull_primitive_example(k: int):
  """Model and qpos of example k; the primitive kinds take turns, so each one gets 2 or more."""
  rng = example_rng(2, k)
  kind = sorted(PRIMITIVES)[k % len(PRIMITIVES)]
  while (mjm := hull_primitive_model(draw_hull(rng), kind, [draw_float(rng, 0.01, 0.05) for _ in range(3)])) is None:
    pass
  return mjm, placements(mjm, draw_poses(rng))


@pytest.mark.parametrize("k", range(NEXAMPLE))
def test_hull_hull_against_separating_axes(k):
  check_hull_hull(*hull_hull_example(k))


@pytest.mark.parametrize("k", range(NEXAMPLE))
def test_hull_primitive_against_mujoco(k):
  check_hull_primitive(*hull_primitive_example(k))


# --- regressions ----------------------------------------------------------------------------------

# Examples the fuzzing failed on, one world each: hull A's vertices, shape B (a hull's vertices or
# a primitive's type and size, as the MJCF held them), B's qpos.
REGRESSIONS = {
  # Hypothesis' example: the exact depth 3.12082 mm, the plugin's 3.10766 mm
  "hull_hull_duplicate_shallower": (
    "0.005470969 -0.00169028 -0.02441048 -0.0126475 -0.009591373 -0.01592048 0.01309474 0.03248663 -0.003056243 "
    "-0.001521449 -0.04298941 -0.007899842 -0.01748293 0.006153617 0.002041667 0.01375122 -0.002472481 0.0168831 "
    "-0.005947918 -0.04995231 0.0005055971 0.01574671 -0.0261697 0.006625072 -0.008135459 -0.02846113 0.0174859 "
    "-0.008109684 0.0468425 -0.003918115 0.009026239 0.03658703 -0.01000043 -0.008241039 -0.009162017 -0.02357693 "
    "-0.002341212 0.03187758 0.01720184 -0.008581518 0.03845758 0.01263354 0.01517616 -0.00586432 -0.003933523 "
    "-0.01150702 -0.001379027 0.02083921 -0.005302512 0.04219833 0.01145585",
    ("mesh",
     "0.03152514 -0.03122793 -0.005983492 -0.004582223 -0.0271799 -0.01613986 0.03063871 -0.01602098 0.01370287 "
     "-0.02764796 -0.008678944 0.01493127 0.02807562 -0.01963706 0.01070854 -0.03162064 0.01163045 0.01209805 "
     "-0.02166912 0.01212847 -0.01970018 0.05207464 0.007896409 0.001227873 0.02192758 -0.03880871 0.002069838 "
     "-0.02972339 -0.02359615 -0.005912428 -0.0202705 0.003441765 -0.01968285 0.009747629 0.02467561 -0.0145553 "
     "0.02177139 0.03248807 0.00416619 0.03847861 -0.02263354 0.003884973 0.0333416 -0.02608115 -0.01006071 "
     "0.04456861 -0.003939103 -0.01176401 -0.03305336 0.000404379 -0.01242151 0.02034906 -0.02085981 0.01530271 "
     "-0.01624019 0.03065391 -0.01449364 -0.01373879 0.0113536 0.01849759 -0.02657253 0.02805839 0.01270376 "
     "0.006529649 0.006257097 -0.02165743"),
    (0.037749700901941435, -0.01881828246760118, 0.012460322637941912, -0.4293500498959028, 0.19182900991356427,
     -0.21814748074438453, 0.8551443400121678),
  ),
  # Hypothesis' example: a box 32 um into a hull (MuJoCo C and the separating axes
  # agree), the plugin's deepest point 9 um; MPR's own point (50 um, along a normal 3 degrees off
  # the best one) was dropped as a duplicate of a tilt's
  "hull_box_duplicate_shallower": (
    "0.0151571 -0.01089309 0.007086287 -0.01606979 0.001479361 0.009589717 0.003601377 0.01777928 0.006574559 "
    "-0.01295473 -0.01790067 0.00104825 -0.01027466 -0.01119832 0.0117242 -0.00242476 -0.02038833 0.000516519 "
    "0.005961754 -0.00824667 -0.01424848 0.01227957 0.01346033 -0.004834678 -0.01913127 0.001612206 -0.004739471 "
    "0.008485388 -0.02081903 -0.003487863 0.01278015 0.002697344 0.01085618 -0.01313418 -0.01528755 0.006374053 "
    "-0.004565564 -0.01676207 0.01079313 -0.01037495 0.01773944 -0.001934185 0.003369762 -0.0181685 0.005778662 "
    "0.01264563 -0.008336016 0.007777996 -0.01008964 -0.0002901922 0.01346408 -0.01557552 -0.01111626 -0.007438135",
    ("box", "0.0124964 0.0107229 0.0173086"),
    (0.009554760632700663, 0.015242054874501674, 0.0291554092700758, -0.5946592643489659, -0.4095408614279098,
     -0.6738427188913766, 0.15682038241857987),
  ),
  # Hypothesis' example: the rim of a cylinder turned upside down (an exact 180 degrees) against a
  # 4 cm hull edge; MPR's contact point came out 11 mm below the cylinder (mpr._midpoint clamped
  # the barycentric coordinates of a point outside the thin final portal)
  "hull_cylinder_rim_point_outside": (
    "-0.01933576 0.01684764 0.02148553 0.02089861 0.03641111 0.006448554 0.02600993 -0.02433147 0.01951591 "
    "-0.001806941 -0.04587448 0.01053975 0.02438159 0.02347746 0.01301926 -0.01661961 0.01407953 -0.02080621 "
    "-0.03568593 -0.01393946 0.01541028 0.00399082 -0.03138666 0.01563849 0.01011152 -0.03748736 0.01816388 "
    "-0.00137939 -0.007352658 0.02796962 -0.0387106 0.003007096 -0.01704776 -0.01516156 -0.02347632 -0.01863046 "
    "0.02663693 0.01551153 -0.01842593 -0.03758935 -0.01960571 -0.001981561 -0.03683185 0.01258186 -0.01699228 "
    "0.02572419 0.03225385 0.005729802",
    ("cylinder", "0.01 0.0416095"),
    (-0.030077617681553103, 0.01998980014328039, 0.05415986802975287, 0.002777767061104542, 0.9999961419976351,
     0.0, 0.0),
  ),
}


def numbers(text: str) -> np.ndarray:
  return np.array(text.split(), dtype=np.float64)


@pytest.mark.parametrize("name", list(REGRESSIONS))
def test_regression(name):
  hull_a, (kind, b), qpos = REGRESSIONS[name]
  qpos = np.array([qpos])
  if kind == "mesh":
    mjm = hull_hull_model(numbers(hull_a).reshape(-1, 3), numbers(b).reshape(-1, 3))
    check_hull_hull(mjm, qpos)
  else:
    mjm = hull_primitive_model(numbers(hull_a).reshape(-1, 3), kind, numbers(b))
    check_hull_primitive(mjm, qpos)
