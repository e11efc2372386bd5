"""Exact geometry (exact.py) against known answers, and the fidelity metrics of compare_states."""

import math
import os

import mujoco
import mujoco_warp
import numpy as np
import pytest
from conftest import model_path

from mjx_supportfield.options import Options
from mjx_supportfield.tools import exact
from mjx_supportfield.tools.compare import Contact
from mjx_supportfield.tools.compare import _fidelity_summary
from mjx_supportfield.tools.compare import check
from mjx_supportfield.tools.compare import compare_states
from mjx_supportfield.tools.compare import format_report
from mjx_supportfield.tools.compare import match

MJW_MESHES = os.path.join(os.path.dirname(mujoco_warp.__file__), "test_data", "meshes")

SHAPES = """
<mujoco>
  <asset>
    <mesh name="tetra" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/>
    <hfield name="ramp" nrow="2" ncol="2" size="1 1 1 0.1" elevation="0 1 0 0"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 .1" pos="0 0 -1"/>
    <geom name="box" type="box" size=".5 .5 .5" pos="10 0 0"/>
    <geom name="tilted" type="box" size=".5 .2 .1" pos="0 10 0" euler="30 40 50"/>
    <geom name="sphere" type="sphere" size=".3" pos="1 2 3"/>
    <geom name="capsule" type="capsule" size=".2 .5" pos="0 -10 0"/>
    <geom name="cylinder" type="cylinder" size="1 1" pos="-10 0 0"/>
    <geom name="ellipsoid" type="ellipsoid" size="1 2 3" pos="20 0 0"/>
    <geom name="tetra" type="mesh" mesh="tetra"/>
    <geom name="ramp" type="hfield" hfield="ramp" pos="0 20 0"/>
  </worldbody>
</mujoco>
"""

# /work/shared/repro/mpr_dodeca_tetra.xml: two small polyhedra overlapping, MuJoCo C's normal
# has an overlap of 2.11 mm; a normal 58.7 deg off (an MPR answer on a face that is not the
# nearest) has 2.95 mm
DODECA_TETRA = f"""
<mujoco>
  <compiler meshdir="{MJW_MESHES}"/>
  <asset>
    <mesh name="dodeca" file="dodecahedron.stl" scale=".0014 .0014 .0014"/>
    <mesh name="tetra" file="tetrahedron.stl" scale=".016 .016 .016"/>
  </asset>
  <worldbody>
    <body pos="-0.0049174 -0.0230528 0.0129967" quat="-0.9031375 -0.1159824 -0.3806137 0.1613190">
      <freejoint/><geom name="dodeca" type="mesh" mesh="dodeca"/>
    </body>
    <body pos="0.0175709 -0.0056327 0.0225083" quat="-0.4427527 0.2788314 0.1031366 0.8459231">
      <freejoint/><geom name="tetra" type="mesh" mesh="tetra"/>
    </body>
  </worldbody>
</mujoco>
"""
MPR_BAD_NORMAL = (0.66473454, 0.60879236, 0.43301257)
EPA_NORMAL = (0.9227003, -0.30524123, 0.23548245)  # narrowphase="gjk": the best direction


@pytest.fixture(scope="module")
def shapes():
  mjm = mujoco.MjModel.from_xml_string(SHAPES)
  mjd = mujoco.MjData(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  return mjm, mjd


def _geom(shapes, name):
  mjm, mjd = shapes
  g = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name)
  return g, mjd.geom_xpos[g], mjd.geom_xmat[g].reshape(3, 3)


def _support(shapes, name, d):
  g, xpos, xmat = _geom(shapes, name)
  return exact.support(shapes[0], g, xpos, xmat, np.asarray(d, dtype=float))


def _outside(shapes, name, p, hull=True):
  g, xpos, xmat = _geom(shapes, name)
  return exact.distance_outside(shapes[0], g, xpos, xmat, np.asarray(p, dtype=float), hull=hull)


