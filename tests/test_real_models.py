"""The real-model scenes of models/real/ (benchmarks/scenelib/real_scenes.py; benchmarks/fidelity.py judges
the plugin on them): they load and compile in MuJoCo, their scripted MuJoCo C rollouts do what the
scene is for, and the plugin installs on them."""

import importlib.util
import os
import re

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import MODELS
from scenelib import real_scenes

REAL = os.path.join(MODELS, "real")
SCENES = sorted(real_scenes.SCENES)


def _rollout_end(name: str) -> tuple[mujoco.MjModel, mujoco.MjData, dict]:
  """MuJoCo C's scripted rollout of a scene: its last state (forward-computed) and contact figures."""
  scene = real_scenes.SCENES[name]
  mjm = real_scenes.load(name)
  nstep = int(round(scene.seconds / mjm.opt.timestep))
  ref = real_scenes.rollout_mujoco(scene, mjm, real_scenes.initial_data(mjm).qpos.copy(), nstep)
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = ref["qpos"][-1]
  mujoco.mj_forward(mjm, mjd)
  return mjm, mjd, ref


def _script(name: str):
  """models/real/<name>.py (a scene's script) as a module."""
  spec = importlib.util.spec_from_file_location(name, os.path.join(REAL, f"{name}.py"))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def test_every_scene_file_is_in_the_suite():
  files = {f for f in os.listdir(REAL) if f.endswith(".xml") and f not in ("go1.xml", "g1.xml")}  # robots alone
  assert files == {real_scenes.SCENES[s].xml for s in SCENES}


@pytest.mark.parametrize("name", SCENES)
def test_scene_compiles_with_named_collision_geoms(name):
  mjm = real_scenes.load(name)
  mjd = real_scenes.initial_data(mjm)
  assert mjd.ncon > 0 or name in ("bin_drop", "polyhedra")  # the drops start in the air
  collides = (mjm.geom_contype != 0) | (mjm.geom_conaffinity != 0)
  unnamed = [g for g in np.flatnonzero(collides) if not mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g)]
  assert not unnamed, f"{name}: collision geoms {unnamed} have no name (reports group by named pair)"
  assert np.all(np.isfinite(mjd.qpos))


@pytest.mark.parametrize("name", SCENES)
def test_mujoco_rollout_does_the_task(name):
  mjm, mjd, ref = _rollout_end(name)
  assert np.all(np.isfinite(ref["qpos"]))
  assert not [w for w in mjd.warning if w.number], f"{name}: MuJoCo warnings"
  assert ref["ncon"].max() >= 10, f"{name}: too few contacts for a fidelity scene"
  assert not real_scenes.fallen_through(mjm, mjd, real_scenes.static_geoms(mjm))
  outcome = real_scenes.SCENES[name].outcome(mjm, mjd, real_scenes.initial_data(mjm))
  if name == "gripper_grasp":
    assert outcome["can_lift_m"] > 0.12  # the grasp holds: carriage raised 15 cm
  elif name == "bin_drop":
    assert outcome["objects_in_bin"] == outcome["objects"]
  elif name == "arm_sweep":
    assert outcome["objects_on_table"] == outcome["objects"]
    moved = [np.linalg.norm(ref["qpos"][-1][a:a + 2] - ref["qpos"][0][a:a + 2])
             for a in (mjm.jnt_qposadr[mjm.body_jntadr[b]] for b in real_scenes.free_bodies(mjm))]
    assert sum(d > 0.05 for d in moved) >= 4, "the sweep should push most objects"
  elif name == "quadruped_terrain":
    assert outcome["trunk_up_z"] > 0.9 and outcome["trunk_z_m"] > 0.2  # standing, not fallen over
  elif name == "quadruped_rough":
    assert outcome["robots_upright"] == outcome["robots"] == 4 and outcome["lowest_trunk_rise_m"] > -0.15
  elif name == "humanoid_rough":
    assert outcome["robots_down"] == outcome["robots"] == 2  # toppled onto the terrain, not through it
  elif name == "polyhedra":
    assert outcome["polyhedra_in_mug"] >= 3


