"""GJK/EPA's contact points lie on the shapes (issue #20, item 3).

EPA's contact point is the midpoint of its witness points: it must lie within |dist| / 2 + 1 mm
of both geoms, in every step of a rollout. Where faces of A - B tie (a box face against a mesh
vertex, coplanar hull triangles), the witnesses come from the face that holds the origin's
projection. The reduced real-model cases live in tests/data/repro (see its README).
"""

import os

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

import mjx_supportfield as sf
from conftest import ROOT
from conftest import contacts
from conftest import load
from mjx_supportfield.tools import exact

REPRO = os.path.join(ROOT, "tests", "data", "repro")
POINT_SLACK = 1e-3  # a contact point may lie this far beyond |dist| / 2 outside either geom


def repro(name: str) -> mujoco.MjModel:
  return mujoco.MjModel.from_xml_path(os.path.join(REPRO, name))


def poses(d, world: int):
  """float64 copies of the geom poses of one world of a MuJoCo Warp Data."""
  return d.geom_xpos.numpy()[world].astype(np.float64), d.geom_xmat.numpy()[world].astype(np.float64)


def points_off_shapes(mjm, d, world: int) -> list:
  """The contacts of one world whose point lies farther than |dist| / 2 + POINT_SLACK outside
  one of its geoms, as (geoms, dist, pos, distance outside)."""
  c = contacts(d, world)
  xpos, xmat = poses(d, world)
  bad = []
  for k in range(c.n):
    for g in c.geom[k]:
      out = exact.distance_outside(mjm, int(g), xpos[g], xmat[g].reshape(3, 3), c.pos[k])
      if out > abs(float(c.dist[k])) / 2 + POINT_SLACK:
        bad.append((tuple(int(x) for x in c.geom[k]), float(c.dist[k]), c.pos[k].tolist(), out))
  return bad


def test_gjk_points_on_shapes_box_can():
  """A can lying on a table: EPA's nearest face lay beside the origin's projection (faces of
  A - B tie on the table's face) and put one contact 76 mm outside the can."""
  mjm = repro("gjk_pos_box_can.xml")
  sim = load(None, mjm=mjm)
  sf.install(mjm, sim.m, sf.Options(narrowphase="gjk"))
  sf.collision(sim.m, sim.d)
  assert contacts(sim.d, 0).n > 0
  assert not points_off_shapes(mjm, sim.d, 0)


STEPS = 30


def test_gjk_points_on_shapes_ramp_tetra_rollout():
  """A tetrahedron sliding on a ramp, stepped through mjw.step with narrowphase="gjk": the contact
  point lay 32 to 41 mm outside the tetrahedron, step after step."""
  mjm = repro("gjk_pos_ramp_tetra.xml")
  sim = load(None, mjm=mjm, naconmax=64)
  sf.install(mjm, sim.m, sf.Options(narrowphase="gjk"))
  bad, ncontact = [], 0
  for step in range(STEPS):
    mjw.step(sim.m, sim.d)  # the contacts and geom poses it leaves are those of the step's start
    wp.synchronize()
    ncontact += contacts(sim.d, 0).n
    bad += [(step, *b) for b in points_off_shapes(mjm, sim.d, 0)]
  assert ncontact > 0
  assert not bad, bad[:5]
