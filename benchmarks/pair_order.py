"""The order of the pair list on a GPU, timed: the default (pair by pair across the worlds for small
nxn lists, stages/broadphase.py's ``pair_major_by_default``) against world by world, with stock
MuJoCo Warp in the same process.

  python benchmarks/pair_order.py A.xml [B.xml ...] [--nworld 1024,4096,8192] [--launches 50]
                                  [--json OUT]

The broad phase hands its pairs to the narrow phase's queues in the order its threads run
(stages/broadphase.py's ``_world_and_item``). World by world, a warp of a narrow-phase kernel
holds one world's pairs of many kinds of geoms, and runs each kind's branch in turn; pair by
pair, it holds one pair of geoms in 32 worlds. Each scene is timed three ways from one settled
state (bench.time_impl: collision inside evolving graph-captured steps, the whole step): stock,
the plugin, and the plugin with the world-by-world order (``broadphase.PAIR_MAJOR`` off while it
is installed). The order does not change which contacts a world gets, only the order of the rows.
"""

import argparse
import contextlib
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import cost_model  # noqa: E402

from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.stages import broadphase  # noqa: E402
from mjx_supportfield.tools import bench  # noqa: E402


@contextlib.contextmanager
def pair_major(value):
  """broadphase.PAIR_MAJOR set to ``value`` within the block (install reads it)."""
  broadphase.PAIR_MAJOR = value
  try:
    yield
  finally:
    broadphase.PAIR_MAJOR = None


def variants(force_pair_major: bool) -> dict:
  """cost_model.time_impls' variants: stock, the plugin (pair by pair whatever the list's size
  where ``force_pair_major``) and the plugin world by world."""
  return {"stock": ("stock", None, None),
          "plugin": ("plugin", Options(), pair_major(True) if force_pair_major else None),
          "world_major": ("plugin", Options(), pair_major(False))}


def time_orders(path: str, nworld: int, launches: int, settle: int, force_pair_major: bool = False) -> list[dict]:
  """Rows (bench.Row fields plus ``variant``) of stock, the plugin and the plugin world by world,
  from the scene's keyframe where it has one."""
  return cost_model.time_impls(path, variants(force_pair_major), nworld, launches, settle, keyframe=0)


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("models", nargs="+")
  parser.add_argument("--nworld", default="1024,4096,8192")
  parser.add_argument("--launches", type=int, default=50, help="timed calls a variant")
  parser.add_argument("--settle", type=int, default=200, help="MuJoCo C steps before timing")
  parser.add_argument("--pair-major", action="store_true", help="the plugin pair by pair whatever the list's size")
  parser.add_argument("--json", default=None)
  args = parser.parse_args()
  rows = []
  for path in args.models:
    for nworld in (int(n) for n in args.nworld.split(",")):
      rows += time_orders(path, nworld, args.launches, args.settle, args.pair_major)
      ms = {r["variant"]: r["ms"] for r in rows[-6:] if r["stage"] == "collision"}
      print(f"{bench.scene_name(path):22s} {nworld:5d}  collision ms: stock {ms['stock']:.3f}, plugin"
            f" {ms['plugin']:.3f}, world by world {ms['world_major']:.3f}", flush=True)
      if args.json:  # rewritten as it goes: a run cut short keeps what it measured
        with open(args.json, "w") as f:
          json.dump({"device": bench.device_description(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
  main()
