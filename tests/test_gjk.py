"""GJK distance and EPA penetration (mjx_supportfield.geometry.gjk) against closed forms at 1 mm, 1 m
and 10 m in random rigid poses, and on random convex hulls against a brute-force penetration
depth and against MPR.

All pairs of all tests go through one kernel (one compile): each case is written in a
unit-size pair frame, scaled, and moved by a random rotation and translation.
"""

import os
import zlib

import mujoco
import numpy as np
import pytest
import warp as wp
from mujoco_warp._src.types import GeomType

from conftest import MODELS
from conftest import angle_deg
from conftest import quat_mat
from conftest import random_quat
from conftest import unit
from mjx_supportfield import Options
from mjx_supportfield.geometry import gjk
from mjx_supportfield.geometry import support_field
from mjx_supportfield.geometry.mpr import BEHIND
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.tools.compare import match
from mjx_supportfield.tools.compare import mujoco_contacts
from mjx_supportfield.tools.compare import sample_states
from mjx_supportfield.tools.compare import warp_contacts
from mjx_supportfield.types import SUPPORT_REFINED
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import Shape

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

_GJK = gjk.gjk_funcs(SUPPORT_REFINED)
_MPR = mpr_funcs(SUPPORT_REFINED)
SCALES = (1e-3, 1.0, 10.0)
TOL = 1e-6
ITERATIONS = 50
FEW = (2, 5)  # iteration caps that stop GJK and EPA early
CUBE_HALF = 0.25  # half side of the mesh cubes, before scaling
NHULL = 4  # random hulls (per scale)
NRANDOM = 8  # random hull pairs of each kind (deep, shallow) per scale

SPHERE, CAPSULE, ELLIPSOID = GeomType.SPHERE, GeomType.CAPSULE, GeomType.ELLIPSOID
CYLINDER, BOX, MESH = GeomType.CYLINDER, GeomType.BOX, GeomType.MESH


def rot(axis, angle):
  """Rotation matrix about an axis."""
  q = np.zeros(4)
  mujoco.mju_axisAngle2Quat(q, np.asarray(axis, dtype=np.float64), angle)
  return quat_mat(q)


Z_TO_X = rot([0, 1, 0], np.pi / 2)
Z_TO_Y = rot([1, 0, 0], -np.pi / 2)
VERTEX_DOWN = rot(unit(np.cross([1, 1, 1], [0, 0, -1])), np.arccos(-1 / np.sqrt(3)))  # (1, 1, 1) -> -z


def geom(gtype, size=(0, 0, 0), pos=(0, 0, 0), rot=np.eye(3), mesh=None):
  """A shape in the unit pair frame (mesh: the name of one of the models' meshes, sized at scale 1)."""
  size = np.pad(np.asarray(size, float), (0, 3 - len(size)))
  return dict(gtype=int(gtype), size=size, pos=np.array(pos, float), rot=np.asarray(rot, float), mesh=mesh)


def cube(pos=(0, 0, 0), rot=np.eye(3)):
  """The mesh cube (half side CUBE_HALF) in the unit pair frame."""
  return geom(MESH, pos=pos, rot=rot, mesh="cube")


# --- cases in the unit pair frame: (A, B, expected) -----------------------------------------
# dist: separation; depth: penetration of A (grown by band) and B; normal: from A to B; pos: the
# midpoint of the witness points, where they are unique.

G = 0.05  # separation of the separated cases

BOX_A = geom(BOX, [0.4, 0.3, 0.2])
SMALL_BOX = [0.2, 0.25, 0.15]
R_SEP = 0.25  # sphere radius of the sphere-box cases
CYL = [0.2, 0.3]
CAPSULE_X = geom(CAPSULE, [0.1, 0.4], rot=Z_TO_X)

