"""Non-convex meshes: marking, the baked SDF of a torus against its closed form, vertex and
edge passes against analytic contacts, and a ball that stays inside a bowl."""

import os
import warnings

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp
from conftest import MODELS
from conftest import angle_deg
from conftest import contacts
from conftest import load

import mjx_supportfield as sf
from mjx_supportfield.geometry.sdf import MeshSdf
from mjx_supportfield.geometry.sdf import build_mesh_sdf
from mjx_supportfield.geometry.sdf import mesh_sdf_value
from mjx_supportfield.stages import nonconvex

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

BIG, SMALL = 0.05, 0.015  # the torus of models/meshes/torus.obj


def _scene(bodies: str, marker: str = "torus") -> str:
  return f"""<mujoco><compiler meshdir="{os.path.join(MODELS, 'meshes')}"/>
    <custom><text name="mjx_supportfield.nonconvex" data="{marker}"/></custom>
    <asset><mesh name="torus" file="torus.obj"/><mesh name="bowl" file="bowl.obj"/></asset>
    <worldbody>{bodies}</worldbody></mujoco>"""


TORUS = '<body><geom name="torus" type="mesh" mesh="torus"/></body>'


def _torus_sdf(p: np.ndarray, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
  h = p @ np.asarray(axis)
  rho = np.linalg.norm(p - h[:, None] * np.asarray(axis), axis=1)
  return np.hypot(rho - BIG, h) - SMALL


@wp.kernel
def _query(sdf: MeshSdf, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
  i = wp.tid()
  out[i] = mesh_sdf_value(sdf, 0, points[i])


def test_torus_sdf_matches_the_closed_form():
  mjm = mujoco.MjModel.from_xml_string(_scene(TORUS))
  res = 64
  with wp.ScopedDevice("cpu"):
    sdf = build_mesh_sdf(mjm, res, {mjm.mesh("torus").id}, "cpu", nonconvex.mesh_triangles)
    cell = float(sdf.cell.numpy()[0])
    # MuJoCo moves a mesh to its inertia frame: the torus's axis is its vertices' flattest direction
    torus = mjm.mesh("torus").id
    adr, num = mjm.mesh_vertadr[torus], mjm.mesh_vertnum[torus]
    verts = np.asarray(mjm.mesh_vert[adr : adr + num], np.float64)
    axis = np.linalg.eigh(np.cov((verts - verts.mean(axis=0)).T))[1][:, 0]
    rng = np.random.default_rng(0)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    pad = 0.15 * (hi - lo)  # inside the baked grid (20 % padding)
    pts = rng.uniform(lo - pad, hi + pad, size=(2000, 3)).astype(np.float32)
    out = wp.zeros(len(pts), dtype=float)
    wp.launch(_query, dim=len(pts), inputs=[sdf, wp.array(pts, dtype=wp.vec3)], outputs=[out])
  truth = _torus_sdf(pts.astype(np.float64), axis)
  err = np.abs(out.numpy() - truth)
  assert np.median(err) < 0.15 * cell, (np.median(err), cell)
  assert err.max() < 0.7 * cell, (err.max(), cell)
  # inside and outside are told apart everywhere away from the surface
  far = np.abs(truth) > cell
  assert np.all(np.sign(out.numpy()[far]) == np.sign(truth[far]))


def _contacts(xml: str):
  sim = load(xml)
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  return sim, contacts(sim.d, 0)


def test_sphere_in_the_hole_touches_the_inner_ring():
  """Vertex pass: the ball sits in the torus's hole, 1 mm into the inner ring on its +x side."""
  r = BIG - SMALL - 0.005 + 0.001
  ball = f'<body pos="0.005 0 0"><freejoint/><geom name="ball" type="sphere" size="{r}"/></body>'
  sim, c = _contacts(_scene(TORUS + ball))
  assert c.n >= 1
  deepest = int(np.argmin(c.dist))
  assert abs(-c.dist[deepest] - 0.001) < 3e-4, c.dist
  # the normal points from geom 0 to geom 1 of the contact: from the torus into the ball, -x
  torus_first = c.geom[deepest][0] == sim.mjm.geom("torus").id
  normal = c.normal[deepest] if torus_first else -c.normal[deepest]
  assert angle_deg(normal, [-1.0, 0.0, 0.0]) < 3.0, normal
  np.testing.assert_allclose(c.pos[deepest], [BIG - SMALL + 0.0005, 0.0, 0.0], atol=5e-4)  # between 35 and 36 mm


def test_box_edge_across_the_tube_needs_the_edge_pass():
  """A thin bar on its edge crosses the tube top between two columns of torus vertices: no
  vertex of either is inside the other, the edges are."""
  a = np.pi / 32  # half-way between vertex columns (32 around)
  x, y = BIG * np.cos(a), BIG * np.sin(a)
  half = 0.002
  z = SMALL - 0.001 + half * np.sqrt(2)  # the bar's lowest edge 1 mm into the tube top
  # long axis (local y) radial, across the tube; turned 45 degrees about it: an edge down
  quat = np.zeros(4)
  mujoco.mju_mulQuat(quat, [np.cos((a - np.pi / 2) / 2), 0, 0, np.sin((a - np.pi / 2) / 2)],
                     [np.cos(np.pi / 8), 0, np.sin(np.pi / 8), 0])
  bar = (f'<body pos="{x} {y} {z}" quat="{" ".join(map(str, quat))}"><freejoint/>'
         f'<geom name="bar" type="box" size="{half} 0.04 {half}"/></body>')
  sim, c = _contacts(_scene(TORUS + bar))
  assert c.n >= 1
  deepest = int(np.argmin(c.dist))
  # the faceted tube top between vertex columns lies a sagitta below the round one
  sagitta = (BIG + SMALL) * (1 - np.cos(a))
  assert abs(-c.dist[deepest] - (0.001 - sagitta)) < 3e-4, (c.dist, sagitta)
  torus_first = c.geom[deepest][0] == sim.mjm.geom("torus").id
  normal = c.normal[deepest] if torus_first else -c.normal[deepest]
  assert angle_deg(normal, [0.0, 0.0, 1.0]) < 10.0, normal


def test_marking():
  mjm = mujoco.MjModel.from_xml_string(_scene(TORUS + '<geom name="ball" size="0.01" pos="1 0 0"/>'))
  assert nonconvex.nonconvex_geom_ids(mjm, ()) == [mjm.geom("torus").id]
  with pytest.raises(ValueError, match="no geom named 'cup'"):
    nonconvex.nonconvex_geom_ids(mjm, ("cup",))
  with pytest.raises(ValueError, match="geom 'ball' is a .*SPHERE, not a mesh"):
    sf.install(mjm, mjw.put_model(mjm), sf.Options(nonconvex_geoms=["ball"]))
  with pytest.raises(ValueError, match="nonconvex_geoms"):
    sf.Options(nonconvex_geoms="torus")


def test_open_mesh_warns_and_still_works():
  """A bowl without its inner surface is not watertight: install warns, naming the geom."""
  verts = np.loadtxt(os.path.join(MODELS, "meshes", "torus.obj"), skiprows=1, usecols=(1, 2, 3),
                     max_rows=32 * 16)  # line 1 is the file's comment
  faces = []
  for i in range(31):  # leave the last column of quads out: an open tube
    for j in range(16):
      a, b, cc, d = i * 16 + j, (i + 1) * 16 + j, i * 16 + (j + 1) % 16, (i + 1) * 16 + (j + 1) % 16
      faces += [a, b, d, a, d, cc]
  xml = f"""<mujoco><custom><text name="mjx_supportfield.nonconvex" data="tube"/></custom>
    <asset><mesh name="tube" vertex="{' '.join(map(str, verts.ravel()))}" face="{' '.join(map(str, faces))}"/></asset>
    <worldbody><geom name="tube" type="mesh" mesh="tube"/>
    <body pos="0.005 0 0"><freejoint/><geom type="sphere" size="0.031"/></body></worldbody></mujoco>"""
  sim = load(xml)
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    sf.install(sim.mjm, sim.m)
  assert any("geom 'tube'" in str(w.message) and "not watertight" in str(w.message) for w in caught)
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  assert c.n >= 1 and np.all(np.isfinite(c.dist))


BOWL = """<mujoco><compiler meshdir="{meshes}"/><option timestep="0.002"/>
  <custom><text name="mjx_supportfield.nonconvex" data="bowl"/></custom>
  <asset><mesh name="bowl" file="bowl.obj"/></asset>
  <worldbody><geom name="floor" type="plane" size="1 1 .1"/>
    <body name="bowl" pos="0 0 0.08"><freejoint/><geom name="bowl" type="mesh" mesh="bowl" density="2000"/></body>
    <body name="ball" pos="0.02 0 0.1"><freejoint/><geom name="ball" type="sphere" size="0.015"/></body>
  </worldbody></mujoco>""".format(meshes=os.path.join(MODELS, "meshes"))
STEPS = 2000


@pytest.fixture(scope="module")
def bowl_runs():
  """The ball's final position relative to the bowl: plugin (true bowl) and MuJoCo C (its hull)."""
  sim = load(BOWL)
  sf.install(sim.mjm, sim.m)
  for _ in range(STEPS):
    mjw.step(sim.m, sim.d)
  xpos = sim.d.xpos.numpy()[0]
  mjd = mujoco.MjData(sim.mjm)
  for _ in range(STEPS):
    mujoco.mj_step(sim.mjm, mjd)
  ball, bowl = sim.mjm.body("ball").id, sim.mjm.body("bowl").id
  return {"plugin": xpos[ball] - xpos[bowl], "mujoco": mjd.xpos[ball] - mjd.xpos[bowl],
          "finite": bool(np.all(np.isfinite(sim.d.qpos.numpy())))}


@pytest.mark.slow
def test_ball_stays_in_the_bowl(bowl_runs):
  """Inside the rim (radius 8 cm) and resting on the inner bottom (1 cm thick shell, ball 1.5 cm)."""
  rel = bowl_runs["plugin"]
  assert bowl_runs["finite"]
  assert np.linalg.norm(rel[:2]) < 0.07, rel
  bowl_bottom_to_centre = 0.08 - 0.08 + 0.0  # the bowl body sits at its centre of mass
  assert rel[2] < 0.0 + bowl_bottom_to_centre, rel  # below the bowl's centre of mass: inside it


def test_hull_leaves_it_outside(bowl_runs):
  """MuJoCo C collides the bowl's convex hull: the ball cannot get in."""
  rel = bowl_runs["mujoco"]
  assert np.linalg.norm(rel[:2]) > 0.07 or rel[2] > 0.0, rel


def test_nonconvex_scene_matches_generator():
  import sys

  sys.path.insert(0, MODELS)
  import make_nonconvex

  with open(os.path.join(MODELS, "nonconvex.xml")) as f:
    assert f.read() == make_nonconvex.SCENE


CUBE = "-.01 -.01 -.01 .01 -.01 -.01 -.01 .01 -.01 .01 .01 -.01 -.01 -.01 .01 .01 -.01 .01 -.01 .01 .01 .01 .01 .01"


def _in_bowl(body: str, marker: str):
  """A static bowl (its inner bottom at z = 0.01) and one body; contacts of the pair."""
  xml = f"""<mujoco><compiler meshdir="{os.path.join(MODELS, 'meshes')}"/>
    <custom><text name="mjx_supportfield.nonconvex" data="{marker}"/></custom>
    <asset><mesh name="bowl" file="bowl.obj"/><mesh name="small" file="bowl.obj" scale=".5 .5 .5"/>
      <mesh name="cube" vertex="{CUBE}"/></asset>
    <worldbody><body pos="0 0 0.08"><geom name="bowl" type="mesh" mesh="bowl"/></body>{body}</worldbody></mujoco>"""
  sim, c = _contacts(xml)
  bowl = sim.mjm.geom("bowl").id
  up = np.array([n if g[0] == bowl else -n for n, g in zip(c.normal, c.geom)])
  return sim, c, up


def test_convex_mesh_in_the_bowl():
  """A convex mesh cube sunk into the bowl's inner bottom (a sphere of radius 7 cm about the bowl's
  centre): contacts at its lower corners, normals towards that centre, the corners' depths."""
  centre, inner, pos = np.array([0.0, 0.0, 0.08]), 0.07, np.array([0.002, 0.001, 0.019])
  _, c, up = _in_bowl(f'<body pos="{pos[0]} {pos[1]} {pos[2]}"><freejoint/><geom name="cube" type="mesh" mesh="cube"/>'
                      "</body>", "bowl")
  corners = pos + np.array([[x, y, -0.01] for x in (-0.01, 0.01) for y in (-0.01, 0.01)])
  depths = np.linalg.norm(corners - centre, axis=1) - inner
  assert c.n >= 3
  assert abs(-c.dist.min() - depths.max()) < 3e-4, (c.dist, depths)
  for n, p in zip(up, c.pos):  # the mesh's facets span 9 degrees of the sphere: normals within 8
    assert angle_deg(n, centre - p) < 8.0, (n, p)


def test_nonconvex_pair_nested_bowls():
  """Both non-convex: a half-size bowl resting in the big one, its bottom 1 mm into the inner bottom."""
  _, c, up = _in_bowl('<body pos="0 0 0.049"><freejoint/><geom name="small" type="mesh" mesh="small"/></body>',
                      "bowl small")
  assert c.n >= 1
  assert np.all(up[:, 2] > 0.95), up
  assert abs(-c.dist.min() - 0.001) < 5e-4, c.dist
