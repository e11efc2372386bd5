"""install / uninstall / dispatch: the plugin replaces MuJoCo Warp's collision stage of one model."""

import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp

import mjx_supportfield as sf
from conftest import contacts
from conftest import load
from conftest import load_mjmodel

NWORLD = 2


def contact_records(d):
  """All active contacts as a sorted list of exact (world, geom1, geom2, dist, pos, frame) tuples."""
  recs = []
  for w in range(d.nworld):
    c = contacts(d, w)
    for i in range(c.n):
      recs.append((w, *(int(x) for x in c.geom[i]), float(c.dist[i]), *c.pos[i].tolist(), *c.frame[i].ravel().tolist()))
  return sorted(recs)


@pytest.fixture(scope="module")
def pile_stock():
  """convex_pile, never installed: stock MuJoCo Warp contacts at qpos0 (mesh-mesh pairs overlap)."""
  sim = load("convex_pile", nworld=NWORLD)
  mjw.collision(sim.m, sim.d)
  return sim, contact_records(sim.d), int(sim.d.nacon.numpy()[0])


def test_install_uninstall_restores_stock(pile_stock):
  ref_sim, ref, _ = pile_stock
  sim = load("convex_pile", nworld=NWORLD)
  m, d = sim.m, sim.d
  assert sf.get_collider(m) is None
  collider = sf.install(sim.mjm, m)
  assert sf.get_collider(m) is collider

  mjw.collision(m, d)  # the patched entry point dispatches to the plugin
  plugin = contact_records(d)
  assert sf.get_collider(m).stats(d)["pairs"] > 0
  # the plugin's contacts (points, depths, order) are not stock's: the two must differ
  assert plugin != ref

  # a model without the plugin keeps stock collision while another model has it
  d_other = mjw.put_data(ref_sim.mjm, ref_sim.mjd, nworld=NWORLD)
  mjw.kinematics(ref_sim.m, d_other)
  mjw.collision(ref_sim.m, d_other)
  assert contact_records(d_other) == ref

  sf.uninstall(m)
  assert sf.get_collider(m) is None
  mjw.collision(m, d)
  assert contact_records(d) == ref
  d.nacon.zero_()
  mjw.fwd_position(m, d)
  assert contact_records(d) == ref


def test_install_twice_raises():
  mjm = load_mjmodel("convex_pile")
  m = mjw.put_model(mjm)
  sf.install(mjm, m)
  with pytest.raises(ValueError, match="already installed"):
    sf.install(mjm, m)
  sf.uninstall(m)
  sf.install(mjm, m)  # fine again after uninstall
  sf.uninstall(m)


def test_uninstall_without_plugin_raises():
  mjm = load_mjmodel("convex_pile")
  m = mjw.put_model(mjm)
  with pytest.raises(ValueError, match="not installed"):
    sf.uninstall(m)
  d = mjw.make_data(mjm)
  with pytest.raises(ValueError, match="not installed"):
    sf.collision(m, d)
  sf.install(mjm, m)
  sf.uninstall(m)
  with pytest.raises(ValueError, match="not installed"):
    sf.uninstall(m)


def test_install_argument_checks():
  mjm = load_mjmodel("convex_pile")
  m = mjw.put_model(mjm)
  with pytest.raises(TypeError):
    sf.install("convex_pile", m)
  with pytest.raises(TypeError):
    sf.install(mjm, mjm)
  with pytest.raises(TypeError):
    sf.install(mjm, m, 180)
  other = load_mjmodel("primitives_plane")
  with pytest.raises(ValueError):
    sf.install(other, m)
  with pytest.raises(ValueError, match="bogus"):
    sf.install(mjm, m, {"bogus": 1})
  assert sf.get_collider(m) is None  # failed installs leave the model stock
  collider = sf.install(mjm, m, {"support_res": 64, "support_mode": "exact"})
  assert collider.options == sf.Options(support_res=64, support_mode="exact")
  sf.uninstall(m)


def test_data_from_other_model_raises():
  sim = load("convex_pile")
  sf.install(sim.mjm, sim.m)
  other = load("primitives_plane")  # 14 geoms against 7
  with pytest.raises(ValueError):
    sf.collision(sim.m, other.d)
  sf.uninstall(sim.m)


@pytest.fixture(scope="module")
def pile_installed():
  sim = load("convex_pile", nworld=NWORLD)
  sf.install(sim.mjm, sim.m)
  return sim


def test_step_runs_plugin(pile_installed, pile_stock):
  _, ref, _ = pile_stock
  sim = pile_installed
  m = sim.m
  # what the plugin alone gives at qpos0
  d0 = mjw.put_data(sim.mjm, sim.mjd, nworld=NWORLD)
  mjw.kinematics(m, d0)
  sf.collision(m, d0)
  expected = contact_records(d0)
  assert expected != ref

  d = mjw.put_data(sim.mjm, sim.mjd, nworld=NWORLD)
  assert sf.get_collider(m).stats(d)["pairs"] == 0
  mjw.step(m, d)
  # step's contacts are those of the state it started from
  assert contact_records(d) == expected
  assert sf.get_collider(m).stats(d)["pairs"] > 0
  for _ in range(4):
    mjw.step(m, d)
  assert np.all(np.isfinite(d.qpos.numpy()))