SEPARATED = {
  "sphere-sphere": (geom(SPHERE, [0.3]), geom(SPHERE, [0.5], unit([1, 2, -2]) * (0.8 + G)),
                    dict(dist=G, normal=unit([1, 2, -2]))),
  "sphere-box-face": (BOX_A, geom(SPHERE, [R_SEP], [0.1, -0.05, 0.2 + R_SEP + G]), dict(dist=G, normal=[0, 0, 1])),
  "sphere-box-edge": (BOX_A, geom(SPHERE, [R_SEP], np.array([0.4, 0.3, 0.1]) + unit([1, 1, 0]) * (R_SEP + G)),
                      dict(dist=G, normal=unit([1, 1, 0]))),
  "sphere-box-vertex": (BOX_A, geom(SPHERE, [R_SEP], np.array([0.4, 0.3, 0.2]) + unit([1, 2, 2]) * (R_SEP + G)),
                        dict(dist=G, normal=unit([1, 2, 2]))),
  "box-box-face": (BOX_A, geom(BOX, SMALL_BOX, [0.1, 0.1, 0.35 + G]), dict(dist=G, normal=[0, 0, 1])),
  "box-box-face-yawed": (BOX_A, geom(BOX, SMALL_BOX, [0.05, 0, 0.35 + G], rot([0, 0, 1], 0.5)),
                         dict(dist=G, normal=[0, 0, 1])),
  "box-box-edge": (BOX_A, geom(BOX, SMALL_BOX, [0.63, 0, 0.39]), dict(dist=0.05, normal=[0.6, 0, 0.8])),
  "box-box-vertex": (BOX_A, geom(BOX, SMALL_BOX, [0.62, 0.58, 0.41]), dict(dist=0.07, normal=unit([2, 3, 6]))),
  "box-box-vertex-down": (BOX_A, geom(BOX, [0.15] * 3, [0.1, 0.05, 0.2 + 0.15 * np.sqrt(3) + G], VERTEX_DOWN),
                          dict(dist=G, normal=[0, 0, 1])),
  "capsule-capsule-skew": (CAPSULE_X, geom(CAPSULE, [0.15, 0.3], [0.1, 0.05, 0.25 + G], Z_TO_Y),
                           dict(dist=G, normal=[0, 0, 1])),
  "capsule-capsule-parallel": (CAPSULE_X, geom(CAPSULE, [0.15, 0.3], [0.2, 0, 0.25 + G], Z_TO_X),
                               dict(dist=G, normal=[0, 0, 1])),
  "capsule-capsule-ends": (geom(CAPSULE, [0.1, 0.4]), geom(CAPSULE, [0.15, 0.3], [0, 0, 0.95 + G]),
                           dict(dist=G, normal=[0, 0, 1])),
  "capsule-capsule-end-side": (CAPSULE_X, geom(CAPSULE, [0.15, 0.3], [0.1, 0, 0.55 + G]),
                               dict(dist=G, normal=[0, 0, 1])),
  "cube-cube-face": (cube(), cube([0.1, -0.1, 0.5 + G], rot([0, 0, 1], 0.3)), dict(dist=G, normal=[0, 0, 1])),
  "cube-cube-edge": (cube(), cube([0.53, 0, 0.54]), dict(dist=0.05, normal=[0.6, 0, 0.8])),
  "cube-cube-vertex": (cube(), cube([-0.52, 0.53, -0.56]), dict(dist=0.07, normal=unit([-2, 3, -6]))),
  "cube-box-vertex-down": (BOX_A, cube([0.1, 0.05, 0.2 + CUBE_HALF * np.sqrt(3) + G], VERTEX_DOWN),
                           dict(dist=G, normal=[0, 0, 1])),
  "cylinder-box-standing": (geom(BOX, [0.5, 0.5, 0.1]), geom(CYLINDER, CYL, [0.1, 0.1, 0.4 + G]),
                            dict(dist=G, normal=[0, 0, 1])),
  "cylinder-box-lying": (geom(BOX, [0.5, 0.5, 0.1]), geom(CYLINDER, CYL, [0.1, 0.1, 0.3 + G], Z_TO_X),
                         dict(dist=G, normal=[0, 0, 1])),
  # tilted by 0.4 rad: the lowest rim point is h cos + r sin below the centre
  "cylinder-box-tilted": (geom(BOX, [0.5, 0.5, 0.1]),
                          geom(CYLINDER, CYL, [0, 0.1, 0.1 + 0.3 * np.cos(0.4) + 0.2 * np.sin(0.4) + G],
                               rot([1, 0, 0], 0.4)),
                          dict(dist=G, normal=[0, 0, 1])),
  "cylinder-sphere-rim": (geom(CYLINDER, CYL), geom(SPHERE, [0.1], [0.2 + 0.6 * (0.1 + G), 0, 0.3 + 0.8 * (0.1 + G)]),
                          dict(dist=G, normal=[0.6, 0, 0.8])),
}