def test_box(shapes):
  assert _support(shapes, "box", (1, 1, 1)) == pytest.approx(10 + 1.5)
  assert _support(shapes, "box", (-1, 0, 0)) == pytest.approx(-9.5)
  assert _outside(shapes, "box", (11, 0, 0)) == pytest.approx(0.5)
  assert _outside(shapes, "box", (11, 1, 0)) == pytest.approx(math.sqrt(0.5))
  assert _outside(shapes, "box", (10.2, -0.4, 0.3)) == 0.0


def test_rotated_box_matches_its_corners(shapes):
  mjm, mjd = shapes
  g, xpos, xmat = _geom(shapes, "tilted")
  corners = xpos + (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * mjm.geom_size[g]) @ xmat.T
  rng = np.random.default_rng(0)
  for d in rng.normal(size=(20, 3)):
    assert _support(shapes, "tilted", d) == pytest.approx((corners @ d).max(), abs=1e-12)
  face_normal = xmat[:, 0]
  assert _outside(shapes, "tilted", xpos + 0.7 * face_normal) == pytest.approx(0.2)


def test_sphere_capsule_cylinder(shapes):
  d = np.array([1.0, -2.0, 2.0])
  assert _support(shapes, "sphere", d) == pytest.approx(np.dot((1, 2, 3), d) + 0.3 * 3.0)
  assert _outside(shapes, "sphere", (1, 2, 4)) == pytest.approx(0.7)
  assert _support(shapes, "capsule", (0, 0, 1)) == pytest.approx(0.7)
  assert _support(shapes, "capsule", (1, 0, 0)) == pytest.approx(0.2)
  assert _outside(shapes, "capsule", (0, -10, 1.7)) == pytest.approx(1.0)
  assert _outside(shapes, "capsule", (1.2, -10, 0.3)) == pytest.approx(1.0)
  assert _support(shapes, "cylinder", (1, 0, 1)) == pytest.approx(-10 + 2.0)
  assert _outside(shapes, "cylinder", (-8, 0, 3)) == pytest.approx(math.sqrt(5.0))
  assert _outside(shapes, "cylinder", (-10, 0.5, 0.5)) == 0.0


def test_ellipsoid(shapes):
  assert _support(shapes, "ellipsoid", (0, 0, 1)) == pytest.approx(3.0)
  assert _support(shapes, "ellipsoid", (1, 1, 0)) == pytest.approx(20 + math.sqrt(5.0))
  assert _outside(shapes, "ellipsoid", (22, 0, 0)) == pytest.approx(1.0)
  assert _outside(shapes, "ellipsoid", (20, 0, 5)) == pytest.approx(2.0)
  assert _outside(shapes, "ellipsoid", (20.5, 0.5, 0.5)) == 0.0
  # off-axis: the nearest point found is on the ellipsoid, along its normal from the point
  radii, p = np.array([1.0, 2.0, 3.0]), np.array([1.5, 1.0, -2.5])
  dist = exact.ellipsoid_distance(radii, p)
  normals = np.random.default_rng(1).normal(size=(200000, 3))
  surface = radii * normals / np.linalg.norm(normals, axis=1, keepdims=True)
  sampled = np.linalg.norm(surface - p, axis=1).min()
  assert dist <= sampled + 1e-12 and dist == pytest.approx(sampled, rel=1e-3)


def test_tetrahedron_mesh(shapes):
  """Mesh vertices are stored recentred (in float32); the geom pose puts them back where the MJCF
  put them."""
  assert _support(shapes, "tetra", (1, 1, 1)) == pytest.approx(1.0)
  assert _support(shapes, "tetra", (-1, 0, 0)) == pytest.approx(0.0, abs=1e-7)
  assert _outside(shapes, "tetra", (1, 1, 1)) == pytest.approx(2 / math.sqrt(3))  # face
  assert _outside(shapes, "tetra", (1, 1, 0)) == pytest.approx(math.sqrt(0.5))  # edge
  assert _outside(shapes, "tetra", (-1, -1, -1)) == pytest.approx(math.sqrt(3))  # vertex
  assert _outside(shapes, "tetra", (0.1, 0.1, 0.1)) == 0.0
  assert _outside(shapes, "tetra", (2, 0, 0)) == pytest.approx(1.0)
  # its true triangles: the same shape, here by winding number
  assert _outside(shapes, "tetra", (1, 1, 1), hull=False) == pytest.approx(2 / math.sqrt(3))
  assert _outside(shapes, "tetra", (0.1, 0.1, 0.1), hull=False) == 0.0
  many = exact.distance_outside(shapes[0], *_geom(shapes, "tetra"), np.array([[1.0, 1, 1], [0.1, 0.1, 0.1]]))
  assert many.shape == (2,) and many[0] == pytest.approx(2 / math.sqrt(3)) and many[1] == 0.0


