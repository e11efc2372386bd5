"""Launches of one collision call, stock MuJoCo Warp against the plugin, per scene (no GPU needed).

  python benchmarks/launch_count.py [MODEL.xml ...] [--nworld 4] [--json OUT]

Where each world holds little work, a collision stage's time is its launches, each waiting for
its longest thread (issue #37): this counts them. Every ``wp.launch`` and ``wp.launch_tiled`` of
a collision call after a warm-up call (MuJoCo Warp's and the plugin's alike), plus Warp's scans
and sorts (``wp.utils.array_scan``, ``radix_sort_pairs``, ``segmented_sort_pairs``: one launch or
more each on a GPU, counted as one), and ``wp.capture_if`` gates; and how many of them a CUDA graph
makes (``in_graph``: the deep-pair check is gated on its queue there). Default scenes: the
suite's primitive scenes, a mesh pile, terrain, the real-robot scenes and aloha_pot.
``--stock-pair-classes primitive,...`` counts the plugin with those pair classes routed to MuJoCo
Warp's kernels (Options.stock_pair_classes).
"""

import argparse
import collections
import contextlib
import json
import os
import sys

import mujoco
import mujoco_warp as mjw
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from mjx_supportfield.driver import get_collider  # noqa: E402
from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools.bench import settled_state  # noqa: E402

_COUNTED = (("launch", wp), ("launch_tiled", wp), ("array_scan", wp.utils), ("radix_sort_pairs", wp.utils),
            ("segmented_sort_pairs", wp.utils), ("capture_if", wp))


@contextlib.contextmanager
def counting(counts: collections.Counter):
  """Counts the launches made inside the block by name: the kernel's key, or the utility's."""
  saved = [(name, owner, getattr(owner, name)) for name, owner in _COUNTED]

  def wrap(name, fn):
    def counted(*args, **kwargs):
      kernel = args[0] if args else kwargs.get("kernel")
      counts[getattr(kernel, "key", name) if name.startswith("launch") else name] += 1
      return fn(*args, **kwargs)
    return counted

  for name, owner, fn in saved:
    setattr(owner, name, wrap(name, fn))
  try:
    yield
  finally:
    for name, owner, fn in saved:
      setattr(owner, name, fn)


DEEP_CHECK = "deep_kernels"  # the deep-pair check's kernels, gated on their queue inside a graph


def in_graph(counts: collections.Counter, deep_queued: int) -> int:
  """The launches of the same call inside a CUDA graph (m.opt.graph_conditional): there the
  deep-pair check's launches sit behind one conditional node and run only where an answer was
  queued, so a call that queued none makes the gate's launch and not theirs."""
  deep = sum(n for name, n in counts.items() if name.startswith(DEEP_CHECK))
  if not deep or deep_queued:
    return sum(counts.values())
  return sum(counts.values()) - deep + 1


def count(path: str, nworld: int, plugin: bool, options: Options = Options()) -> tuple[collections.Counter, int]:
  """The launches of one collision call on ``path``'s settled state (stock, or the plugin with
  ``options``), and how many launches it makes inside a CUDA graph (in_graph)."""
  mjm = mujoco.MjModel.from_xml_path(path)
  mjd = settled_state(mjm, 200)
  m = mjw.put_model(mjm)
  if plugin:
    install(mjm, m, options)
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=max(64, 2 * mjd.ncon), njmax=max(256, 12 * mjd.ncon))
  mjw.kinematics(m, d)
  mjw.collision(m, d)  # warm-up: compiles, makes the per-Data state
  counts = collections.Counter()
  with counting(counts):
    mjw.collision(m, d)
  collider = get_collider(m) if plugin else None
  deep_queued = 0
  if collider is not None and not collider.stock_path:
    deep_queued = int(collider.state(m, d).deep.count.numpy()[0])
  return counts, in_graph(counts, deep_queued)


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("models", nargs="*")
  p.add_argument("--nworld", type=int, default=4)
  p.add_argument("--json", default=None)
  p.add_argument("--stock-pair-classes", default="", help="pair classes routed to MuJoCo Warp's kernels")
  args = p.parse_args()
  options = Options(stock_pair_classes=tuple(c for c in args.stock_pair_classes.split(",") if c))
  wp.config.log_level = wp.LOG_WARNING
  scenes = os.path.join(HERE, "scenes")
  models = args.models or [os.path.join(scenes, "primitives_32.xml"), os.path.join(scenes, "primitives_layers_48.xml"),
                           os.path.join(scenes, "pile_32_128.xml"), os.path.join(scenes, "terrain_32.xml"),
                           os.path.join(ROOT, "models", "real", "quadruped_rough.xml"),
                           *(os.path.join(ROOT, "models", "real", f"{name}.xml") for name in (
                             "gripper_grasp", "bin_drop", "polyhedra", "arm_sweep")),
                           os.path.join(os.path.dirname(mjw.__file__), "test_data", "aloha_pot", "scene.xml")]
  rows = []
  for path in models:
    (stock, stock_graph), (plugin, plugin_graph) = count(path, args.nworld, False), count(path, args.nworld, True,
                                                                                         options)
    name = os.path.basename(os.path.dirname(path)) if path.endswith("scene.xml") else os.path.basename(path)[:-4]
    rows.append({"scene": name, "stock": sum(stock.values()), "plugin": sum(plugin.values()),
                 "stock_in_graph": stock_graph, "plugin_in_graph": plugin_graph,
                 "stock_launches": dict(stock), "plugin_launches": dict(plugin)})
    print(f"{name:24s} stock {sum(stock.values()):3d} launches ({stock_graph} in a graph), plugin"
          f" {sum(plugin.values()):3d} ({plugin_graph} in a graph)", flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump({"nworld": args.nworld, "stock_pair_classes": options.stock_pair_classes, "rows": rows}, f, indent=1)


if __name__ == "__main__":
  main()