D = 0.03  # penetration of the shallow cases

PENETRATING = {
  "box-box-face": (BOX_A, geom(BOX, SMALL_BOX, [0.05, 0.02, 0.35 - D], rot([0, 0, 1], 0.3)),
                   dict(depth=D, normal=[0, 0, 1])),
  "sphere-sphere": (geom(SPHERE, [0.3]), geom(SPHERE, [0.5], unit([1, -1, 2]) * 0.7),
                    dict(depth=0.1, normal=unit([1, -1, 2]), pos=unit([1, -1, 2]) * 0.25)),
  "sphere-in-box": (BOX_A, geom(SPHERE, [0.05], [0.1, -0.2, 0.05]),
                    dict(depth=0.15, normal=[0, -1, 0], pos=[0.1, -0.225, 0.05])),
  "box-deep-in-box": (geom(BOX, [0.5] * 3), geom(BOX, [0.1] * 3, [0.25, 0.1, 0]), dict(depth=0.35, normal=[1, 0, 0])),
  "cube-deep-in-box": (geom(BOX, [0.5] * 3), cube([0.1, 0.05, 0], rot([0, 0, 1], 0.3)),
                       dict(depth=0.4 + CUBE_HALF * (np.cos(0.3) + np.sin(0.3)), normal=[1, 0, 0])),
  "cube-box-face": (cube(), geom(BOX, [0.2, 0.2, 0.1], [0.05, 0, 0.35 - D], rot([0, 0, 1], 0.7)),
                    dict(depth=D, normal=[0, 0, 1])),
  "capsule-capsule-skew": (CAPSULE_X, geom(CAPSULE, [0.15, 0.3], [0.1, 0.05, 0.1], Z_TO_Y),
                           dict(depth=0.15, normal=[0, 0, 1], pos=[0.1, 0, 0.025])),
  # the core segments cross: the normal is either way along their common perpendicular
  "capsule-capsule-crossing": (CAPSULE_X, geom(CAPSULE, [0.15, 0.3], rot=Z_TO_Y),
                               dict(depth=0.25, normal=None, axis=[0, 0, 1])),
  "sphere-in-cylinder": (geom(CYLINDER, [0.3, 0.4]), geom(SPHERE, [0.05], [0.22, 0, 0.1]),
                         dict(depth=0.13, normal=[1, 0, 0], pos=[0.235, 0, 0.1])),
  # a sphere's centre sunk in a mesh: answered from the hull's face planes, in either order
  "sphere-in-cube": (cube(), geom(SPHERE, [0.05], [0.05, 0.025, 0.2]),
                     dict(depth=0.1, normal=[0, 0, 1], pos=[0.05, 0.025, 0.2])),
  "cube-around-sphere": (geom(SPHERE, [0.05], [0.05, -0.22, 0.025]), cube(),
                         dict(depth=0.08, normal=[0, 1, 0], pos=[0.05, -0.21, 0.025])),
}

CURVED = ("sphere-in-cylinder",)  # EPA on a curved surface

BAND = 0.1  # A's margin band (inflate) in the band cases, which are G apart: depth BAND - G
IN_BAND = {k: SEPARATED[k] for k in ("sphere-box-edge", "box-box-face-yawed", "capsule-capsule-skew", "cube-cube-vertex",
                                     "cylinder-box-tilted")}

TOUCHING = {  # exactly touching (distance 0)
  "sphere-sphere": (geom(SPHERE, [0.3]), geom(SPHERE, [0.5], unit([1, 2, -2]) * 0.8), dict(normal=unit([1, 2, -2]))),
  "box-box-face": (BOX_A, geom(BOX, SMALL_BOX, [0.1, 0.1, 0.35], rot([0, 0, 1], 0.5)), dict(normal=[0, 0, 1])),
  "cube-cube-face": (cube(), cube([0.1, -0.1, 0.5]), dict(normal=[0, 0, 1])),
  "cube-box-vertex-down": (BOX_A, cube([0.1, 0.05, 0.2 + CUBE_HALF * np.sqrt(3)], VERTEX_DOWN), dict(normal=[0, 0, 1])),
}


