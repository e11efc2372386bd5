"""The soak's checkpoints (benchmarks/scenelib/checkpoint.py, written and read by benchmarks/soak.py): a
resumed soak continues the state exactly, a mismatched one is refused."""

import os
import subprocess
import sys
import types

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from conftest import ROOT

from mjx_supportfield import Options
from scenelib import checkpoint
from mjx_supportfield.driver import install

SCENE = os.path.join(ROOT, "benchmarks", "scenes", "pile_32_128.xml")
NSTEP = 10
NCONMAX = 256  # contacts per world: room for the pile's at rest


def _moving_data(mjm, m, nworld):
  """Data at the scene's initial state with small random velocities, as a soak starts."""
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=NCONMAX, njmax=6 * NCONMAX)
  rng = np.random.default_rng(0)
  d.qvel.assign((0.05 * rng.uniform(-1, 1, size=(nworld, mjm.nv))).astype(np.float32))
  mjw.forward(m, d)
  return d


def _meta(d, ref):
  return {"format": checkpoint.FORMAT, "scene": os.path.basename(SCENE), "scene_path": SCENE,
          "scene_sha256": checkpoint.scene_sha256(SCENE), "nworld": d.nworld, "ref": ref, "versions": {}}


@pytest.mark.slow
def test_resume_continues_bitwise(tmp_path):
  """Without the plugin's warm start (the one cache a resume loses), N steps, a checkpoint, and N
  more steps from a fresh Data give the qpos of 2N steps in one go, bit for bit."""
  mjm = mujoco.MjModel.from_xml_path(SCENE)
  mjm.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
  m = mjw.put_model(mjm)
  install(mjm, m, Options(warm_start=False))
  d, ref = _moving_data(mjm, m, 2), {"nconmax": NCONMAX}
  for _ in range(NSTEP):
    mjw.step(m, d)
  path = str(tmp_path / "ck.npz")
  saved = checkpoint.save_checkpoint(path, d, _meta(d, ref), 15.0)
  assert saved["warmstart_saved"]
  for _ in range(NSTEP):
    mjw.step(m, d)
  meta, state = checkpoint.load_checkpoint(path)
  assert meta["ref"] == ref and set(state) == set(checkpoint.STATE) | {checkpoint.WARMSTART}
  d2 = checkpoint.resume_start(mjm, m, meta, state)
  for _ in range(NSTEP):
    mjw.step(m, d2)
  np.testing.assert_array_equal(d2.qpos.numpy(), d.qpos.numpy())
  np.testing.assert_array_equal(d2.time.numpy(), d.time.numpy())


