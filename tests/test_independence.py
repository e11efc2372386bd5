"""Worlds are independent: a world's contacts and trajectory depend on its own state and history
alone, not on the other worlds of the batch nor on its place in it (benchmarks/independence.py
steps the batches; its docstring says why they have the same size).

The plugin keeps state between calls per world: each world's call count, its warm-start entries
(normal, depth and the deep-pair check's last call, per geom pair) and its sweep-and-prune order;
the deep-pair check's queue gives each world rows of its own. A masked reset drops exactly the
masked worlds' state.
"""

import importlib.util
import os

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import ROOT
from conftest import bitwise_repeatable
from conftest import load
from conftest import on_gpu
from conftest import set_qpos
from conftest import sorted_rows
from conftest import world_contact_fields
from mjx_supportfield.stages import deep_pairs
from mjx_supportfield.stages import narrowphase

_spec = importlib.util.spec_from_file_location("independence", os.path.join(ROOT, "benchmarks", "independence.py"))
independence = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(independence)

STEPS = 500
MESHES = os.path.join(ROOT, "tests", "data", "repro", "meshes")
CPU_ONLY = "MuJoCo Warp's step sums constraint forces in atomic order on a GPU; the GPU lane checks one collision call"
# every preset on a mesh pile, real robots with deep and resting mesh pairs, and terrain
EVERY_PRESET = ["convex_pile", "polyhedra", "bin_drop", "quadruped_terrain"]
DEFAULT_ONLY = ["gripper_grasp", "arm_sweep", "terrain"]
CASES = [(s, p) for s in EVERY_PRESET for p in independence.PRESETS] + [(s, "default") for s in DEFAULT_ONLY]


def _assert_independent(r: dict):
  assert r["identical_worlds"] is None, (
    f"identical worlds parted at step {r['identical_worlds']}, {r['apart_m']:.3g} m apart at the end")
  assert r["among_copies"] is None, f"a world among others left its run among copies at step {r['among_copies']}"


@pytest.mark.cpu_only(CPU_ONLY)
@pytest.mark.slow
@pytest.mark.parametrize("scene,preset", CASES)
def test_identical_worlds_stay_identical(scene, preset):
  """X in the first and last of 3 worlds, another between them, and X among copies of itself:
  bitwise the same qpos for 500 steps."""
  r = independence.check(independence.SCENES[scene], independence.PRESETS[preset], STEPS, 3)
  _assert_independent(r)


@pytest.mark.cpu_only(CPU_ONLY)
@pytest.mark.slow
@pytest.mark.parametrize("scene", ["polyhedra", "quadruped_terrain"])
def test_a_world_among_63_others(scene):
  """X as world 63 of 64 among 62 other worlds (and world 0) runs as world 0 of 64 copies."""
  r = independence.check(independence.SCENES[scene], {}, 200, 64)
  _assert_independent(r)


@pytest.mark.cpu_only(CPU_ONLY)
@pytest.mark.slow
@pytest.mark.parametrize("scene", ["polyhedra", "bin_drop"])
def test_masked_reset_clears_exactly_the_masked_worlds(scene):
  """Worlds 1 and 2 of 4 reset at step 101 repeat a fresh Data's run bit for bit, while worlds 0
  and 3 (X) go on as X's copies do."""
  r = independence.check(independence.SCENES[scene], {}, 400, 4, reset_at=101)
  _assert_independent(r)
  assert r["reset_worlds"] is None, f"the reset worlds left a fresh Data's run at step {r['reset_worlds']}"


TWO_DEEP_PAIRS = """
<mujoco>
  <compiler meshdir="{meshes}"/>
  <asset><mesh name="dodeca" file="dodecahedron.stl" scale=".0014 .0014 .0014"/>
         <mesh name="tetra" file="tetrahedron.stl" scale=".016 .016 .016"/></asset>
  <worldbody>
    <body name="dodeca" pos="-0.0049174 -0.0230528 0.0129967" quat="-0.9031375 -0.1159824 -0.3806137 0.1613190">
      <freejoint/><geom type="mesh" mesh="dodeca"/></body>
    <body name="tetra" pos="0.0175709 -0.0056327 0.0225083" quat="-0.4427527 0.2788314 0.1031366 0.8459231">
      <freejoint/><geom type="mesh" mesh="tetra"/></body>
    <body name="dodeca2" pos="0.4950826 -0.0230528 0.0129967" quat="-0.9031375 -0.1159824 -0.3806137 0.1613190">
      <freejoint/><geom type="mesh" mesh="dodeca"/></body>
    <body name="tetra2" pos="0.5175709 -0.0056327 0.0225083" quat="-0.4427527 0.2788314 0.1031366 0.8459231">
      <freejoint/><geom type="mesh" mesh="tetra"/></body>
  </worldbody>
</mujoco>
"""