# --- meshes --------------------------------------------------------------------------------


def _hull_points(rng):
  p = rng.normal(size=(int(rng.integers(12, 40)), 3))
  return p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0.5, 1.0, 3) * 0.3


@pytest.fixture(scope="module")
def meshes():
  """MeshSupport of a cube per scale and of NHULL random hulls per scale: {name: mesh id}, ms."""
  rng = np.random.default_rng(11)
  hulls = [_hull_points(rng) for _ in range(NHULL)]
  corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * CUBE_HALF
  assets, ids = [], {}
  for s in SCALES:
    for name, pts in [("cube", corners)] + [(f"hull{i}", h) for i, h in enumerate(hulls)]:
      ids[(name, s)] = len(assets)
      assets.append(f'<mesh name="{name}_{s:g}" vertex="{" ".join(f"{x:.9g}" for x in (pts * s).ravel())}"/>')
  mjm = mujoco.MjModel.from_xml_string(f"<mujoco><asset>{''.join(assets)}</asset></mujoco>")
  cube_ids = [ids[("cube", s)] for s in SCALES]
  # the cube's vertices must stay in the frame they were written in (closed forms below)
  assert np.allclose(mjm.mesh_quat[cube_ids], [1, 0, 0, 0]) and np.allclose(mjm.mesh_pos[cube_ids], 0)
  ms = support_field.build_mesh_support(mjm, wp.array(mjm.mesh_vert, dtype=wp.vec3), 32)
  return ids, ms


def _bound(g):
  """Bounding radius of a primitive."""
  r, h = g["size"][0], g["size"][1]
  bounds = {SPHERE: r, CAPSULE: r + h, CYLINDER: np.hypot(r, h), BOX: np.linalg.norm(g["size"]), ELLIPSOID: max(g["size"])}
  return bounds[g["gtype"]]


class Pairs:
  """Shapes of all cases in world poses; run() evaluates gjk_distance, gjk_epa and mpr_refined."""

  def __init__(self, meshes):
    self.ids, self.ms = meshes
    host = {k: getattr(self.ms, k).numpy() for k in ("hull_center", "vert", "vertadr", "hull_adr", "hull_num", "hull_vert",
                                                      "nbr_adr", "nbr_num", "nbr")}
    self.host = {k: v.astype(np.float64) if v.dtype == np.float32 else v for k, v in host.items()}
    self.a, self.b, self.scale, self.meta = [], [], [], []

  def hull(self, mesh):
    """Hull vertices and edge vectors of a mesh (its frame), from the hull graph."""
    h = self.host
    adr, num = h["hull_adr"][mesh], h["hull_num"][mesh]
    v = h["vert"][h["vertadr"][mesh] + h["hull_vert"][adr : adr + num]]
    edges = []
    for k in range(num):
      start = h["nbr_adr"][adr + k]
      edges += [v[j] - v[k] for j in h["nbr"][start : start + h["nbr_num"][adr + k]] if j > k]
    return v, np.array(edges)

  def _shape(self, g, s, R, t, inflate):
    sh = Shape()
    sh.gtype = g["gtype"]
    pos = R @ (g["pos"] * s) + t
    rot = R @ g["rot"]
    sh.pos = wp.vec3(*pos)
    sh.rot = wp.mat33(*rot.ravel())
    sh.size = wp.vec3(*(g["size"] * s))
    sh.mesh = -1
    sh.center = wp.vec3(*pos)
    sh.inflate = inflate
    if g["gtype"] != MESH:
      return sh, _bound(dict(g, size=g["size"] * s)), None
    sh.mesh = self.ids[(g["mesh"], s)]
    center = self.host["hull_center"][sh.mesh]
    sh.center = wp.vec3(*(pos + rot @ center))
    v, e = self.hull(sh.mesh)
    # the hull in the world, as the kernel sees it (float32 pose)
    pos32 = np.array(sh.pos, np.float64)
    rot32 = np.array(sh.rot, np.float64).reshape(3, 3)
    return sh, float(np.linalg.norm(v - center, axis=1).max()), (v @ rot32.T + pos32, e @ rot32.T)

  def add(self, kind, name, a, b, expected, s, seed, band=0.0):
    """Adds a pair: case geometry (unit frame) scaled by s, in a random pose drawn from seed."""
    rng = np.random.default_rng(seed)
    R = quat_mat(random_quat(rng))
    t = rng.uniform(-1, 1, 3) * s
    sa, ra, hull_a = self._shape(a, s, R, t, band * s)
    sb, rb, hull_b = self._shape(b, s, R, t, 0.0)
    self.a.append(sa)
    self.b.append(sb)
    self.scale.append(ra + rb)
    world = {}
    for key, val in expected.items():
      if key in ("normal", "axis"):
        world[key] = None if val is None else R @ np.asarray(val, float)
      elif key == "pos":
        world[key] = R @ (np.asarray(val, float) * s) + t
      else:
        world[key] = val * s
    self.meta.append(dict(kind=kind, name=name, s=s, band=band * s, pair_scale=ra + rb, hull_a=hull_a, hull_b=hull_b,
                          **world))

  def run(self, iterations):
    """{kind: [(meta, row)]}: the outputs (columns below) of every pair."""
    out = wp.zeros((len(self.a), NOUT), dtype=float)
    wp.launch(_evaluate, dim=len(self.a), inputs=[self.ms, wp.array(self.a, dtype=Shape), wp.array(self.b, dtype=Shape),
                                                  wp.array(self.scale, dtype=float), iterations], outputs=[out])
    grouped = {}
    for meta, row in zip(self.meta, out.numpy().astype(np.float64)):
      grouped.setdefault(meta["kind"], []).append((meta, row))
    return grouped