def test_a_failing_chunks_start_restores_its_state_and_controls(tmp_path):
  """soak.py --save-failing writes a chunk start's state with its controls (save_state): read
  back into a fresh Data it gives that state and those controls, from which the chunk replays."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  m = mjw.put_model(mjm)
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  d = mjw.put_data(mjm, mjd, nworld=2, nconmax=256, njmax=1024)
  rng = np.random.default_rng(1)
  d.ctrl.assign(rng.uniform(-1, 1, size=(2, mjm.nu)).astype(np.float32))
  d.qvel.assign(rng.uniform(-0.1, 0.1, size=(2, mjm.nv)).astype(np.float32))
  state = checkpoint.read_state(d, checkpoint.STATE + (checkpoint.WARMSTART, "ctrl"))
  path = str(tmp_path / "failing.npz")
  meta = dict(_meta(d, {"nconmax": 256}), start_step=500, failed_at=1500, what=["a geom stuck"])
  checkpoint.save_state(path, state, meta)
  meta2, state2 = checkpoint.load_checkpoint(path)
  assert meta2["start_step"] == 500 and meta2["failed_at"] == 1500 and set(state2) == set(state)
  d2 = checkpoint.resume_start(mjm, m, meta2, state2)
  np.testing.assert_array_equal(d2.ctrl.numpy(), d.ctrl.numpy())
  np.testing.assert_array_equal(d2.qvel.numpy(), d.qvel.numpy())


@pytest.mark.parametrize("nworld, nconmax, needle", [(8, None, "--nworld 8"), (None, 5, "--nconmax 5")])
def test_mismatch_refused(nworld, nconmax, needle):
  meta = {"scene": "pile_32_128.xml", "scene_sha256": checkpoint.scene_sha256(SCENE), "nworld": 2,
          "ref": {"nconmax": 100}, "versions": {}}
  with pytest.raises(checkpoint.CheckpointError, match=needle):
    checkpoint.check_resume(meta, "ck.npz", SCENE, meta["scene_sha256"], nworld, nconmax)


def test_other_scene_refused():
  meta = {"scene": "pile_32_128.xml", "scene_sha256": checkpoint.scene_sha256(SCENE), "nworld": 2,
          "ref": {"nconmax": 100}, "versions": {}}
  other = os.path.join(ROOT, "benchmarks", "scenes", "primitives_32.xml")
  with pytest.raises(checkpoint.CheckpointError, match="sha256"):
    checkpoint.check_resume(meta, "ck.npz", other, checkpoint.scene_sha256(other), 2, None)


def test_script_exits_with_the_refusal(tmp_path):
  """benchmarks/soak.py turns a refused checkpoint into its message on stderr and exit status 2."""
  missing = str(tmp_path / "none.npz")
  run = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "soak.py"), "--resume", missing],
                       capture_output=True, text=True, cwd=ROOT)
  assert run.returncode == 2 and f"soak: no checkpoint at {missing}" in run.stderr


def _soak_module():
  sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
  import soak  # noqa: PLC0415 - a script of benchmarks/, not a package

  return soak


def test_ground_finds_a_geom_through_the_terrain():
  """The soak's ground check: nothing is through the ground at the keyframe; a robot moved a metre
  down in one world has its geoms reported with that world, and one moved off the terrain is
  off it, its geoms not judged."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  m = mjw.put_model(mjm)
  mjd = soak.real_scenes.initial_data(mjm)
  d = mjw.put_data(mjm, mjd, nworld=3, nconmax=64, njmax=256)
  mjw.kinematics(m, d)
  ground = soak.Ground(mjm)
  assert ground.geoms_through(d) == []
  assert not ground.off_terrain(d).any()
  trunk = soak.real_scenes.free_bodies(mjm)[0]
  adr = mjm.jnt_qposadr[mjm.body_jntadr[trunk]]
  qpos = d.qpos.numpy()
  qpos[1, adr + 2] -= 1.0  # a metre down: under any tile
  qpos[2, adr:adr + 2] += 10.0  # ten metres away: beyond the terrain, falling
  qpos[2, adr + 2] -= 1.0
  d.qpos.assign(qpos)
  mjw.kinematics(m, d)
  through = ground.geoms_through(d)
  assert through and all(w == 1 for w, _ in through)
  assert all(mjm.body_rootid[mjm.geom(name).bodyid[0]] == trunk for _, name in through)
  np.testing.assert_array_equal(ground.off_terrain(d), [False, False, True])


def _host(a: np.ndarray):
  """One world's array as a batch with .numpy(), as soak.Ground reads MuJoCo Warp's data."""
  return types.SimpleNamespace(numpy=lambda: a[None])