def test_two_data_alternately(pile_installed):
  """One installed model, Data of nworld 1 and 3 used in turn: each keeps its own state."""
  sim = pile_installed
  m = sim.m
  d1 = mjw.put_data(sim.mjm, sim.mjd, nworld=1)
  d3 = mjw.put_data(sim.mjm, sim.mjd, nworld=3)
  for _ in range(3):
    mjw.step(m, d1)
    mjw.step(m, d3)
  c1 = contacts(d1, 0)
  assert c1.n > 0
  for w in range(3):
    cw = contacts(d3, w)
    assert cw.n == c1.n
    np.testing.assert_allclose(np.sort(cw.dist), np.sort(c1.dist), atol=1e-6)
    np.testing.assert_allclose(d3.qpos.numpy()[w], d1.qpos.numpy()[0], atol=1e-5)
  s1 = sf.get_collider(m).stats(d1)
  s3 = sf.get_collider(m).stats(d3)
  assert len(s1["pairs_per_world"]) == 1 and len(s3["pairs_per_world"]) == 3
  assert s3["pairs_per_world"] == s1["pairs_per_world"] * 3
  assert s3["pairs"] == 3 * s1["pairs"]
  # collision only, alternating again, against a fresh Data on d1's state given d1's calls
  # alone: MPR is warm-started from each Data's own last call, so d3's calls between d1's must
  # not show in d1's contacts. d1's history is dropped first, since the steps above cannot bring
  # a fresh Data to d1's exact state on a GPU (MuJoCo Warp's step is not bitwise repeatable there).
  fresh = mjw.put_data(sim.mjm, sim.mjd, nworld=1)
  wp.copy(fresh.qpos, d1.qpos)
  wp.copy(fresh.qvel, d1.qvel)
  sf.get_collider(m).reset_worlds(d1)
  for d in (d1, d3, fresh):
    mjw.kinematics(m, d)
  sf.collision(m, d1)
  sf.collision(m, d3)
  sf.collision(m, d1)
  sf.collision(m, fresh)
  sf.collision(m, fresh)
  assert contact_records(fresh) == contact_records(d1)


def test_graph_capture_matches_uncaptured():
  """A step replayed from a captured graph (CUDA, or Warp's CPU graphs) matches plain steps."""
  with wp.ScopedDevice(wp.get_device()):
    sim = load("convex_pile", nworld=4)
    m = sim.m
    sf.install(sim.mjm, m)
    d_ref = mjw.put_data(sim.mjm, sim.mjd, nworld=4)
    d_cap = mjw.put_data(sim.mjm, sim.mjd, nworld=4)
    mjw.step(m, d_ref)  # load every kernel before capturing
    mjw.step(m, d_cap)
    with wp.ScopedCapture() as capture:
      mjw.step(m, d_cap)
    for _ in range(5):
      wp.capture_launch(capture.graph)
      mjw.step(m, d_ref)
    wp.synchronize()
    np.testing.assert_allclose(d_cap.qpos.numpy(), d_ref.qpos.numpy(), atol=1e-5)
    assert int(d_cap.nacon.numpy()[0]) == int(d_ref.nacon.numpy()[0])
    assert sf.get_collider(m).stats(d_cap)["pairs"] == sf.get_collider(m).stats(d_ref)["pairs"]
    sf.uninstall(m)


def test_more_pairs_than_threads_of_the_analytic_kernel():
  """The analytic kernel runs as many threads as contacts fit (as stock MuJoCo Warp does) and
  walks its queue with a grid-stride loop: with 12 analytic pairs and room for 4 contacts, the
  2 touching pairs still give MuJoCo C's contacts. (Stock MuJoCo Warp, whose pair list holds
  naconmax pairs, drops them here.)"""
  near = "".join(  # capsule pairs end to end, offset sideways: boxes and bounding spheres overlap, 24 mm apart
    f'<body pos="{2 * k} 0 1"><freejoint/><geom type="capsule" size=".05 .2"/></body>'
    f'<body pos="{2 * k + 0.08} 0.08 1.45"><freejoint/><geom type="capsule" size=".05 .2"/></body>' for k in range(10))
  touching = ('<body pos="30 0 1"><freejoint/><geom type="sphere" size=".1"/></body>'
              '<body pos="30 0 1.19"><freejoint/><geom type="sphere" size=".1"/></body>'
              '<body pos="40 0 1"><freejoint/><geom type="capsule" size=".1 .2"/></body>'
              '<body pos="40 0 1.29"><freejoint/><geom type="sphere" size=".1"/></body>')
  xml = f"<mujoco><worldbody>{near}{touching}</worldbody></mujoco>"
  sim = load(xml, naconmax=4)
  sf.install(sim.mjm, sim.m, sf.Options(stock_for_analytic_models=False))
  sf.collision(sim.m, sim.d)
  assert sf.get_collider(sim.m).stats(sim.d)["pairs"] == 12
  got = contacts(sim.d, 0)
  ref = np.array([sim.mjd.contact[i].dist for i in range(sim.mjd.ncon)])  # MuJoCo C
  assert got.n == len(ref) == 2
  np.testing.assert_allclose(np.sort(got.dist), np.sort(ref), atol=1e-6)