# output columns
SEP, DIST, GNORMAL, PA, PB, HIT, DEPTH, NORMAL, POS, MHIT, MDEPTH, MNORMAL, APART = 0, 1, 2, 5, 8, 11, 12, 13, 16, 19, 20, 21, 24
NOUT = 25


@wp.func
def _put(out: wp.array2d(dtype=float), i: int, col: int, v: wp.vec3):
  for c in range(3):
    out[i, col + c] = v[c]


@wp.kernel
def _evaluate(ms: MeshSupport, sa: wp.array(dtype=Shape), sb: wp.array(dtype=Shape), scale: wp.array(dtype=float),
              iterations: int, out: wp.array2d(dtype=float)):
  i = wp.tid()
  a = sa[i]
  b = sb[i]
  g = _GJK.gjk_distance(a, b, ms, scale[i], TOL, iterations)
  out[i, SEP] = float(g.separated)
  out[i, DIST] = g.dist
  _put(out, i, GNORMAL, g.normal)
  _put(out, i, PA, g.pa)
  _put(out, i, PB, g.pb)
  r = _GJK.gjk_epa(a, b, ms, scale[i], TOL, iterations)
  out[i, HIT] = float(r.hit)
  out[i, DEPTH] = r.depth
  _put(out, i, NORMAL, r.normal)
  _put(out, i, POS, r.pos)
  m = _MPR.mpr_refined(a, b, ms, scale[i], TOL, iterations, 4, BEHIND)
  out[i, MHIT] = float(m.hit)
  out[i, MDEPTH] = m.depth
  _put(out, i, MNORMAL, m.normal)
  out[i, APART] = float(_MPR.apart_along_centres(a, b, ms, scale[i]))


def _seed(*parts):
  return zlib.crc32(repr(parts).encode())


def facet_normals(ea, eb):
  """Unit directions among which are all facet normals of A - B for polytopes A and B with edges
  ea and eb: cross products of two edges (face normals of A and B, and an edge of each), both signs."""
  e = np.concatenate([ea, eb])
  e /= np.linalg.norm(e, axis=1, keepdims=True)
  i, j = np.triu_indices(len(e), 1)
  u = np.cross(e[i], e[j])
  ln = np.linalg.norm(u, axis=1)
  u = u[ln > 1e-6] / ln[ln > 1e-6, None]
  return np.concatenate([u, -u])


