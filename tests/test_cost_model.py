"""benchmarks/cost_model.py: a scene for every pair class, holding pairs of that class, and the
variants each timing compares (the routed class, or whole scenes under routings)."""

import collections

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from mujoco_warp._src.types import GeomType

import cost_model  # benchmarks/, on the path in conftest
import make_scenes
from mjx_supportfield.options import PAIR_CLASSES
from mjx_supportfield.stages.routing import PairClass
from mjx_supportfield.tools import bench


def _classes_of(xml: str) -> collections.Counter:
  """The model's geom pairs (after MuJoCo Warp's static filters) counted by pair class."""
  mjm = mujoco.MjModel.from_xml_string(xml)
  pairs = np.asarray(mjw.put_model(mjm).nxn_geom_pair_filtered.numpy()).reshape(-1, 2)
  gtype = np.asarray(mjm.geom_type)
  return collections.Counter(PairClass.of(*sorted((GeomType(int(gtype[a])), GeomType(int(gtype[b])))))
                             .name.lower() for a, b in pairs)


def test_every_pair_class_has_a_scene():
  assert set(cost_model.SCENES) == set(PAIR_CLASSES)
  assert {f"cost_{c}.xml" for c in PAIR_CLASSES} == set(make_scenes.class_scenes())


@pytest.mark.parametrize("pair_class", PAIR_CLASSES)
def test_class_scene_holds_pairs_of_its_class(pair_class):
  counts = _classes_of(make_scenes.class_scenes()[f"cost_{pair_class}.xml"])
  # geom against geom of the class; the floor's pairs are analytic, the terrain's are the class's
  assert counts[pair_class] >= 24, counts
  if pair_class.startswith("hfield"):
    other = "hfield_prism" if pair_class == "hfield_round" else "hfield_round"
    assert counts[other] == 0, counts


def test_terrain_scene_is_unchanged_by_the_class_scenes():
  """terrain_32 (the suite's, with committed results) draws the same sizes as before the kinds
  became a parameter: its meshes are made even where a class scene leaves them out."""
  full = make_scenes.terrain(32)
  assert full.count("<mesh ") == 32 // 6 + 1 and full.count('type="mesh"') == 5
  rounds = make_scenes.terrain(32, kinds=("sphere", "capsule"))
  assert "<mesh " not in rounds


def _fake_time_impl(calls: list):
  def time_impl(mjm, mjd, scene, nworld, impl, ncon, launches, options):
    calls.append((impl, None if options is None else options.stock_pair_classes))
    row = bench.Row(scene, nworld, impl, "collision", 1.0, 1.0)
    return row, bench.Row(scene, nworld, impl, "step", 2.0, 1.0), 0

  return time_impl


def test_a_class_is_timed_stock_all_the_plugins_and_routed(monkeypatch):
  calls = []
  monkeypatch.setattr(bench, "time_impl", _fake_time_impl(calls))
  monkeypatch.setattr(bench, "settled_state", lambda mjm, settle, keyframe=None: mujoco.MjData(mjm))
  rows = cost_model.time_class("primitive", 4, 1, 0)
  assert calls == [("stock", None), ("plugin", ()), ("plugin", ("primitive",))]
  assert [r["variant"] for r in rows] == ["stock", "stock", "plugin", "plugin", "routed", "routed"]
  assert {r["pair_class"] for r in rows} == {"primitive"}


def test_a_scene_is_timed_under_each_routing(monkeypatch):
  calls = []
  monkeypatch.setattr(bench, "time_impl", _fake_time_impl(calls))
  monkeypatch.setattr(bench, "settled_state", lambda mjm, settle, keyframe=None: mujoco.MjData(mjm))
  rows = cost_model.time_scene(cost_model.SCENES["mesh"], [("mesh",), ("analytic", "mesh")], 4, 1, 0)
  assert calls == [("stock", None), ("plugin", ()), ("plugin", ("mesh",)), ("plugin", ("analytic", "mesh"))]
  assert {r["variant"] for r in rows} == {"stock", "plugin", "route:mesh", "route:analytic+mesh"}


def test_pair_order_times_each_order_and_restores_the_default(monkeypatch):
  """benchmarks/pair_order.py: stock, the plugin as by default and the plugin world by world (or
  forced pair by pair), broadphase.PAIR_MAJOR as each asks while it is installed, None after."""
  import pair_order
  from mjx_supportfield.stages import broadphase

  for force, plugin_order in ((False, None), (True, True)):
    seen = []

    def time_impl(mjm, mjd, scene, nworld, impl, ncon, launches, options):
      seen.append((impl, broadphase.PAIR_MAJOR))
      return bench.Row(scene, nworld, impl, "collision", 1.0, 1.0), bench.Row(scene, nworld, impl, "step", 2.0, 1.0), 0

    monkeypatch.setattr(bench, "time_impl", time_impl)
    monkeypatch.setattr(bench, "settled_state", lambda mjm, settle, keyframe=None: mujoco.MjData(mjm))
    rows = pair_order.time_orders(cost_model.SCENES["mesh"], 4, 1, 0, force)
    assert seen == [("stock", None), ("plugin", plugin_order), ("plugin", False)]
    assert [r["variant"] for r in rows] == ["stock", "stock", "plugin", "plugin", "world_major", "world_major"]
    assert broadphase.PAIR_MAJOR is None