def test_plane(shapes):
  mjm, mjd = shapes
  floor, sphere = (mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("floor", "sphere"))
  xpos, xmat = mjd.geom_xpos, mjd.geom_xmat
  # sphere at z = 3, radius 0.3, plane at z = -1: separated by 3.7 along the plane's normal
  assert exact.overlap_along(mjm, floor, sphere, xpos, xmat, (0, 0, 1)) == pytest.approx(-3.7)
  assert exact.overlap_along(mjm, sphere, floor, xpos, xmat, (0, 0, -1)) == pytest.approx(-3.7)
  assert exact.overlap_along(mjm, floor, sphere, xpos, xmat, (0, 0.1, 1)) == math.inf  # not the plane's normal
  assert exact.overlap_along(mjm, floor, sphere, xpos, xmat, (0, 0, -1)) == math.inf
  assert _outside(shapes, "floor", (3, 4, 1.5)) == pytest.approx(2.5)
  assert _outside(shapes, "floor", (3, 4, -1.5)) == 0.0


def test_heightfield_uses_mujocos_triangulation(shapes):
  """One cell, corner (row 1, col 1) raised to 1: MuJoCo C splits the cell along the diagonal
  from (row 0, col 0) to (row 1, col 1), so over x > y the surface is z = (y + 1) / 2."""
  assert shapes[0].hfield_data.tolist() == [0, 0, 0, 1]  # MuJoCo stores the MJCF's rows from the last
  y0 = 20.0
  assert _outside(shapes, "ramp", (0.6, y0 - 0.5, 0.3)) == pytest.approx(0.05 / math.sqrt(1.25))
  assert _outside(shapes, "ramp", (-0.5, y0 + 0.6, 0.3)) == pytest.approx(0.05 / math.sqrt(1.25))  # z = (x + 1) / 2
  assert _outside(shapes, "ramp", (0.5, y0 - 0.5, 0.2)) == 0.0  # under the other diagonal it would be 0.2 above
  assert _outside(shapes, "ramp", (0.0, y0, -0.2)) == pytest.approx(0.1)  # under the base
  assert _outside(shapes, "ramp", (1.5, y0, 0.0)) == pytest.approx(0.5)  # beside the grid
  with pytest.raises(exact.NotConvexError):
    _support(shapes, "ramp", (0, 0, 1))


def test_dodeca_tetra_overlaps():
  """The repro case: MuJoCo C's normal beats MPR's bad one, and is itself 4.6 deg from the
  best separating direction, which GJK/EPA finds (the smallest overlap over all directions)."""
  mjm = mujoco.MjModel.from_xml_string(DODECA_TETRA)
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  assert mjd.ncon >= 1

  def overlap(n):
    return exact.overlap_along(mjm, 0, 1, mjd.geom_xpos, mjd.geom_xmat, n)

  assert overlap(mjd.contact[0].frame[:3]) == pytest.approx(2.106e-3, abs=5e-6)
  assert overlap(MPR_BAD_NORMAL) == pytest.approx(2.954e-3, abs=5e-6)
  assert overlap(EPA_NORMAL) == pytest.approx(1.8914e-3, abs=5e-7)
  dirs = np.random.default_rng(2).normal(size=(2000, 3))
  assert min(overlap(d) for d in dirs) >= overlap(EPA_NORMAL) - 1e-9
  # the same figure from the vertices by brute force
  world = [mjd.geom_xpos[g] + exact.mesh_vertices(mjm, mjm.geom_dataid[g]) @ mjd.geom_xmat[g].reshape(3, 3).T
           for g in (0, 1)]
  n = np.asarray(MPR_BAD_NORMAL) / np.linalg.norm(MPR_BAD_NORMAL)
  assert overlap(n) == pytest.approx((world[0] @ n).max() - (world[1] @ n).min(), abs=1e-15)


