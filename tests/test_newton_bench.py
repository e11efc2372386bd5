"""Newton's column of the benchmarks (mjx_supportfield/tools/newton_bench.py): the setup that matches
MuJoCo (poses, pairs) and Newton's contacts on a resting scene; never timings. Skipped without
the optional ``newton`` extra."""

import json
import os
import sys

import mujoco
import numpy as np
import pytest

from conftest import MODELS
from conftest import on_gpu
from mjx_supportfield.tools import newton_bench
from mjx_supportfield.tools.cli import main

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


def test_bench_newton_without_newton_is_one_error_line(capsys, monkeypatch):
  monkeypatch.setitem(sys.modules, "newton", None)
  rc = main(["bench", RESTING, "--newton", "--nworld", "1"])
  err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
  assert rc == 2 and len(err) == 1 and "mjx-supportfield[newton]" in err[0], err


def test_bench_newton_writes_the_newton_column(tmp_path, capsys, resting):
  """bench --newton: the JSON has a newton entry per scene and world count beside the rows (which
  carry the frozen-state figure), and the table prints the three columns."""
  if on_gpu():
    pytest.skip("a quick CPU run")
  results = tmp_path / "bench.json"
  rc = main(["bench", os.path.join(MODELS, "mesh_on_plane.xml"), "--newton", "--nworld", "2", "--settle", "50",
             "--json", str(results)])
  out = capsys.readouterr().out
  assert rc == 0
  assert "newton ms" in out and "exact" in out
  data = json.loads(results.read_text())
  assert data["newton_version"] == "1.8.0"
  (entry,) = data["newton"]
  assert entry["nworld"] == 2 and entry["broadphase"] in newton_bench.BROAD_PHASES
  assert sorted(entry["ms_by_broadphase"]) == sorted(newton_bench.BROAD_PHASES)
  assert entry["contacts_per_world"] > 0 and entry["notes"] == []
  assert all(r["frozen_ms"] > 0 for r in data["rows"] if r["stage"] == "collision")


def test_newton_tests_mujocos_pairs_exactly():
  """nxn and sap test MuJoCo's pairs, no more, no fewer: on arm_sweep the first link is welded to
  the world, where MuJoCo collides parent and child and Newton's import filters them."""
  newton = pytest.importorskip("newton", reason="Newton 1.8 is not installed: pip install mjx-supportfield[newton]")
  world = newton_bench.build_world(os.path.join(MODELS, "real", "arm_sweep.xml"))
  assert world.notes == []
  ours = newton_bench._newton_pairs(world.builder, int(newton.ShapeFlags.COLLIDE_SHAPES))
  assert set(map(tuple, ours.tolist())) == set(map(tuple, world.pairs.tolist()))
