"""benchmarks/fidelity.py's summaries of the rollouts over worlds (no rollout run here)."""

import importlib.util
import os

import numpy as np
import pytest

FIDELITY = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "fidelity.py")


@pytest.fixture(scope="module")
def fidelity():
  spec = importlib.util.spec_from_file_location("fidelity", FIDELITY)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def _judged(per_world, on_table):
  return {"max_penetration_per_world": per_world,
          "outcome": [{"objects_on_table": n, "objects": 7} for n in on_table]}


def test_world_spread_tail_and_lost_objects(fidelity):
  """The 90th percentile and the largest of each world's deepest, and the worlds with an object off
  the table: what the median alone hides."""
  per_world = [0.001 * k for k in range(1, 11)]  # 1..10 mm
  spread = fidelity.world_spread(_judged(per_world, [7, 7, 6, 7, 7, 5, 7, 7, 7, 7]))
  assert spread["max_penetration_median_world"] == pytest.approx(5.5e-3)
  assert spread["max_penetration_p90_world"] == pytest.approx(np.percentile(per_world, 90))
  assert spread["max_penetration_p90_world"] == pytest.approx(9.1e-3)
  assert spread["max_penetration_max_world"] == pytest.approx(10e-3)
  assert spread["worlds_object_lost"] == 2


def test_world_spread_without_object_count(fidelity):
  """Scenes whose task figure counts no objects (the grasp's lift) report None, not 0."""
  spread = fidelity.world_spread({"max_penetration_per_world": [0.001, 0.002],
                                  "outcome": [{"can_lift_m": 0.15}, {"can_lift_m": 0.15}]})
  assert spread["worlds_object_lost"] is None
  assert spread["max_penetration_max_world"] == pytest.approx(0.002)


def test_world_spread_no_worlds(fidelity):
  with pytest.raises(ValueError, match="max_penetration_per_world"):
    fidelity.world_spread({"max_penetration_per_world": [], "outcome": []})


def test_tables_show_spread_and_old_results(fidelity):
  """The spread's table has a row per implementation; results written before world_spread
  (median only) still print."""
  judged = _judged([0.002, 0.004, 0.009], [7, 7, 6])
  new = {"rollouts": {"worlds": 3}}
  old = {"rollouts": {"worlds": 3}}
  for impl in ["mujoco", *fidelity.IMPLS]:
    new["rollouts"][impl] = {**judged, **fidelity.world_spread(judged)}
    old["rollouts"][impl] = {"max_penetration_median_world": 0.004}
  rows = fidelity._spread_rows({"arm_sweep": new, "old": old}, list(fidelity.IMPLS))
  assert "| arm_sweep | MuJoCo C | 4.00 | 8.00 | 9.00 | 1 of 3 |" in rows
  assert "| old | stock | 4.00 | – | – | – |" in rows