def test_position_error_pairs_each_point_with_its_nearest():
  """Two equally deep points: the deepest of one list and of the other are opposite corners."""
  n = np.array([0.0, 0.0, 1.0])
  ref = [Contact((0, 1), -1e-3, np.array([0.0, 0, 0]), n), Contact((0, 1), -1e-3 + 1e-9, np.array([1.0, 0, 0]), n)]
  got = [Contact((0, 1), -1e-3, np.array([1.0, 0, 0]), n), Contact((0, 1), -1e-3 + 1e-9, np.array([0.0, 0, 0]), n)]
  row = match(ref, got, 5e-4, np.ones(2))["rows"][0]
  assert row["position_error"] == 0.0 and row["position_errors"] == [0.0, 0.0]


@pytest.fixture(scope="module")
def dodeca_tetra_report():
  mjm = mujoco.MjModel.from_xml_string(DODECA_TETRA)
  impls = {"plugin": Options(), "plugin_gjk": Options(narrowphase="gjk"), "stock": None}
  return compare_states(mjm, [mjm.qpos0.copy()], impls)


def test_compare_states_on_the_repro(dodeca_tetra_report):
  report = dodeca_tetra_report
  stock = report["impls"]["stock"]["summary"]
  assert stock["deep_points_reference"] == 2 and stock["deep_points_missed"] == 0
  assert stock["normals_differ"] == 0 and stock["contacts_outside"] == 0
  for name in ("plugin", "plugin_gjk"):
    summary = report["impls"][name]["summary"]
    assert summary["deep_points_reference"] == 2
    for row in report["impls"][name]["states"][0]["normals"]:  # each verdict comes with both exact overlaps
      assert row["overlap_reference"] == pytest.approx(2.106e-3, abs=5e-6)
      assert row["verdict"] == ("worse" if row["overlap"] > row["overlap_reference"] else "better")
  text = format_report({"model": "dodeca_tetra", **report})
  assert "legend:" in text and text.splitlines()[-1].startswith("plugin: ")


def test_check_names_each_failure():
  summary = {"deep_points_missed": 3, "deep_points_reference": 100, "pairs_normal_worse": 1, "contacts_outside": 2,
             "max_outside": 0.05}
  reasons = check({"impls": {"plugin": {"summary": summary}}})
  assert len(reasons) == 3 and "3 of 100" in reasons[0] and "worse" in reasons[1] and "50.00 mm" in reasons[2]
  summary.update(deep_points_missed=2, pairs_normal_worse=0, contacts_outside=0)
  assert check({"impls": {"plugin": {"summary": summary}}}) == []


def test_convex_pile_metrics_are_consistent():
  """On a scene of convex meshes on a plane: every deep point's nearest contact is reported,
  and MuJoCo C's own contacts lie on its shapes."""
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile.xml"))
  report = compare_states(mjm, [mjm.qpos0.copy()], {"stock": None})
  assert report["reference"]["contacts_checked"] > 0 and report["reference"]["contacts_outside"] == 0
  stock = report["impls"]["stock"]
  deep = stock["states"][0]["deep_points"]
  assert len(deep) == stock["summary"]["deep_points_reference"] > 0
  assert all((r["nearest"] is None or r["nearest"] > 3e-3) == r["missed"] for r in deep)