# free capsules and spheres over a plane: MuJoCo's analytic pairs only
_ANALYTIC_ONLY = "<mujoco><worldbody><geom type='plane' size='5 5 .1'/>" + "".join(
  f"<body pos='{0.3 * k} {0.1 * (k % 2)} {0.1 + 0.12 * k}'><freejoint/>"
  f"<geom type='{('capsule', 'sphere')[k % 2]}' size='.1 .15' euler='{20 * k} {35 * k} 0'/></body>"
  for k in range(6)) + "</worldbody></mujoco>"


@pytest.mark.parametrize("options, stock_path", [
  ({}, True),
  ({"stock_for_analytic_models": False}, False),
  ({"broadphase": "nxn"}, False),
  ({"contacts_per_world": 64}, False),  # 3 worlds x 64 rows
])
def test_analytic_only_model_collides_through_stock(options, stock_path):
  """A model of analytic pairs only collides through MuJoCo Warp's own stage by default (the
  plugin would run the same routines with more launches); the plugin's own pipeline, when asked
  for, writes the same contacts."""
  ref = load(_ANALYTIC_ONLY, nworld=3, naconmax=192)
  sim = load(_ANALYTIC_ONLY, nworld=3, naconmax=192)
  collider = sf.install(sim.mjm, sim.m, sf.Options(**options))
  assert collider.stock_path == stock_path
  for _ in range(20):
    mjw.step(ref.m, ref.d)
    mjw.step(sim.m, sim.d)
  wp.copy(sim.d.qpos, ref.d.qpos)  # the same state, whatever the steps did
  for s in (ref, sim):
    mjw.kinematics(s.m, s.d)
    mjw.collision(s.m, s.d)
  records = contact_records(sim.d)
  assert len(records) >= 6 and records == contact_records(ref.d)
  stats = collider.stats(sim.d)
  assert stats["path"] == ("stock" if stock_path else "plugin")
  assert stats["pairs"] == (int(ref.d.ncollision.numpy()[0]) if stock_path else sum(stats["pairs_per_world"]))
  assert ("MuJoCo Warp's own collision stage" in str(stats)) == stock_path


def test_stock_path_checks_the_data_and_resets_it():
  """The stock path refuses a Data made for another model, as the plugin's pipeline does, and
  reset_worlds on a Data it stepped has nothing to drop."""
  sim = load(_ANALYTIC_ONLY, nworld=2, naconmax=64)
  collider = sf.install(sim.mjm, sim.m)
  assert collider.stock_path
  other = load("terrain", nworld=2)
  with pytest.raises(ValueError, match=r"Data\.geom_xpos .*another model"):
    sf.collision(sim.m, other.d)
  mjw.step(sim.m, sim.d)
  collider.reset_worlds(sim.d)
  mjw.step(sim.m, sim.d)
  assert int(sim.d.nacon.numpy()[0]) > 0


def test_models_the_plugin_adds_to_keep_its_pipeline():
  """Meshes (MPR), heightfields and non-convex meshes keep the plugin's pipeline."""
  for scene in ("convex_pile", "terrain", "nonconvex"):
    sim = load(scene)
    assert not sf.install(sim.mjm, sim.m).stock_path, scene


def test_a_swapped_model_array_reaches_the_kernels():
  """Domain randomization may put a new array in the model (m.geom_friction = ...): the kernels'
  mixing struct is made again from it, so the contacts carry the new friction (MuJoCo mixes the
  larger of the two geoms': halving every geom's halves every contact's)."""
  sim = load("convex_pile", nworld=1)
  sf.install(sim.mjm, sim.m, sf.Options(warm_start=False))  # the second call repeats the first's geometry
  sf.collision(sim.m, sim.d)
  n = contacts(sim.d, 0).n
  assert n > 0
  dist_before = sim.d.contact.dist.numpy()[:n].copy()
  mu_before = sim.d.contact.friction.numpy()[:n, 0].copy()
  friction = sim.m.geom_friction.numpy()
  friction[..., 0] *= 0.5
  sim.m.geom_friction = wp.array(friction, dtype=wp.vec3)
  sf.collision(sim.m, sim.d)
  np.testing.assert_array_equal(sim.d.contact.dist.numpy()[:n], dist_before)
  np.testing.assert_allclose(sim.d.contact.friction.numpy()[:n, 0], 0.5 * mu_before, rtol=1e-6)
