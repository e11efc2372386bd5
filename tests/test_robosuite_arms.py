"""robosuite's arms as shipped (benchmarks/robosuite_arms.py): the Panda, UR5e and Sawyer with
their hands and every visual mesh install, and the plugin's contacts pass compare's check against
MuJoCo C. robosuite's files are fetched by that script into a cache (157 MB wheel): the tests skip
where the cache does not hold them, and never download."""

import importlib.util
import os

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from conftest import ROOT

import mjx_supportfield as sf
from mjx_supportfield.tools import compare

_spec = importlib.util.spec_from_file_location("robosuite_arms", os.path.join(ROOT, "benchmarks", "robosuite_arms.py"))
robosuite_arms = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(robosuite_arms)

if not os.path.isdir(os.path.join(robosuite_arms.cache_dir(), robosuite_arms.ASSETS, "robots")):
  pytest.skip("robosuite's files are not in the cache: python benchmarks/robosuite_arms.py fetches them",
              allow_module_level=True)


@pytest.fixture(scope="module")
def scenes():
  return robosuite_arms.write_scenes()


@pytest.mark.cpu_only("the scenes' MuJoCo C rollouts and compare's host checks dominate; the kernels are the suite's")
@pytest.mark.parametrize("arm", sorted(robosuite_arms.ARMS))
def test_arm_as_shipped_passes_compare(scenes, arm):
  """Installs with every visual mesh (they get nothing), and on states along MuJoCo C's rollout
  the plugin misses at most 2 % of C's deep points, has no worse normal and no contact off its
  shapes."""
  mjm = mujoco.MjModel.from_xml_path(scenes[arm])
  visual = (mjm.geom_contype == 0) & (mjm.geom_conaffinity == 0)
  assert visual.sum() > 20
  collider = sf.install(mjm, mjw.put_model(mjm))
  visual_meshes = set(np.asarray(mjm.geom_dataid)[visual & (mjm.geom_type == mujoco.mjtGeom.mjGEOM_MESH)])
  assert not visual_meshes & set(collider.collided_meshes)
  report = compare.compare(scenes[arm], steps=200, samples=3)
  assert report["impls"]["plugin"]["summary"]["deep_points_reference"] > 0
  assert compare.check(report) == []
