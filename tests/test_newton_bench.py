"""Newton's column of the benchmarks (mjx_supportfield/newton_bench.py): the setup that matches
MuJoCo (poses, pairs) and Newton's contacts on a resting scene; never timings. Skipped without
the optional ``newton`` extra."""

import os
import sys

import mujoco
import numpy as np
import pytest

from conftest import MODELS
from mjx_supportfield import newton_bench

RESTING = os.path.join(MODELS, "resting.xml")


def test_missing_newton_names_the_extra(monkeypatch):
  monkeypatch.setitem(sys.modules, "newton", None)  # import newton raises ImportError
  with pytest.raises(ImportError, match=r"mjx-supportfield\[newton\]"):
    newton_bench.import_newton()


@pytest.fixture(scope="module")
def resting():
  pytest.importorskip("newton", reason="Newton 1.8 is not installed: pip install mjx-supportfield[newton]")
  mjm = mujoco.MjModel.from_xml_path(RESTING)
  mjd = mujoco.MjData(mjm)
  for _ in range(200):
    mujoco.mj_step(mjm, mjd)
  mujoco.mj_forward(mjm, mjd)
  return mjm, mjd, newton_bench.build_world(RESTING, mjm)


def test_world_matches_mujoco(resting):
  mjm, mjd, world = resting
  assert world.notes == []
  assert (world.body_of >= 0).all()
  colliding = (mjm.geom_contype | mjm.geom_conaffinity) != 0
  assert sorted(g for g in world.geom_of if g >= 0) == list(np.nonzero(colliding)[0])
  assert newton_bench.pose_mismatches(world, mjm, mjd) == []


def test_pose_check_catches_a_wrong_body(resting):
  mjm, mjd, world = resting
  swapped = newton_bench.NewtonWorld(world.builder, np.roll(world.body_of, 1), world.geom_of, world.pairs, [])
  assert newton_bench.pose_mismatches(swapped, mjm, mjd)


@pytest.mark.parametrize("broad_phase", ["nxn", "explicit"])
def test_newton_touches_where_mujoco_does(resting, broad_phase):
  mjm, mjd, _ = resting
  mujoco_pairs = {tuple(sorted((int(c.geom1), int(c.geom2)))) for c in mjd.contact[:mjd.ncon]}
  assert len(mujoco_pairs) >= 4  # floor under each body, and the stacked mesh cubes
  newton_pairs, per_world = newton_bench.settled_contact_pairs(RESTING, 200, broad_phase)
  assert mujoco_pairs <= newton_pairs
  # no contact on a pair MuJoCo filters, and a handful per touching pair, not hundreds
  assert newton_pairs <= {tuple(p) for p in mujoco_pairs_allowed(mjm)}
  assert len(mujoco_pairs) <= per_world <= 8 * len(mujoco_pairs)


def mujoco_pairs_allowed(mjm):
  import mujoco_warp as mjw

  m = mjw.put_model(mjm)
  contact = m.nxn_pairid_filtered.numpy().reshape(-1, 2)[:, 0] > -2
  return [tuple(sorted(map(int, p))) for p in m.nxn_geom_pair_filtered.numpy().reshape(-1, 2)[contact]]


def test_newton_fk_of_mujoco_qpos_is_exact(resting):
  """The fallback when body poses cannot be mapped: Newton's FK of MuJoCo's qpos."""
  mjm, mjd, world = resting
  fk = newton_bench.newton_fk_poses(world, mjm, mjd)
  assert fk is not None
  assert newton_bench.pose_mismatches(world, mjm, mjd, fk) == []
  np.testing.assert_allclose(fk[:, :3], newton_bench.mujoco_body_poses(world, mjd)[:, :3], atol=1e-5)