def polytope_depth(va, ea, vb, eb):
  """Penetration depth and normal (A to B) of two overlapping convex polytopes by brute force: the
  least support of A - B over its facet normals."""
  u = facet_normals(ea, eb)
  h = (va @ u.T).max(axis=0) - (vb @ u.T).min(axis=0)
  k = int(np.argmin(h))
  return float(h[k]), u[k]


def _random_pair(pairs, rng, shallow):
  """Two random hulls in random orientations: B's origin a random offset from A's (deep), or
  (shallow) 0.5 to 3 % of the unit short of where B, moved along that line, would touch A."""
  i, j = rng.choice(NHULL, 2)
  rot_a, rot_b = quat_mat(random_quat(rng)), quat_mat(random_quat(rng))
  u = unit(rng.normal(size=3))
  dist = rng.uniform(0.05, 0.2)
  if shallow:
    va, ea = (x @ rot_a.T for x in pairs.hull(pairs.ids[(f"hull{i}", 1.0)]))
    vb, eb = (x @ rot_b.T for x in pairs.hull(pairs.ids[(f"hull{j}", 1.0)]))
    # B at d u overlaps A while every facet direction n of A - B has support h(n) - d n.u > 0
    n = facet_normals(ea, eb)
    h = (va @ n.T).max(axis=0) - (vb @ n.T).min(axis=0)
    along = n @ u
    dist = (h[along > 0] / along[along > 0]).min() - rng.uniform(0.005, 0.03)
  return geom(MESH, rot=rot_a, mesh=f"hull{i}"), geom(MESH, pos=u * dist, rot=rot_b, mesh=f"hull{j}")


@pytest.fixture(scope="module")
def pairs(meshes):
  """Every case at every scale, and the random hull pairs."""
  pairs = Pairs(meshes)
  for s in SCALES:
    for kind, cases, band in (("separated", SEPARATED, 0.0), ("penetrating", PENETRATING, 0.0), ("band", IN_BAND, BAND),
                              ("touching", TOUCHING, 0.0)):
      for name, (a, b, expected) in cases.items():
        exp = dict(expected)
        if kind == "band":
          exp = dict(depth=BAND - expected["dist"], normal=expected["normal"])
        # a band case has the pose of its separated case
        pairs.add(kind, name, a, b, exp, s, _seed("separated" if kind == "band" else kind, name, s), band)
    rng = np.random.default_rng(_seed("random", s))
    for k in range(NRANDOM):
      for kind in ("deep", "shallow"):
        a, b = _random_pair(pairs, rng, kind == "shallow")
        pairs.add(kind, f"hulls{k}", a, b, {}, s, _seed(kind, s, k))
  return pairs


@pytest.fixture(scope="module")
def results(pairs):
  return pairs.run(ITERATIONS)


def _where(meta):
  return f"{meta['kind']} {meta['name']} at {meta['s']:g} m"


def test_all_finite(results):
  """No NaN or infinity anywhere, touching and deep pairs included."""
  for kind in results.values():
    for meta, row in kind:
      assert np.all(np.isfinite(row)), f"{_where(meta)}: {row}"


def test_apart_along_centres(results):
  """The narrow phase's queue drops pairs that MPR's first step proves apart: only pairs MPR
  misses, never an overlapping one (the separated pairs here are mostly offset from the line
  through their centres, so only some of them are proven apart)."""
  napart = nseparated = 0
  for kind, rows in results.items():
    for meta, row in rows:
      if row[APART]:
        assert row[MHIT] == 0, f"{_where(meta)}: proven apart, yet MPR finds a contact"
      if kind in ("penetrating", "band"):
        assert not row[APART], f"{_where(meta)}: overlapping, yet proven apart"
      if kind == "separated":
        nseparated += 1
        napart += int(row[APART])
  assert napart >= nseparated // 3, f"only {napart} of {nseparated} separated pairs proven apart"


