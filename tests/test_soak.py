"""The soak's checkpoints (benchmarks/scenelib/checkpoint.py, written and read by benchmarks/soak.py): a
resumed soak continues the state exactly, a mismatched one is refused."""

import os
import subprocess
import sys

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


def test_ground_finds_a_body_through_the_terrain():
  """The soak's ground check: nothing is through the ground at the keyframe; a robot's trunk moved
  under the heightfield's surface in one world is reported with that world and body."""
  soak = _soak_module()
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "models", "real", "quadruped_rough.xml"))
  m = mjw.put_model(mjm)
  mjd = soak.real_scenes.initial_data(mjm)
  d = mjw.put_data(mjm, mjd, nworld=3, nconmax=64, njmax=256)
  mjw.kinematics(m, d)
  ground = soak.Ground(mjm)
  assert ground.bodies_through(d) == []
  trunk = soak.real_scenes.free_bodies(mjm)[0]
  qpos = d.qpos.numpy()
  qpos[1, mjm.jnt_qposadr[mjm.body_jntadr[trunk]] + 2] -= 1.0  # a metre down: under any tile
  d.qpos.assign(qpos)
  mjw.kinematics(m, d)
  assert (1, mjm.body(trunk).name) in ground.bodies_through(d)
  assert all(w == 1 for w, _ in ground.bodies_through(d))


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