def test_a_foot_hanging_over_the_edge_under_the_slab_is_not_through_the_ground():
  """A heightfield is a slab hfield_size[3] thick: a foot that hung over the terrain's edge and
  swung under the slab, its robot standing on the terrain, is not in the ground (MuJoCo C has no
  contact there either); the same foot inside the slab is, and so is every geom of a robot whose
  trunk went under the surface, below the slab too."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  mjd = soak.real_scenes.initial_data(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  ground = soak.Ground(mjm)
  tile = mjm.geom("terrain_rough").id
  base = mjd.geom_xpos[tile][2] - mjm.hfield_size[mjm.geom_dataid[tile]][3]
  foot = mjm.geom("r0_FR_foot_collision").id

  def through(foot_z, trunk_z=None):
    geom_xpos, xpos = mjd.geom_xpos.copy(), mjd.xpos.copy()
    geom_xpos[foot, 2] = foot_z
    if trunk_z is not None:
      xpos[soak.real_scenes.free_bodies(mjm)[0], 2] = trunk_z
    view = types.SimpleNamespace(nworld=1, geom_xpos=_host(geom_xpos), xpos=_host(xpos))
    return ground.geoms_through(view)

  assert through(base - 0.01) == []
  assert through(base + 0.01) == [(0, "r0_FR_foot_collision")]
  assert through(base - 0.01, trunk_z=base - 0.02) == [(0, "r0_FR_foot_collision")]


def test_a_geom_in_the_ground_fails_only_at_two_chunk_ends_in_a_row():
  """check_chunk counts a geom whose centre is in the ground and fails the chunk only when the
  same geom of the same world was there at the chunk end before (a jam MuJoCo C also makes and
  leaves again is reported, a geom that stays through the ground fails)."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  mjm.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
  m = mjw.put_model(mjm)
  collider = install(mjm, m)
  d = mjw.put_data(mjm, soak.real_scenes.initial_data(mjm), nworld=2, nconmax=64, njmax=256)
  mjw.forward(m, d)
  ground = soak.Ground(mjm)
  trunk = soak.real_scenes.free_bodies(mjm)[0]
  qpos = d.qpos.numpy()
  qpos[1, mjm.jnt_qposadr[mjm.body_jntadr[trunk]] + 2] -= 1.0  # world 1's first robot a metre down
  d.qpos.assign(qpos)
  mjw.forward(m, d)
  row, bad, through = soak.check_chunk(d, collider, 2, None, ground)
  assert row["geoms_through_ground"] == len(through) > 0 and row["geoms_stuck"] == 0 and not bad
  row, bad, _ = soak.check_chunk(d, collider, 2, None, ground, set(through[:2]) | {(0, through[0][1])})
  assert row["geoms_stuck"] == 2 and bad and "two chunk ends in a row" in bad[0]


def test_a_reset_lifts_robots_out_of_the_ground():
  """A reset shifts each robot horizontally from the keyframe and lifts it clear of the bumps it
  would sink into there: no geom of a reset world is in the ground more than the solver's slack."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  m = mjw.put_model(mjm)
  d = mjw.put_data(mjm, soak.real_scenes.initial_data(mjm), nworld=6, nconmax=128, njmax=512)
  episodes = soak.Episodes(mjm, m, 6, 0.0, 1)
  soak.RESET_SHIFT, shift = 0.3, soak.RESET_SHIFT  # far enough to land on other bumps
  try:
    episodes.reset(d, 0)
  finally:
    soak.RESET_SHIFT = shift
  static = set(soak.real_scenes.static_geoms(mjm))
  mjd = mujoco.MjData(mjm)
  for w in range(6):
    mjd.qpos[:] = d.qpos.numpy()[w]
    mujoco.mj_forward(mjm, mjd)
    sunk = [c.dist for c in mjd.contact[:mjd.ncon] if (c.geom[0] in static) != (c.geom[1] in static)]
    assert min(sunk, default=0.0) > -1e-6, (w, min(sunk))


def test_masked_reset_touches_only_the_worlds_it_ends():
  """Episodes.reset resets the worlds whose episode ends (to the keyframe, shifted) and leaves
  the others' state as it was."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  m = mjw.put_model(mjm)
  d = mjw.put_data(mjm, soak.real_scenes.initial_data(mjm), nworld=4, nconmax=64, njmax=256)
  d.qpos.assign(d.qpos.numpy() + 0.01)
  before = d.qpos.numpy()
  episodes = soak.Episodes(mjm, m, 4, 0.0, 2)
  episodes.reset(d, 0)  # chunk 0: worlds with (0 + w) % 2 == 1
  after = d.qpos.numpy()
  assert episodes.resets == 2
  np.testing.assert_array_equal(after[[0, 2]], before[[0, 2]])
  for w in (1, 3):
    assert np.abs(after[w] - episodes.qpos0).max() <= soak.RESET_SHIFT + 1e-6