def test_separated_distance(results):
  """GJK distance, witness points and normal against the closed forms; gjk_epa misses."""
  worst = 0.0
  for meta, row in results["separated"]:
    s, where = meta["s"], _where(meta)
    assert row[SEP] == 1, f"{where}: reported overlapping"
    err = abs(row[DIST] - meta["dist"]) / s
    worst = max(worst, err)
    assert err < 2e-5, f"{where}: dist {row[DIST] / s:.7f} s, expected {meta['dist'] / s:.7f} s"
    pa, pb, n = row[PA : PA + 3], row[PB : PB + 3], row[GNORMAL : GNORMAL + 3]
    assert np.linalg.norm(pb - pa) == pytest.approx(meta["dist"], rel=1e-3), f"{where}: witnesses {pa} {pb}"
    assert angle_deg(pb - pa, n) < 0.1, f"{where}: normal {n} is not along the witnesses"
    assert angle_deg(n, meta["normal"]) < 0.1, f"{where}: normal {n}, expected {meta['normal']}"
    assert row[HIT] == 0, f"{where}: gjk_epa reports a contact"
  print(f"separated: worst distance error {worst:.2e} x scale")


def test_within_band(results):
  """A grown by the band overlaps B by band - distance: the answer comes from GJK's distance, the
  point is halfway between B and the grown A (GJK's witnesses of the same pair, separated)."""
  separated = {(meta["name"], meta["s"]): row for meta, row in results["separated"]}
  for meta, row in results["band"]:
    where = _where(meta)
    assert row[HIT] == 1, f"{where}: no contact within the band"
    assert abs(row[DEPTH] - meta["depth"]) < 2e-5 * meta["s"], f"{where}: depth {row[DEPTH]}, expected {meta['depth']}"
    n = row[NORMAL : NORMAL + 3]
    assert angle_deg(n, meta["normal"]) < 0.1, f"{where}: normal {n}"
    sep = separated[(meta["name"], meta["s"])]
    want = 0.5 * (sep[PA : PA + 3] + meta["band"] * n + sep[PB : PB + 3])
    err = np.linalg.norm(row[POS : POS + 3] - want)
    assert err < 1e-5 * meta["s"], f"{where}: pos {row[POS : POS + 3]} is {err / meta['s']:.2g} s off {want}"
    assert row[MHIT] == 1 and row[MDEPTH] == pytest.approx(meta["depth"], rel=1e-3), f"{where}: MPR disagrees"


def test_penetration(results):
  """Depth, normal and point of overlapping pairs (EPA where the cores overlap) against the closed forms."""
  worst = worst_pos = 0.0
  for meta, row in results["penetrating"]:
    s, where = meta["s"], _where(meta)
    assert row[HIT] == 1, f"{where}: no contact"
    assert row[SEP] == 0, f"{where}: GJK calls it separated"
    err = abs(row[DEPTH] - meta["depth"]) / s
    worst = max(worst, err)
    assert err < 2e-5, f"{where}: depth {row[DEPTH] / s:.7f} s, expected {meta['depth'] / s:.7f} s"
    # EPA's polytope on the cylinder's curved side: the face normal is off by a fraction of a degree
    curved = meta["name"] in CURVED
    n = row[NORMAL : NORMAL + 3]
    assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-5)
    if meta["normal"] is not None:
      assert angle_deg(n, meta["normal"]) < (0.5 if curved else 0.01), f"{where}: normal {n}, expected {meta['normal']}"
    else:
      assert abs(np.dot(n, meta["axis"])) > 0.9999, f"{where}: normal {n} is not along {meta['axis']}"
    if "pos" in meta:
      err = np.linalg.norm(row[POS : POS + 3] - meta["pos"]) / s
      worst_pos = max(worst_pos, 0.0 if curved else err)
      assert err < (1e-3 if curved else 1e-5), f"{where}: pos {row[POS : POS + 3]} is {err:.2g} s off {meta['pos']}"
  print(f"penetrating: worst depth error {worst:.2e} x scale, worst point error {worst_pos:.2e} x scale (curved aside)")


def test_touching(results):
  """Exactly touching pairs: no NaN, distance 0, and a contact of depth ~0 along the face normal."""
  for meta, row in results["touching"]:
    s, where = meta["s"], _where(meta)
    assert row[DIST] < 1e-5 * s, f"{where}: distance {row[DIST]}"
    assert row[HIT] == 1, f"{where}: no contact"
    assert row[DEPTH] < 1e-5 * s, f"{where}: depth {row[DEPTH]}"
    assert angle_deg(row[NORMAL : NORMAL + 3], meta["normal"]) < 0.1, f"{where}: normal {row[NORMAL : NORMAL + 3]}"