def test_squeeze_deepens_contacts():
  mjm = real_scenes.load("bin_drop")
  scene = real_scenes.SCENES["bin_drop"]
  ref = real_scenes.rollout_mujoco(scene, mjm, real_scenes.initial_data(mjm).qpos.copy(), 750)
  mjd = mujoco.MjData(mjm)
  before, _ = real_scenes.deepest_penetration(mjm, mjd, ref["qpos"][-1])
  after, _ = real_scenes.deepest_penetration(mjm, mjd, real_scenes.squeeze(mjm, ref["qpos"][-1]))
  assert after > before + 0.5e-3


def test_replay_repeats_mujoco_own_rollout():
  """replay_mujoco from a MuJoCo C rollout's own state (qpos, qvel) under the scene's controls runs
  that rollout again: the same deepest penetration, at the same step. The window is the grasp's
  fingers closing on the can (0.5-0.8 s), where the controls move the fingers: a replay that held
  the controls still or dropped the velocities would press less."""
  name = "gripper_grasp"
  scene = real_scenes.SCENES[name]
  mjm = real_scenes.load(name)
  start, nstep = 300, 60
  mjd = real_scenes.initial_data(mjm)
  judge = mujoco.MjData(mjm)
  depths = []
  for step in range(start + nstep + 1):
    if step == start:
      qpos, qvel = mjd.qpos.copy(), mjd.qvel.copy()
    if step >= start:
      depths.append(real_scenes.deepest_penetration(mjm, judge, mjd.qpos)[0])
    mjd.ctrl[:] = real_scenes.control(scene, mjm, step)
    mujoco.mj_step(mjm, mjd)
  replay = real_scenes.replay_mujoco(scene, mjm, qpos, qvel, start, nstep)
  assert max(depths) > 0.3e-3  # the fingers press into the can
  # the replay's solver starts cold (no warm start), so the depths agree to its tolerance only
  np.testing.assert_allclose(replay["max_penetration"], max(depths), rtol=1e-3)
  assert replay["step"] == start + int(np.argmax(depths))


def test_quadruped_terrain_is_what_its_script_writes():
  spec = _script("make_quadruped_terrain").build()
  committed = mujoco.MjModel.from_xml_path(os.path.join(REAL, "quadruped_terrain.xml"))
  built = spec.compile()
  np.testing.assert_allclose(committed.hfield_data, built.hfield_data, atol=1e-5)  # the MJCF keeps 6 digits
  assert committed.nu == built.nu == 12 and committed.nkey == 1


def test_quadruped_rough_is_what_its_script_writes():
  committed = mujoco.MjModel.from_xml_path(os.path.join(REAL, "quadruped_rough.xml"))
  built = _script("make_quadruped_rough").build().compile()
  np.testing.assert_allclose(committed.hfield_data, built.hfield_data, atol=1e-5)  # the MJCF keeps 6 digits
  assert committed.nu == built.nu == 48 and committed.nhfield == 4 and committed.nkey == 1


def test_humanoid_rough_is_what_its_script_writes():
  committed = mujoco.MjModel.from_xml_path(os.path.join(REAL, "humanoid_rough.xml"))
  built = _script("make_humanoid_rough").build().compile()
  np.testing.assert_allclose(committed.hfield_data, built.hfield_data, atol=1e-5)
  np.testing.assert_allclose(committed.actuator_gainprm[:, 0], built.actuator_gainprm[:, 0], rtol=1e-5)
  assert committed.nu == built.nu == 58 and committed.nkey == 1


def test_readme_lists_every_asset_with_a_licence():
  readme = open(os.path.join(REAL, "README.md")).read()
  for root, _, files in os.walk(os.path.join(REAL, "meshes")):
    for f in files:
      assert f in readme, f"models/real/README.md does not list {f}"
  for licence in re.findall(r"LICENSE-[\w_]+", readme):
    assert os.path.exists(os.path.join(REAL, licence)), licence


@pytest.mark.parametrize("name", SCENES)
def test_plugin_installs(name):
  mjm = real_scenes.load(name)
  m = mjw.put_model(mjm)
  collider = sf.install(mjm, m)
  assert sf.get_collider(m) is collider
  sf.uninstall(m)