@pytest.mark.parametrize("engine", ["mujoco_c", "plugin"])
def test_soak_rate_runs_the_soaks_driving_and_check(engine):
  """soak_rate.py drives MuJoCo C's or MuJoCo Warp's worlds as soak.py drives the plugin's and
  counts the same check: every world judged at each check unless its robot left the terrain, and
  a geom pushed into the ground is found."""
  import soak_rate

  report = soak_rate.run(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"), 2, 100, 50, engine)
  assert 0 < report["world_checks"] <= 4
  assert report["geoms_in_ground"] == sum(len(f["geoms"]) for f in report["found"])
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  soak = _soak_module()
  ground = soak.Ground(mjm)
  mjd = soak.real_scenes.initial_data(mjm)
  mujoco.mj_kinematics(mjm, mjd)
  foot = mjm.geom("r0_FR_foot_collision").id
  view = soak_rate.types.SimpleNamespace(nworld=1, geom_xpos=soak_rate._batch([mjd], "geom_xpos"),
                                          xpos=soak_rate._batch([mjd], "xpos"))
  assert not ground.geoms_through(view)
  mjd.geom_xpos[foot, 2] -= 0.05  # 3 cm under the rough tile's surface, in its slab
  assert ground.geoms_through(view) == [(0, "r0_FR_foot_collision")]


@pytest.mark.parametrize("engine", ["plugin", "mujoco_c"])
def test_replay_finds_the_failing_worlds_robot_in_the_ground(tmp_path, engine):
  """benchmarks/soak_replay.py puts the world a --save-failing checkpoint names (here world 1, its
  first robot a metre down) into one world of the engine and finds its geoms in the ground."""
  sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
  import soak_replay  # noqa: PLC0415 - a script of benchmarks/, not a package

  soak = _soak_module()
  scene = os.path.join(ROOT, "models", "real", "quadruped_rough.xml")
  mjm = mujoco.MjModel.from_xml_path(scene)
  d = mjw.put_data(mjm, soak.real_scenes.initial_data(mjm), nworld=2, nconmax=256, njmax=1024)
  trunk = soak.real_scenes.free_bodies(mjm)[0]
  qpos = d.qpos.numpy()
  qpos[1, mjm.jnt_qposadr[mjm.body_jntadr[trunk]] + 2] -= 1.0
  d.qpos.assign(qpos)
  state = checkpoint.read_state(d, checkpoint.STATE + (checkpoint.WARMSTART, "ctrl"))
  meta = {"format": checkpoint.FORMAT, "scene": "quadruped_rough.xml", "scene_path": scene,
          "scene_sha256": checkpoint.scene_sha256(scene), "nworld": 2, "ref": {"nconmax": 256}, "versions": {},
          "start_step": 500, "failed_at": 1500, "what": ["2 geoms in the ground at two chunk ends in a row, "
                                                         "first (world, geom) [(1, 'r0_trunk_collision')]"]}
  path = str(tmp_path / "failing.npz")
  checkpoint.save_state(path, state, meta)
  result = soak_replay.replay(path, steps=20, check_every=10, engine=engine)
  assert result["world"] == 1 and result["first_in_ground"] == 510 and result["most_in_ground"] > 0
  with pytest.raises(ValueError, match="--world 5"):
    soak_replay.replay(path, world=5, steps=1, engine=engine)
