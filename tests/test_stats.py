"""collider.stats(d): the counters as a dict, printed as a summary that stays short at any nworld."""

import json
import pickle

import mujoco_warp as mjw

import mjx_supportfield as sf
from conftest import load
from mjx_supportfield.stats import CollisionStats


def _stats(nworld=8192, **changes):
  values = {"pairs": 3 * nworld, "pairs_per_world": [3] * nworld, "dropped_pairs_per_world": [0] * nworld,
            "nonfinite_worlds": [], "dropped_contacts": 0, "warm_start_misses": 4, "hfield_mprs_unqueued": 0}
  values.update(changes)
  return CollisionStats(values)


def test_summary_is_short_at_scale():
  pairs = [3] * 8192
  pairs[17], pairs[4000] = 40, 41
  dropped = [0] * 8192
  dropped[4000] = 9
  s = _stats(pairs_per_world=pairs, dropped_pairs_per_world=dropped, nonfinite_worlds=[5, 6, 7, 8],
             dropped_contacts=12)
  text = str(s)
  assert len(text.splitlines()) <= 8 and len(text) < 1000
  assert "8192 worlds" in text and "max 41" in text
  assert text.index("world 4000: 41") < text.index("world 17: 40")  # the busiest worlds first
  assert "dropped pairs: 9 in 1 world" in text and "max_collision_pairs" in text
  assert "dropped contacts: 12" in text and "naconmax" in text
  assert "NaN or inf geom poses: 4 (5, 6, 7, ...)" in text
  assert "\n" not in repr(s) and "dropped_pairs=9" in repr(s) and "nonfinite_worlds=4" in repr(s)


def test_summary_names_the_worlds_past_their_contact_rows():
  per_world = [0] * 8192
  per_world[3], per_world[9] = 5, 7
  text = str(_stats(dropped_contacts=12, dropped_contacts_per_world=per_world))
  assert "dropped contacts: 12, 12 of them in 2 worlds past their rows (most: world 9: 7, world 3: 5)" in text
  assert "contacts_per_world" in text


def test_still_the_dict_of_raw_counters():
  s = _stats(nworld=4)
  assert isinstance(s, dict) and s["pairs_per_world"] == [3, 3, 3, 3]
  assert s == dict(s) and json.loads(json.dumps(s)) == dict(s)
  assert pickle.loads(pickle.dumps(s)) == s and type(pickle.loads(pickle.dumps(s))) is CollisionStats
  assert s.nworld == 4 and "most:" not in str(s)  # all worlds alike: none to single out
  s["pairs_per_world"] = [3, 5, 4, 3]
  assert s.summary(worst=1).count("world ") == 1 and "most: world 1: 5)" in s.summary(worst=1)


def test_before_any_collision():
  s = _stats(nworld=0, pairs=0)
  assert str(s) == "no collision has run on this Data yet" and s.nworld == 0


def test_collider_stats_prints_a_summary():
  sim = load("convex_pile", nworld=3)
  collider = sf.install(sim.mjm, sim.m)
  assert str(collider.stats(sim.d)) == "no collision has run on this Data yet"
  mjw.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  assert isinstance(stats, CollisionStats) and isinstance(stats, dict)
  assert len(stats["pairs_per_world"]) == 3
  text = str(stats)
  assert f"{stats['pairs']} broad-phase pairs in 3 worlds" in text and "dropped pairs: 0" in text