def test_hull_distance_is_the_support_function_bound():
  """Outside a convex shape, distance = max over unit n of (p.n - h(n)): sampled directions
  bound it from below and come within a fraction of a percent of it."""
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile.xml"))
  mjd = mujoco.MjData(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  g = int(np.flatnonzero(mjm.geom_type == mujoco.mjtGeom.mjGEOM_MESH)[0])
  xpos, xmat = mjd.geom_xpos[g], mjd.geom_xmat[g].reshape(3, 3)
  verts = xpos + exact.mesh_vertices(mjm, mjm.geom_dataid[g]) @ xmat.T
  rng = np.random.default_rng(3)
  dirs = rng.normal(size=(100000, 3))
  dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
  h = (dirs @ verts.T).max(axis=1)
  for p in xpos + rng.normal(size=(5, 3)) * mjm.geom_rbound[g]:
    dist = exact.distance_outside(mjm, g, xpos, xmat, p)
    bound = max((dirs @ p - h).max(), 0.0)
    assert bound <= dist + 1e-12 and dist <= bound + 5e-3 * mjm.geom_rbound[g], (p, dist, bound)


def test_warp_contacts_reruns_when_the_buffer_overflows(monkeypatch):
  """Contacts that did not fit are not dropped: the collision reruns with room for them."""
  from mjx_supportfield.tools import compare

  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile.xml"))
  states = compare.sample_states(mjm, 0, 1)
  full = compare.warp_contacts(mjm, states, 2)
  real, calls = compare._collide, []

  def tight(mjm, qpos, plugin, nconmax):
    calls.append(nconmax)
    return real(mjm, qpos, plugin, 1 if len(calls) == 1 else nconmax)

  monkeypatch.setattr(compare, "_collide", tight)
  again = compare.warp_contacts(mjm, states, 2)
  assert len(calls) == 2 and [len(w) for w in again] == [len(w) for w in full] and len(full[0]) > 1


def test_nonconvex_pairs_are_labelled_and_not_counted():
  """MuJoCo C collides a non-convex mesh's hull: its pairs' deep points and normals are kept
  apart from the counts --check uses."""
  from mjx_supportfield.tools.compare import sample_states

  mjm = mujoco.MjModel.from_xml_path(model_path("nonconvex.xml"))
  report = compare_states(mjm, sample_states(mjm, 100, 2), {"stock": None})
  assert report["nonconvex_geoms"] == ["bowl", "cup"]  # the model's custom text
  summary = report["impls"]["stock"]["summary"]
  deep = [r for s in report["impls"]["stock"]["states"] for r in s["deep_points"]]
  assert summary["deep_points_reference_nonconvex"] > 0
  assert summary["deep_points_reference"] == sum(1 for r in deep if r["kind"] != "nonconvex")
  assert all(r["kind"] == "nonconvex" for r in deep if {"bowl", "cup"} & set(r["pair"].split("-")))
  assert "MuJoCo C collides this mesh's convex hull" in format_report({"model": "nonconvex", **report})


def test_missed_points_on_pairs_where_mujocos_normal_is_worse_are_counted_apart():
  """A missed point of a pair whose normal is far from MuJoCo C's and better by exact overlap is
  counted in deep_points_missed_reference_worse (C's points lie on another feature there); a
  missed point of a pair whose normal is worse, or of another state, is not."""
  def deep(geoms, missed):
    return {"pair": "a-b", "geoms": geoms, "kind": "convex", "dist": -0.01, "pos": [0.0, 0.0, 0.0],
            "nearest": 0.01, "missed": missed}

  def normal(geoms, verdict):
    return {"pair": "a-b", "geoms": geoms, "angle_deg": 40.0, "verdict": verdict, "kind": "convex"}

  outside = {"checked": 0, "max_outside": 0.0, "off": []}
  states = [
    {"world": 0, "state": 0, "deep_points": [deep((0, 1), True), deep((0, 1), True), deep((1, 2), True)],
     "normals": [normal((0, 1), "better"), normal((1, 2), "worse")], "outside": outside},
    {"world": 1, "state": 1, "deep_points": [deep((0, 1), True), deep((0, 1), False)], "normals": [], "outside": outside},
  ]
  summary = _fidelity_summary(states)
  assert summary["deep_points_missed"] == 4
  assert summary["deep_points_missed_reference_worse"] == 2


def test_inner_prism_walls_are_told_apart():
  """A heightfield contact of MuJoCo C's inside the grid along a normal steeper than every
  triangle of the grid is a side wall's between two prisms (the terrain's surface has no such
  normal); at the grid's outer edge the wall is the terrain's own, and a normal no steeper than
  the steepest triangle may be the surface's."""
  from mjx_supportfield.tools.compare import Reference
  from mjx_supportfield.tools.compare import _inner_wall
  from mjx_supportfield.tools.compare import _scene
  from mjx_supportfield.tools.compare import steepest_facet_nz

  peak = np.zeros((11, 11))
  peak[5, 5] = 1.0  # 0.2 m up over cells of 0.2 m: slopes of 1 along x, y or both
  mjm = mujoco.MjModel.from_xml_string(f"""<mujoco><asset><hfield name="h" nrow="11" ncol="11" size="1 1 .2 .1"
    elevation="{' '.join(map(str, peak.ravel()))}"/></asset><worldbody>
    <geom type="hfield" hfield="h" pos="1 2 0" euler="0 0 90"/>
    <body><freejoint/><geom type="sphere" size=".05"/></body></worldbody></mujoco>""")
  assert steepest_facet_nz(mjm, 0) == pytest.approx(1.0 / np.sqrt(3.0))
  mjd = mujoco.MjData(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  ref = Reference([], mjd.geom_xpos.copy(), mjd.geom_xmat.reshape(-1, 3, 3).copy())
  scene = _scene(mjm, {"stock": None}, 5e-4, 3e-3)
  inside, border = np.array([1.3, 2.2, 0.05]), np.array([1.05, 2.95, 0.05])  # the cells are 0.2 m
  assert _inner_wall(scene, ref, Contact((0, 1), -0.01, inside, np.array([0.6, 0.8, 0.0])))
  assert _inner_wall(scene, ref, Contact((0, 1), -0.01, inside, np.array([0.0, 0.999, -0.045])))  # EPA tilted below
  assert _inner_wall(scene, ref, Contact((0, 1), -0.01, inside, np.array([0.0, 0.866, 0.5])))  # steeper than any
  assert not _inner_wall(scene, ref, Contact((0, 1), -0.01, border, np.array([0.6, 0.8, 0.0])))
  assert not _inner_wall(scene, ref, Contact((0, 1), -0.01, inside, np.array([0.0, 0.6, 0.8])))


def test_a_heightfield_point_is_answered_on_its_own_prism_by_as_good_a_normal():
  """MuJoCo C writes one contact a triangle's prism, at EPA's witness, anywhere on a flat overlap:
  a missed point of C's counts as answered on its prism when a contact of the pair lies over the
  same triangle with a normal whose exact overlap of the geom and the prism is no larger; not
  from the cell's other triangle, and not with a worse normal."""
  from mjx_supportfield.tools.compare import Reference
  from mjx_supportfield.tools.compare import _prism_answered
  from mjx_supportfield.tools.compare import _scene

  mjm = mujoco.MjModel.from_xml_string("""<mujoco><asset><hfield name="h" nrow="3" ncol="3" size="1 1 .1 .1"
    elevation="0 0 0 0 0 0 0 0 0"/></asset><worldbody>
    <geom type="hfield" hfield="h"/>
    <body pos="0.3 0.2 0.098"><freejoint/><geom type="box" size=".1 .1 .1"/></body></worldbody></mujoco>""")
  mjd = mujoco.MjData(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  ref = Reference([], mjd.geom_xpos.copy(), mjd.geom_xmat.reshape(-1, 3, 3).copy())
  scene = _scene(mjm, {"stock": None}, 5e-4, 3e-3)
  up, tilted = np.array([0.0, 0.0, 1.0]), np.array([np.sin(0.5), 0.0, np.cos(0.5)])
  # cell (1, 1) spans x, y in [0, 1]; its diagonal y = x parts the triangle under y < x from the other
  c = Contact((0, 1), -0.002, np.array([0.35, 0.15, -0.001]), up)  # the box's face 2 mm into the flat terrain
  assert _prism_answered(scene, ref, c, [Contact((0, 1), -0.002, np.array([0.25, 0.12, -0.001]), up)])
  assert not _prism_answered(scene, ref, c, [Contact((0, 1), -0.002, np.array([0.22, 0.28, -0.001]), up)])
  assert not _prism_answered(scene, ref, c, [Contact((0, 1), -0.002, np.array([0.25, 0.12, -0.001]), tilted)])
