"""Warm start: the cache keeps exactly the previous call's contact pairs, and warm-started MPR
gives the contacts of a cold start, on a static scene and along a trajectory where pairs come,
go and change side."""

import os

import mujoco
import numpy as np
import pytest
import warp as wp
from conftest import angle_deg
from conftest import contact_table
from conftest import load
from conftest import set_qpos

import mjx_supportfield as sf
from mjx_supportfield.stages import warmstart

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "scenes")


@wp.kernel
def _insert_keys(cache_stamp: wp.array2d(dtype=int), cache_key: wp.array2d(dtype=int),
                 cache_value: wp.array2d(dtype=wp.vec4), now: int, keys: wp.array2d(dtype=int)):
  w, i = wp.tid()
  k = keys[w, i]
  if k >= 0:
    warmstart.insert(cache_stamp, cache_key, cache_value, now, w, k, wp.vec4(float(k), 0.0, 0.0, 1.0))


@wp.kernel
def _lookup_keys(cache_stamp: wp.array2d(dtype=int), cache_key: wp.array2d(dtype=int),
                 cache_value: wp.array2d(dtype=wp.vec4), cache_checked: wp.array2d(dtype=int), now: int,
                 keys: wp.array2d(dtype=int), out: wp.array2d(dtype=wp.vec4)):
  w, i = wp.tid()
  value, _ = warmstart.lookup(cache_stamp, cache_key, cache_value, cache_checked, now, w, keys[w, i])
  out[w, i] = value


def _cycle(cache, now, insert_keys, probe_keys):
  """Looks up probe_keys as call ``now``, then inserts insert_keys as call ``now`` (like the kernel)."""
  probe = wp.array(np.asarray(probe_keys, np.int32), dtype=int, device="cpu")
  found = wp.zeros(probe.shape, dtype=wp.vec4, device="cpu")
  wp.launch(_lookup_keys, dim=probe.shape,
            inputs=[cache.slot_stamp, cache.slot_key, cache.slot_value, cache.slot_checked, now, probe],
            outputs=[found], device="cpu")
  ins = wp.array(np.asarray(insert_keys, np.int32), dtype=int, device="cpu")
  wp.launch(_insert_keys, dim=ins.shape, inputs=[cache.slot_stamp, cache.slot_key, cache.slot_value, now, ins],
            device="cpu")
  return found.numpy()


def test_cache_keeps_exactly_the_previous_call():
  rng = np.random.default_rng(0)
  nworld, nslot = 3, 64
  with wp.ScopedDevice("cpu"):
    cache = warmstart.make_cache(nworld, nslot)
  universe = np.arange(0, 4000, 7)
  previous = [set() for _ in range(nworld)]
  for now in range(1, 12):
    # each call: about 25 live keys per world, half of them carried over from the last call
    keys = np.full((nworld, 30), -1, np.int32)
    for w in range(nworld):
      carried = [k for k in previous[w] if rng.random() < 0.5]
      fresh = rng.choice(universe, size=30 - len(carried), replace=False)
      live = list(dict.fromkeys(carried + [int(k) for k in fresh]))[: rng.integers(10, 30)]
      keys[w, : len(live)] = live
    probe = np.tile(universe[:200], (nworld, 1)).astype(np.int32)
    found = _cycle(cache, now, keys, probe)
    for w in range(nworld):
      hit = {int(k) for k, v in zip(probe[w], found[w]) if v[3] > 0}
      assert hit == {k for k in previous[w] if k < universe[199] + 1}
      for k, v in zip(probe[w], found[w]):
        if v[3] > 0:
          assert v[0] == float(k)
    previous = [{int(k) for k in keys[w] if k >= 0} for w in range(nworld)]


def test_full_table_skips_inserts_without_harm():
  with wp.ScopedDevice("cpu"):
    cache = warmstart.make_cache(1, 8)
  keys = np.arange(20, dtype=np.int32)[None]
  _cycle(cache, 1, keys, keys)
  found = _cycle(cache, 2, np.full((1, 1), -1, np.int32), keys)
  hit = [int(k) for k, v in zip(keys[0], found[0]) if v[3] > 0]
  assert len(hit) == 8  # the table's slots, each with its own key
  assert all(found[0][k][0] == k for k in hit)


def test_slots_per_world():
  assert warmstart.slots_per_world(0) == 8
  assert warmstart.slots_per_world(100) == 256
  assert warmstart.slots_per_world(10**6) == warmstart.MAX_SLOTS


def _trajectory(mjm, nstate, every):
  """qpos of MuJoCo C stepping the scene (the pile falls, settles and shifts)."""
  mjd = mujoco.MjData(mjm)
  out = []
  for i in range(nstate * every):
    mujoco.mj_step(mjm, mjd)
    if i % every == every - 1:
      out.append(mjd.qpos.copy())
  return out


@pytest.fixture(scope="module")
def runs():
  """Contact tables of the same qpos sequence, collided warm and cold (twice per state: the
  second call of a state is warm-started from the first)."""
  mjm = load("convex_pile").mjm
  states = _trajectory(mjm, 10, 40)
  out = {"misses": []}
  for warm in (True, False):
    sim = load("convex_pile", mjm=mjm)
    sf.install(sim.mjm, sim.m, sf.Options(warm_start=warm))
    tables = []
    for q in states:
      set_qpos(sim, q)
      sf.collision(sim.m, sim.d)
      first = contact_table(sim.d, 0)
      sf.collision(sim.m, sim.d)
      tables.append((first, contact_table(sim.d, 0)))
      if warm:
        out["misses"].append(sf.get_collider(sim.m).stats(sim.d)["warm_start_misses"])
    out[warm] = tables
  return out


def _assert_same(warm, cold):
  assert set(warm) == set(cold)
  for pair, (dist, normal, pos) in cold.items():
    wdist, wnormal, wpos = warm[pair]
    assert abs(wdist - dist) < 1e-6, (pair, wdist, dist)
    assert angle_deg(wnormal, normal) < 0.05, pair


def test_mpr_pairs_present(runs):
  floor = 0
  assert sum(1 for t, _ in runs[False] for pair in t if floor not in pair) >= 10


@pytest.mark.parametrize("call", [0, 1])
def test_warm_equals_cold_along_the_trajectory(runs, call):
  for warm, cold in zip(runs[True], runs[False]):
    _assert_same(warm[call], cold[call])


def test_warm_start_point_lies_inside(runs):
  """The second call of a state starts every pair from its own exact normal: none may miss and
  pay a cold retry (a start point microns behind a resting contact used to)."""
  assert runs["misses"] == [0] * len(runs["misses"])


@pytest.mark.slow
def test_resting_pile_warm_starts_without_misses():
  """A settled pile's resting contacts are microns deep; warm starts must still land inside."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(SCENES, "pile_32_128.xml"))
  mjd = mujoco.MjData(mjm)
  for _ in range(400):
    mujoco.mj_step(mjm, mjd)
  sim = load(None, mjm=mjm, qpos=mjd.qpos, naconmax=4 * mjd.ncon + 64)
  sf.install(sim.mjm, sim.m)
  misses = []
  for _ in range(3):
    sf.collision(sim.m, sim.d)
    misses.append(sf.get_collider(sim.m).stats(sim.d)["warm_start_misses"])
  assert misses == [0, 0, 0]
