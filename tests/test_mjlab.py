"""mjlab (docs/mjlab.md): the plugin under one of its tasks, on the CPU. Skipped where mjlab is
not installed (CI does not install it; mjlab 1.6.0 pins another MuJoCo Warp)."""

import importlib.util
import os

import pytest
from conftest import ROOT

if importlib.util.find_spec("mjlab") is None:
  pytest.skip("mjlab is not installed (docs/mjlab.md says how)", allow_module_level=True)

_spec = importlib.util.spec_from_file_location("mjlab_tasks", os.path.join(ROOT, "benchmarks", "mjlab_tasks.py"))
mjlab_tasks = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mjlab_tasks)


@pytest.mark.cpu_only("the GPU lane of mjlab is benchmarks/mjlab_tasks.py")
@pytest.mark.slow
def test_go1_on_rough_terrain_with_the_plugin():
  """Unitree Go1 on mjlab's rough terrain (heightfields and box stairs, its visual meshes kept),
  the plugin installed under mjlab, stepped with random actions and mjlab's resets: contacts,
  no NaN, nothing through the ground, no overflow."""
  import mjx_supportfield as sf

  mjlab_tasks.stub_optional_imports()
  env = mjlab_tasks.make_env("Mjlab-Velocity-Rough-Unitree-Go1", 2, "cpu", plugin=True)
  collider = sf.get_collider(env.sim.wp_model)
  assert collider is not None and collider.hfield.has_pairs
  row = mjlab_tasks.run(env, steps=40, warmup=2)
  assert row["contacts_per_world"] > 0
  assert row["nonfinite_worlds"] == 0 and row["bodies_below_ground"] == 0 and row["buffer_overflow"] == []
  assert collider.stats(env.sim.wp_data)["path"] == "plugin"
