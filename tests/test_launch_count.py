"""benchmarks/launch_count.py: the launches a collision call makes, and how many of them a CUDA
graph makes, where the deep-pair check waits behind a conditional node on its queue."""

import collections
import os

import launch_count  # benchmarks/, on the path in conftest
from conftest import MODELS


def test_in_graph_takes_the_gate_for_an_empty_deep_queue():
  counts = collections.Counter({"start_collision": 1, "deep_kernels__locals__deep_faces": 1,
                                "deep_kernels__locals__deep_round": 4, "pass_kernels__locals__patch_kernel": 1})
  assert launch_count.in_graph(counts, deep_queued=0) == 3  # the start, the gate, the patch kernel
  assert launch_count.in_graph(counts, deep_queued=2) == 7
  assert launch_count.in_graph(collections.Counter({"kernel": 3}), deep_queued=0) == 3  # no check, no gate


def test_a_mesh_scene_counts_the_plugins_stages():
  """On convex_pile the plugin launches its broad phase, narrow phase, deep-pair check and
  multi-contact pass (more than stock's stage), and a graph makes fewer where nothing was queued
  for the check."""
  path = os.path.join(MODELS, "convex_pile.xml")
  stock, stock_graph = launch_count.count(path, 2, plugin=False)
  plugin, plugin_graph = launch_count.count(path, 2, plugin=True)
  assert stock_graph == sum(stock.values()) > 0
  assert {"update_aabbs", "start_collision"} <= set(plugin)
  assert any(name.startswith("deep_kernels") for name in plugin)
  assert any(name.startswith("pass_kernels") for name in plugin)
  deep = sum(n for name, n in plugin.items() if name.startswith("deep_kernels"))
  assert plugin_graph in (sum(plugin.values()), sum(plugin.values()) - deep + 1)
