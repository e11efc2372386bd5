"""Deep and face-on-face contacts of real robot links, reduced to one pair each
(tests/data/repro, made by benchmarks/reduce_pair.py): every one of MuJoCo C's deep points has a
contact of the plugin's within COVER, no normal worse than MuJoCo C's by exact overlap, no point
off its shapes.

- aloha_wrist_finger: aloha_pot's wrist link 35 mm deep in the other arm's finger. A 40-gon
  face of the wrist on a triangle of the finger, past the old face-pair budget (the tilts kept
  the deepest edge only); then the triangle cut by the 40-gon, whose corners farthest along the
  face frame's axes fall on three of MuJoCo's four.
- panda_hand_finger: robosuite's Panda gripper as shipped, a finger's pad (two coplanar
  triangles) 13 mm into the hand: the incident face was the one facing the hand's face, the pad's
  other half, where MuJoCo takes the one along the contact normal.
- jaco_hand_thumb_tip: robosuite's Jaco hand, a thumb tip box 43 mm into the hand's hull: the SDF
  fallback's answer (its depth the deepest point's, below the overlap along its normal) skipped
  the deep-pair check, and its normal overlapped 52.9 mm where MuJoCo C's overlaps 43.3.
"""

import os

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import ROOT
from conftest import contacts
from conftest import load
from mjx_supportfield.tools import exact

REPRO = os.path.join(ROOT, "tests", "data", "repro")
COVER = 3e-3  # compare's radius: a deep point is found when a contact of its pair lies this near
MIN_DEPTH = 5e-4  # compare's deep point
CASES = ("aloha_wrist_finger", "panda_hand_finger", "jaco_hand_thumb_tip")


def _collide(name):
  mjm = mujoco.MjModel.from_xml_path(os.path.join(REPRO, f"{name}.xml"))
  sim = load(None, mjm=mjm, naconmax=64)
  sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  sf.collision(sim.m, sim.d)  # warm-started, as in a rollout (compare collides twice too)
  return sim, contacts(sim.d, 0)


@pytest.mark.parametrize("name", CASES)
def test_mujocos_deep_points_are_covered(name):
  sim, got = _collide(name)
  ref = np.array([c.pos for c in sim.mjd.contact[: sim.mjd.ncon] if c.dist < -MIN_DEPTH])
  assert len(ref) >= 2 and got.n >= 2
  nearest = np.linalg.norm(ref[:, None, :] - got.pos[None, :, :], axis=2).min(axis=1)
  assert (nearest < COVER).all(), f"MuJoCo C's points {np.round(nearest * 1e3, 1)} mm from the plugin's nearest"


@pytest.mark.parametrize("name", CASES)
def test_normal_no_worse_than_mujocos_and_points_on_shapes(name):
  sim, got = _collide(name)
  xpos, xmat = sim.mjd.geom_xpos, sim.mjd.geom_xmat
  g1, g2 = (int(g) for g in sim.mjd.contact[0].geom)  # MuJoCo orders a pair by geom type
  c_overlap = exact.overlap_along(sim.mjm, g1, g2, xpos, xmat, sim.mjd.contact[0].frame[:3])
  for k in range(got.n):
    assert tuple(got.geom[k]) == (g1, g2)
    overlap = exact.overlap_along(sim.mjm, g1, g2, xpos, xmat, got.normal[k])
    assert overlap <= c_overlap + 1e-4, f"overlap {overlap * 1e3:.2f} mm along the plugin's normal, C's {c_overlap * 1e3:.2f}"
    for g in (0, 1):
      outside = exact.distance_outside(sim.mjm, g, xpos[g], xmat[g].reshape(3, 3), got.pos[k])
      assert outside <= abs(got.dist[k]) / 2 + 1e-3, f"contact {k} {outside * 1e3:.1f} mm outside geom {g}"
  # the deepest point carries the overlap along the normal (an SDF answer's depth fell short of it)
  deepest = float(-got.dist.min())
  overlap = exact.overlap_along(sim.mjm, g1, g2, xpos, xmat, got.normal[int(np.argmin(got.dist))])
  assert abs(deepest - overlap) < 0.05 * overlap, f"depth {deepest * 1e3:.2f} mm, overlap {overlap * 1e3:.2f} mm"