def _apart(mjm) -> np.ndarray:
  """qpos of the two-deep-pairs model with every body lifted apart (no deep pair)."""
  q = mjm.qpos0.copy()
  for b in range(1, mjm.nbody):
    q[mjm.jnt_qposadr[mjm.body_jntadr[b]] + 2] += 0.2 * b
  return q


def test_deep_pair_rows_are_each_worlds_own(monkeypatch):
  """Each world's deep answers beyond its own rows of the check's queue keep MPR's answer,
  whatever the other worlds queued: world 1's two deep pairs (one row a world here) get the same
  contacts beside a world with no deep pair as beside a copy of themselves."""
  monkeypatch.setattr(deep_pairs, "DEEP_PAIRS_PER_WORLD", 1)
  mjm = mujoco.MjModel.from_xml_string(TWO_DEEP_PAIRS.format(meshes=MESHES))
  out = {}
  for batch in ("copies", "beside_none"):
    sim = load(None, nworld=2, mjm=mjm)
    collider = sf.install(mjm, sim.m)
    first = mjm.qpos0 if batch == "copies" else _apart(mjm)
    set_qpos(sim, np.stack([first, mjm.qpos0]))
    with bitwise_repeatable(sim.m):
      sf.collision(sim.m, sim.d)
    stats = collider.stats(sim.d)
    out[batch] = sorted_rows(world_contact_fields(sim.d, 1))
    assert stats["deep_pairs_unchecked"] == (2 if batch == "copies" else 1), stats
  for field, value in out["copies"].items():
    np.testing.assert_array_equal(value, out["beside_none"][field], err_msg=field)


def _drift(mjm, ncall: int, seed: int) -> list:
  """qpos of the two-deep-pairs model drifting call by call: each free body moved by up to
  1 mm and turned by up to 0.03 rad a call: the pairs stay deep, and their nearest faces change."""
  rng = np.random.default_rng(seed)
  q = mjm.qpos0.copy()
  out = []
  for _ in range(ncall):
    for b in range(1, mjm.nbody):
      adr = mjm.jnt_qposadr[mjm.body_jntadr[b]]
      q[adr:adr + 3] += rng.uniform(-1e-3, 1e-3, 3)
      quat = q[adr + 3:adr + 7]
      mujoco.mju_quatIntegrate(quat, rng.uniform(-1.0, 1.0, 3), 0.03)
      q[adr + 3:adr + 7] = quat / np.linalg.norm(quat)
    out.append(q.copy())
  return out


def test_contacts_of_identical_histories_are_identical():
  """One collision call a state, the two deep pairs drifting: the same states in worlds 0 and 3,
  other drifts in world 1 and the bodies apart in world 2. Worlds 0 and 3 get the same contacts
  (as sets of rows, bitwise) at every call, warm-started from identical histories, through the
  deep-pair check's verdicts and rechecks, on the CPU and the GPU."""
  mjm = mujoco.MjModel.from_xml_string(TWO_DEEP_PAIRS.format(meshes=MESHES))
  ncall = 3 * narrowphase.DEEP_RECHECK_CALLS
  mine, other = _drift(mjm, ncall, 0), _drift(mjm, ncall, 1)
  sim = load(None, nworld=4, mjm=mjm)
  collider = sf.install(mjm, sim.m)
  checked = reused = 0
  with bitwise_repeatable(sim.m):
    for q, o in zip(mine, other):
      set_qpos(sim, np.stack([q, o, _apart(mjm), q]))
      sf.collision(sim.m, sim.d)
      stats = collider.stats(sim.d)
      checked += stats["deep_pairs"]
      reused += stats["deep_pairs_reused"]
      a, b = sorted_rows(world_contact_fields(sim.d, 0)), sorted_rows(world_contact_fields(sim.d, 3))
      assert len(a["dist"]) > 0
      for field in a:
        np.testing.assert_array_equal(a[field], b[field], err_msg=field)
  assert checked > 0 and reused > 0  # the deep-pair check ran, and its verdicts were kept between checks


def test_warm_start_misses_are_counted_per_world():
  sim = load("convex_pile", nworld=3)
  collider = sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  sf.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  per_world = stats["warm_start_misses_per_world"]
  assert len(per_world) == 3 and sum(per_world) == stats["warm_start_misses"]
  if not on_gpu():
    assert per_world == [0, 0, 0]  # a resting pile: every warm start holds