def _hull_pairs(results):
  return results["deep"] + results["shallow"]


def test_random_hulls_depth(results):
  """EPA on random overlapping hulls against the brute-force depth; MPR is never shallower."""
  worst = 0.0
  for meta, row in _hull_pairs(results):
    where, tol = _where(meta), 1e-5 * meta["pair_scale"]
    (va, ea), (vb, eb) = meta["hull_a"], meta["hull_b"]
    depth, _ = polytope_depth(va, ea, vb, eb)
    assert row[HIT] == 1 and row[MHIT] == 1, f"{where}: hit {row[HIT]}, MPR {row[MHIT]}"
    worst = max(worst, abs(row[DEPTH] - depth) / meta["pair_scale"])
    assert abs(row[DEPTH] - depth) <= tol, f"{where}: depth {row[DEPTH]:.7g}, brute force {depth:.7g}"
    # the normal realises the depth: A - B reaches exactly that far along it
    n = row[NORMAL : NORMAL + 3]
    along = (va @ n).max() - (vb @ n).min()
    assert abs(along - row[DEPTH]) <= tol, f"{where}: A - B reaches {along:.7g} along the normal, depth {row[DEPTH]:.7g}"
    # MPR reports a penetration along some direction, not necessarily the least one
    assert row[DEPTH] <= row[MDEPTH] + tol, f"{where}: EPA {row[DEPTH]:.7g} deeper than MPR {row[MDEPTH]:.7g}"
  print(f"random hulls: worst depth error {worst:.2e} x pair scale")


def test_agrees_with_mpr(results):
  """Shallow overlaps of random hulls: EPA and MPR find the same depth and normal."""
  for meta, row in results["shallow"]:
    where = _where(meta)
    diff = abs(row[DEPTH] - row[MDEPTH])
    assert diff <= 1e-5 * meta["pair_scale"], f"{where}: EPA {row[DEPTH]:.7g}, MPR {row[MDEPTH]:.7g}"
    ang = angle_deg(row[NORMAL : NORMAL + 3], row[MNORMAL : MNORMAL + 3])
    assert ang < 0.1, f"{where}: normals {ang:.3f} deg apart"


@pytest.mark.parametrize("iterations", FEW)
def test_few_iterations(pairs, results, iterations):
  """Stopped early, GJK and EPA still answer bounds: GJK's distance is that of a point of A - B
  (no less than the true one), EPA's depth that of a polytope inside A - B (no more), and the
  depth from a GJK distance no more than the true one."""
  few = pairs.run(iterations)
  for kind, rows in few.items():
    for (meta, row), (_, full) in zip(rows, results[kind]):
      where, tol = f"{_where(meta)} ({iterations} iterations)", 1e-5 * meta["pair_scale"]
      assert np.all(np.isfinite(row)), f"{where}: {row}"
      if kind == "separated":
        assert row[SEP] == 1 and row[DIST] >= full[DIST] - tol, f"{where}: distance {row[DIST]}, converged {full[DIST]}"
      if row[HIT]:
        assert row[DEPTH] <= full[DEPTH] + tol, f"{where}: depth {row[DEPTH]}, converged {full[DEPTH]}"


def test_gjk_narrowphase_in_the_pipeline():
  """Options(narrowphase="gjk") on convex_pile: every pair MuJoCo C finds, the same depths and normals."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(MODELS, "convex_pile.xml"))
  states = sample_states(mjm, 200, 3)
  worlds = warp_contacts(mjm, states, len(states), Options(narrowphase="gjk"))
  size = 2.0 * mjm.geom_rbound
  rows = []
  for q, got in zip(states, worlds):
    m = match(mujoco_contacts(mjm, q), got, 5e-4, size)
    assert not m["missed"], m["missed"]
    rows += m["rows"]
  assert len(rows) >= 15
  assert np.median([r["normal_angle_deg"] for r in rows]) < 0.1
  assert np.median([r["depth_error"] for r in rows]) < 1e-6
  assert max(r["depth_error"] for r in rows) < 1e-4
