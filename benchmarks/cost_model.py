"""The cost model of issue #37: each pair class timed through the plugin's kernels and through
MuJoCo Warp's own, at each world count, on the GPU.

  python benchmarks/cost_model.py [--nworld 1024,4096,8192] [--classes analytic,primitive,...]
                                  [--launches 100] [--json OUT] [--markdown OUT]
                                  [--scenes A.xml,B.xml --routings "analytic+primitive;mesh"]

For each pair class (``Options.stock_pair_classes``: stages/routing.py's PairClass) a scene whose
contacts are mostly of that class, stacked so that geoms rest on each other or dropped on bumps
(make_scenes.py's cost_<class>.xml), is timed three ways in one process,
collision inside evolving graph-captured steps and the whole step, from the same settled state
with the same room: stock MuJoCo Warp, the plugin, and the plugin with that class routed to
MuJoCo Warp's narrow phase. The class goes to whichever is faster: the routed column against the
plugin's says what routing it gains on a scene that holds it, the stock column what stock's
whole stage costs. ``--scenes`` times whole scenes instead (stock, the plugin, and the plugin with
each ``--routings`` set of classes sent to MuJoCo Warp: ``;`` between sets, ``+`` within one), to
check a routing rule on scenes that mix classes. Writes the rows (bench.Row fields plus
``variant``) as JSON with the device's name, and a markdown table for docs/performance.md.
"""

import argparse
import contextlib
import dataclasses
import json
import os
import sys
from typing import Optional

import mujoco

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from mjx_supportfield.options import PAIR_CLASSES  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools import bench  # noqa: E402

SCENES = {c: os.path.join(HERE, "scenes", f"cost_{c}.xml") for c in PAIR_CLASSES}


def time_impls(path: str, variants: dict, nworld: int, launches: int, settle: int, keyframe: Optional[int] = None,
               **extra) -> list[dict]:
  """Rows (bench.Row fields, ``variant`` and ``extra``) of each variant (name -> (implementation,
  Options or None, a context manager the variant is installed and timed in, or None)) on one
  scene at ``nworld``, all from one state: settled from qpos0, or from ``keyframe`` where the
  model has one, with the same room."""
  mjm = mujoco.MjModel.from_xml_path(path)
  mjd = bench.settled_state(mjm, settle, keyframe if keyframe is not None and keyframe < mjm.nkey else None)
  ncon = int(1.5 * mjd.ncon) + 16
  rows = []
  for variant, (impl, options, context) in variants.items():
    with context or contextlib.nullcontext():
      collision, step, overflow = bench.time_impl(mjm, mjd, bench.scene_name(path), nworld, impl, ncon, launches,
                                                  options)
    if overflow:
      sys.stderr.write(f"warning: {path}, nworld {nworld}, {variant}: overflow bits {overflow}\n")
    for row in (collision, step):
      rows.append(dict(dataclasses.asdict(row), variant=variant, **extra))
  return rows


def time_variants(path: str, routings: dict, nworld: int, launches: int, settle: int,
                  keyframe: Optional[int] = None, pair_class: Optional[str] = None) -> list[dict]:
  """Rows of stock and of the plugin under each routing (variant name -> the classes it routes)
  on one scene at ``nworld`` (time_impls)."""
  variants = {"stock": ("stock", None, None)}
  variants.update({name: ("plugin", Options(stock_pair_classes=classes), None) for name, classes in routings.items()})
  return time_impls(path, variants, nworld, launches, settle, keyframe, pair_class=pair_class)


def time_class(pair_class: str, nworld: int, launches: int, settle: int) -> list[dict]:
  """Rows of the three variants (stock, plugin with every class its own, the class routed) of
  one class's scene at ``nworld``."""
  return time_variants(SCENES[pair_class], {"plugin": (), "routed": (pair_class,)}, nworld, launches, settle,
                       pair_class=pair_class)


def time_scene(path: str, routings: list[tuple[str, ...]], nworld: int, launches: int, settle: int,
               keyframe: Optional[int] = None) -> list[dict]:
  """Rows of stock, the plugin (every class its own) and the plugin under each routing on one scene."""
  named = {"plugin": (), **{"route:" + "+".join(classes): classes for classes in routings}}
  return time_variants(path, named, nworld, launches, settle, keyframe)


def markdown(rows: list[dict]) -> str:
  """Per class and world count: collision ms of stock, the plugin and the class routed to stock,
  and the faster of the plugin's two."""
  keyed = {(r["pair_class"], r["nworld"], r["variant"]): r for r in rows if r["stage"] == "collision"}
  out = ["| pair class | worlds | stock ms | plugin ms | routed to stock ms | faster |", "|---|---|---|---|---|---|"]
  for pair_class, nworld in sorted({(c, n) for c, n, _ in keyed}, key=lambda k: (PAIR_CLASSES.index(k[0]), k[1])):
    ms = {v: keyed[(pair_class, nworld, v)]["ms"] for v in ("stock", "plugin", "routed")}
    faster = "stock's kernels" if ms["routed"] < ms["plugin"] else "plugin's kernels"
    out.append(f"| {pair_class} | {nworld} | {ms['stock']:.3f} | {ms['plugin']:.3f} | {ms['routed']:.3f} | {faster} |")
  return "\n".join(out) + "\n"


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--nworld", default=None, help="world counts, comma separated (default: bench's for the"
                      " device, 1024,4096,8192 on a GPU)")
  parser.add_argument("--classes", default=",".join(PAIR_CLASSES))
  parser.add_argument("--launches", type=int, default=100, help="timed collision calls a variant")
  parser.add_argument("--settle", type=int, default=200, help="MuJoCo C steps before timing")
  parser.add_argument("--scenes", default=None, help="MJCF files, comma separated: time these whole scenes"
                      " under --routings instead of the classes' scenes")
  parser.add_argument("--routings", default="hfield_prism", help="sets of classes to route for --scenes")
  parser.add_argument("--keyframe", type=int, default=None, help="settle --scenes from this keyframe (those that"
                      " have it; robots that stand where their keyframe puts them)")
  parser.add_argument("--json", default=None)
  parser.add_argument("--markdown", default=None)
  args = parser.parse_args()
  classes = args.classes.split(",")
  unknown = [c for c in classes if c not in SCENES]
  if unknown:
    parser.error(f"--classes: {unknown[0]!r} is not one of {', '.join(SCENES)}")
  nworlds = [int(n) for n in args.nworld.split(",")] if args.nworld else list(bench.default_world_counts())
  if not all(os.path.exists(SCENES[c]) for c in classes):
    make_scenes.main()
  rows = []
  if args.scenes:
    routings = [tuple(r.split("+")) for r in args.routings.split(";")]
    for path in args.scenes.split(","):
      for nworld in nworlds:
        rows += time_scene(path, routings, nworld, args.launches, args.settle, args.keyframe)
        sys.stderr.write(f"{path} nworld {nworld} done\n")
        if args.json:
          with open(args.json, "w") as f:
            json.dump({"device": bench.device_description(), "rows": rows}, f, indent=1)
    return
  for pair_class in classes:
    for nworld in nworlds:
      rows += time_class(pair_class, nworld, args.launches, args.settle)
      sys.stderr.write(f"{pair_class} nworld {nworld} done\n")
      if args.json:  # rewritten as it goes: a run cut short keeps what it measured
        with open(args.json, "w") as f:
          json.dump({"device": bench.device_description(), "rows": rows}, f, indent=1)
  table = markdown(rows)
  print(table)
  if args.markdown:
    with open(args.markdown, "w") as f:
      f.write(table)


if __name__ == "__main__":
  main()
